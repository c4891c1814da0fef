"""Real-motion benchmark: a real mouse's 3D motion filmed by simulated rigs, trackers vs. truth.

The data (``shared/data/real-mouse-motion-3d/poses3d.csv``, ``--data``): 3600 frames of a
freely moving mouse, 34 keypoints, real motion and real body deformation (bone lengths vary by
5-30%). `adjust.scene.motion` films it: a rig of 2, 3 or 4 cameras placed around the floor the
paws define (`floor_frame`, `motion_rig`: side + front; + top; + back), the scene detector model
(self-occlusion by body proxies fitted to the animal, dropout bursts, left/right swaps, far
outliers, likelihoods) with a detector seed; the scene folder (calibration.toml, one DeepLabCut
CSV per camera, truth.npz) is what a user has (`adjust.scene.write_scene`).

Split, fixed here before any choice was made: the **validation** segment is frames 1200-2199
(``--split val``: settings may be chosen on it), the **test** segment frames 2400-3399
(``--split test``, the default for reporting: the last third of the recording, which no net
may train on). ``--frames N`` (<= 1000) crops the segment from its start. ``--stride N`` films
every Nth frame of the segment (a camera at 1/N of the recording's frame rate; the median step
of a part per frame grows from 0.34 mm to about N times that): ``--frames`` is then at most
1000 / N (default: that), so the scenes stay inside their segment.

Scenes (cached under ``--work``, keyed by all their settings): every camera count of
``--cameras`` with the paper's 8 parts (renamed to the default mouse's names), plus the 22-part
set (`MOTION_PARTS22`) and all 34 parts at 3 cameras (``--parts 8,22,34``; at other rigs with
``--many-parts-cameras 2,3``), for each detector
seed of ``--seeds``. Methods (``--methods``; default dlt,aniposelib,default,rigid):

- ``dlt``: `adjust-triangulate` (likelihood-weighted linear triangulation, >= 2 views;
  ``body=mouse`` for the 8 parts, the files' own parts otherwise);
- ``aniposelib``: aniposelib's `triangulate_optim` with anipose's settings (`peers/anipose.py`,
  its own environment): 8 parts with the head triangle strong and the trunk weak as elsewhere;
  22 / 34 parts with the edges of ``skeleton.csv`` among the chosen parts, those between head
  parts (Nose, Ear_L, Ear_R, Head, Eye_L, Eye_R) strong, the others weak, plus the head triangle
  Nose / Ear_L / Ear_R strong (the 22-part set has no skeleton edge among its head parts);
- ``default``: `adjust-track` with its defaults (no override);
- ``rigid``: `adjust-track deformation=rigid`;
- ``self``: `adjust-track deformation=self` (``adapt.max_time`` = ``--adapt-minutes``; the
  fine-tuning time is reported apart as ``adapt_s``);
- ``net``: `adjust-track deformation=default` (the shipped net, not adapted).

A method that raises records its error in its row; the benchmark goes on.

Metrics per row (`adjust.metrics.point_errors` against truth.npz; occluded = seen by < 2
cameras): RMSE (mm) all / seen >= 2 / occluded, fraction within 5 mm (a missing point is a
miss), completeness, seconds; the ratio of each RMSE to aniposelib's in the same scene; for
adjust-track rows the calibration ratios rms error / rms ``{part}_sigma`` on seen and occluded
part-frames, ``converged``, the body scale, the median reprojection error, whether the net was
used (``adapt_used`` for self, ``net_parts`` for net / default's net check) and ``diverged``
(non-finite or incomplete points, RMSE all > 50 mm or median reprojection error > 10 px).
Tables: per (cameras, parts) the mean over seeds (RMSE all's min-max beside it), and the
defaults' calibration ratios part by part (seen >= 2 / occluded / unseen by any camera;
``calib_per_part``; how many parts are within range in the checks, not a target).

Targets (``default`` against aniposelib, ratios of the seed means): RMSE all and occluded
<= 0.6x at 2 and 3 cameras and <= 0.8x at 4 (8 parts), <= 0.8x with 22 and 34 parts; seen >= 2
<= 0.5x everywhere; no adjust-track run diverges; calibration ratios of ``default`` within
0.8-1.25. Stability (``--no-stability`` skips it; the 3- and 2-camera 8-part scenes, seed 0):
``default`` re-run with ``body_fit.scale_factor`` x0.95 / x0.99 / x1.01 / x1.05, with 1% of the
accepted detections of every camera dropped (likelihood 0, fixed seed), and on another detector
seed (100) of the same frames; target: spread (max - min) / median of RMSE all < 10%.
Beside each perturbation: the share of frames whose body orientation is more than 0.2 rad from
the base run's (a pose in another basin); and aniposelib on the two detector seeds (its RMSE's
change between them, the part of a seed's change that is the data's).

    .venv/bin/python benchmarks/real_motion.py [--split test] [--frames 1000] [--stride 1] \\
        [--cameras 2,3,4] [--parts 8,22,34] [--many-parts-cameras 3] [--seeds 0,1] \\
        [--methods dlt,aniposelib,default,rigid[,self,net]] [--adapt-minutes 3] \\
        [--no-stability] [--no-peer-stability] [--threads 1] [--data poses3d.csv] \\
        [--work DIR] [--out FILE] [-o deform.max_iterations=20 ...]

Prints the tables; the last line is JSON, also written to runs/benchmarks/real_motion.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, start, subset  # noqa: E402
from domain_gap import evaluate  # noqa: E402
from peers.anipose import (  # noqa: E402
    MOUSE_CONSTRAINTS,
    MOUSE_CONSTRAINTS_WEAK,
    constraint_indices,
    run_anipose,
)
from peers.anipose import wanted as anipose_wanted  # noqa: E402
from tracking import run_track, scene_inputs, view_fractions  # noqa: E402

from adjust.camera import Camera  # noqa: E402
from adjust.io import load_scene, read_dlc, read_points3d, write_dlc_csv  # noqa: E402
from adjust.scene.motion import (  # noqa: E402
    MOTION_FEET,
    film_part_set,
    floor_frame,
    load_motion,
    motion_rig,
    part_set,
    write_motion_scene,
)
from deformnet.atomic import atomic_path  # noqa: E402
from deformnet.body import default_mouse  # noqa: E402
from deformnet.confutil import compose  # noqa: E402
from deformnet.paths import CONF_DIR, real_mouse_motion_dir  # noqa: E402
from deformnet.tables import read_points3d_table  # noqa: E402

log = logging.getLogger("benchmarks.real_motion")

ROOT = CONF_DIR.parent
DATA = real_mouse_motion_dir() / "poses3d.csv"  # $MOUSETRACK_SHARED or ../shared

#: the split, fixed before any choice: segment start frames (1000 frames each)
SPLITS = {"val": 1200, "test": 2400}
SEGMENT_FRAMES = 1000
PART_SETS = (8, 22, 34)
CAMERA_COUNTS = (2, 3, 4)
#: beyond 8 parts, the scenes' camera count (the default grid: 22 and 34 parts at 3 cameras)
MANY_PARTS_CAMERAS = 3
METHODS = ("dlt", "aniposelib", "default", "rigid", "self", "net")
TRACK_METHODS = ("default", "rigid", "self", "net")
HEAD = ("Nose", "Ear_L", "Ear_R", "Head", "Eye_L", "Eye_R")
HEAD_TRIANGLE = [("Nose", "Ear_L"), ("Nose", "Ear_R"), ("Ear_L", "Ear_R")]
ACCEPTED = 0.5  # likelihood threshold of the apps (input.likelihood_threshold)

#: a run diverged: non-finite or incomplete points, or beyond these
DIVERGED_RMSE_MM = 50.0
DIVERGED_REPROJ_PX = 10.0
CALIBRATED = (0.8, 1.25)

#: stability: the scenes (cameras, parts), seed, perturbations
STABILITY_SCENES = ((3, 8), (2, 8))
STABILITY_SEED = 0
SCALE_FACTORS = (0.95, 0.99, 1.01, 1.05)
DROP_FRACTION = 0.01
DROP_SEED = 12_345
OTHER_DETECTOR_SEED = 100
SPREAD_TARGET = 0.10


def target_ratio(cameras: int, parts: int) -> float:
    """The largest ``default`` / aniposelib RMSE (all, occluded) the targets allow."""
    if parts != 8:
        return 0.8
    return 0.6 if cameras <= 3 else 0.8


# --- scenes ---------------------------------------------------------------------------------


class Motion:
    """The recording (`load_motion`) and its floor frame (`floor_frame`, from the paws)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.points, self.parts = load_motion(self.path)
        self.floor = floor_frame(self.points, self.parts, MOTION_FEET)
        st = self.path.stat()
        self.tag = hashlib.sha1(f"{self.path.resolve()}:{st.st_size}".encode()).hexdigest()[:8]


