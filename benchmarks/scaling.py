"""Scaling of the rigid pose-track adjustment: wall time at T = 10,000 and 100,000 frames.

Synthetic scene: the default mouse body model (8 parts), 3 ring cameras, a smooth trajectory
that keeps turning through 180 degrees, 2 px Gaussian detector noise, 20 % missing detections.
Default solver settings (grid constraint, two-Gaussian mixture, Cauchy kernel), fit
initialisation included in the time. Prints one line per size and a JSON summary as the last
line, also written to runs/benchmarks/scaling.json.

    .venv/bin/python benchmarks/scaling.py [--frames 10000 100000] [--threads 1]
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import time

import numpy as np
import torch

from adjust.camera import CameraTensors
from adjust.lsq import SolverConfig, adjust_poses, synthetic
from adjust.lsq.geometry import pose_difference
from deformnet.atomic import write_text
from deformnet.body import default_mouse
from deformnet.paths import CONF_DIR

log = logging.getLogger("benchmarks.scaling")


def run_one(T: int, threads: int, seed: int = 0) -> dict:
    body = torch.tensor(default_mouse().points)
    cams = CameraTensors.from_cameras(synthetic.ring_cameras(3))
    truth = synthetic.smooth_trajectory(T, seed=seed)
    xy, w, _ = synthetic.simulate(truth, body, cams, noise_px=2.0, drop=0.2, seed=seed)
    cfg = SolverConfig(num_threads=threads)
    t0, c0 = time.perf_counter(), time.process_time()
    res = adjust_poses(xy, w, cams, body, cfg, progress=False)
    seconds = time.perf_counter() - t0
    cpu = time.process_time() - c0
    d = pose_difference(torch.as_tensor(res.poses), truth)
    return {
        "frames": T,
        "seconds": round(seconds, 3),
        "cpu_seconds": round(cpu, 3),
        "iterations": res.iterations,
        "chunks": res.chunks,
        "converged": bool(res.converged),
        "rot_rmse_rad": float(d[:, :3].pow(2).sum(-1).mean().sqrt()),
        "trans_rmse_mm": float(d[:, 3:].pow(2).sum(-1).mean().sqrt()),
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[10000, 100000])
    ap.add_argument("--threads", type=int, default=1, help="torch threads (0: torch default)")
    ap.add_argument("--out", default=str(CONF_DIR.parent / "runs" / "benchmarks" / "scaling.json"))
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    rows = []
    for T in args.frames:
        row = run_one(T, args.threads)
        rows.append(row)
        log.info(
            "T=%7d  %.2f s wall, %.2f s cpu  (%d iterations, %d chunks, "
            "rot rmse %.4f rad, trans rmse %.3f mm)",
            T,
            row["seconds"],
            row["cpu_seconds"],
            row["iterations"],
            row["chunks"],
            row["rot_rmse_rad"],
            row["trans_rmse_mm"],
        )
    secs = [r["seconds"] for r in rows]
    ratio = secs[-1] / secs[0] if len(secs) > 1 and secs[0] > 0 else None
    cpus = [r["cpu_seconds"] for r in rows]
    cpu_ratio = cpus[-1] / cpus[0] if len(cpus) > 1 and cpus[0] > 0 else None
    summary = {
        "benchmark": "scaling",
        "parts": 8,
        "cameras": 3,
        "runs": rows,
        "ratio": round(ratio, 3) if ratio is not None else None,
        "cpu_ratio": round(cpu_ratio, 3) if cpu_ratio is not None else None,
        "frame_ratio": args.frames[-1] / args.frames[0] if len(args.frames) > 1 else 1,
        "targets": {"seconds_at_100k": 20.0, "ratio": 12.0},
        "threads": args.threads or torch.get_num_threads(),
        "cpu": platform.processor() or platform.machine(),
        "load_avg_1min": round(float(np.round(_loadavg(), 2)), 2),
    }
    line = json.dumps(summary)
    write_text(args.out, line + "\n")
    print(line)
    return summary


def _loadavg() -> float:
    try:
        import os

        return os.getloadavg()[0]
    except OSError:  # pragma: no cover
        return float("nan")


if __name__ == "__main__":
    main()
