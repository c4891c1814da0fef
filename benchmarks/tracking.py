"""Tracking benchmark: DLT triangulation vs. rigid vs. deformable pose-track adjustment on a
simulated scene with known 3D truth.

The scene is written by `adjust-simulate`'s `run` (default rig: top, side and front cameras;
default detector: about half of the part-frames seen by >= 2 cameras and a tenth by none; the
measured fractions are reported) with a seed no training run uses. Methods, each run end to end
through its CLI's `run(cfg)` on the scene folder (the files a user has):

- ``dlt``: `adjust-triangulate` (likelihood-weighted linear triangulation, >= 2 views);
- ``rigid``: `adjust-track deformation=rigid` (rigid body model, default solver settings);
- ``interp``: `adjust-track` (its default, ``deformation=interp``: each part's body-frame
  offset interpolated across its gaps, fused with the frame's detections);
- ``deformable``: `adjust-track deformation=CHECKPOINT`; without ``--checkpoint`` a net is
  first trained with `deformnet-train`'s default CPU config (its `run()`), time reported apart.

Metrics (`adjust.metrics.point_errors` against truth.npz): completeness; RMSE (mm) over all
part-frames, over those seen by >= 2 cameras and over the "occluded" ones (< 2 cameras),
also over the unseen ones (0 cameras); fraction within 5 mm; seconds; and the RMSE of every
method on the part-frames DLT could triangulate (the "DLT-able" subset, computed explicitly).
Targets: completeness 1.0 for the adjustments; deformable occluded RMSE <= 0.7 x rigid's; both
adjustments better than DLT on the DLT-able subset.

    .venv/bin/python benchmarks/tracking.py [--frames 1500] [--seed 91000] \\
        [--checkpoint runs/train/.../best.ckpt] [--threads 1] [-o solver.constraint=spline]

Prints a table; the last line is JSON keyed by method, also written atomically to
runs/benchmarks/tracking.json.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import time
from pathlib import Path

import numpy as np
import torch
from common import emit, print_table, start

from adjust.io import read_points3d
from adjust.metrics import point_errors
from deformnet.confutil import compose
from deformnet.paths import CONF_DIR

log = logging.getLogger("benchmarks.tracking")

ROOT = CONF_DIR.parent
SCENE_SEED = 91_000  # held out: deformnet-train uses seeds 0.. and 10_000..


def simulate(out: Path, frames: int, seed: int, overrides: list[str] = ()) -> dict:
    from adjust.apps.simulate import run

    t0 = time.perf_counter()
    ov = [f"output.dir={out}", f"num_frames={frames}", f"seed={seed}", *overrides]
    res = run(compose("scene", ov))
    log.info("scene: %d frames in %.1f s -> %s", frames, time.perf_counter() - t0, out)
    return res


def ensure_scene(out: Path, frames: int, seed: int, overrides: list[str] = ()) -> Path:
    """The scene folder `out`, simulated first (`simulate`) unless its truth.npz is there."""
    if not (out / "truth.npz").exists():
        simulate(out, frames, seed, overrides)
    return out


def view_fractions(nviews: np.ndarray) -> dict:
    """The fractions of part-frames seen by >= 2 cameras, by 1 and by none."""
    return {
        "seen_ge2": float((nviews >= 2).mean()),
        "seen_1": float((nviews == 1).mean()),
        "seen_0": float((nviews == 0).mean()),
    }


def scene_inputs(scene: Path) -> list[str]:
    """The apps' input overrides for a scene folder (its calibration and detections)."""
    return [
        f"input.calibration={scene / 'calibration.toml'}",
        f"input.detections={scene / 'detections'}",
    ]


def train_net(out: Path, overrides: list[str]) -> tuple[str, float, dict]:
    from deformnet.train import run

    t0 = time.perf_counter()
    res = run(
        compose("train", [f"output.dir={out}", "logger=none", "progress_bar=none", *overrides])
    )
    ckpt = res.get("best_checkpoint") or res.get("last_checkpoint")
    if not ckpt:
        raise RuntimeError(f"deformnet-train wrote no checkpoint into {out}")
    return str(ckpt), time.perf_counter() - t0, res.get("metrics", {})


def run_dlt(scene: Path, out: Path) -> tuple[np.ndarray, float]:
    from adjust.apps.triangulate import run

    t0 = time.perf_counter()
    run(compose("triangulate", [*scene_inputs(scene), f"output.dir={out}", "body=mouse"]))
    return read_points3d(out / "points3d.csv")["points"], time.perf_counter() - t0


def run_track(scene: Path, out: Path, overrides: list[str]) -> tuple[np.ndarray, float, dict]:
    from adjust.apps.track import run

    t0 = time.perf_counter()
    summary = run(
        compose("track", [*scene_inputs(scene), f"output.dir={out}", "progress=false", *overrides])
    )
    return read_points3d(out / "points3d.csv")["points"], time.perf_counter() - t0, summary


def _rmse(err: np.ndarray, mask: np.ndarray) -> float:
    e = err[mask]
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e * e))) if e.size else float("nan")