def scene_key(
    split: str, start: int, frames: int, cameras: int, parts: int, seed: int, stride: int = 1
) -> str:
    tail = f"_x{stride}" if stride > 1 else ""
    return f"{split}_{start}-{start + frames * stride}_c{cameras}_p{parts}_s{seed}{tail}"


def input_args(ap: argparse.ArgumentParser, name: str, cameras: str) -> None:
    """The arguments of a benchmark of an input condition over the 8-part scenes (`sync.py`,
    `units.py`, `moves.py`): ``--cameras``, ``--frames``, ``--seeds``, ``--threads``,
    ``--work`` and ``--out`` (under ``runs/benchmarks/NAME``)."""
    ap.add_argument("--cameras", default=cameras, help="camera counts (8 parts)")
    ap.add_argument("--frames", type=int, default=SEGMENT_FRAMES, help="frames (<= 1000)")
    ap.add_argument("--seeds", default="0", help="detector seeds")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (0: torch default)")
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / name))
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / f"{name}.json"))


def input_settings(ap: argparse.ArgumentParser, args) -> tuple[list[int], list[int]]:
    """`input_args`' camera counts and seeds (a bad one is the parser's error)."""
    if not 1 <= args.frames <= SEGMENT_FRAMES:
        ap.error(f"--frames must be within 1..{SEGMENT_FRAMES}, got {args.frames}")
    cameras = [int(c) for c in subset(ap, args.cameras, ("2", "3", "4"), "--cameras")]
    return cameras, [int(s) for s in args.seeds.split(",") if s.strip()]


def input_run(args) -> tuple[Motion, Path, str]:
    """The recording, the work folder of `input_args`' benchmark (below ``--work``, by the
    recording's tag) and adjust-track's ``threads=`` override from ``--threads``."""
    motion = Motion(DATA)
    threads = f"threads={args.threads}" if args.threads else "threads=null"
    return motion, Path(args.work) / motion.tag, threads


def spoil_scene(base: Path, out: Path, edits: dict) -> Path:
    """A copy of scene `base` at `out` (cached: kept if its truth.npz is there) with each camera
    ``c`` of `edits` given new detections, ``edits[c](table)`` -> (xy, likelihood) from its
    `adjust.io.read_dlc` table; the input-condition benchmarks' spoilt scenes. truth.npz is
    copied last (the cache's mark); a cached aniposelib result is not copied."""
    if (out / "truth.npz").exists():
        return out
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(base, out, ignore=shutil.ignore_patterns("truth.npz", "aniposelib.npz"))
    for cam, fn in edits.items():
        t = read_dlc(base / "detections" / f"{cam}.csv")
        xy, likelihood = fn(t)
        write_dlc_csv(out / "detections" / f"{cam}.csv", t.parts, xy, likelihood)
    shutil.copy2(base / "truth.npz", out / "truth.npz")
    return out


#: recording frames beyond those filmed that `refilmed_scene`'s spline is fitted on
PAD = 10


def refilmed_scene(
    base: Path, out: Path, motion: Motion, camera: str, times: np.ndarray, around: np.ndarray,
    ncams: int, seed: int,
) -> Path:  # fmt: skip
    """A copy of scene `base` (`film_scene`'s, 8 parts) whose `camera`'s file is filmed at
    the recording's (fractional) frames `times` instead: the whole rig filmed from the
    recording through a cubic spline fitted on `around`'s frames and `PAD` beyond (times
    clipped to them), that camera's file kept (a camera late, or on its own clock: the
    subframe and clocks benchmarks). Cached: kept if truth.npz is there (copied last)."""
    if (out / "truth.npz").exists():
        return out
    if out.exists():
        shutil.rmtree(out)
    lo = max(int(np.min(around)) - PAD, 0)
    hi = min(int(np.max(around)) + PAD + 1, len(motion.points))
    spline = CubicSpline(np.arange(lo, hi), motion.points[lo:hi], axis=0)
    tmp = out.with_name(out.name + ".rig")
    if tmp.exists():
        shutil.rmtree(tmp)
    X = spline(np.clip(times, lo, hi - 1))
    film_part_set(tmp, X, motion.parts, motion.floor, ncams, 8, seed=seed)
    shutil.copytree(base, out, ignore=shutil.ignore_patterns("truth.npz", "aniposelib.npz"))
    shutil.copy2(tmp / "detections" / f"{camera}.csv", out / "detections" / f"{camera}.csv")
    shutil.rmtree(tmp)
    shutil.copy2(base / "truth.npz", out / "truth.npz")  # last: the cache's mark
    return out


