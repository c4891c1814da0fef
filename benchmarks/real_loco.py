"""Leave-one-camera-out on real data: the accuracy measure that needs no 3D truth.

For every real session in shared/data (the 4-camera hand, DeepLabCut CSVs; the 3-camera fly,
DeepLabCut-style CSVs with extreme long-lens intrinsics; the 4-camera SLEAP mouse, whose `side`
camera has a wrong pose in its calibration, so it is left out of that rig and the leave-outs run
over the three good cameras) and every camera of it: track with the *other* cameras only,
project the 3D points into the left-out camera and measure the pixel distance to its confident
detections (likelihood >= 0.9). Methods, side by side on the same subsets:

- ``dlt``: `adjust-triangulate` (linear, >= 2 views);
- ``dlt_kalman``: the Kalman-smoother peer on those points (`peers/kalman.py`, pykalman, the
  `bench` extra: constant-velocity Kalman filter + RTS smoother per part, noise fitted by EM;
  gaps filled; ``--no-kalman`` skips it);
- ``dlt_disk``: the DISK-style imputation peer on those points (`peers/disk.py`: a transformer
  trained for ``--adapt-seconds`` on the leave-out's own DLT points, hidden present points as
  targets, then filling the gaps; no body model; ``--no-disk`` skips it);
- ``aniposelib``: aniposelib's `triangulate_optim` (anipose's settings; no skeleton constraints:
  these keypoint sets have none we could state), in its own environment (`make bench-env`);
- ``rigid``: `adjust-track body=auto deformation=rigid`;
- ``interp``: `adjust-track body=auto` (default `deformation=interp`);
- ``self``: `adjust-track body=auto deformation=self`: a net trained on the leave-out's own
  recording (self-supervised; these skeletons are not the shipped net's, so from scratch) for
  ``--adapt-seconds`` (30), then used in the adjustment for the part-frames without a 3D
  observation of their own; the prior of those with one (rigid model or neighbouring frames)
  chosen by held-out cameras among the tracking cameras (`adjust.validate`; >= 3 of them)
  (``--no-self`` skips it).

All `adjust-track` variants use `body=auto`'s rigid model re-estimated from the detections
themselves (`body_fit.refine=views`, `adjust.estimate.place_from_rays`).

The first ``--frames`` (200) frames of each session, the same for every method (aniposelib's
optimisation takes minutes per leave-out on the whole hand session on 2 cores). Per session and
left-out camera: coverage (fraction of the confident detections the method gave
a 3D point for), median and 90th percentile pixel error over those, and the same on the part-
frames every method covers (``common``). Every leave-out must run.

Aggregates over the leave-outs, per method: the median of the common-subset medians (with
10 leave-outs, the mean of the 5th and 6th), and, scale-free, the geometric mean over the
leave-outs of each method's common-subset median relative to rigid's and to interp's (below 1:
lower error on average); ``self`` is also counted per leave-out (below rigid, below interp).
The same two over each method's median over *all* confident detections, for the methods that
cover them all (beyond DLT's coverage: the parts one camera sees, where the body model and the
deformation place them; the common subset cannot show it). Check: in no leave-out is the
default's median over all confident detections 1.5x the rigid model's or more
(``interp_below_max_over_rigid``; the code before stop 55 gave 7.2x on the SLEAP mouse).

    .venv/bin/python benchmarks/real_loco.py [--sessions hand,fly,mouse_sleap] [--no-anipose]
        [--no-kalman] [--no-disk] [-o deform.anchors=rays]  # -o: for every tracked method

Last line JSON, also written to runs/benchmarks/real_loco.json.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import cell, start  # noqa: E402
from peers.anipose import run_anipose  # noqa: E402
from peers.anipose import wanted as anipose_wanted  # noqa: E402
from peers.disk import WINDOW, fit_disk, impute  # noqa: E402
from peers.kalman import kalman_smooth  # noqa: E402
from peers.kalman import wanted as kalman_wanted  # noqa: E402
from tracking import compose, emit  # noqa: E402

from adjust.camera import CameraTensors, project_cameras  # noqa: E402
from adjust.io import load_calibration, load_scene, read_points3d, save_calibration  # noqa: E402
from adjust.io.dlc import write_dlc_csv  # noqa: E402
from deformnet.paths import CONF_DIR, shared_dir  # noqa: E402

log = logging.getLogger("benchmarks.real_loco")
ROOT = CONF_DIR.parent
CONFIDENT = 0.9
METHODS = ("dlt", "dlt_kalman", "dlt_disk", "aniposelib", "rigid", "interp", "self")


def sessions() -> dict[str, dict]:
    d = shared_dir() / "data"
    return {
        "hand": {"dir": d / "real-hand-4cam", "detections": "trial_000", "exclude": []},
        "fly": {"dir": d / "real-fly-3cam", "detections": ".", "exclude": []},
        "mouse_sleap": {
            "dir": d / "real-mouse-sleap-4cam",
            "detections": ".",
            "exclude": ["side"],
            "pattern": "*.analysis.h5",
        },
    }


def subset_session(src_cal: Path, det, keep: list[str], frames: int, out: Path) -> Path:
    """A session folder with only the cameras `keep` and the first `frames` frames:
    calibration.toml + detections/<camera>.csv (DeepLabCut CSVs written from the loaded
    detections, whatever their original format; likelihoods below the threshold included)."""
    if out.exists():
        shutil.rmtree(out)
    (out / "detections").mkdir(parents=True)
    cams = [c for c in load_calibration(src_cal) if c.name in keep]
    save_calibration(out / "calibration.toml", cams)
    for name in keep:
        c = det.cameras.index(name)
        write_dlc_csv(
            out / "detections" / f"{name}.csv",
            list(det.parts),
            det.xy[:frames, :, c],
            np.nan_to_num(det.likelihood[:frames, :, c]),
        )
    return out


def _run(app: str, session: Path, out: Path, overrides: list[str]):
    if app == "track":
        from adjust.apps.track import run
    else:
        from adjust.apps.triangulate import run
    cfg = compose(
        app,
        [
            f"input.calibration={session / 'calibration.toml'}",
            f"input.detections={session / 'detections'}",
            f"output.dir={out}",
            "input.camera_check=off",
            *(["progress=false", "threads=1"] if app == "track" else []),
            *overrides,
        ],
    )
    t0 = time.perf_counter()
    run(cfg)
    d = read_points3d(out / "points3d.csv")
    return d["parts"], d["points"], time.perf_counter() - t0


def loco(
    name: str,
    spec: dict,
    work: Path,
    anipose: bool,
    frames: int,
    adapt: str | None,
    kalman: bool = False,
    disk: float | None = None,
    overrides: list[str] | None = None,
) -> dict:
    """All leave-outs of one session; ``adapt``: deformation=self's max_time (None: skip);
    ``kalman``: the Kalman-smoother peer on the DLT points too; ``disk``: the DISK-style peer's
    training seconds (None: skip)."""
    base = spec["dir"]
    cal = base / "calibration.toml"
    cameras, det = load_scene(cal, base / spec["detections"], None, pattern=spec.get("pattern"))
    good = [c for c in det.cameras if c not in spec["exclude"]]
    parts = list(det.parts)
    out: dict = {"cameras": good, "excluded": spec["exclude"], "parts": len(parts), "leave_out": {}}
    for left in good:
        keep = [c for c in good if c != left]
        sess = subset_session(cal, det, keep, frames, work / name / f"without_{left}" / "session")
        ci = det.cameras.index(left)
        cam = CameraTensors.from_cameras([cameras[ci]], dtype=torch.float64)
        target = det.xy[:frames, :, ci]  # (T, K, 2)
        conf = np.isfinite(target).all(-1) & (det.likelihood[:frames, :, ci] >= CONFIDENT)
        preds: dict[str, np.ndarray] = {}
        secs: dict[str, float] = {}
        for m in METHODS:
            mo = work / name / f"without_{left}" / m
            try:
                if m == "dlt":
                    p, X, s = _run("triangulate", sess, mo, [])
                    dlt = (p, X, s)
                elif m == "dlt_kalman":
                    if not kalman or "dlt" not in preds:
                        continue
                    p, X0, s0 = dlt
                    X, ks = kalman_smooth(X0)
                    s = s0 + ks
                elif m == "dlt_disk":
                    if disk is None or "dlt" not in preds:
                        continue
                    p, X0, s0 = dlt
                    t0 = time.perf_counter()
                    model, _ = fit_disk(np.asarray(X0)[None], seconds=disk,
                                        window=min(WINDOW, len(X0)))  # fmt: skip
                    X = impute(model, np.asarray(X0))
                    s = s0 + time.perf_counter() - t0
                elif m == "aniposelib":
                    if not anipose:
                        continue
                    _, dsub = load_scene(sess / "calibration.toml", sess / "detections", None)
                    X, s = run_anipose(
                        sess / "calibration.toml",
                        dsub.cameras,
                        dsub.xy,
                        dsub.likelihood,
                        np.zeros((0, 2), dtype=np.int64),
                        np.zeros((0, 2), dtype=np.int64),
                    )
                    p = list(dsub.parts)
                else:
                    ov = ["body=auto", *(overrides or [])] + {
                        "rigid": ["deformation=rigid"],
                        "interp": [],
                        "self": ["deformation=self", f"adapt.max_time={adapt}"],
                    }[m]
                    if m == "self" and adapt is None:
                        continue
                    p, X, s = _run("track", sess, mo, ov)
            except Exception as exc:  # every leave-out must run: record, do not hide
                log.error("%s without %s: %s failed: %s", name, left, m, exc)
                out["leave_out"].setdefault(left, {})[m] = {"error": str(exc)}
                continue
            idx = [list(p).index(q) for q in parts]
            preds[m] = np.asarray(X)[:, idx]
            secs[m] = s
        res: dict = {}
        errs = {}
        for m, X in preds.items():
            with torch.no_grad():
                uv = project_cameras(torch.as_tensor(np.nan_to_num(X)), cam).numpy()[:, :, 0]
            e = np.linalg.norm(uv - target, axis=-1)
            has = np.isfinite(X).all(-1) & conf
            errs[m] = np.where(has, e, np.nan)
            v = e[has]
            res[m] = {
                "coverage": float(has.sum() / max(conf.sum(), 1)),
                "median_px": float(np.median(v)) if v.size else float("nan"),
                "p90_px": float(np.percentile(v, 90)) if v.size else float("nan"),
                "seconds": round(secs[m], 2),
            }
        common = conf.copy()
        for e in errs.values():
            common &= np.isfinite(e)
        for m, e in errs.items():
            v = e[common]
            res[m]["common_median_px"] = float(np.median(v)) if v.size else float("nan")
            res[m]["common_p90_px"] = float(np.percentile(v, 90)) if v.size else float("nan")
        res["confident_detections"] = int(conf.sum())
        res["common_fraction"] = float(common.sum() / max(conf.sum(), 1))
        out["leave_out"].setdefault(left, {}).update(res)
    return out


#: the most the default's median over a leave-out's confident detections may be over the rigid
#: model's (`checks`)
DEFAULT_OVER_RIGID_MAX = 1.5


def aggregate(results: dict, key: str, complete: bool = False) -> tuple[dict, dict]:
    """Over all leave-outs: each method's median of ``key`` and the geometric mean of its
    ratio to rigid's and interp's (leave-outs where both have it). ``complete``: only the
    methods that cover every confident detection (coverage 1) in every leave-out they ran in
    (DLT's median over what it covers is not comparable)."""
    leave_outs = [res for r in results.values() for res in r["leave_out"].values()]
    partial = {
        m
        for res in leave_outs
        for m in METHODS
        if isinstance(res.get(m), dict) and res[m].get("coverage", 1.0) < 1.0
    }

    def value(res: dict, m: str) -> float:
        r = res.get(m)
        if not isinstance(r, dict) or key not in r or (complete and m in partial):
            return float("nan")
        return float(r[key])

    overall = {}
    for m in METHODS:
        vals = [v for v in (value(res, m) for res in leave_outs) if math.isfinite(v)]
        if vals:
            overall[m] = float(np.median(vals))
    geo = {}
    for ref in ("rigid", "interp"):
        for m in METHODS:
            logs = [
                math.log(value(res, m) / value(res, ref))
                for res in leave_outs
                if math.isfinite(value(res, m)) and math.isfinite(value(res, ref))
            ]
            if logs and m != ref:
                geo[f"{m}_over_{ref}"] = float(math.exp(np.mean(logs)))
    return overall, geo


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", default="hand,fly,mouse_sleap")
    ap.add_argument("--no-anipose", action="store_true")
    ap.add_argument("--no-kalman", action="store_true", help="skip the Kalman-smoother peer")
    ap.add_argument("--no-disk", action="store_true", help="skip the DISK-style peer")
    ap.add_argument("--frames", type=int, default=200, help="first N frames of each session")
    ap.add_argument("--adapt-seconds", type=int, default=30, help="deformation=self budget")
    ap.add_argument("--no-self", action="store_true")
    ap.add_argument("-o", "--override", action="append", default=[],
                    help="an adjust-track setting of every tracked method")  # fmt: skip
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "real_loco"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "real_loco.json"))
    ap.set_defaults(threads=1)  # one torch thread (`start`)
    args = start(ap, argv)
    anipose = anipose_wanted(args.no_anipose)
    kalman = kalman_wanted(args.no_kalman)
    work = Path(args.work)
    results = {}
    all_specs = sessions()
    for name in args.sessions.split(","):
        adapt = (
            None
            if args.no_self
            else f"00:00:{args.adapt_seconds // 60:02d}:" + (f"{args.adapt_seconds % 60:02d}")
        )
        disk = None if args.no_disk else float(args.adapt_seconds)
        results[name] = loco(
            name, all_specs[name], work, anipose, args.frames, adapt, kalman, disk, args.override
        )
    cols = ["coverage", "median_px", "p90_px", "common_median_px", "common_p90_px", "seconds"]
    failures = 0
    for name, r in results.items():
        print(f"\n{name}: cameras {r['cameras']} (excluded {r['excluded']}), {r['parts']} parts")
        print(f"{'left out':<12}{'method':<12}" + "".join(f"{c:>18}" for c in cols))
        for left, res in r["leave_out"].items():
            for m in METHODS:
                if m not in res:
                    continue
                if "error" in res[m]:
                    failures += 1
                    print(f"{left:<12}{m:<12}FAILED: {res[m]['error']}")
                    continue
                print(f"{left:<12}{m:<12}" + "".join(f"{cell(res[m].get(c), 2):>18}" for c in cols))
    # medians over all leave-outs of each method's common-subset median (every method on the
    # part-frames DLT covers too), and of its median over all confident detections (the methods
    # that cover them all: beyond DLT's coverage, where the parts one camera sees are placed)
    overall, geo = aggregate(results, "common_median_px")
    print(
        "\nmedian over leave-outs of the common-subset median error (px): "
        + ", ".join(f"{m} {v:.2f}" for m, v in overall.items())
    )
    print(
        "geometric mean over leave-outs of the common-subset median ratio: "
        + ", ".join(f"{k} {v:.3f}" for k, v in geo.items())
    )
    overall_all, geo_all = aggregate(results, "median_px", complete=True)
    print(
        "median over leave-outs of the median error over all confident detections (px; methods "
        "that cover them all): " + ", ".join(f"{m} {v:.2f}" for m, v in overall_all.items())
    )
    print(
        "geometric mean over leave-outs of that median's ratio: "
        + ", ".join(f"{k} {v:.3f}" for k, v in geo_all.items())
    )
    checks = {}
    # the default against the rigid model it starts from, over every confident detection: no
    # leave-out where it is far worse (stop 50's start made the 2-camera SLEAP mouse's 7x)
    worst = max(
        (
            res["interp"]["median_px"] / res["rigid"]["median_px"]
            for r in results.values()
            for res in r["leave_out"].values()
            if all(
                isinstance(res.get(m), dict) and "median_px" in res[m] for m in ("interp", "rigid")
            )
        ),
        default=float("nan"),
    )
    checks["interp_worst_leave_out_over_rigid"] = round(worst, 3)
    checks["interp_below_max_over_rigid"] = bool(worst < DEFAULT_OVER_RIGID_MAX)
    if "self" in overall:
        checks["self_below_rigid"] = bool(overall["self"] < overall["rigid"])
        checks["self_below_interp"] = bool(overall["self"] < overall["interp"])
        # per leave-out: how often self's common-subset median is below rigid's and interp's
        wins = [
            (res["self"]["common_median_px"] < res["rigid"]["common_median_px"])
            + (res["self"]["common_median_px"] < res["interp"]["common_median_px"])
            for r in results.values()
            for res in r["leave_out"].values()
            if all(m in res and "common_median_px" in res[m] for m in ("self", "rigid", "interp"))
        ]
        checks["self_wins_per_leave_out_of_2"] = wins
        checks["self_geomean_below_rigid"] = bool(geo.get("self_over_rigid", 9.0) < 1.0)
        checks["self_geomean_below_interp"] = bool(geo.get("self_over_interp", 9.0) < 1.0)
    print("checks: " + ", ".join(f"{k}={v}" for k, v in checks.items()))
    summary = {
        **results,
        "overall_common_median_px": overall,
        "geomean_common_median_ratio": geo,
        "overall_all_median_px": overall_all,
        "geomean_all_median_ratio": geo_all,
        "checks": checks,
        "failures": failures,
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    return emit(summary, args.out)


if __name__ == "__main__":
    main()
