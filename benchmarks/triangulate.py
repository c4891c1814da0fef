"""Time batched triangulation: T frames x K parts x C cameras (default 100k x 8 x 3).

Synthetic rig (cameras ~1 m around a lock-box-sized volume, OpenCV distortion), random points,
projection, Gaussian pixel noise, NaN dropout and a few far outliers; times
`adjust.triangulate.triangulate` (plain and robust) and reports accuracy. Prints one JSON
line last and writes it to runs/benchmarks/triangulate.json (atomically).

    .venv/bin/python benchmarks/triangulate.py [--frames 100000] [--threads 1]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch
from common import emit

from adjust.camera import Camera, CameraTensors, look_at_pose, project_cameras
from adjust.triangulate import triangulate
from deformnet.so3 import matrix_to_rodrigues

OUT = Path(__file__).resolve().parents[1] / "runs" / "benchmarks" / "triangulate.json"
CENTERS = [(0, -1000, 150), (30, 20, 1100), (1000, 40, 200), (-700, -700, 400), (700, 700, 500)]


def look_at(name: str, center, f: float = 1200.0) -> Camera:
    c = np.asarray(center, float)
    z = -c / np.linalg.norm(c)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    R, t = look_at_pose(c, np.zeros(3), up, name)
    K = np.array([[f, 0.0, 640.0], [0.0, f, 512.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.2, 0.08, 1e-3, -7e-4, -0.01])
    return Camera(name, K, dist, matrix_to_rodrigues(torch.as_tensor(R)).numpy(), t)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--parts", type=int, default=8)
    ap.add_argument("--cameras", type=int, default=3, choices=range(2, len(CENTERS) + 1))
    ap.add_argument(
        "--threads", type=int, default=1, help="torch intra-op threads inside triangulate"
    )
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--noise-px", type=float, default=1.0)
    ap.add_argument("--dropout", type=float, default=0.2)
    ap.add_argument("--outlier-rate", type=float, default=0.02)
    ap.add_argument("--float32", action="store_true")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    dtype = torch.float32 if args.float32 else torch.float64
    T, K, C = args.frames, args.parts, args.cameras

    g = torch.Generator().manual_seed(0)
    cams64 = CameraTensors.from_cameras([look_at(f"cam{i}", CENTERS[i]) for i in range(C)])
    X = (torch.rand(T, K, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor(
        [300.0, 200.0, 150.0], dtype=torch.float64
    )
    xy = project_cameras(X, cams64)
    xy += torch.randn(xy.shape, generator=g, dtype=torch.float64) * args.noise_px
    outlier = torch.rand(T, K, C, generator=g) < args.outlier_rate
    xy[outlier] += 200.0
    w = torch.rand(T, K, C, generator=g, dtype=torch.float64) * 0.7 + 0.3
    drop = torch.rand(T, K, C, generator=g) < args.dropout
    xy[drop] = float("nan")
    w[drop] = 0.0
    cams, xy, w = cams64.to(dtype), xy.to(dtype), w.to(dtype)

    def timed(**kw) -> tuple[list[float], list[float], object]:
        walls, cpus, res = [], [], None
        for _ in range(args.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            res = triangulate(xy, w, cams, num_threads=args.threads, **kw)
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        return walls, cpus, res

    load_before = os.getloadavg()
    walls, cpus, res = timed()
    walls_r, cpus_r, res_r = timed(robust=True)
    load_after = os.getloadavg()

    def accuracy(r) -> dict:
        ok = r.ncams >= 2
        e = (r.points[ok].double() - X[ok]).norm(dim=-1)
        three = (r.nviews == C) & ok
        e3 = (r.points[three].double() - X[three]).norm(dim=-1)
        return {
            "median_mm": float(e.median()),
            "p99_mm": float(torch.quantile(e[: 1 << 24], 0.99)),
            "p99_allviews_mm": float(torch.quantile(e3[: 1 << 24], 0.99)),
            "triangulated_frac": float(ok.double().mean()),
        }

    result = {
        "benchmark": "triangulate",
        "frames": T,
        "parts": K,
        "cameras": C,
        "points": T * K,
        "dtype": str(dtype).removeprefix("torch."),
        "threads": args.threads,
        "noise_px": args.noise_px,
        "dropout": args.dropout,
        "outlier_rate": args.outlier_rate,
        "wall_s": round(min(walls), 3),
        "wall_s_all": [round(t, 3) for t in walls],
        "cpu_s": round(min(cpus), 3),
        "robust_wall_s": round(min(walls_r), 3),
        "robust_wall_s_all": [round(t, 3) for t in walls_r],
        "robust_cpu_s": round(min(cpus_r), 3),
        "points_per_s": round(T * K / min(walls)),
        "plain": accuracy(res),
        "robust": accuracy(res_r),
        "loadavg_1min_before_after": [round(load_before[0], 2), round(load_after[0], 2)],
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "machine": platform.machine(),
    }
    return emit(result, args.out)


if __name__ == "__main__":
    main()