def film_scene(
    out: Path,
    motion: Motion,
    start: int,
    frames: int,
    cameras: int,
    parts: int,
    seed: int,
    stride: int = 1,
) -> Path:
    """Film `frames` frames from `start`, every `stride`-th, with a `cameras` rig (detector seed
    `seed`), keep the `parts`-part set and write the scene folder `out` (cached: kept if
    truth.npz is there)."""
    if (out / "truth.npz").exists():
        return out
    t0 = time.perf_counter()
    X = motion.points[start : start + frames * stride : stride]
    film_part_set(out, X, motion.parts, motion.floor, cameras, parts, seed=seed)
    log.info(
        "scene %s: %d frames, %d cameras, %d parts, seed %d (%.1f s)",
        out.name,
        frames,
        cameras,
        parts,
        seed,
        time.perf_counter() - t0,
    )
    return out


def lens_rig(
    floor, ncams: int, distance: float, focal: float, dist, fisheye: bool = False
) -> list[Camera]:
    """`motion_rig` moved to `distance` mm with lenses of `focal` px and coefficients `dist`
    (OpenCV's five, or a fisheye's k1-k4 with `fisheye`): the lens benchmarks' rigs."""
    d = np.zeros(5)
    d[: len(dist)] = dist
    out = []
    for cam in motion_rig(floor, ncams, distance_mm=distance):
        K = cam.K.copy()
        K[0, 0] = K[1, 1] = focal
        out.append(dataclasses.replace(cam, K=K, dist=d.copy(), fisheye=fisheye))
    return out


def lens_args(ap: argparse.ArgumentParser, name: str, distance: float, focal: float) -> None:
    """`input_args` and the lens benchmarks' ``--split``, ``--distance`` (mm), ``--focal`` (px)
    and ``--no-peer``."""
    input_args(ap, name, "2,3,4")
    ap.add_argument("--split", default="test", choices=tuple(SPLITS), help="the segment")
    ap.add_argument("--distance", type=float, default=distance, help="cameras' distance (mm)")
    ap.add_argument("--focal", type=float, default=focal, help="focal length (px)")
    ap.add_argument("--no-peer", action="store_true", help="without aniposelib")


def lens_scene(
    work: Path, motion: Motion, split: str, frames: int, ncams: int, seed: int,
    distance: float, focal: float, dist, fisheye: bool = False,
) -> tuple[str, Path, list[Camera]]:  # fmt: skip
    """The 8-part scene of `split`'s first `frames` frames filmed through `lens_rig` (cached
    under ``work/scenes``: kept if its truth.npz is there): (its key, its folder, the rig)."""
    start = SPLITS[split]
    tag = "_".join(f"{v:g}" for v in dist)
    key = f"{split}_{start}-{start + frames}_c{ncams}_s{seed}_d{distance:g}_f{focal:g}_k{tag}"
    scene = work / "scenes" / key
    rig = lens_rig(motion.floor, ncams, distance, focal, dist, fisheye)
    if not (scene / "truth.npz").exists():
        if scene.exists():
            shutil.rmtree(scene)
        src, names = part_set(8, motion.parts)
        X = motion.points[start : start + frames]
        write_motion_scene(scene, X, motion.parts, rig, src, dict(zip(src, names)), seed=seed)
    return key, scene, rig


def drop_detections(src: Path, out: Path, fraction: float, seed: int) -> Path:
    """A copy of scene `src` at `out` with the likelihood of a random `fraction` of each
    camera's accepted (>= 0.5) detections set to 0 (cached: kept if truth.npz is there)."""
    if (out / "truth.npz").exists():
        return out
    if out.exists():
        shutil.rmtree(out)
    (out / "detections").mkdir(parents=True)
    shutil.copy2(src / "calibration.toml", out / "calibration.toml")
    rng = np.random.default_rng(seed)
    for f in sorted((src / "detections").glob("*.csv")):
        df = pd.read_csv(f, header=[0, 1, 2], index_col=0)
        cols = [c for c in df.columns if c[2] == "likelihood"]
        lik = df[cols].to_numpy(np.float64)
        rows, ks = np.nonzero(lik >= ACCEPTED)
        n = int(round(fraction * rows.size))
        pick = rng.choice(rows.size, size=n, replace=False)
        lik[rows[pick], ks[pick]] = 0.0
        df[cols] = lik
        df.to_csv(out / "detections" / f.name)
    shutil.copy2(src / "truth.npz", out / "truth.npz")  # last: the cache's mark
    return out


# --- methods --------------------------------------------------------------------------------


def align(est: np.ndarray, parts, truth_parts) -> np.ndarray:
    """est (T, K', 3) of `parts` reordered to `truth_parts`; a ValueError names missing ones."""
    parts = [str(p) for p in parts]
    missing = [p for p in truth_parts if p not in parts]
    if missing:
        raise ValueError(f"output lacks the parts {missing}")
    return est[:, [parts.index(p) for p in truth_parts]]


#: part-frames a per-part calibration ratio needs (fewer: NaN)
MIN_CALIB_FRAMES = 20


def _ratio(err: np.ndarray, sig: np.ndarray, m: np.ndarray, min_count: int = 1) -> float:
    """rms err / rms sig over the finite entries of mask m (NaN below ``min_count``)."""
    ok = m & np.isfinite(err) & np.isfinite(sig)
    if ok.sum() < min_count:
        return float("nan")
    return float(np.sqrt(np.mean(err[ok] ** 2)) / np.sqrt(np.mean(sig[ok] ** 2)))


def calibration(points_csv: Path, est, truth, nviews, parts) -> dict:
    """rms error / rms ``{part}_sigma`` on seen (>= 2 cameras) and occluded part-frames, pooled
    (``calib_seen``, ``calib_occluded``) and per part (``calib_per_part``: part -> seen,
    occluded, unseen (no camera), NaN with fewer than `MIN_CALIB_FRAMES` part-frames)."""
    extra = read_points3d(points_csv)["extra"]  # the sigmas: in the sidecar
    sig = np.stack([np.asarray(extra[f"{p}_sigma"], float) for p in parts], 1)
    err = np.linalg.norm(est - truth, axis=-1)
    masks = {"seen": nviews >= 2, "occluded": nviews < 2, "unseen": nviews == 0}
    res = {f"calib_{n}": _ratio(err, sig, masks[n]) for n in ("seen", "occluded")}
    res["calib_per_part"] = {
        p: {n: _ratio(err[:, k], sig[:, k], m[:, k], MIN_CALIB_FRAMES) for n, m in masks.items()}
        for k, p in enumerate(parts)
    }
    return res


