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
frames are the session's). Every lag is compared on the same frames (those with a row at
every lag). A camera's offset is accepted only where most of its pairs back it on their own
(`_backs`): the pair's closest lag lies within a frame of it, and there the pair's median is
at least ``SYNC_RATIO`` (1.1) times smaller than with the camera left at 0; and never at the
edge of the lags (a trend, not a minimum). A still animal gives flat curves and no offset (the
real fly); a camera whose extrinsics are wrong gives pairs that disagree on the lag (the real
SLEAP mouse's `side`), and stays for the camera check.

A lag that changes during the session (a camera that dropped frames) is found block by block
(`block_curves`, `block_lags`, `steps_of`: blocks of `BLOCK_FRAMES` frames, the change placed
by the frames' capped votes) and undone piecewise; a change by one frame is not told from the
jitter of a slow animal's broad minimum, and with two cameras a new lag must hold for two
blocks.

A camera with offset o is read as its row for frame f + o at frame f (`shift_cameras`; the
frame numbers of the files, ``Detections.frames``, so a sample of rows is shifted exactly);
frames it has no row for are missing. Detections: ``Detections`` (T, K, C, 2) px."""

from __future__ import annotations

import dataclasses
import logging
import warnings
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
BLOCK_FRAMES = 250  #: frames per block whose own lag is measured (a lag that changes)
MAX_BLOCKS = 40  #: ... and at most this many blocks (longer ones in long sessions)
SPLIT_CAP_PX = 1.0  #: a frame's say in where a lag changes is capped at this difference (px)


def frame_numbers(det: Detections) -> np.ndarray | None:
    """(T,) int64 frame number of each row (the files' ``frames``, else 0..T-1); None where
    the rows are labelled images (names, no time order)."""
    if det.frames is None:
        return np.arange(det.num_frames, dtype=np.int64)
    frames = np.asarray(det.frames)
    if frames.dtype.kind not in "iu":
        return None
    return frames.astype(np.int64)


def spread_rows(T: int, most: int) -> np.ndarray:
    """Rows 0..T-1, or, for T > `most`, `most` rows spread evenly over them."""
    if T <= most:
        return np.arange(T)
    return np.linspace(0, T - 1, most).astype(np.int64)


def focal_px(cam: Camera) -> float:
    """A camera's focal length in pixels, sqrt(fx fy): the scale of its epipolar distances."""
    return float(np.sqrt(cam.K[0, 0] * cam.K[1, 1]))


def epipolar_medians(
    cameras: Sequence[Camera],
    x: np.ndarray,
    ia: Sequence[int],
    ib: Sequence[int],
    min_pairs: int,
) -> np.ndarray:
    """(C, C) median symmetric epipolar distance (px) between camera a's parts `ia` and camera
    b's parts `ib` at the same rows, for each camera pair a < b (symmetric; NaN with fewer than
    `min_pairs` part-frames seen by both); x: (N, K, C, 2) `normalised_points`."""
    C = len(cameras)
    focal = [focal_px(cam) for cam in cameras]
    out = np.full((C, C), np.nan)
    for a in range(C):
        for b in range(a + 1, C):
            xa, xb = x[:, list(ia), a], x[:, list(ib), b]
            ok = np.isfinite(xa).all(-1) & np.isfinite(xb).all(-1)
            if ok.sum() < min_pairs:
                continue
            E = essential(cameras[a], cameras[b])
            out[a, b] = out[b, a] = float(
                np.median(epipolar_px(E, xa[ok], xb[ok], focal[a], focal[b]))
            )
    return out


def block_rows(T: int, most: int, block: int) -> np.ndarray:
    """Rows 0..T-1, or, for T > `most`, blocks of `block` consecutive rows spread evenly over
    them (`most` rows in all): consecutive rows keep each frame's neighbours at hand."""
    if T <= most:
        return np.arange(T)
    starts = np.linspace(0, T - block, most // block).astype(np.int64)
    return np.unique((starts[:, None] + np.arange(block)[None]).ravel())


def rows_at(frames: np.ndarray, target: np.ndarray, order: np.ndarray | None = None) -> np.ndarray:
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


def homog(x: np.ndarray) -> np.ndarray:
    """Homogeneous coordinates (..., 3) of points x (..., 2)."""
    return np.concatenate([x, np.ones((*x.shape[:-1], 1))], axis=-1)


def epipolar_lines(h: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Epipolar lines h @ M of homogeneous points h (..., 3) and 1 / the norm of their normals."""
    line = h @ M
    return line, 1.0 / np.maximum(np.linalg.norm(line[..., :2], axis=-1), 1e-12)


def symmetric_px(hb, lb, inv_b, inv_a, fa: float, fb: float) -> np.ndarray:
    """The mean of b's distance (px) from a's epipolar line lb and a's from b's (inverse normal
    norms inv_b, inv_a): both share the residual |x_b^T E x_a|."""
    r = np.abs((hb * lb).sum(-1))
    return 0.5 * r * (fb * inv_b + fa * inv_a)


def epipolar_px(E: np.ndarray, xa: np.ndarray, xb: np.ndarray, fa: float, fb: float) -> np.ndarray:
    """Symmetric epipolar distance (px) of normalised points xa, xb (N, 2): the mean of b's
    distance from a's epipolar line (times fb) and a's from b's (times fa)."""
    ha, hb = homog(xa), homog(xb)
    lb, inv_b = epipolar_lines(ha, E.T)  # lines in b
    _, inv_a = epipolar_lines(hb, E)  # lines in a
    return symmetric_px(hb, lb, inv_b, inv_a, fa, fb)


def normalised_points(xy: np.ndarray, cameras: Sequence[Camera]) -> np.ndarray:
    """(N, K, C, 2) undistorted normalised coordinates of detections xy (N, K, C, 2) px (NaN
    where missing)."""
    out = np.full(xy.shape, np.nan)
    for c, cam in enumerate(cameras):
        ok = np.isfinite(xy[:, :, c]).all(-1)
        if ok.any():
            n = undistort_points(
                torch.as_tensor(xy[:, :, c][ok]),
                torch.as_tensor(cam.K),
                torch.as_tensor(cam.dist),
                fisheye=torch.tensor(cam.fisheye),
            )
            out[:, :, c][ok] = n.numpy()
    return out


def lag_curves(
    cameras: Sequence[Camera], det: Detections, max_offset: int, rows: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(lags (L,), curves (C, C, L)): curves[a, b, i] the median symmetric epipolar distance
    (px) between camera a at frame f and camera b at frame f + lags[i] over the parts both saw
    (NaN with fewer than `MIN_PAIRS`); curves[b, a] is curves[a, b] reversed in lag. Measured on
    the frames of ``rows`` (None: at most `MAX_FRAMES` rows, in blocks of `BLOCK` spread over
    the session)."""
    C = len(cameras)
    lags = np.arange(-max_offset, max_offset + 1)
    curves = np.full((C, C, lags.size), np.nan)
    frames = frame_numbers(det)
    T = len(frames)
    if rows is None:  # blocks of consecutive rows: few rows beyond them to undistort
        rows = block_rows(T, MAX_FRAMES, BLOCK)
    focal = [focal_px(cam) for cam in cameras]
    order = np.argsort(frames, kind="stable")
    at = [rows_at(frames, frames[rows] + L, order) for L in lags]  # rows of f + L
    # every lag on the same frames f (those with a row at every f + L): medians over other
    # frames would differ by what the animal did there, not by the lag
    common = np.logical_and.reduce([r >= 0 for r in at])
    rows, at = rows[common], [r[common] for r in at]
    need = np.unique(np.concatenate([rows, *[r[r >= 0] for r in at]]))
    x = normalised_points(det.xy[need], cameras)  # only the rows compared
    seen = np.isfinite(x).all(-1)  # (N, K, C)
    pairs = [(np.searchsorted(need, rows[r >= 0]), np.searchsorted(need, r[r >= 0])) for r in at]
    for a in range(C):
        for b in range(a + 1, C):
            E = essential(cameras[a], cameras[b])
            ha, hb = homog(x[:, :, a]), homog(x[:, :, b])
            lb, inv_b = epipolar_lines(ha, E.T)  # every row's lines, once per pair
            _, inv_a = epipolar_lines(hb, E)
            for i, (ra, rb) in enumerate(pairs):
                both = seen[ra, :, a] & seen[rb, :, b]
                if both.sum() < MIN_PAIRS:
                    continue
                d = symmetric_px(hb[rb], lb[ra], inv_b[ra], inv_a[rb], focal[a], focal[b])
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


def nan_reduce(fn, x: np.ndarray, axis: int) -> np.ndarray:
    """np.nanmedian / np.nanmean along `axis`, NaN where every value is (without its warning)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return fn(x, axis=axis)


def _frame_costs(cameras, det, x_of, c: int, lag: int, offsets, rows) -> np.ndarray:
    """(len(rows),) camera c at frame f + lag against each other camera d at f + o_d: the
    median over the parts of their symmetric epipolar distance (px), averaged over the pairs
    (NaN where no part was seen by both). ``x_of(r)``: normalised coordinates of rows r."""
    frames = frame_numbers(det)
    order = np.argsort(frames, kind="stable")
    rc = rows_at(frames, frames[rows] + lag, order)
    fc = focal_px(cameras[c])
    per = []
    for d in range(len(cameras)):
        if d == c:
            continue
        rd = rows_at(frames, frames[rows] + int(offsets[d]), order)
        ok = (rc >= 0) & (rd >= 0)
        dist = np.full((len(rows), det.num_parts), np.nan)
        if ok.any():
            xc, xd = x_of(rc[ok])[:, :, c], x_of(rd[ok])[:, :, d]
            both = np.isfinite(xc).all(-1) & np.isfinite(xd).all(-1)
            fd = focal_px(cameras[d])
            hc, hd = homog(np.nan_to_num(xc)), homog(np.nan_to_num(xd))
            E = essential(cameras[c], cameras[d])
            ld, inv_d = epipolar_lines(hc, E.T)
            _, inv_c = epipolar_lines(hd, E)
            dist[ok] = np.where(both, symmetric_px(hd, ld, inv_d, inv_c, fc, fd), np.nan)
        per.append(nan_reduce(np.nanmedian, dist, 1))
    return nan_reduce(np.nanmean, np.stack(per), 0)


def block_curves(cameras, det, max_offset: int) -> list[tuple[int, int, np.ndarray]]:
    """`lag_curves` of each block of about `BLOCK_FRAMES` consecutive frames (at most
    `MAX_BLOCKS` blocks, a longer one measured on its middle `BLOCK_FRAMES`): [(start, stop,
    curves)], start / stop positions in the frames' order."""
    order = np.argsort(frame_numbers(det), kind="stable")
    n = max(1, len(order) // max(BLOCK_FRAMES, len(order) // MAX_BLOCKS))
    edges = np.linspace(0, len(order), n + 1).astype(int)
    out = []
    for a, b in zip(edges[:-1], edges[1:]):
        mid = (a + b - BLOCK_FRAMES) // 2  # a longer block's lag from its middle frames
        rows = order[a:b] if b - a <= BLOCK_FRAMES else order[mid : mid + BLOCK_FRAMES]
        out.append((int(a), int(b), lag_curves(cameras, det, max_offset, rows=rows)[1]))
    return out


def block_lags(blocks, lags, offsets, c: int) -> list[tuple[int, int, int | None]]:
    """Camera c's lag in each block of `block_curves` (the others at `offsets`): [(start, stop,
    lag or None)]. The block's lag is the middle of the lags whose summed pair distance is
    within 2% of its least (a slow animal leaves a broad minimum); it is c's own offset where it
    lies within a frame of it, another lag where that is `SYNC_RATIO` below c's offset's and
    most pairs put their own minimum within a frame of it; None otherwise (a still animal, a
    camera with a wrong pose)."""
    out = []
    own_lag = int(offsets[c])
    for start, stop, cb in blocks:
        cost = np.array([_camera_cost(cb, lags, offsets, c, int(v)) for v in lags])
        lag = None
        if np.isfinite(cost).any():
            low = np.nanmin(np.where(np.isfinite(cost), cost, np.nan))
            mid = float(np.median(lags[cost <= 1.02 * low]))
            best = int(lags[int(np.nanargmin(np.where(np.isfinite(cost), cost, np.nan)))])
            v = int(mid) if mid == int(mid) else int(np.floor(mid) + (best > mid))
            if abs(v - own_lag) <= 1:
                lag = own_lag
            elif abs(v) >= int(lags[-1]):  # the least at the edge of the lags: a trend
                lag = None
            else:
                pairs = [d for d in range(cb.shape[0]) if d != c and np.isfinite(cb[c, d]).any()]
                own = [int(lags[int(np.nanargmin(cb[c, d]))]) for d in pairs]
                backed = sum(abs(o - (offsets[d] - v)) <= 1 for o, d in zip(own, pairs))
                at_own = cost[own_lag + int(lags[-1])]
                if at_own >= SYNC_RATIO * low and 2 * backed > len(pairs):
                    lag = v
        out.append((start, stop, lag))
    return out


def steps_of(cameras, det, blocks, lags, offsets, c: int) -> list[tuple[int, int]] | None:
    """Where camera c changes its lag during the session (a dropped frame): [(first frame,
    lag), ...] from the blocks that tell (`block_lags`; a change by one frame is taken for the
    jitter of a broad minimum), each change placed at the frame that best splits the stretch
    between two such blocks (per-frame epipolar costs at the two lags); None where every block
    that tells agrees. With two cameras a lag other than c's own must be told by two blocks
    (no other pair backs a block: a real hand's noisy 2-camera block read a 2-frame lag)."""
    known = []
    for a, b, v in block_lags(blocks, lags, offsets, c):
        if v is None:
            continue
        if known and abs(v - known[-1][2]) <= 1:  # a frame's jitter of a broad minimum:
            v = known[-1][2]  # changes of one frame are not told from it
        known.append((a, b, v))
    if len(cameras) == 2:  # no other pair backs a block's lag: a new lag needs two blocks
        told = {v: sum(k[2] == v for k in known) for *_, v in known}
        own = int(offsets[c])
        known = [k for k in known if k[2] == own or told[k[2]] >= 2]
    if len({v for *_, v in known}) <= 1:
        return None
    frames = frame_numbers(det)
    order = np.argsort(frames, kind="stable")
    cache: dict[int, np.ndarray] = {}

    def x_of(r: np.ndarray) -> np.ndarray:  # normalised rows, each undistorted once
        new = np.array([i for i in np.unique(r) if int(i) not in cache], dtype=np.int64)
        if new.size:
            for i, row in zip(new, normalised_points(det.xy[new], cameras)):
                cache[int(i)] = row
        return np.stack([cache[int(i)] for i in r])

    steps = [(int(frames[order[0]]), known[0][2])]
    for (s0, _, a), (_, e1, b) in zip(known, known[1:]):
        if a == b:
            continue
        span = order[s0:e1]
        ca = _frame_costs(cameras, det, x_of, c, a, offsets, span)
        cb = _frame_costs(cameras, det, x_of, c, b, offsets, span)
        # each frame weighs in for the lag that fits it better, by at most `SPLIT_CAP_PX` (a
        # swap or an outlier cannot outvote the rest); the split leaves the most weight for a
        # before it and for b after it
        score = np.nan_to_num(np.clip(cb - ca, -SPLIT_CAP_PX, SPLIT_CAP_PX))
        split = min(int(np.argmax(np.r_[0.0, np.cumsum(score)])), len(span) - 1)
        steps.append((int(frames[span[split]]), b))
    return steps


def shift_cameras(det: Detections, offsets: dict) -> Detections:
    """The detections with camera ``name`` read at frame f from its row for frame f + offset
    (missing where it has none); an offset is an int or (T,) ints, one per row (a camera whose
    lag changes during the session)."""
    if not any(np.any(o) for o in offsets.values()):
        return det
    frames = frame_numbers(det)
    if frames is None:
        raise ValueError("labelled images (frames by name) have no time order to shift")
    order = np.argsort(frames, kind="stable")
    xy, lik = det.xy.copy(), det.likelihood.copy()
    for name, o in offsets.items():
        if not np.any(o):
            continue
        c = det.cameras.index(name)
        src = rows_at(frames, frames + np.asarray(o, dtype=np.int64), order)
        ok = src >= 0
        xy[:, :, c] = np.nan
        lik[:, :, c] = 0.0
        xy[ok, :, c] = det.xy[src[ok], :, c]
        lik[ok, :, c] = det.likelihood[src[ok], :, c]
    return dataclasses.replace(det, xy=xy, likelihood=lik)


def row_offsets(det: Detections, steps: Sequence[tuple[int, int]]) -> np.ndarray:
    """(T,) int: each row's offset under `steps` [(first frame, offset), ...] (the first step's
    offset before its frame too)."""
    frames = frame_numbers(det)
    firsts = np.array([f for f, _ in steps])
    values = np.array([v for _, v in steps], dtype=np.int64)
    return values[np.clip(np.searchsorted(firsts, frames, side="right") - 1, 0, None)]


def check_sync(
    cameras: Sequence[Camera], det: Detections, max_offset: int, mode: str = "warn"
) -> tuple[Detections, dict]:
    """Find and undo frame offsets between the cameras (module doc). ``mode`` as the camera
    check's: warn = shift the camera back and say so, error = an `InputError` naming it, off =
    nothing. Returns the (shifted) detections and the report {"max_offset", "offsets" {name:
    frames}, "epipolar_px" {name: [at 0, at the offset]}, "steps" {name: [[first frame,
    offset], ...]} (a lag that changes during the session; `steps_of`)} (only where found)."""
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
        if not pairs or 2 * len(backing) <= len(pairs) or abs(offsets[c]) >= max_offset:
            continue  # (a least at the edge of the lags: no minimum, a trend)
        found[cam.name] = int(offsets[c])
        zero = _camera_cost(curves, lags, offsets, c, 0) / len(pairs)
        at = _camera_cost(curves, lags, offsets, c, int(offsets[c])) / len(pairs)
        report["epipolar_px"][cam.name] = [round(zero, 3), round(at, 3)]
    # a lag that changes during the session (a camera that dropped frames): block by block
    accepted = np.array([found.get(cam.name, 0) for cam in cameras], dtype=np.int64)
    blocks = block_curves(cameras, det, max_offset) if det.num_frames >= 2 * BLOCK_FRAMES else []
    steps: dict[str, list[tuple[int, int]]] = {}
    for c, cam in enumerate(cameras):
        if len(cameras) == 2 and c == 0:  # two cameras: the first keeps the session's time
            continue
        st = steps_of(cameras, det, blocks, lags, accepted, c) if len(blocks) > 1 else None
        if st is not None:
            steps[cam.name] = st
            found.pop(cam.name, None)
            report["epipolar_px"].pop(cam.name, None)
    if not found and not steps:
        return det, report
    report["offsets"] = found
    report["steps"] = {n: [[f, v] for f, v in st] for n, st in steps.items()}
    names = [cam.name for cam in cameras]
    for name, o in found.items():
        c = names.index(name)
        zero, at = report["epipolar_px"][name]
        msg = (
            f"camera '{name}' ({det.files[c]}) is {abs(o)} frame{'s' * (abs(o) != 1)} out of "
            f"step with the others: its frame f {'+' if o > 0 else '-'} {abs(o)} matches their "
            f"frame f (its detections lie {zero:.1f} px from the other cameras' epipolar lines "
            f"in step, {at:.1f} px shifted; a video started early or late?)"
        )
        _say(msg, mode, f"SHIFTED back by {o} frames")
    for name, st in steps.items():
        c = names.index(name)
        said = ", ".join(f"{v:+d} from frame {f}" for f, v in st)
        msg = (
            f"camera '{name}' ({det.files[c]}) changes its step with the others during the "
            f"session (its frame f + offset matches their frame f): {said} (dropped or "
            "repeated frames?)"
        )
        _say(msg, mode, "SHIFTED back piecewise")
    shifts: dict = dict(found)
    shifts.update({n: row_offsets(det, st) for n, st in steps.items()})
    return shift_cameras(det, shifts), report


def _say(msg: str, mode: str, done: str) -> None:
    """The warning (mode warn) or the error (mode error) about a camera out of step."""
    if mode == "error":
        raise InputError(
            msg + "; fix its frame numbers, or set input.camera_check=warn to shift it back "
            "(input.max_frame_offset=0: no check)"
        )
    log.warning("%s; %s (input.camera_check=warn)", msg, done)
