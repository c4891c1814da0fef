"""Frame rates: find a camera recorded at a whole multiple (or a whole fraction) of the others'
frame rate (one camera set to 60 fps, the others to 30) and renumber its frames to theirs.

    det, report = check_rates(cameras, det)

Detection files are matched by frame number, so a camera at twice the others' rate lies in
time by a growing amount: its frame f shows their frame f / 2. Unnoticed, its detections
disagree with the others' at almost every frame, the camera check excludes it (naming a wrong
cause), and the second half of its frames, where no other camera has any, is tracked from
nothing. A camera whose file spans k times the others' frames (k = 2..`MAX_RATIO`, within
`SPAN_TOL`), or 1 / k of them, is tested: its detections are held against the other cameras'
epipolar lines as numbered and with its frame k f + p (faster) or f (slower, at their k f +
p) matched to theirs, for every phase p < k (`pair_medians`: the median symmetric epipolar
distance over the part-frames both saw). Where the best renumbering brings the camera's
median distance down by `BETTER` (3x) or more and to within `PLAUSIBLE_PX` (5 px) or twice
the other pairs' own median, its frames are renumbered (`renumber`): a faster camera's rows
k f + p become frame f (its other rows are left out; a fraction of a frame left over is
`adjust.subframe`'s), a slower camera's row f becomes frame k f + p (it has no detection at
the frames between). Frames no camera has left are dropped. Runs before the sync check
(`adjust.camera_check`); with two cameras the first keeps the session's time (the second is
renumbered); ``input.camera_check=error`` stops instead, ``input.rate_check=false`` does not
look; a long session tracked in chunks is refused with the camera named (its chunks are cut
by frame number). Detections: ``Detections`` (T, K, C, 2) px."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np

from adjust.camera import Camera
from adjust.io import Detections, InputError
from adjust.sync import (
    epipolar_medians,
    frame_numbers,
    normalised_points,
    spread_rows,
)

log = logging.getLogger(__name__)

MAX_RATIO = 8  #: whole ratios looked for: 2 .. this
SPAN_TOL = 0.02  #: a camera's frame span within this fraction of k times the others'
BETTER = 3.0  #: the renumbered camera's median epipolar distance must fall by this factor
PLAUSIBLE_PX = 5.0  #: ... to within this many px (or twice the other pairs' median)
MIN_PAIRS = 50  #: part-frames a pair needs for its median to count
MAX_ROWS = 5_000  #: rows of the slower frame numbering the medians are measured on


def spans(det: Detections) -> np.ndarray | None:
    """(C,) each camera's frame span (last - first frame of its rows, + 1); None without frame
    numbers. A row of a camera is one with any likelihood or detection (its file has it)."""
    frames = frame_numbers(det)
    if frames is None:
        return None
    has = (det.likelihood > 0).any(1) | np.isfinite(det.xy).all(-1).any(1)  # (T, C)
    out = np.zeros(det.num_cameras, dtype=np.int64)
    for c in range(det.num_cameras):
        f = frames[has[:, c]]
        out[c] = int(f.max() - f.min() + 1) if f.size else 0
    return out


def ratio_of(span: int, others: float) -> int | None:
    """k (> 1: the camera spans k times the others' frames; < -1: 1 / k of them) or None."""
    if span <= 0 or others <= 0:
        return None
    r = span / others
    for k in range(2, MAX_RATIO + 1):
        if abs(r - k) <= SPAN_TOL * k:
            return k
        if abs(1 / r - k) <= SPAN_TOL * k:
            return -k
    return None


def renumber(det: Detections, c: int, k: int, phase: int) -> Detections:
    """The detections with camera c's frames renumbered (module doc): k > 1 its frame k f +
    phase becomes frame f; k < -1 its frame f becomes |k| f + phase. Rows are the union of
    the frames any camera then has, in order."""
    frames = frame_numbers(det)
    if frames is None:
        raise ValueError("labelled images (frames by name) have no frame numbers to renumber")
    has = (det.likelihood > 0).any(1) | np.isfinite(det.xy).all(-1).any(1)  # (T, C)
    own = frames[has[:, c]]
    src = np.flatnonzero(has[:, c])
    if k > 1:
        keep = (own - phase) % k == 0
        new, src = (own[keep] - phase) // k, src[keep]
    else:
        new = own * (-k) + phase
    others = [d for d in range(det.num_cameras) if d != c]
    rest = frames[has[:, others].any(1)]
    union = np.unique(np.concatenate([rest, new])).astype(np.int64)
    T = len(union)
    xy = np.full((T, det.num_parts, det.num_cameras, 2), np.nan)
    lik = np.zeros((T, det.num_parts, det.num_cameras))
    at = np.searchsorted(union, frames)
    inside = (at < T) & (union[np.minimum(at, T - 1)] == frames)
    rows = np.flatnonzero(inside)
    for d in others:
        xy[at[rows], :, d] = det.xy[rows, :, d]
        lik[at[rows], :, d] = det.likelihood[rows, :, d]
    dst = np.searchsorted(union, new)
    xy[dst, :, c] = det.xy[src, :, c]
    lik[dst, :, c] = det.likelihood[src, :, c]
    return dataclasses.replace(det, xy=xy, likelihood=lik, frames=union)


def pair_medians(cameras: Sequence[Camera], det: Detections) -> np.ndarray:
    """(C, C) median symmetric epipolar distance (px) of each camera pair at the same frame
    (NaN with fewer than `MIN_PAIRS` part-frames); measured on at most `MAX_ROWS` rows."""
    x = normalised_points(det.xy[spread_rows(det.num_frames, MAX_ROWS)], cameras)
    parts = range(det.num_parts)
    return epipolar_medians(cameras, x, parts, parts, MIN_PAIRS)


def camera_px(m: np.ndarray, c: int) -> float:
    """Camera c's median over its pairs' medians (NaN where none counts)."""
    v = np.delete(m[c], c)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else float("nan")


def check_rates(
    cameras: Sequence[Camera], det: Detections, mode: str = "warn"
) -> tuple[Detections, dict]:
    """Find and undo a camera at a whole multiple or fraction of the others' frame rate
    (module doc). ``mode`` as the camera check's: warn = renumber its frames and say so, error
    = an `InputError` naming it, off = nothing. Returns the (renumbered) detections and the
    report {"renumbered": {name: {"ratio", "phase", "epipolar_px": [as numbered,
    renumbered]}}}."""
    report: dict = {"renumbered": {}}
    sp = spans(det) if mode != "off" and len(cameras) >= 2 else None
    if sp is None:
        return det, report
    for c, cam in enumerate(cameras):
        if len(cameras) == 2 and c == 0:  # two cameras: the first keeps the session's time
            continue
        others = np.delete(sp, c)
        k = ratio_of(int(sp[c]), float(np.median(others[others > 0])) if (others > 0).any() else 0)
        if k is None:
            continue
        base = pair_medians(cameras, det)
        before = camera_px(base, c)
        rest = np.delete(np.delete(base, c, 0), c, 1)
        rest_px = float(np.nanmedian(rest)) if np.isfinite(rest).any() else float("nan")
        best = None
        for p in range(abs(k)):
            cand = renumber(det, c, k, p)
            px = camera_px(pair_medians(cameras, cand), c)
            if np.isfinite(px) and (best is None or px < best[1]):
                best = (p, px, cand)
        if best is None:
            continue
        p, after, cand = best
        plausible = max(PLAUSIBLE_PX, 2 * rest_px) if np.isfinite(rest_px) else PLAUSIBLE_PX
        if not (after <= plausible and (not np.isfinite(before) or after * BETTER <= before)):
            log.info(
                "camera '%s' spans %s the others' frames, but renumbering it does not make it "
                "agree (%.1f px as numbered, %.1f px renumbered): left as it is",
                cam.name,
                f"{k}x" if k > 1 else f"1/{-k} of",
                before,
                after,
            )
            continue
        if k > 1:
            said = (
                f"has {k}x the others' frames: recorded at {k}x their frame rate? its frame "
                f"{k} f + {p} matches their frame f"
            )
        else:
            said = (
                f"has 1/{-k} of the others' frames: recorded at 1/{-k} of their frame rate? its "
                f"frame f matches their frame {-k} f + {p}"
            )
        msg = (
            f"camera '{cam.name}' ({det.files[c]}) {said} (its detections lie {before:.1f} px "
            f"from the other cameras' epipolar lines as numbered, {after:.1f} px renumbered)"
        )
        if mode == "error":
            raise InputError(
                msg + "; resample its file to the others' frame rate, or set "
                "input.camera_check=warn to renumber it (input.rate_check=false: no check)"
            )
        log.warning("%s; its frames RENUMBERED to theirs (input.camera_check=warn)", msg)
        report["renumbered"][cam.name] = {
            "ratio": k if k > 1 else 1.0 / -k,
            "phase": p,
            "epipolar_px": [round(before, 3), round(after, 3)],
        }
        det = cand
        sp = spans(det)
    return det, report