def run_dlt(scene: Path, out: Path, mouse: bool) -> tuple[np.ndarray, tuple, float]:
    """`adjust-triangulate` on the scene (``body=mouse`` if `mouse`, else the files' parts)."""
    from adjust.apps.triangulate import run

    t0 = time.perf_counter()
    run(compose("triangulate", [*scene_inputs(scene), f"output.dir={out}",
                                *(["body=mouse"] if mouse else [])]))  # fmt: skip
    pts = read_points3d(out / "points3d.csv")
    return pts["points"], pts["parts"], time.perf_counter() - t0


def skeleton_constraints(skeleton: Path, parts) -> tuple[list, list]:
    """aniposelib's length constraints for the recording's parts: skeleton.csv's edges among
    `parts` (strong between head parts, weak otherwise) plus the head triangle, strong."""
    strong = [e for e in HEAD_TRIANGLE if e[0] in parts and e[1] in parts]
    weak = []
    if skeleton.is_file():
        for a, b in pd.read_csv(skeleton)[["part_a", "part_b"]].itertuples(index=False):
            if a in parts and b in parts:
                e = (a, b)
                if a in HEAD and b in HEAD:
                    if e not in strong and (b, a) not in strong:
                        strong.append(e)
                else:
                    weak.append(e)
    else:
        log.warning("%s not found: aniposelib gets the head triangle only", skeleton)
    return strong, weak


def run_aniposelib(scene: Path, nparts: int, skeleton: Path) -> tuple[np.ndarray, tuple, float]:
    """aniposelib's points for a scene (cached beside it: aniposelib.npz) and its seconds."""
    body = default_mouse() if nparts == 8 else None
    _, det = load_scene(scene / "calibration.toml", scene / "detections", body)
    parts = [str(p) for p in det.parts]
    if nparts == 8:
        strong, weak = MOUSE_CONSTRAINTS, MOUSE_CONSTRAINTS_WEAK
    else:
        strong, weak = skeleton_constraints(skeleton, parts)
    cache = scene / "aniposelib.npz"  # the peer's result depends on the scene alone
    if cache.exists():
        z = np.load(cache)
        return z["points"], tuple(parts), float(z["seconds"])
    pts, secs = run_anipose(
        scene / "calibration.toml",
        det.cameras,
        det.xy,
        det.likelihood,
        constraint_indices(parts, strong),
        constraint_indices(parts, weak),
    )
    with atomic_path(cache) as tmp:
        np.savez(tmp, points=pts, seconds=secs)
    return pts, tuple(parts), secs


def common_overrides(args) -> list[str]:
    """The adjust-track settings of every tracker run of the tables: its threads and ``-o``."""
    return [f"threads={args.threads}" if args.threads else "threads=null", *args.override]


def track_overrides(method: str, adapt_minutes: float) -> list[str]:
    if method == "default":
        return []
    if method == "rigid":
        return ["deformation=rigid"]
    if method == "net":
        return ["deformation=default"]
    if method == "self":
        return ["deformation=self", f"adapt.max_time={_hms(adapt_minutes)}"]
    raise ValueError(f"not an adjust-track method: {method}")


def _hms(minutes: float) -> str:
    secs = int(round(60 * minutes))
    return f"00:{secs // 3600:02d}:{secs % 3600 // 60:02d}:{secs % 60:02d}"


def track_row(scene: Path, out: Path, overrides: list[str], truth, nviews, truth_parts) -> dict:
    """`adjust-track` on the scene with `overrides`, evaluated."""
    est, secs, summ = run_track(scene, out, overrides)
    est = align(est, summ["parts"], truth_parts)
    row = {**evaluate(est, truth, nviews), "seconds": round(secs, 2)}
    row.update(calibration(out / "points3d.csv", est, truth, nviews, truth_parts))
    t = summ.get("time_s", {})
    if "adapt_s" in t:
        row["adapt_s"] = t["adapt_s"]
        row["seconds"] = round(secs - t["adapt_s"], 2)  # the tracking alone
    reproj = summ.get("reprojection_error_px") or {}
    row.update(
        converged=bool(summ.get("converged")),
        iterations=summ.get("iterations"),
        body_scale=body_scale(summ.get("body") or {}),
        scale_factor=(summ.get("body") or {}).get("scale_factor"),
        reproj_median_px=reproj.get("median"),
        deformation=(summ.get("deformation") or {}).get("mode"),
    )
    d = summ.get("deformation") or {}
    if "adapt" in d:  # deformation=self: whether the fine-tuned net was used
        row["adapt_used"] = (d["adapt"] or {}).get("used")
    if "heldout" in d:  # a net not trained here: the parts it is used for
        row["net_parts"] = (d["heldout"] or {}).get("net_parts")
    row["diverged"] = diverged(row)
    return row


def checked_row(scene: Path, out: Path, overrides: list[str]) -> tuple[dict, dict]:
    """`track_row` of an 8-part scene against its own truth.npz, and its run's camera check
    (``summary.json`` ``camera_check``): the input-condition benchmarks' run (`moves.py`,
    `subframe.py`, `fisheye.py`)."""
    tr = np.load(scene / "truth.npz")
    parts = [str(p) for p in tr["parts"]]
    row = track_row(scene, out, overrides, tr["points"], tr["nviews"], parts)
    summary = json.loads((out / "summary.json").read_text())
    return row, summary.get("camera_check") or {}


def checked_or_refused(scene: Path, out: Path, overrides: list[str]) -> tuple[dict, dict]:
    """`checked_row`, or NaN scores and the reason where adjust-track refuses the scene (its
    tracks cannot be trusted: a non-zero exit, not a wrong result)."""
    try:
        return checked_row(scene, out, overrides)
    except Exception as exc:  # noqa: BLE001 - recorded in the row
        why = f"{type(exc).__name__}: {str(exc).splitlines()[0][:300]}"
        log.warning("%s refused: %s", scene.name, why)
        return {"rmse_all": float("nan"), "rmse_seen2": float("nan"), "refused": why}, {}


def peer_row(scene: Path, nparts: int = 8, truth_frames: bool = False) -> dict:
    """aniposelib on a scene of `nparts` parts (`run_aniposelib`, cached), evaluated on its
    truth.npz; `truth_frames`: on the truth's frames only (a camera's file longer than the
    others' makes the session longer; its frames beyond the truth's are not scored)."""
    tr = np.load(scene / "truth.npz")
    est, eparts, _ = run_aniposelib(scene, nparts, DATA.parent / "skeleton.csv")
    est = align(est, eparts, [str(p) for p in tr["parts"]])
    return evaluate(est[: len(tr["points"])] if truth_frames else est, tr["points"], tr["nviews"])


