"""Statistical efficiency of the rigid pose-track adjustment against the Cramer-Rao bound.

Rigid-body data (default mouse, 3 ring cameras, smooth trajectory), Gaussian pixel noise only
(no deformation, no outliers), many frames. The estimator is run with the matching stochastic
model (single Gaussian, no robust kernel) and the default track constraint. The bound is
computed from the Fisher information of the same problem: the banded normal matrix J^T W J
(detections with weight 1 / sigma^2 plus the track constraint with its weight) at the true
poses; its inverse's diagonal blocks (selected inversion) give sqrt(mean diag) per component
group. Pose errors are measured in the solver's tangent space (left increment: rotation in
rad about the global axes, translation in mm). Passes when RMSE <= 1.2 x bound for rotation
and translation. Last line JSON, also written to runs/benchmarks/efficiency.json.

    .venv/bin/python benchmarks/efficiency.py [--frames 5000] [--noise 2.0] [--seeds 2]
"""

from __future__ import annotations

import argparse
import json
import logging

import numpy as np
import torch

from adjust.camera import CameraTensors
from adjust.lsq import SolverConfig, adjust_poses, normal_matrix, synthetic
from adjust.lsq.banded import diagonal_blocks_of_inverse
from adjust.lsq.geometry import pose_difference
from deformnet.atomic import write_text
from deformnet.body import default_mouse
from deformnet.paths import CONF_DIR

log = logging.getLogger("benchmarks.efficiency")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=5000)
    ap.add_argument("--noise", type=float, default=2.0, help="pixel noise std")
    ap.add_argument("--drop", type=float, default=0.2, help="share of missing detections")
    ap.add_argument("--seeds", type=int, default=2, help="independent noise draws")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--constraint", default="grid", choices=("grid", "spline", "none"))
    ap.add_argument(
        "--out", default=str(CONF_DIR.parent / "runs" / "benchmarks" / "efficiency.json")
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    torch.set_num_threads(args.threads)
    body = torch.tensor(default_mouse().points)
    cams = CameraTensors.from_cameras(synthetic.ring_cameras(3))
    cfg = SolverConfig(
        sigma_det_px=args.noise,
        sigma_def_mm=0.0,
        robust="none",
        num_threads=args.threads,
        constraint=args.constraint,
    )
    sq_err = np.zeros(6)
    bound = np.zeros(6)
    n = 0
    for seed in range(args.seeds):
        truth = synthetic.smooth_trajectory(args.frames, seed=seed)
        xy, w, _ = synthetic.simulate(
            truth, body, cams, noise_px=args.noise, drop=args.drop, seed=100 + seed
        )
        res = adjust_poses(xy, w, cams, body, cfg, progress=False)
        d = pose_difference(torch.as_tensor(res.poses), truth).numpy()
        sq_err += (d**2).sum(0)
        fisher = normal_matrix(truth, xy, w, cams, body, cfg)
        cov = diagonal_blocks_of_inverse(fisher)
        bound += np.diagonal(cov, axis1=-2, axis2=-1).sum(0)
        n += args.frames
        log.info("seed %d: %d iterations, converged=%s", seed, res.iterations, res.converged)
    rmse = np.sqrt(sq_err / n)
    crb = np.sqrt(bound / n)
    rot_rmse, rot_crb = (
        float(np.sqrt(np.mean(rmse[:3] ** 2))),
        float(np.sqrt(np.mean(crb[:3] ** 2))),
    )
    tr_rmse, tr_crb = float(np.sqrt(np.mean(rmse[3:] ** 2))), float(np.sqrt(np.mean(crb[3:] ** 2)))
    ratios = {"rotation": rot_rmse / rot_crb, "translation": tr_rmse / tr_crb}
    log.info(
        "rotation:    RMSE %.5f rad   CRB %.5f rad   ratio %.3f",
        rot_rmse,
        rot_crb,
        ratios["rotation"],
    )
    log.info(
        "translation: RMSE %.4f mm    CRB %.4f mm    ratio %.3f",
        tr_rmse,
        tr_crb,
        ratios["translation"],
    )
    summary = {
        "benchmark": "efficiency",
        "frames": args.frames,
        "seeds": args.seeds,
        "noise_px": args.noise,
        "drop": args.drop,
        "constraint": cfg.constraint,
        "rmse_per_param": [round(float(x), 6) for x in rmse],
        "crb_per_param": [round(float(x), 6) for x in crb],
        "rotation": {"rmse_rad": rot_rmse, "crb_rad": rot_crb, "ratio": ratios["rotation"]},
        "translation": {"rmse_mm": tr_rmse, "crb_mm": tr_crb, "ratio": ratios["translation"]},
        "max_ratio": max(ratios.values()),
        "target_ratio": 1.2,
        "passed": bool(max(ratios.values()) <= 1.2),
    }
    line = json.dumps(summary)
    write_text(args.out, line + "\n")
    print(line)
    return summary


if __name__ == "__main__":
    main()
