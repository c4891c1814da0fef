"""The real SLEAP mouse against the peer's own output: sleap-anipose's stored 3D points.

`shared/data/real-mouse-sleap-4cam/sleap_anipose_points3d.h5` holds what sleap-anipose (SLEAP's
triangulation pipeline: aniposelib's `triangulate_optim` on every camera, no score threshold,
`scale_smooth=4`, `scale_length=2`, `reproj_error_threshold=15`, `n_deriv_smooth=1`)
triangulated from these very files, with all four cameras, `side` included, whose pose in the
calibration is a copy of `top`'s. A lab using sleap-anipose has these points. Side by side, in
one run, on the 120 frames of the session:

- ``sleap_anipose``: the stored points, as the peer wrote them;
- ``aniposelib_4``: aniposelib with sleap-anipose's settings on the four cameras (our harness,
  `peers/anipose.py`; it should reproduce the stored points: their RMS difference is printed);
- ``aniposelib_3``: the same on the three good cameras (what the peer gives once a user knows
  to drop `side`);
- ``ours``: `adjust-track body=auto input.likelihood_threshold=0` on the four files, the
  README's command: its camera check finds `side` and leaves it out by itself.

Each is projected into each camera and compared with that camera's detections (every present
detection: these are human-proofread predictions), per camera: median and 90th percentile
pixel error. These are in-sample errors (every method used the camera it is scored in), so the
leave-one-camera-out errors follow: for each good camera, ``aniposelib_2`` and ``ours_2``
track from the other two good cameras and are scored in the left-out one (the peer given the
good cameras, as `benchmarks/real_loco.py` does with anipose's own settings).

    .venv/bin/python benchmarks/real_sleap_peer.py [--no-anipose]

Last line JSON, also written to runs/benchmarks/real_sleap_peer.json. aniposelib runs in its own
environment (`make bench-env`); without it only the stored points and ours are compared.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, start  # noqa: E402
from peers.anipose import run_anipose  # noqa: E402
from peers.anipose import wanted as anipose_wanted  # noqa: E402
from real_loco import subset_session  # noqa: E402

from adjust.camera import CameraTensors, project_cameras  # noqa: E402
from adjust.io import load_scene, read_points3d  # noqa: E402
from deformnet.confutil import compose  # noqa: E402
from deformnet.paths import CONF_DIR, shared_dir  # noqa: E402

log = logging.getLogger("benchmarks.real_sleap_peer")
ROOT = CONF_DIR.parent
BAD = "side"  # the camera whose calibrated pose is a copy of top's
#: sleap-anipose's `triangulate` defaults (its click options), on every detection (no scores)
SLEAP_ANIPOSE = {
    "score_threshold": 0.0,
    "scale_smooth": 4.0,
    "scale_length": 2.0,
    "scale_length_weak": 0.5,
    "reproj_error_threshold": 15.0,
    "n_deriv_smooth": 1,
}


def track(calibration: Path, detections: Path, out: Path, pattern: str | None = None):
    """`adjust-track body=auto` (the README's SLEAP command) -> (parts, points (T, K, 3),
    seconds, summary)."""
    from adjust.apps.track import run

    over = [
        f"input.calibration={calibration}",
        f"input.detections={detections}",
        f"output.dir={out}",
        "body=auto",
        "input.likelihood_threshold=0",
        "progress=false",
        "threads=1",
    ] + ([f"input.pattern='{pattern}'"] if pattern else [])
    t0 = time.perf_counter()
    summary = run(compose("track", over))
    d = read_points3d(out / "points3d.csv")
    return list(d["parts"]), d["points"], time.perf_counter() - t0, summary


def scores(X: np.ndarray, camera, target: np.ndarray) -> dict:
    """Pixel errors of points X (T, K, 3) projected into `camera` against target (T, K, 2)."""
    cam = CameraTensors.from_cameras([camera], dtype=torch.float64)
    with torch.no_grad():
        uv = project_cameras(torch.as_tensor(np.nan_to_num(X)), cam).numpy()[:, :, 0]
    e = np.linalg.norm(uv - target, axis=-1)
    has = np.isfinite(target).all(-1)
    v = e[has & np.isfinite(X).all(-1)]
    return {
        "coverage": float(v.size / max(has.sum(), 1)),
        "median_px": float(np.median(v)) if v.size else float("nan"),
        "p90_px": float(np.percentile(v, 90)) if v.size else float("nan"),
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-anipose", action="store_true")
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "real_sleap_peer"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "real_sleap_peer.json"))
    ap.add_argument("--threads", type=int, default=1, help="torch threads (0: torch's default)")
    args = start(ap, argv)
    anipose = anipose_wanted(args.no_anipose)
    work = Path(args.work)
    base = shared_dir() / "data" / "real-mouse-sleap-4cam"
    cal = base / "calibration.toml"
    cameras, det = load_scene(cal, base, None, 0.0, pattern="*.analysis.h5")
    parts, names = list(det.parts), list(det.cameras)
    good = [c for c in names if c != BAD]
    by_name = dict(zip(names, cameras, strict=True))
    with h5py.File(base / "sleap_anipose_points3d.h5", "r") as f:
        stored = np.asarray(f["tracks"][:, 0], dtype=np.float64)  # (T, K, 3), the file's nodes
    if stored.shape != (det.xy.shape[0], len(parts), 3):
        raise ValueError(f"stored points {stored.shape} do not fit {det.xy.shape[0]} frames x "
                         f"{len(parts)} parts")  # fmt: skip

    def peer(cams: list[str]) -> tuple[np.ndarray, float]:
        idx = [names.index(c) for c in cams]
        return run_anipose(
            cal,
            cams,
            det.xy[:, :, idx],
            np.ones(det.xy.shape[:2] + (len(idx),)),
            np.zeros((0, 2), dtype=np.int64),
            np.zeros((0, 2), dtype=np.int64),
            settings=SLEAP_ANIPOSE,
        )

    points: dict[str, np.ndarray] = {"sleap_anipose": stored}
    secs: dict[str, float] = {}
    if anipose:
        points["aniposelib_4"], secs["aniposelib_4"] = peer(names)
        points["aniposelib_3"], secs["aniposelib_3"] = peer(good)
    p, X, secs["ours"], summary = track(cal, base, work / "ours", "*.analysis.h5")
    points["ours"] = X[:, [p.index(q) for q in parts]]
    excluded = sorted(summary.get("camera_check", {}).get("excluded", {}))
    in_sample = {
        m: {c: scores(X, by_name[c], det.xy[:, :, names.index(c)]) for c in names}
        for m, X in points.items()
    }
    loco: dict[str, dict] = {}
    for left in good:
        keep = [c for c in good if c != left]
        sess = subset_session(cal, det, keep, det.xy.shape[0], work / f"without_{left}" / "session")
        target = det.xy[:, :, names.index(left)]
        res = {}
        if anipose:
            Xa, _ = peer(keep)
            res["aniposelib_2"] = scores(Xa, by_name[left], target)
        p, X, _, _ = track(
            sess / "calibration.toml", sess / "detections", work / f"without_{left}" / "ours"
        )
        res["ours_2"] = scores(X[:, [p.index(q) for q in parts]], by_name[left], target)
        loco[left] = res
    harness = None
    if "aniposelib_4" in points:
        d = points["aniposelib_4"] - stored
        harness = float(np.sqrt(np.nanmean(np.sum(d**2, -1))))

    def fmt(v: float) -> str:
        return "n/a" if not math.isfinite(v) else f"{v:.2f}"

    print(f"\nreal SLEAP mouse, {det.xy.shape[0]} frames x {len(parts)} parts; ours excluded "
          f"{excluded} by itself")  # fmt: skip
    if harness is not None:
        print(f"aniposelib (our harness, sleap-anipose's settings, 4 cameras) vs the stored "
              f"points: RMS {harness:.2f} mm (the stored points do not come from this "
              f"calibration's four cameras alone)")  # fmt: skip
    print("\nin-sample (every method used the camera it is scored in): median / p90 px")
    print(f"{'method':<16}" + "".join(f"{c:>18}" for c in names))
    for m, r in in_sample.items():
        cells = [f"{fmt(r[c]['median_px'])} / {fmt(r[c]['p90_px'])}" for c in names]
        print(f"{m:<16}" + "".join(f"{s:>18}" for s in cells))
    print("\nleave one good camera out (tracked from the other two): median / p90 px")
    for left, r in loco.items():
        cells = [f"{m} {fmt(v['median_px'])} / {fmt(v['p90_px'])}" for m, v in r.items()]
        print(f"{left:<8}" + "   ".join(cells))

    def geomean(pairs) -> float:
        """exp(mean(log(a / b))) over (a, b) median-error pairs: below 1, a is lower."""
        return float(math.exp(np.mean([math.log(a / b) for a, b in pairs])))

    med = {m: {c: r[c]["median_px"] for c in good} for m, r in in_sample.items()}
    ratios = {f"ours_over_{m}": geomean((med["ours"][c], med[m][c]) for c in good)
              for m in med if m != "ours"}  # fmt: skip
    loco_med = {c: {m: v["median_px"] for m, v in r.items()} for c, r in loco.items()}
    if anipose:
        ratios["ours_2_over_aniposelib_2"] = geomean(
            (r["ours_2"], r["aniposelib_2"]) for r in loco_med.values()
        )
    # the left-out camera's error against the stored points' in-sample error in it
    ratios["ours_2_over_sleap_anipose"] = geomean(
        (loco_med[c]["ours_2"], med["sleap_anipose"][c]) for c in good
    )
    print(
        "\ngeometric mean over the good cameras of the median error ratio: "
        + ", ".join(f"{k} {v:.3f}" for k, v in ratios.items())
    )
    return emit(
        {
            "frames": int(det.xy.shape[0]),
            "parts": len(parts),
            "cameras": names,
            "good_cameras": good,
            "ours_excluded": excluded,
            "harness_rms_mm": harness,
            "seconds": {k: round(v, 2) for k, v in secs.items()},
            "in_sample": in_sample,
            "leave_one_out": loco,
            "ratios": ratios,
        },
        args.out,
    )


if __name__ == "__main__":
    main()