def frames_row(scene: Path, out: Path, overrides: list[str]) -> tuple[dict, dict]:
    """adjust-track on an 8-part scene whose files may make the session longer than its
    truth (a camera at another frame rate, unchecked): RMSE on the truth's frames, the frames
    it wrote (``frames_out``), and its run's camera check."""
    tr = np.load(scene / "truth.npz")
    est, _, summ = run_track(scene, out, overrides)
    est = align(est, summ["parts"], [str(p) for p in tr["parts"]])
    T = len(tr["points"])
    row = {**evaluate(est[:T], tr["points"], tr["nviews"]), "frames_out": len(est)}
    return row, summ.get("camera_check") or {}


def body_scale(body: dict):
    """The body model's size against the default mouse's: ``scale`` (body.shape=table), else
    the similarity scale of its frame's alignment to the mouse (body.shape=data); None."""
    s = body.get("scale")
    return s if s is not None else (body.get("frame") or {}).get("scale")


def diverged(row: dict) -> bool:
    """Non-finite or incomplete points, RMSE all > 50 mm or median reprojection > 10 px."""
    rmse, rep = row.get("rmse_all"), row.get("reproj_median_px")
    return bool(
        rmse is None
        or not math.isfinite(rmse)
        or rmse > DIVERGED_RMSE_MM
        or row.get("completeness", 0.0) < 1.0
        or (rep is not None and (not math.isfinite(rep) or rep > DIVERGED_REPROJ_PX))
    )


def guarded(label: str, fn) -> dict:
    """fn()'s row, or {"error": ...} if it raises: one row never stops the benchmark."""
    try:
        return fn()
    except Exception as exc:  # noqa: BLE001 - recorded in the row
        msg = f"{type(exc).__name__}: {exc}".strip()
        log.warning("%s failed: %s", label, msg.splitlines()[0] if msg else type(exc).__name__)
        return {"error": msg[:2000]}


def run_scene(
    scene: Path, runs: Path, nparts: int, methods: list[str], args, skeleton: Path
) -> dict[str, dict]:
    """Every method's row on one scene."""
    tr = np.load(scene / "truth.npz")
    truth, nviews = tr["points"], tr["nviews"]
    parts = [str(p) for p in tr["parts"]]
    common = common_overrides(args)
    rows: dict[str, dict] = {}
    for m in methods:
        label = f"{scene.name} {m}"
        if m == "dlt":

            def fn():
                est, eparts, secs = run_dlt(scene, runs / "dlt", mouse=nparts == 8)
                est = align(est, eparts, parts)
                return {**evaluate(est, truth, nviews), "seconds": round(secs, 2)}

        elif m == "aniposelib":

            def fn():
                est, eparts, secs = run_aniposelib(scene, nparts, skeleton)
                est = align(est, eparts, parts)
                return {**evaluate(est, truth, nviews), "seconds": round(secs, 2)}

        else:

            def fn(m=m):
                ov = [*common, *track_overrides(m, args.adapt_minutes)]
                return track_row(scene, runs / m, ov, truth, nviews, parts)

        t0 = time.perf_counter()
        rows[m] = guarded(label, fn)
        log.info("%s: %.1f s", label, time.perf_counter() - t0)
    ani = rows.get("aniposelib", {})
    for m, r in rows.items():
        for c, k in (("rmse_all", "all"), ("rmse_seen2", "seen"), ("rmse_occluded", "occluded")):
            if m != "aniposelib" and c in r and _finite(ani.get(c)) and ani[c] > 0:
                r[f"over_aniposelib_{k}"] = r[c] / ani[c]
    return rows


# --- aggregation ----------------------------------------------------------------------------


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _mean(vals) -> float:
    v = [x for x in vals if _finite(x)]
    return float(np.mean(v)) if v else float("nan")


def aggregate(rows: list[dict]) -> dict:
    """Per "c{cameras}_p{parts}" and method: means over seeds (RMSE min and max too)."""
    out: dict[str, dict] = {}
    for r in rows:
        key = f"c{r['cameras']}_p{r['parts']}"
        out.setdefault(key, {}).setdefault(r["method"], []).append(r)
    agg: dict[str, dict] = {}
    for key, by in out.items():
        agg[key] = {}
        for m, rs in by.items():
            ok = [r for r in rs if "error" not in r]
            a: dict = {"seeds": [r["seed"] for r in ok], "errors": len(rs) - len(ok)}
            for c in ("rmse_all", "rmse_seen2", "rmse_occluded"):
                v = [r[c] for r in ok if _finite(r.get(c))]
                a[c] = _mean(v)
                a[f"{c}_min"] = min(v) if v else float("nan")
                a[f"{c}_max"] = max(v) if v else float("nan")
            for c in ("within5", "completeness", "seconds", "adapt_s", "calib_seen",
                      "calib_occluded", "body_scale"):  # fmt: skip
                a[c] = _mean(r.get(c) for r in ok)
            per = [r["calib_per_part"] for r in ok if isinstance(r.get("calib_per_part"), dict)]
            if per:  # per part: the mean over seeds
                a["calib_per_part"] = {
                    p: {n: _mean(d.get(p, {}).get(n) for d in per) for n in per[0][p]}
                    for p in per[0]
                }
            if any("converged" in r for r in ok):
                a["converged"] = all(r.get("converged") for r in ok)
                a["diverged"] = any(r.get("diverged") for r in ok)
            agg[key][m] = a
        ani = agg[key].get("aniposelib")
        for m, a in agg[key].items():
            for c, k in (("rmse_all", "all"), ("rmse_seen2", "seen"), ("rmse_occluded", "occl")):
                if ani is not None and m != "aniposelib" and _finite(ani[c]) and ani[c] > 0:
                    a[f"over_aniposelib_{k}"] = a[c] / ani[c]
    return agg


