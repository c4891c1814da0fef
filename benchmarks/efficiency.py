"""Statistical efficiency of the rigid pose-track adjustment against the Cramer-Rao bound.

Rigid-body data (default mouse, 3 ring cameras, smooth trajectory), Gaussian pixel noise only
(no deformation, no outliers), many frames. The estimator is run with the matching stochastic
model (single Gaussian, no robust kernel) and the default track constraint. The bound is
computed from the Fisher information of the same problem: the banded normal matrix J^T W J at
the true poses, its inverse's diagonal blocks (selected inversion) giving sqrt(mean diag) per
component group, in two forms: the true Cramer-Rao bound (detections with weight 1 / sigma^2
only, no prior) and the posterior bound (plus the track constraint with its weight, a prior).
Pose errors are measured in the solver's tangent space (left increment: rotation in rad about
the global axes, translation in mm). The estimator runs twice, with the track prior and
without it. The 1.2x target is about the true bound: passes when the estimator without the
prior has RMSE <= 1.2 x the Cramer-Rao bound for rotation and translation; the estimator with
the prior is printed against both bounds (it is biased towards smooth tracks, so it may go
below the no-prior bound; the posterior bound holds on average over tracks drawn from the
prior, not for one smooth track). Last line JSON, also written to
runs/benchmarks/efficiency.json.

    .venv/bin/python benchmarks/efficiency.py [--frames 5000] [--noise 2.0] [--seeds 2]
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
import torch
from common import emit, start

from adjust.camera import CameraTensors
from adjust.lsq import SolverConfig, adjust_poses, normal_matrix, synthetic
from adjust.lsq.banded import diagonal_blocks_of_inverse
from adjust.lsq.geometry import pose_difference
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
    args = start(ap, argv)
    body = torch.tensor(default_mouse().points)
    cams = CameraTensors.from_cameras(synthetic.ring_cameras(3))
    cfg = SolverConfig(
        sigma_det_px=args.noise,
        sigma_def_mm=0.0,
        robust="none",
        num_threads=args.threads,
        constraint=args.constraint,
    )
    free = cfg.replace(constraint="none")  # the same estimator without the track prior
    sq_err, sq_err_free = np.zeros(6), np.zeros(6)
    bound_post, bound_crb = np.zeros(6), np.zeros(6)
    n = 0
    for seed in range(args.seeds):
        truth = synthetic.smooth_trajectory(args.frames, seed=seed)
        xy, w, _ = synthetic.simulate(
            truth, body, cams, noise_px=args.noise, drop=args.drop, seed=100 + seed
        )
        runs = [(cfg, sq_err)] + ([(free, sq_err_free)] if cfg.constraint != "none" else [])
        for c, acc in runs:
            res = adjust_poses(xy, w, cams, body, c, progress=False)
            d = pose_difference(torch.as_tensor(res.poses), truth).numpy()
            acc += (d**2).sum(0)
            log.info(
                "seed %d, constraint %s: %d iterations, converged=%s",
                seed,
                c.constraint,
                res.iterations,
                res.converged,
            )
        if cfg.constraint == "none":
            sq_err_free[:] = sq_err
        for c, acc in ((cfg, bound_post), (free, bound_crb)):
            cov = diagonal_blocks_of_inverse(normal_matrix(truth, xy, w, cams, body, c))
            acc += np.diagonal(cov, axis1=-2, axis2=-1).sum(0)
        n += args.frames

    def groups(v: np.ndarray) -> tuple[float, float]:
        r = np.sqrt(v / n)
        return float(np.sqrt(np.mean(r[:3] ** 2))), float(np.sqrt(np.mean(r[3:] ** 2)))

    rmse, rmse_free = groups(sq_err), groups(sq_err_free)
    post, crb = groups(bound_post), groups(bound_crb)
    rows = [
        ("estimator (track prior)", "posterior bound (with prior)", rmse, post),
        ("estimator (track prior)", "Cramer-Rao bound (no prior)", rmse, crb),
        ("estimator (no prior)", "Cramer-Rao bound (no prior)", rmse_free, crb),
    ]
    print(f"{'estimate':26s} {'against':30s} {'rot rad':>9s} {'bound':>9s} {'ratio':>6s} "
          f"{'tr mm':>8s} {'bound':>8s} {'ratio':>6s}")  # fmt: skip
    for est, against, (er, et), (br, bt) in rows:
        print(f"{est:26s} {against:30s} {er:9.5f} {br:9.5f} {er / br:6.3f} "
              f"{et:8.4f} {bt:8.4f} {et / bt:6.3f}")  # fmt: skip
    target = {
        "rotation": rmse_free[0] / crb[0],
        "translation": rmse_free[1] / crb[1],
    }
    print(
        "The 1.2x target is about the true Cramer-Rao bound (detections only, no prior), which "
        "no unbiased estimator beats: it is met when the estimator without the track prior "
        "reaches it within 1.2x (last row). With the track prior the estimator is biased "
        "towards smooth tracks and may go below that bound (middle row); the posterior bound "
        "(first row) counts the prior as information and is a lower bound only on average "
        "over tracks drawn from the prior, not for one smooth track."
    )

    def block(r, b):
        return {"rmse": r, "bound": b, "ratio": r / b}

    summary = {
        "benchmark": "efficiency",
        "frames": args.frames,
        "seeds": args.seeds,
        "noise_px": args.noise,
        "drop": args.drop,
        "constraint": cfg.constraint,
        "units": {"rotation": "rad", "translation": "mm"},
        "with_prior_vs_posterior_bound": {
            "rotation": block(rmse[0], post[0]),
            "translation": block(rmse[1], post[1]),
        },
        "with_prior_vs_cramer_rao": {
            "rotation": block(rmse[0], crb[0]),
            "translation": block(rmse[1], crb[1]),
        },
        "no_prior_vs_cramer_rao": {
            "rotation": block(rmse_free[0], crb[0]),
            "translation": block(rmse_free[1], crb[1]),
        },
        "target": "no_prior_vs_cramer_rao ratio <= 1.2 (the true bound, no prior)",
        "max_ratio": max(target.values()),
        "target_ratio": 1.2,
        "passed": bool(max(target.values()) <= 1.2),
    }
    return emit(summary, args.out)


if __name__ == "__main__":
    main()