def evaluate(est: np.ndarray, truth: np.ndarray, nviews: np.ndarray, dltable: np.ndarray) -> dict:
    m = point_errors(est, truth, nviews)
    err = np.linalg.norm(est - truth, axis=-1)
    return {
        "completeness": m["completeness"],
        "rmse_all": m["rmse_all"],
        "rmse_seen2": m["rmse_seen"],
        "rmse_occluded": m["rmse_occluded"],
        "rmse_unseen": _rmse(err, nviews == 0),
        "rmse_dltable": _rmse(err, dltable),
        "within5_all": m["within5_all"],
        "within5_occluded": m["within5_occluded"],
        "median_all": m["median_all"],
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=SCENE_SEED)
    ap.add_argument("--checkpoint", default=None, help="deformation checkpoint (else: train one)")
    ap.add_argument("--no-deformable", action="store_true", help="skip the deformable method")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (0: torch default)")
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "tracking"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "tracking.json"))
    ap.add_argument(
        "-o", "--override", action="append", default=[], help="adjust-track override (repeat)"
    )
    ap.add_argument(
        "-t", "--train-override", action="append", default=[], help="deformnet-train override"
    )
    args = start(ap, argv)
    work = Path(args.work)
    scene = ensure_scene(work / f"scene_{args.frames}_{args.seed}", args.frames, args.seed)
    truth = np.load(scene / "truth.npz")
    P, nviews = truth["points"], truth["nviews"]
    fractions = view_fractions(nviews)
    log.info(
        "part-frames seen by >= 2 cameras %.3f, by 1 %.3f, by none %.3f",
        fractions["seen_ge2"],
        fractions["seen_1"],
        fractions["seen_0"],
    )
    threads = [f"threads={args.threads}"] if args.threads else ["threads=null"]
    results: dict[str, dict] = {}
    extra: dict = {}

    dlt, secs = run_dlt(scene, work / "dlt")
    dltable = np.isfinite(dlt).all(-1)
    results["dlt"] = {**evaluate(dlt, P, nviews, dltable), "seconds": round(secs, 2)}

    for name in ("rigid", "interp"):
        est, secs, summ = run_track(
            scene, work / name, [f"deformation={name}", *threads, *args.override]
        )
        results[name] = {
            **evaluate(est, P, nviews, dltable),
            "seconds": round(secs, 2),
            "iterations": summ["iterations"],
        }

    if not args.no_deformable:
        ckpt = args.checkpoint
        if ckpt is None:
            log.info("no --checkpoint: training a net with deformnet-train's default CPU config")
            ckpt, tsecs, tmetrics = train_net(work / "net", args.train_override)
            extra["training"] = {"checkpoint": ckpt, "seconds": round(tsecs, 1), **tmetrics}
        est, secs, summ = run_track(
            scene, work / "deformable", [f"deformation={ckpt}", *threads, *args.override]
        )
        results["deformable"] = {
            **evaluate(est, P, nviews, dltable),
            "seconds": round(secs, 2),
            "iterations": summ["iterations"],
            "rigid_iterations": summ.get("rigid_iterations"),
        }
        extra["checkpoint"] = str(ckpt)

    cols = [
        ("completeness", "complete"),
        ("rmse_all", "rmse all"),
        ("rmse_seen2", "rmse >=2"),
        ("rmse_occluded", "rmse occl"),
        ("rmse_unseen", "rmse 0cam"),
        ("rmse_dltable", "rmse DLTable"),
        ("within5_all", "<=5mm"),
        ("seconds", "seconds"),
    ]
    print(f"\nscene {scene}: {args.frames} frames, seed {args.seed}")
    print(
        f"part-frames: seen by >=2 cameras {fractions['seen_ge2']:.3f}, by 1 "
        f"{fractions['seen_1']:.3f}, by none {fractions['seen_0']:.3f}; DLT-able "
        f"{dltable.mean():.3f} (RMSE in mm; occl = seen by < 2 cameras)"
    )
    print_table(results, cols, 13)
    checks = {
        "complete": all(results[m]["completeness"] == 1.0 for m in results if m != "dlt"),
        "rigid_beats_dlt_on_dltable": results["rigid"]["rmse_dltable"]
        < results["dlt"]["rmse_dltable"],
    }
    if "deformable" in results:
        ratio = results["deformable"]["rmse_occluded"] / results["rigid"]["rmse_occluded"]
        checks["deformable_occluded_ratio"] = round(ratio, 3)
        checks["deformable_occluded_le_0.7_rigid"] = ratio <= 0.7
        checks["deformable_beats_dlt_on_dltable"] = (
            results["deformable"]["rmse_dltable"] < results["dlt"]["rmse_dltable"]
        )
    print("checks: " + ", ".join(f"{k}={v}" for k, v in checks.items()))
    summary = {
        **{m: {k: _round(v) for k, v in r.items()} for m, r in results.items()},
        "scene": {
            "frames": args.frames,
            "seed": args.seed,
            "fractions": fractions,
            "dltable": float(dltable.mean()),
        },
        "checks": checks,
        **extra,
        "threads": args.threads or torch.get_num_threads(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    return emit(summary, args.out)


def _round(v):
    return round(v, 4) if isinstance(v, float) and math.isfinite(v) else v


if __name__ == "__main__":
    main()