def targets(agg: dict, rows: list[dict], stability: dict | None) -> dict:
    """The targets, as booleans (and the ratios they rest on)."""
    checks: dict = {}
    met = []
    for key, by in agg.items():
        d, a = by.get("default"), by.get("aniposelib")
        if d is None or a is None:
            continue
        cams, parts = (int(s[1:]) for s in key.split("_"))
        lim = target_ratio(cams, parts)
        r_all, r_seen, r_occ = (d.get(f"over_aniposelib_{k}") for k in ("all", "seen", "occl"))
        c = {
            "limit": lim,
            "all_ratio": r_all,
            "occluded_ratio": r_occ,
            "seen_ratio": r_seen,
            "all_ok": _finite(r_all) and r_all <= lim,
            "occluded_ok": _finite(r_occ) and r_occ <= lim,
            "seen_ok": _finite(r_seen) and r_seen <= 0.5,
        }
        checks[key] = c
        met += [c["all_ok"], c["occluded_ok"], c["seen_ok"]]
    track = [r for r in rows if r["method"] in TRACK_METHODS]
    if stability:
        track += [r for s in stability.values() for r in s["rows"].values()]
    if track:
        checks["track_errors"] = sum("error" in r for r in track)
        checks["no_divergence"] = all("error" not in r and not r.get("diverged") for r in track)
        checks["all_converged"] = all(r.get("converged") for r in track)
        met.append(checks["no_divergence"])
    lo, hi = CALIBRATED
    cal = [r for r in rows if r["method"] == "default" and "error" not in r]
    if cal:
        checks["default_calibrated"] = all(
            _finite(r.get(k)) and lo <= r[k] <= hi
            for r in cal
            for k in ("calib_seen", "calib_occluded")
        )
        met.append(checks["default_calibrated"])
        # per part (not a target of issue 45: its ratios are pooled): parts within the range
        checks["default_parts_calibrated"] = {
            key: calibrated_parts(by["default"]["calib_per_part"])
            for key, by in agg.items()
            if "calib_per_part" in by.get("default", {})
        }
    if stability:
        checks["stability_spread_lt_10pct"] = all(
            _finite(s["spread"]) and s["spread"] < SPREAD_TARGET for s in stability.values()
        )
        met.append(checks["stability_spread_lt_10pct"])
    ratios = any(isinstance(v, dict) and "limit" in v for v in checks.values())  # vs the peer
    checks["targets_met"] = all(bool(x) for x in met) if ratios else None
    return checks


def calibrated_parts(per_part: dict) -> dict:
    """How many parts' calibration ratios are within `CALIBRATED`, of those measured, on seen
    and on occluded part-frames: {"seen": [within, measured], "occluded": [...]}."""
    lo, hi = CALIBRATED
    out = {}
    for n in ("seen", "occluded"):
        v = [d[n] for d in per_part.values() if _finite(d.get(n))]
        out[n] = [sum(lo <= x <= hi for x in v), len(v)]
    return out


# --- stability ------------------------------------------------------------------------------


def stability(args, motion: Motion, start: int, work: Path, base_rows: dict) -> dict:
    """``default`` under small perturbations on the 3- and 2-camera 8-part scenes (seed 0)."""
    common = common_overrides(args)
    drop = f"drop {100 * DROP_FRACTION:g}%"
    other = f"seed {OTHER_DETECTOR_SEED}"
    # name: (scene: base | drop | other, overrides)
    variants = {"base": ("base", [])}
    variants.update(
        {f"scale x{f:g}": ("base", [f"body_fit.scale_factor={f}"]) for f in SCALE_FACTORS}
    )
    variants.update({drop: ("drop", []), other: ("other", [])})
    res = {}
    for cams, nparts in STABILITY_SCENES:
        key = scene_key(args.split, start, args.frames, cams, nparts, STABILITY_SEED, args.stride)

        def scene_of(which: str, cams=cams, nparts=nparts, key=key) -> Path:
            seed = OTHER_DETECTOR_SEED if which == "other" else STABILITY_SEED
            k = scene_key(args.split, start, args.frames, cams, nparts, seed, args.stride)
            scene = film_scene(work / "scenes" / k, motion, start, args.frames, cams, nparts, seed,
                               args.stride)  # fmt: skip
            if which == "drop":
                out = work / "scenes" / f"{key}_drop{DROP_FRACTION:g}_r{DROP_SEED}"
                scene = drop_detections(scene, out, DROP_FRACTION, DROP_SEED)
            return scene

        rows, outs = {}, {}
        for name, (which, ov) in variants.items():
            if name == "base" and "default" in base_rows.get((cams, nparts), {}):
                rows[name] = base_rows[(cams, nparts)]["default"]
                outs[name] = work / "runs" / key / "default"
                continue
            slug = name.replace(" ", "_").replace("%", "pct")
            out = work / "runs" / key / f"stability_{slug}"

            def fn(which=which, ov=ov, out=out, scene_of=scene_of):
                scene = scene_of(which)
                tr = np.load(scene / "truth.npz")
                parts = [str(p) for p in tr["parts"]]
                return track_row(scene, out, [*common, *ov], tr["points"], tr["nviews"], parts)

            rows[name] = guarded(f"stability {key} {name}", fn)
            outs[name] = out
        base_poses = read_poses(outs["base"] / "points3d.csv")
        for name, out in outs.items():
            if name != "base" and "error" not in rows[name]:
                rows[name]["pose_flips"] = pose_flips(base_poses, read_poses(out / "points3d.csv"))
        v = [r["rmse_all"] for r in rows.values() if _finite(r.get("rmse_all"))]
        spread = (max(v) - min(v)) / float(np.median(v)) if len(v) >= 2 else float("nan")
        # the peer on the same two detector seeds: how much of a seed's change is the data's
        peer = {}
        if not args.no_peer_stability:
            for which in ("base", "other"):
                scene = scene_of(which)
                tr = np.load(scene / "truth.npz")
                parts = [str(p) for p in tr["parts"]]

                def pfn(scene=scene, tr=tr, parts=parts, nparts=nparts):
                    est, eparts, secs = run_aniposelib(
                        scene, nparts, Path(args.data).parent / "skeleton.csv"
                    )
                    return evaluate(align(est, eparts, parts), tr["points"], tr["nviews"])

                peer[which] = guarded(f"stability {key} aniposelib {which}", pfn)
        pv = [r["rmse_all"] for r in peer.values() if _finite(r.get("rmse_all"))]
        peer_seed = abs(pv[1] - pv[0]) / float(np.mean(pv)) if len(pv) == 2 else float("nan")
        base_v, other_v = rows["base"].get("rmse_all"), rows[other].get("rmse_all")
        own_seed = (
            abs(other_v - base_v) / float(np.mean([base_v, other_v]))
            if _finite(base_v) and _finite(other_v)
            else float("nan")
        )
        res[f"c{cams}_p{nparts}"] = {
            "scene": key,
            "rows": rows,
            "spread": spread,
            "seed_change": own_seed,
            "aniposelib_seed_change": peer_seed,
            "aniposelib": peer,
        }
    return res


POSE_FLIP_RAD = 0.2  # "a different basin": the body's orientation more than this apart


