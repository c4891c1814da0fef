"""Real-data benchmark: `adjust-track body=auto` vs. DLT triangulation on the 4-camera hand data.

Data: `deformnet.paths.real_hand_dir()` (shared/data/real-hand-4cam beside the checkout or under
$MOUSETRACK_SHARED; anipose calibration.toml + trial_000/ DeepLabCut CSVs,
21 hand keypoints, 513 frames; no 3D truth). Both methods run end to end through their CLI's
`run(cfg)` with default settings (likelihood threshold 0.5): `adjust-triangulate` (linear
triangulation from >= 2 views) and `adjust-track body=auto` (rigid model estimated from the
data, deformation std from its spread, pose-track adjustment, fused parts).

Metrics: completeness (fraction of part-frames with a 3D point); reprojection error (px) of the
reported points against the accepted detections — per point (mean over its detections), over
all points each method reports, and over the common subset (part-frames DLT triangulated) for a
like-for-like comparison; seconds.

    .venv/bin/python benchmarks/real_hand.py [--data ../shared/data/real-hand-4cam] \\
        [--threads 1] [-o solver.constraint=spline]

Prints a table; the last line is JSON keyed by method, also written atomically to
runs/benchmarks/real_hand.json.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from common import emit, print_table, start

from adjust.camera import CameraTensors
from adjust.io import load_scene, read_points3d
from adjust.metrics import error_summary, reprojection_errors
from deformnet.confutil import compose
from deformnet.paths import CONF_DIR, real_hand_dir

log = logging.getLogger("benchmarks.real_hand")

ROOT = CONF_DIR.parent
DATA = real_hand_dir()


_stats = error_summary  # n, mean, median, p90, rmse, max (NaN if none)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(DATA))
    ap.add_argument("--trial", default="trial_000")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (0: torch default)")
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "real_hand"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "real_hand.json"))
    ap.add_argument(
        "-o", "--override", action="append", default=[], help="adjust-track override (repeat)"
    )
    args = start(ap, argv)
    data, work = Path(args.data), Path(args.work)
    calib, dets = data / "calibration.toml", data / args.trial
    inputs = [f"input.calibration={calib}", f"input.detections={dets}"]

    from adjust.apps.track import run as track
    from adjust.apps.triangulate import run as triangulate

    t0 = time.perf_counter()
    s_dlt = triangulate(compose("triangulate", [*inputs, f"output.dir={work / 'dlt'}"]))
    t_dlt = time.perf_counter() - t0
    threads = [f"threads={args.threads}"] if args.threads else ["threads=null"]
    t0 = time.perf_counter()
    s_adj = track(
        compose(
            "track",
            [
                *inputs,
                f"output.dir={work / 'track'}",
                "body=auto",
                "progress=false",
                *threads,
                *args.override,
            ],
        )
    )
    t_adj = time.perf_counter() - t0

    # reprojection errors recomputed the same way for both (mean over a point's detections)
    cameras, det = load_scene(calib, dets, None)
    cams = CameraTensors.from_cameras(cameras, dtype=torch.float64)
    pts = {
        "dlt": read_points3d(work / "dlt" / "points3d.csv")["points"],
        "adjust_track": read_points3d(work / "track" / "points3d.csv")["points"],
    }
    common = np.isfinite(pts["dlt"]).all(-1)
    results: dict[str, dict] = {}
    for name, P in pts.items():
        view = reprojection_errors(np.nan_to_num(P, nan=0.0), det.xy, cams, det.observed)
        view = np.where(np.isfinite(P).all(-1)[..., None], view, np.nan)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            err = np.nanmean(view, -1)
        done = np.isfinite(P).all(-1)
        results[name] = {
            "completeness": float(done.mean()),
            "reproj_median_px": _stats(err)["median"],
            "reproj_p90_px": _stats(err)["p90"],
            "reproj_median_px_common": _stats(err[common])["median"],
            "reproj_median_px_not_dltable": _stats(err[~common])["median"],
            "points_with_detections": int(np.isfinite(err).sum()),
            "seconds": round(t_dlt if name == "dlt" else t_adj, 2),
        }
    results["adjust_track"]["iterations"] = s_adj["iterations"]
    results["adjust_track"]["body_rms_deviation_mm"] = s_adj["body"].get("rms_deviation_mm")
    results["adjust_track"]["summary_reproj_median_px"] = s_adj["reprojection_error_px"]["median"]
    results["dlt"]["summary_reproj_median_px"] = s_dlt["reprojection_error_px"]["median"]

    cols = [
        ("completeness", "complete"),
        ("reproj_median_px", "reproj med"),
        ("reproj_p90_px", "reproj p90"),
        ("reproj_median_px_common", "med DLTable"),
        ("reproj_median_px_not_dltable", "med others"),
        ("seconds", "seconds"),
    ]
    print(
        f"\nreal hand data {dets}: {det.num_frames} frames, {det.num_parts} parts, "
        f"{det.num_cameras} cameras (reprojection error px, per point, over its accepted "
        "detections; DLTable = part-frames DLT triangulated)"
    )
    print_table(results, cols, 13, large_digits=None)
    summary = {
        **results,
        "data": str(dets),
        "threads": args.threads or torch.get_num_threads(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    return emit(summary, args.out)


if __name__ == "__main__":
    main()
