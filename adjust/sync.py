"""Frame offsets between cameras: find a camera whose detections are out of step in time with
the others (its video started a few frames early or late, or lost a frame at its start) and
shift it back.

    det, report = check_sync(cameras, det, max_offset=30)

For every pair of cameras (a, b), camera a's detections at frame t and camera b's at frame
t + L are held against the rig's epipolar geometry: the median over the parts both saw of the
symmetric distance (px) of each detection from the epipolar line of the other
(`lag_curves`), for every lag |L| <= ``max_offset``. A synchronised pair agrees best at L = 0
while the animal moves. The cameras' offsets o (integers) minimise the sum over the pairs of
their medians at o_b - o_a (`solve_offsets`: coordinate descent from all zeros), referred to
the most common offset (the majority is in step; with two cameras, or a tie, the first
camera of the calibration keeps its time: nothing in the detections tells which camera's
frames are the session's). A camera's offset is accepted only where
most of its pairs back it on their own (`_backs`): the pair's closest lag lies within a frame
of it, and there the pair's median is at least ``SYNC_RATIO`` (1.1) times smaller than with the
camera left at 0. A still animal gives flat curves and no offset (the real fly: pairs within 2%
of flat); a camera whose extrinsics are wrong gives pairs that disagree on the lag (the real
SLEAP mouse's `side`), and stays for the camera check.

A camera with offset o is read as its row for frame f + o at frame f (`shift_cameras`; the
frame numbers of the files, ``Detections.frames``, so a sample of rows is shifted exactly);
frames it has no row for are missing. Detections: ``Detections`` (T, K, C, 2) px."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np
import torch

from adjust.camera import Camera
from adjust.distortion import undistort_points
from adjust.io import Detections, InputError

log = logging.getLogger(__name__)

SYNC_RATIO = 1.1  #: an offset must cut a pair's median epipolar distance by this factor
MIN_PAIRS = 50  #: part-frames a pair needs at a lag for its median there to count
MAX_FRAMES = 4_000  #: frames the curves are measured on (in blocks spread over the session)
BLOCK = 200  #: consecutive frames per block


def frame_numbers(det: Detections) -> np.ndarray | None:
    """(T,) int64 frame number of each row (the files' ``frames``, else 0..T-1); None where
    the rows are labelled images (names, no time order)."""
    if det.frames is None:
        return np.arange(det.num_frames, dtype=np.int64)
    frames = np.asarray(det.frames)
    if frames.dtype.kind not in "iu":
        return None
    return frames.astype(np.int64)


def _rows_at(frames: np.ndarray, target: np.ndarray, order: np.ndarray | None = None) -> np.ndarray:
    """Row of each target frame number in ``frames``, -1 where absent (``order``: frames'
    argsort, when the caller has it)."""
    if order is None:
        order = np.argsort(frames, kind="stable")
    fs = frames[order]
    i = np.clip(np.searchsorted(fs, target), 0, max(len(fs) - 1, 0))
    hit = (fs[i] == target) if len(fs) else np.zeros(target.shape, bool)
    return np.where(hit, order[i], -1)


def essential(a: Camera, b: Camera) -> np.ndarray:
    """(3, 3) essential matrix E with x_b^T E x_a = 0 for a point's normalised, undistorted
    homogeneous coordinates x_a, x_b in cameras a and b (world -> camera x = R X + t)."""
    R = b.R @ a.R.T
    t = b.tvec - R @ a.tvec
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return tx @ R


def _homog(x: np.ndarray) -> np.ndarray:
    return np.concatenate([x, np.ones((*x.shape[:-1], 1))], axis=-1)


def _lines(h: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Epipolar lines h @ M of homogeneous points h (..., 3) and 1 / the norm of their normals."""
    line = h @ M
    return line, 1.0 / np.maximum(np.linalg.norm(line[..., :2], axis=-1), 1e-12)


def _symmetric(hb, lb, inv_b, inv_a, fa: float, fb: float) -> np.ndarray:
    """The mean of b's distance (px) from a's epipolar line lb and a's from b's (inverse normal
    norms inv_b, inv_a): both share the residual |x_b^T E x_a|."""
    r = np.abs((hb * lb).sum(-1))
    return 0.5 * r * (fb * inv_b + fa * inv_a)


def epipolar_px(E: np.ndarray, xa: np.ndarray, xb: np.ndarray, fa: float, fb: float) -> np.ndarray:
    """Symmetric epipolar distance (px) of normalised points xa, xb (N, 2): the mean of b's
    distance from a's epipolar line (times fb) and a's from b's (times fa)."""
    ha, hb = _homog(xa), _homog(xb)
    lb, inv_b = _lines(ha, E.T)  # lines in b
    _, inv_a = _lines(hb, E)  # lines in a
    return _symmetric(hb, lb, inv_b, inv_a, fa, fb)


def _normalised(xy: np.ndarray, cameras: Sequence[Camera]) -> np.ndarray:
    """(N, K, C, 2) undistorted normalised coordinates of detections xy (N, K, C, 2) px (NaN
    where missing)."""
    out = np.full(xy.shape, np.nan)
    for c, cam in enumerate(cameras):
        ok = np.isfinite(xy[:, :, c]).all(-1)
        if ok.any():
            n = undistort_points(
                torch.as_tensor(xy[:, :, c][ok]), torch.as_tensor(cam.K), torch.as_tensor(cam.dist)
            )
            out[:, :, c][ok] = n.numpy()
    return out


def lag_curves(
    cameras: Sequence[Camera], det: Detections, max_offset: int
) -> tuple[np.ndarray, np.ndarray]:
    """(lags (L,), curves (C, C, L)): curves[a, b, i] the median symmetric epipolar distance
    (px) between camera a at frame f and camera b at frame f + lags[i] over the parts both saw
    (NaN with fewer than `MIN_PAIRS`); curves[b, a] is curves[a, b] reversed in lag. Measured on
    at most `MAX_FRAMES` rows, in blocks of `BLOCK` spread over the session."""
    C = len(cameras)
    lags = np.arange(-max_offset, max_offset + 1)
    curves = np.full((C, C, lags.size), np.nan)
    frames = frame_numbers(det)
    T = len(frames)
    rows = np.arange(T)
    if T > MAX_FRAMES:  # blocks of consecutive rows: few rows beyond them to undistort
        starts = np.linspace(0, T - BLOCK, MAX_FRAMES // BLOCK).astype(np.int64)
        rows = np.unique((starts[:, None] + np.arange(BLOCK)[None]).ravel())
    focal = [float(np.sqrt(cam.K[0, 0] * cam.K[1, 1])) for cam in cameras]
    order = np.argsort(frames, kind="stable")
    at = [_rows_at(frames, frames[rows] + L, order) for L in lags]  # rows of f + L
    need = np.unique(np.concatenate([rows, *[r[r >= 0] for r in at]]))
    x = _normalised(det.xy[need], cameras)  # only the rows compared
    seen = np.isfinite(x).all(-1)  # (N, K, C)
    pairs = [(np.searchsorted(need, rows[r >= 0]), np.searchsorted(need, r[r >= 0])) for r in at]
    for a in range(C):
        for b in range(a + 1, C):
            E = essential(cameras[a], cameras[b])
            ha, hb = _homog(x[:, :, a]), _homog(x[:, :, b])
            lb, inv_b = _lines(ha, E.T)  # every row's lines, once per pair
            _, inv_a = _lines(hb, E)
            for i, (ra, rb) in enumerate(pairs):
                both = seen[ra, :, a] & seen[rb, :, b]
                if both.sum() < MIN_PAIRS:
                    continue
                d = _symmetric(hb[rb], lb[ra], inv_b[ra], inv_a[rb], focal[a], focal[b])
                curves[a, b, i] = float(np.median(d[both]))
            curves[b, a] = curves[a, b, ::-1]
    return lags, curves


def _pair_cost(curves: np.ndarray, lags: np.ndarray, a: int, b: int, lag: int) -> float:
    """curves[a, b] at `lag` (inf outside the lags or where not measured)."""
    i = int(lag) + int(lags[-1])
    if not 0 <= i < lags.size or not np.isfinite(curves[a, b, i]):
        return float("inf")
    return float(curves[a, b, i])


def _camera_cost(curves, lags, offsets, c: int, oc: int) -> float:
    """Sum over camera c's measured pairs of their median at the offsets, c at `oc`."""
    total, n = 0.0, 0
    for d in range(len(offsets)):
        if d == c or not np.isfinite(curves[c, d]).any():
            continue
        total += _pair_cost(curves, lags, c, d, offsets[d] - oc)
        n += 1
    return total if n else float("nan")


def _backs(curves, lags, offsets, c: int, d: int) -> bool:
    """Whether the pair (c, d) alone backs camera c's offset: its own closest lag is within one
    frame of the offsets' (o_d - o_c), and there it is `SYNC_RATIO` times closer than with c
    left at 0."""
    curve = curves[c, d]
    lag = int(offsets[d] - offsets[c])
    own = int(lags[int(np.nanargmin(curve))])
    at = _pair_cost(curves, lags, c, d, lag)
    zero = _pair_cost(curves, lags, c, d, int(offsets[d]))
    return abs(own - lag) <= 1 and np.isfinite(at) and zero > SYNC_RATIO * at


def solve_offsets(lags: np.ndarray, curves: np.ndarray, sweeps: int = 5) -> np.ndarray:
    """(C,) int offsets minimising the summed pair medians (coordinate descent from zeros, one
    camera at a time: the one out of step moves alone), then referred to their most common
    value (ties: camera 0's)."""
    C = curves.shape[0]
    o = np.zeros(C, dtype=np.int64)
    for _ in range(sweeps):
        moved = False
        for c in range(C):
            costs = [_camera_cost(curves, lags, o, c, int(v)) for v in lags]
            if not np.isfinite(costs).any():
                continue
            best = int(lags[int(np.nanargmin(np.where(np.isfinite(costs), costs, np.nan)))])
            if best != o[c] and costs[int(best + lags[-1])] < costs[int(o[c] + lags[-1])]:
                o[c], moved = best, True
        if not moved:
            break
    values, counts = np.unique(o, return_counts=True)
    ref = values[counts == counts.max()]
    base = o[0] if o[0] in ref else ref[0]
    return o - base


def shift_cameras(det: Detections, offsets: dict[str, int]) -> Detections:
    """The detections with camera ``name`` read at frame f from its row for frame f + offset
    (missing where it has none)."""
    if not any(offsets.values()):
        return det
    frames = frame_numbers(det)
    if frames is None:
        raise ValueError("labelled images (frames by name) have no time order to shift")
    xy, lik = det.xy.copy(), det.likelihood.copy()
    for name, o in offsets.items():
        if not o:
            continue
        c = det.cameras.index(name)
        src = _rows_at(frames, frames + int(o))
        ok = src >= 0
        xy[:, :, c] = np.nan
        lik[:, :, c] = 0.0
        xy[ok, :, c] = det.xy[src[ok], :, c]
        lik[ok, :, c] = det.likelihood[src[ok], :, c]
    return dataclasses.replace(det, xy=xy, likelihood=lik)


def check_sync(
    cameras: Sequence[Camera], det: Detections, max_offset: int, mode: str = "warn"
) -> tuple[Detections, dict]:
    """Find and undo frame offsets between the cameras (module doc). ``mode`` as the camera
    check's: warn = shift the camera back and say so, error = an `InputError` naming it, off =
    nothing. Returns the (shifted) detections and the report {"max_offset", "offsets" {name:
    frames}, "epipolar_px" {name: [at 0, at the offset]}} (offsets only where found)."""
    report: dict = {"max_offset": int(max_offset), "offsets": {}, "epipolar_px": {}}
    if mode == "off" or max_offset <= 0 or len(cameras) < 2 or frame_numbers(det) is None:
        return det, report
    max_offset = min(int(max_offset), max(det.num_frames // 4, 1))
    lags, curves = lag_curves(cameras, det, max_offset)
    offsets = solve_offsets(lags, curves)
    found: dict[str, int] = {}
    for c, cam in enumerate(cameras):
        if offsets[c] == 0:
            continue
        pairs = [d for d in range(len(cameras)) if d != c and np.isfinite(curves[c, d]).any()]
        backing = [d for d in pairs if _backs(curves, lags, offsets, c, d)]
        if not pairs or 2 * len(backing) <= len(pairs):
            continue
        found[cam.name] = int(offsets[c])
        zero = _camera_cost(curves, lags, offsets, c, 0) / len(pairs)
        at = _camera_cost(curves, lags, offsets, c, int(offsets[c])) / len(pairs)
        report["epipolar_px"][cam.name] = [round(zero, 3), round(at, 3)]
    if not found:
        return det, report
    report["offsets"] = found
    for name, o in found.items():
        c = [cam.name for cam in cameras].index(name)
        zero, at = report["epipolar_px"][name]
        msg = (
            f"camera '{name}' ({det.files[c]}) is {abs(o)} frame{'s' * (abs(o) != 1)} out of "
            f"step with the others: its frame f {'+' if o > 0 else '-'} {abs(o)} matches their "
            f"frame f (its detections lie {zero:.1f} px from the other cameras' epipolar lines "
            f"in step, {at:.1f} px shifted; a video started early or late?)"
        )
        if mode == "error":
            raise InputError(
                msg + "; fix its frame numbers, or set input.camera_check=warn to shift it back "
                "(input.max_frame_offset=0: no check)"
            )
        log.warning("%s; SHIFTED back by %d frames (input.camera_check=warn)", msg, o)
    return shift_cameras(det, found), report