def read_poses(points_csv: Path) -> np.ndarray:
    """(T, 3) rotation vectors (rad) of `points3d.csv`'s ``pose_r*`` columns."""
    df = read_points3d_table(points_csv)  # the pose columns are in points3d.extra.csv
    return df[["pose_rx", "pose_ry", "pose_rz"]].to_numpy(float)


def pose_flips(a: np.ndarray, b: np.ndarray) -> float:
    """Fraction of frames whose body orientations (rotation vectors (T, 3)) differ by more than
    `POSE_FLIP_RAD` (the angle of R_a^T R_b)."""
    ok = np.isfinite(a).all(1) & np.isfinite(b).all(1)
    if not ok.any():
        return float("nan")
    ang = (Rotation.from_rotvec(a[ok]).inv() * Rotation.from_rotvec(b[ok])).magnitude()
    return float(np.mean(ang > POSE_FLIP_RAD))


# --- output ---------------------------------------------------------------------------------


def _fmt(v, width: int = 8) -> str:
    if v is None:
        s = "-"
    elif isinstance(v, bool):
        s = str(v)
    elif isinstance(v, float):
        s = "n/a" if not math.isfinite(v) else f"{v:.3f}" if abs(v) < 10 else f"{v:.2f}"
    else:
        s = str(v)
    return f"{s:>{width}}"


COLS = [
    ("rmse_all", "all"),
    ("range", "all min-max"),
    ("rmse_seen2", ">=2 cams"),
    ("rmse_occluded", "occl"),
    ("within5", "<=5mm"),
    ("completeness", "complete"),
    ("over_aniposelib_all", "/ani all"),
    ("over_aniposelib_seen", "/ani >=2"),
    ("over_aniposelib_occl", "/ani occl"),
    ("calib_seen", "cal >=2"),
    ("calib_occluded", "cal occl"),
    ("seconds", "seconds"),
    ("errors", "errors"),
]


def print_tables(agg: dict, scenes: dict) -> None:
    for key, by in agg.items():
        cams, parts = (int(s[1:]) for s in key.split("_"))
        fr = [s for s in scenes.values() if s["cameras"] == cams and s["parts"] == parts]
        seen = _mean(s["seen_ge2"] for s in fr)
        none = _mean(s["seen_0"] for s in fr)
        print(
            f"\n{cams} cameras, {parts} parts: mean over seeds "
            f"{sorted({s['seed'] for s in fr})} (RMSE mm; part-frames seen by >= 2 cameras "
            f"{seen:.3f}, by none {none:.3f}; occl = seen by < 2)"
        )
        print(f"{'method':<11}" + "".join(f"{h:>{14 if k == 'range' else 12}}" for k, h in COLS))
        for m, a in by.items():
            cells = []
            for k, _ in COLS:
                if k == "range":
                    lo, hi = a["rmse_all_min"], a["rmse_all_max"]
                    span = f"{lo:.1f}-{hi:.1f}" if _finite(lo) else "n/a"
                    cells.append(f"{span:>14}")
                else:
                    cells.append(_fmt(a.get(k), 12))
            print(f"{m:<11}" + "".join(cells))


def print_part_calibration(agg: dict, method: str = "default") -> None:
    """Per scene kind, the method's calibration ratios part by part (mean over seeds)."""
    for key, by in agg.items():
        per = by.get(method, {}).get("calib_per_part")
        if not per:
            continue
        cams, parts = (int(s[1:]) for s in key.split("_"))
        lo, hi = CALIBRATED
        print(
            f"\n{method}: rms error / rms sigma per part, {cams} cameras, {parts} parts (mean "
            f"over seeds; * outside {lo:g}-{hi:g}; unseen = no camera)"
        )
        print(f"  {'part':<18}{'seen >= 2':>11}{'occluded':>11}{'unseen':>11}")
        for p, d in per.items():
            cells = []
            for n in ("seen", "occluded", "unseen"):
                v = d.get(n)
                mark = "*" if _finite(v) and not lo <= v <= hi else " "
                cells.append(f"{_fmt(v, 10)}{mark}")
            print(f"  {p:<18}" + "".join(cells))


def print_rows(rows: list[dict]) -> None:
    print("\nadjust-track runs: converged, body scale, median reprojection (px), diverged")
    for r in rows:
        if r["method"] in TRACK_METHODS:
            state = (
                f"error: {r['error'].splitlines()[0][:100]}"
                if "error" in r
                else f"converged {r.get('converged')}, scale {_fmt(r.get('body_scale'), 0)}, "
                f"reproj {_fmt(r.get('reproj_median_px'), 0)}, diverged {r.get('diverged')}"
                + (f", adapted net used {r['adapt_used']}" if "adapt_used" in r else "")
                + (f", net parts {r['net_parts']}" if "net_parts" in r else "")
            )
            print(f"  c{r['cameras']} p{r['parts']} seed {r['seed']} {r['method']:<8} {state}")
    bad = [r for r in rows if "error" in r and r["method"] not in TRACK_METHODS]
    for r in bad:
        print(f"  c{r['cameras']} p{r['parts']} seed {r['seed']} {r['method']:<8} error: "
              f"{r['error'].splitlines()[0][:100]}")  # fmt: skip


def print_stability(stab: dict) -> None:
    for s in stab.values():
        print(f"\nstability, default on {s['scene']}: RMSE all (mm) per perturbation")
        for name, r in s["rows"].items():
            val = (
                f"error: {r['error'].splitlines()[0][:100]}"
                if "error" in r
                else f"{_fmt(r.get('rmse_all'), 0)}  (occl {_fmt(r.get('rmse_occluded'), 0)}, "
                f"body scale {_fmt(r.get('body_scale'), 0)} x {r.get('scale_factor') or 1:g})"
            )
            flips = r.get("pose_flips")
            flips = (
                f", poses > {POSE_FLIP_RAD:g} rad from base {100 * flips:.1f}%"
                if _finite(flips)
                else ""
            )
            print(f"  {name:<12} {val}{flips}")
        print(f"  spread (max-min)/median {_fmt(s['spread'], 0)} (target < {SPREAD_TARGET:g})")
        print(
            f"  another detector seed changes RMSE all by {_fmt(s.get('seed_change'), 0)} "
            f"(aniposelib on the same two seeds: {_fmt(s.get('aniposelib_seed_change'), 0)})"
        )


def _ints(ap, text: str, allowed, flag: str) -> list[int]:
    return [int(v) for v in subset(ap, text, [str(a) for a in allowed], flag)]


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", choices=sorted(SPLITS), default="test",
                    help="val: frames 1200-2199; test: 2400-3399 (reporting)")  # fmt: skip
    ap.add_argument("--frames", type=int, default=None,
                    help="frames from the segment start (<= 1000 / stride)")  # fmt: skip
    ap.add_argument("--stride", type=int, default=1,
                    help="film every Nth frame (1/N of the recording's frame rate)")  # fmt: skip
    ap.add_argument("--cameras", default="2,3,4", help="camera counts of the 8-part scenes")
    ap.add_argument("--parts", default="8,22,34", help="part sets (22, 34: see the next)")
    ap.add_argument("--many-parts-cameras", default=str(MANY_PARTS_CAMERAS),
                    help="camera counts of the 22- and 34-part scenes")  # fmt: skip
    ap.add_argument("--seeds", default="0,1", help="detector seeds")
    ap.add_argument("--methods", default="dlt,aniposelib,default,rigid",
                    help=f"comma list of {','.join(METHODS)}")  # fmt: skip
    ap.add_argument("--adapt-minutes", type=float, default=3.0, help="self's fine-tuning")
    ap.add_argument("--no-stability", action="store_true", help="skip the stability table")
    ap.add_argument("--no-peer-stability", action="store_true",
                    help="stability without aniposelib on the two detector seeds")  # fmt: skip
    ap.add_argument("--threads", type=int, default=1, help="torch threads (0: torch default)")
    ap.add_argument("--data", default=str(DATA), help="the recording (poses3d.csv)")
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "real_motion"),
                    help="scenes and runs, in a folder named by the data file's hash")  # fmt: skip
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "real_motion.json"))
    ap.add_argument("-o", "--override", action="append", default=[],
                    help="an adjust-track setting of every tracker run (repeat; with its own "
                    "--work: the runs' folders do not name it)")  # fmt: skip
    args = start(ap, argv)
    if args.stride < 1:
        ap.error(f"--stride must be >= 1, got {args.stride}")
    most = SEGMENT_FRAMES // args.stride
    if args.frames is None:
        args.frames = most
    if not 1 <= args.frames <= most:
        ap.error(f"--frames must be within 1..{most} (1000 / --stride), got {args.frames}")
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        ap.error(f"--seeds: comma list of integers, got {args.seeds!r}")
    if not seeds:
        ap.error("--seeds: none given")
    cameras = _ints(ap, args.cameras, CAMERA_COUNTS, "--cameras")
    part_sets = _ints(ap, args.parts, PART_SETS, "--parts")
    methods = subset(ap, args.methods, METHODS, "--methods")
    if "aniposelib" in methods and not anipose_wanted(False):
        methods.remove("aniposelib")
    data = Path(args.data)
    if not data.is_file():
        ap.error(f"--data: {data} not found")
    motion = Motion(data)
    work = Path(args.work) / motion.tag
    start_frame = SPLITS[args.split]
    kinds = [(c, 8) for c in cameras if 8 in part_sets]
    many = _ints(ap, args.many_parts_cameras, CAMERA_COUNTS, "--many-parts-cameras")
    kinds += [(c, p) for c in cameras if c in many for p in part_sets if p != 8]
    if not kinds:
        ap.error("no scene: --parts 22/34 need one of --many-parts-cameras among --cameras")
    log.info(
        "split %s: frames %d-%d, every %d; scenes %s x seeds %s; methods %s",
        args.split,
        start_frame,
        start_frame + args.frames * args.stride - 1,
        args.stride,
        kinds,
        seeds,
        methods,
    )

    rows: list[dict] = []
    scenes: dict[str, dict] = {}
    seed0_rows: dict[tuple, dict] = {}
    for cams, nparts in kinds:
        for seed in seeds:
            key = scene_key(args.split, start_frame, args.frames, cams, nparts, seed, args.stride)
            info = {"cameras": cams, "parts": nparts, "seed": seed}
            try:
                scene = film_scene(work / "scenes" / key, motion, start_frame, args.frames,
                                   cams, nparts, seed, args.stride)  # fmt: skip
            except Exception as exc:  # noqa: BLE001 - recorded, the others go on
                log.warning("scene %s failed: %s", key, exc)
                rows += [{**info, "method": m, "error": f"scene: {exc}"} for m in methods]
                continue
            nviews = np.load(scene / "truth.npz")["nviews"]
            scenes[key] = {**info, **view_fractions(nviews)}
            by = run_scene(scene, work / "runs" / key, nparts, methods, args,
                           data.parent / "skeleton.csv")  # fmt: skip
            if seed == STABILITY_SEED:
                seed0_rows[(cams, nparts)] = by
            rows += [{**info, "method": m, **r} for m, r in by.items()]

    stab = None
    if not args.no_stability:
        stab = stability(args, motion, start_frame, work, seed0_rows)
    agg = aggregate(rows)
    checks = targets(agg, rows, stab)

    print(
        f"\nreal motion ({data.name}), {args.split} segment: frames {start_frame}-"
        f"{start_frame + args.frames * args.stride - 1}"
        + (f", one frame in {args.stride}" if args.stride > 1 else "")
        + f"; detector seeds {seeds}"
    )
    print_tables(agg, scenes)
    print_part_calibration(agg)
    print_rows(rows)
    if stab:
        print_stability(stab)
    print(
        "\ntargets (default / aniposelib; all and occl <= limit, >=2 <= 0.5):\n"
        + "\n".join(
            f"  {k}: {v}" if not isinstance(v, dict) or "limit" not in v else
            f"  {k}: limit {v['limit']:g}: all {_fmt(v['all_ratio'], 0)} {v['all_ok']}, "
            f"occl {_fmt(v['occluded_ratio'], 0)} {v['occluded_ok']}, "
            f">=2 {_fmt(v['seen_ratio'], 0)} {v['seen_ok']}"
            for k, v in checks.items()
        )
    )  # fmt: skip
    summary = {
        "data": str(data),
        "split": args.split,
        "segment": [start_frame, start_frame + SEGMENT_FRAMES],
        "frames": [start_frame, start_frame + args.frames * args.stride],
        "stride": args.stride,
        "seeds": seeds,
        "methods": methods,
        "scenes": scenes,
        "rows": [{k: _round(v) for k, v in r.items()} for r in rows],
        "aggregate": {k: {m: _rounded(a) for m, a in by.items()} for k, by in agg.items()},
        "stability": stab,
        "checks": checks,
        "adapt_minutes": args.adapt_minutes,
        "threads": args.threads,
        "overrides": args.override,
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    return emit(summary, args.out)


def _round(v):
    if isinstance(v, dict):  # per-part blocks
        return {k: _round(x) for k, x in v.items()}
    return round(v, 4) if isinstance(v, float) and math.isfinite(v) else v


def _rounded(d: dict) -> dict:
    return {k: _round(v) for k, v in d.items()}


if __name__ == "__main__":
    main()
