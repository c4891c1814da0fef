"""Cameras that moved during the session: find a camera bumped mid-session (its mount knocked,
slipped or turned) and map its detections after the move back into its calibrated view; and,
first, a camera turned since its calibration (bumped between it and the recording: off over
the whole session, no step in time; three cameras or more, `_since_calibration`).

    det, report = check_moves(cameras, det, max_moves=3, mode="warn")

The calibration holds one pose per camera; a camera turned by a fraction of a degree in the
middle of a session puts its later detections a few pixels off where the rig expects them.
That is below the camera check's 25 px (`adjust.camera_check`), and the tracks come out worse
with nothing said; a larger turn gets the whole camera excluded, its good frames too.

For every frame and pair of cameras (a, b), the median over the parts both saw of the
symmetric distance (px) of each detection from the other's epipolar line (`pair_series`). A
camera c that moved at frame F raises its pairs' series from F on and leaves the other pairs
as they were. Per camera, the mean of its pairs' series is split where one step fits it best
(`split`: two levels, least absolute deviations); a move is a step whose higher level is at
least ``STEP_RATIO`` (2) times and ``STEP_PX`` (1 px) above the lower, over at least
``MIN_FRAMES`` frames on each side, while the pairs without c step by less than
``OTHERS_RATIO`` (1.5); it must not begin at the session's start
(the calibration is taken to hold there: a lens model a little off read moves over the
first few hundred frames, where the mouse stayed in one place).

Every camera's turn about its centre on the higher side is then fitted to its pairs' epipolar
constraints (`fit_rotation`: robust least squares over 3 parameters); the turn that leaves the
rig's distances there lowest must cut their rise at least by half, and the step must hold
for that camera where the parts were at the same places in the images (`same_place`,
``SAME_RATIO`` 1.5x: a calibration's error differs from place to place, and an animal that
stays somewhere for a while steps the distances too). Where several cameras'
turns fit to within ``TELL_RATIO`` (1.25) of it (two cameras always: a turn of either about
most axes; three in a plane, e.g. a top camera and two side cameras facing each other: a tilt
of either side camera), the parts' continuity at the move tells (`jump_mm`: a wrong camera's
turn makes the triangulated parts jump there, by ``JUMP_RATIO`` times and ``JUMP_MM`` more
than the right one's); where it does not, the move is *unresolved*: warned about and
reported, not mapped (a wrong camera's turn tracks worse than none). An accepted move is
undone (`unrotate`: each detection's ray turned back into the calibrated camera; exact for a
turn about the camera's centre, a camera also shifted keeps a parallax the report's
``after_px`` shows) and the check repeats, up to ``max_moves`` moves. A turn that slides the
images along the epipolar lines (a pan of one of two cameras facing each other, a roll of a
few tenths of a degree) is not seen by any check on the detections.

The step is found among at most `MAX_FRAMES` frames (blocks spread over a longer session);
each candidate camera then places it among every frame about it by its own turn (`_refine`;
in a long session tracked in chunks the camera check sees only its sample, so there a move is
placed within the gaps between the sample's blocks).

Modes (the camera check's): ``warn``: undone, with a warning naming camera, file and frame;
``error``: an `InputError` instead; ``off``: no check. A gradual drift, a camera moved
without turning, and a move within `MIN_FRAMES` of a session's ends are not told.
Detections: ``Detections`` (T, K, C, 2) px; rotations in radians (rotation vectors), world ->
camera ``x = R X + t``.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np
import torch
from scipy.optimize import least_squares
from scipy.stats import theilslopes

from adjust.camera import Camera, camera_to_pixels
from adjust.io import Detections, InputError
from adjust.sync import (
    epipolar_lines,
    essential,
    focal_px,
    frame_numbers,
    homog,
    nan_reduce,
    normalised_points,
    symmetric_px,
)
from adjust.triangulate import triangulate
from deformnet.so3 import matrix_to_rodrigues, rodrigues_to_matrix

log = logging.getLogger(__name__)

STEP_RATIO = 2.0  #: a move raises its camera's pairs' median epipolar distance this many times
STEP_PX = 1.0  #: ... and by at least this much (px)
OTHERS_RATIO = 1.5  #: ... while the pairs without the camera rise by less than this factor
TELL_RATIO = 1.25  #: cameras whose turns fit to within this factor of the best are alike
MIN_FRAMES = 100  #: frames with a measured distance each side of a move needs
MIN_PARTS = 2  #: parts a pair must see together in a frame for the frame to count
MAX_FRAMES = 20_000  #: frames measured (in blocks spread over a longer session)
SAMPLE_BLOCK = 500  #: consecutive frames per block of that sample
SPLIT_BLOCKS = 1_000  #: the step is first placed among at most this many block medians
FIT_POINTS = 4_000  #: part-frames per pair the rotation is fitted to (spread over the side)
HUBER_PX = 2.0  #: the fit's robust scale (px)
PRIOR_RAD = np.deg2rad(1.0)  #: a turn this large weighs as one residual of `HUBER_PX` (prior)
PLACE_FRAMES = 25  #: a move's frame is placed again among this many frames each side
CELL_PX = 128  #: image cells within which distances before and after a step are compared
MIN_PLACED = 50  #: part-frames at shared places each side needs
SAME_RATIO = 1.5  #: there the step must still be this large (a 0.3-degree tilt: 1.9x)
SAME_PX = 0.5  #: ... and this many px
JUMP_FRAMES = (8, 12, 16, 20, 24)  #: windows (frames each side of a move) whose parts'
#: continuity tells which camera moved
JUMP_MIN = 4  #: ... points a part needs on each side
JUMP_RATIO = 1.5  #: the other camera's turn must make the parts jump this many times farther
JUMP_MM = 0.5  #: ... and by this much more (mm)
TELL_PX = 0.25  #: since calibration: turns within this of the best's excess (px) are alike
MAX_BUMP_DEG = 5.0  #: a camera turned since its calibration by more is a wrong pose, no bump


def rotate(x: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Normalised points x (..., 2) turned by rotation Q (3, 3): the rays Q [x, 1], divided by
    their depth (NaN where it is not positive)."""
    r = homog(x) @ Q.T
    z = r[..., 2:]
    return np.where(z > 1e-9, r[..., :2] / np.where(z > 1e-9, z, 1.0), np.nan)


def pair_distances(x: np.ndarray, cams: Sequence[Camera], a: int, b: int) -> np.ndarray:
    """(N, K) symmetric epipolar distance (px) between cameras a and b of normalised points x
    (N, K, C, 2) (NaN where either did not see the part)."""
    xa, xb = x[:, :, a], x[:, :, b]
    both = np.isfinite(xa).all(-1) & np.isfinite(xb).all(-1)
    ha, hb = homog(np.nan_to_num(xa)), homog(np.nan_to_num(xb))
    E = essential(cams[a], cams[b])
    lb, inv_b = epipolar_lines(ha, E.T)
    _, inv_a = epipolar_lines(hb, E)
    d = symmetric_px(hb, lb, inv_b, inv_a, focal_px(cams[a]), focal_px(cams[b]))
    return np.where(both, d, np.nan)


def pair_series(
    x: np.ndarray, cams: Sequence[Camera], a: int, b: int, min_parts: int = MIN_PARTS
) -> np.ndarray:
    """(N,) each frame's median over the parts of `pair_distances` (NaN with fewer than
    `min_parts` parts seen by both)."""
    d = pair_distances(x, cams, a, b)
    enough = np.isfinite(d).sum(1) >= min_parts
    return np.where(enough, nan_reduce(np.nanmedian, d, 1), np.nan)


def split(s: np.ndarray, min_frames: int = MIN_FRAMES) -> tuple[int, float, float] | None:
    """Where one step fits the series s (N,) best: (first index after it, the median before,
    the median after), by least absolute deviations from two levels; first among block medians
    (at most `SPLIT_BLOCKS`), then frame by frame near the chosen block edge. None where fewer
    than 2 * `min_frames` values are finite."""
    idx = np.flatnonzero(np.isfinite(s))
    v = s[idx]
    n = v.size
    if n < 2 * min_frames:
        return None
    bs = max(int(np.ceil(n / SPLIT_BLOCKS)), 5)
    nb = n // bs
    bm = np.median(v[: nb * bs].reshape(nb, bs), axis=1)
    lo_b = max(1, int(np.ceil(min_frames / bs)))
    best, jb = np.inf, None
    for j in range(lo_b, nb - lo_b + 1):
        left, right = bm[:j], bm[j:]
        cost = np.abs(left - np.median(left)).sum() + np.abs(right - np.median(right)).sum()
        if cost < best:
            best, jb = cost, j
    if jb is None:
        return None
    m0, m1 = np.median(v[: jb * bs]), np.median(v[jb * bs :])
    c0 = np.r_[0.0, np.cumsum(np.abs(v - m0))]  # cost of v[:i] at level m0
    c1 = np.r_[0.0, np.cumsum(np.abs(v - m1))]
    cost = c0 + (c1[-1] - c1)  # a split before index i
    lo = max(min_frames, (jb - 2) * bs)
    hi = min(n - min_frames, (jb + 2) * bs)
    i = lo + int(np.argmin(cost[lo : hi + 1])) if hi >= lo else jb * bs
    return int(idx[i]), float(np.median(v[:i])), float(np.median(v[i:]))


def _mean_series(x, cams, c: int, others: Sequence[int], min_parts: int = MIN_PARTS) -> np.ndarray:
    series = [pair_series(x, cams, c, d, min_parts) for d in others]
    return nan_reduce(np.nanmean, np.stack(series), 0)


def fit_rotation(
    x: np.ndarray, cams: Sequence[Camera], c: int, others: Sequence[int], rows: np.ndarray
) -> np.ndarray:
    """(3, 3) rotation Q that turns camera c's normalised points of `rows` (x: (N, K, C, 2))
    back into its calibrated view, fitted to the epipolar constraints of its pairs with
    `others` (robust least squares, `HUBER_PX`; at most `FIT_POINTS` part-frames per pair),
    with a prior of `PRIOR_RAD` on the turn: a direction the constraints do not see (a slide
    along the epipolar lines) stays at no turn."""
    data = []
    for d in others:
        xc, xd = x[rows, :, c].reshape(-1, 2), x[rows, :, d].reshape(-1, 2)
        ok = np.flatnonzero(np.isfinite(xc).all(-1) & np.isfinite(xd).all(-1))
        if ok.size > FIT_POINTS:
            ok = ok[np.linspace(0, ok.size - 1, FIT_POINTS).astype(int)]
        if ok.size:
            E = essential(cams[c], cams[d])
            data.append((E, xc[ok], xd[ok], focal_px(cams[c]), focal_px(cams[d])))

    def residuals(w: np.ndarray) -> np.ndarray:
        Q = rodrigues_to_matrix(torch.as_tensor(w)).numpy()
        out = []
        for E, xc, xd, fc, fd in data:
            xq = rotate(xc, Q)
            hc, hd = homog(np.nan_to_num(xq)), homog(xd)
            ld, inv_d = epipolar_lines(hc, E.T)
            _, inv_c = epipolar_lines(hd, E)
            r = (hd * ld).sum(-1) * 0.5 * (fd * inv_d + fc * inv_c)  # signed symmetric px
            out.append(np.where(np.isfinite(xq).all(-1), r, 0.0))
        # a turn that slides the image along the epipolar lines is not seen (two cameras;
        # cameras in a plane): held at none rather than left to drift
        out.append(HUBER_PX * np.asarray(w) / PRIOR_RAD)
        return np.concatenate(out)

    fit = least_squares(residuals, np.zeros(3), loss="huber", f_scale=HUBER_PX, x_scale=1e-3)
    return rodrigues_to_matrix(torch.as_tensor(fit.x)).numpy()


def unrotate(xy: np.ndarray, cam: Camera, Q: np.ndarray) -> np.ndarray:
    """Pixels xy (..., 2) of camera `cam` after it turned, mapped back into its calibrated view:
    each ray turned by Q (3, 3) and projected with the camera's own intrinsics and distortion
    (NaN stays NaN, as do rays turned behind it)."""
    ok = np.isfinite(xy).all(-1)
    out = np.full(xy.shape, np.nan)
    if not ok.any():
        return out
    n = normalised_points(xy[ok].reshape(-1, 1, 1, 2), [cam])[:, 0, 0]
    ray = torch.as_tensor(homog(n) @ Q.T)
    u, v, _ = camera_to_pixels(
        ray, torch.as_tensor(cam.K), torch.as_tensor(cam.dist), fisheye=torch.tensor(cam.fisheye)
    )
    px = torch.stack((u, v), -1).numpy()
    out[ok] = np.where((ray[:, 2] > 1e-9).numpy()[:, None], px, np.nan)
    return out


def apply_moves(det: Detections, cameras: Sequence[Camera], moves: Sequence[dict]) -> Detections:
    """The detections with each move of the report undone: camera ``camera``'s rows of frames
    ``first_frame`` <= f < ``end_frame`` (None: to the end) turned back by ``rotvec`` (the
    frame numbers of the files, so a sample of rows or a chunk is mapped exactly)."""
    if not moves:
        return det
    frames = frame_numbers(det)
    if frames is None:
        raise ValueError("labelled images (frames by name) have no time order to map")
    by_name = {cam.name: cam for cam in cameras}
    xy = det.xy.copy()
    for m in moves:
        if m["camera"] not in det.cameras:
            continue
        c = det.cameras.index(m["camera"])
        rows = frames >= m["first_frame"]
        if m.get("end_frame") is not None:
            rows &= frames < m["end_frame"]
        Q = rodrigues_to_matrix(torch.as_tensor(np.asarray(m["rotvec"], float))).numpy()
        xy[rows, :, c] = unrotate(xy[rows, :, c], by_name[m["camera"]], Q)
    return dataclasses.replace(det, xy=xy)


def _sample_rows(T: int) -> np.ndarray:
    if T <= MAX_FRAMES:
        return np.arange(T)
    starts = np.linspace(0, T - SAMPLE_BLOCK, MAX_FRAMES // SAMPLE_BLOCK).astype(np.int64)
    return np.unique((starts[:, None] + np.arange(SAMPLE_BLOCK)[None]).ravel())


def rig_px(cameras: Sequence[Camera], det: Detections) -> float:
    """How well the cameras agree (px): the median over the frames (at most `MAX_FRAMES`, in
    blocks) of the mean over every camera pair of `pair_series`."""
    rows = np.argsort(frame_numbers(det), kind="stable")[_sample_rows(det.num_frames)]
    x = normalised_points(det.xy[rows], cameras)
    return _rig_level(x, cameras, np.arange(len(rows)))


def _rig_level(x, cams, rows) -> float:
    """The median over `rows` of the mean over every camera pair of `pair_series` (px)."""
    C = len(cams)
    s = nan_reduce(
        np.nanmean,
        np.stack([pair_series(x[rows], cams, a, b) for a in range(C) for b in range(a + 1, C)]),
        0,
    )
    s = s[np.isfinite(s)]
    return float(np.median(s)) if s.size else float("nan")


def _near(det: Detections, frame: int) -> Detections:
    """The rows of `det` within `max(JUMP_FRAMES)` frames of `frame`."""
    frames = frame_numbers(det)
    rows = np.flatnonzero(np.abs(frames - (frame - 0.5)) < max(JUMP_FRAMES))
    return dataclasses.replace(
        det, xy=det.xy[rows], likelihood=det.likelihood[rows], frames=frames[rows]
    )


def _at_step(f: np.ndarray, y: np.ndarray) -> float:
    """A part's coordinate y at f = 0 (the step) from its values at frames f on one side: a
    parabola through the points within 3 robust deviations (at least 2 mm) of a Theil-Sen line
    (a swapped pair of views puts a point tens of mm off; a moving animal's path bends)."""
    slope, icpt, *_ = theilslopes(y, f)
    r = np.abs(y - (icpt + slope * f))
    keep = r <= max(3 * 1.4826 * float(np.median(r)), 2.0)
    if keep.sum() < 5:
        return float(icpt)
    return float(np.polyval(np.polyfit(f[keep], y[keep], 2), 0.0))


def jump_mm(det: Detections, cams: Sequence[Camera], first: int) -> float:
    """How far the triangulated parts jump at frame `first` (mm): per part, a robust parabola
    (`_at_step`) through its points over the W frames before and one through those after,
    their gap at the step; the length of the parts' median gap vector (a wrong camera's turn moves
    every part alike, the lines' own errors differ part by part), over the parts with
    `JUMP_MIN` points on each side; the median over the windows W of `JUMP_FRAMES` (the
    animal's own motion bends the paths differently in each). About 1 mm where the animal
    moves slowly, 2-5 mm where it moves 2-3 mm per frame (the real motion at 100 fps). NaN
    where no window has such a part."""
    frames = frame_numbers(det)
    xy, weight = det.xy, det.weight()
    near = np.flatnonzero(np.abs(frames - (first - 0.5)) < max(JUMP_FRAMES))
    if near.size < 2 * JUMP_MIN:
        return float("nan")
    X = triangulate(xy[near], weight[near], cams, robust=True).points.numpy()  # (n, K, 3)
    f = frames[near].astype(float) - (first - 0.5)
    out = []
    for w in JUMP_FRAMES:
        gaps = []
        for k in range(X.shape[1]):
            ends = []
            for side in (f < 0, f > 0):
                ok = side & (np.abs(f) < w) & np.isfinite(X[:, k]).all(-1)
                if ok.sum() < JUMP_MIN:
                    break
                ends.append(np.array([_at_step(f[ok], X[ok, k, j]) for j in range(3)]))
            if len(ends) == 2:
                gaps.append(ends[1] - ends[0])
        if gaps:
            out.append(float(np.linalg.norm(np.median(np.stack(gaps), 0))))
    return float(np.median(out)) if out else float("nan")


def same_place(x, cams, c: int, good, bad) -> tuple[float, float] | None:
    """Camera c's epipolar distances (px) on the rows `good` and `bad`, compared where the
    parts were at the same places: part-frames binned by their cells (`CELL_PX`) in camera c's
    image and in the other camera's (so the 3D place, its depth too), pooled over c's pairs;
    (median on the good rows, median on the bad rows) over the cells both hold, or None with
    fewer than `MIN_PLACED` part-frames on either side. A calibration's error differs from
    place to place in the images (a lens model a little off), so an animal that stays
    somewhere for a while raises the distances without any camera moving; a move raises them
    at the same places."""
    pools: tuple[list, list] = ([], [])
    for d in range(len(cams)):
        if d == c:
            continue
        dist = pair_distances(x, cams, c, d)  # (N, K)
        cell = np.concatenate(
            [np.floor(x[:, :, k] * focal_px(cams[k]) / CELL_PX) for k in (c, d)], axis=-1
        )  # (N, K, 4): the place in both images (a 3D place, its depth too)
        keys: tuple[dict, dict] = ({}, {})
        for side, rows in enumerate((good, bad)):
            ok = np.isfinite(dist[rows])
            for key, v in zip(map(tuple, cell[rows][ok].astype(np.int64)), dist[rows][ok]):
                keys[side].setdefault(key, []).append(v)
        for key in keys[0].keys() & keys[1].keys():
            for side in (0, 1):
                pools[side].extend(keys[side][key])
    if min(len(pools[0]), len(pools[1])) < MIN_PLACED:
        return None
    return float(np.median(pools[0])), float(np.median(pools[1]))


def _find(x, cams, frames, det) -> tuple[dict | None, str | None]:
    """The next move in the sampled rows (normalised points x (N, K, C, 2), frame numbers
    `frames`) of the detections `det` (every row, the moves found so far undone), as (move,
    None); (None, why) where a step is seen but not explained; (None, None) where there is
    none. The move has ``ambiguous`` where more than one camera's turn explains it and the
    parts' continuity at the step does not tell."""
    C = len(cams)
    found, series_of = [], {}
    for c in range(C):
        others = [d for d in range(C) if d != c]
        series_of[c] = _mean_series(x, cams, c, others)
        sp = split(series_of[c])
        if sp is None:
            continue
        i, m0, m1 = sp
        lo, hi = min(m0, m1), max(m0, m1)
        if hi >= STEP_RATIO * lo and hi - lo >= STEP_PX:
            found.append((hi / max(lo, 1e-9), c, i, m0, m1))
    if not found:
        return None, None
    _, c, i, m0, m1 = max(found)
    N = x.shape[0]
    b0, b1 = (i, N) if m1 > m0 else (0, i)
    low = min(m0, m1)
    series = series_of[c]
    while True:  # a camera turned and put back: the higher side holds a second step
        sp = split(series[b0:b1])
        if sp is None:
            break
        j, n0, n1 = sp
        if not (max(n0, n1) >= STEP_RATIO * min(n0, n1) and min(n0, n1) <= OTHERS_RATIO * low):
            break
        b0, b1 = (b0 + j, b1) if n1 > n0 else (b0, b0 + j)
    if b0 == 0:  # the calibration is taken to hold at the session's start
        return None, (
            f"the epipolar distances of camera '{cams[c].name}' are higher from the session's "
            f"start to frame {int(frames[b1])} than after: the calibration is taken to hold at "
            "the start (an animal that stays in one place first, where the calibration is a "
            "little off, looks so), not a move"
        )
    bad = np.arange(b0, b1)
    good = np.setdiff1d(np.arange(N), bad)
    m0, m1 = low, float(np.nanmedian(series[bad]))
    first = int(frames[bad[0]])
    end = None if bad[-1] == N - 1 else int(frames[bad[-1]] + 1)
    where = f"frames {first}-{'end' if end is None else end - 1}"
    if C >= 3:
        rest = [d for d in range(C) if d != c]
        pairs = [pair_series(x, cams, a, b) for a in rest for b in rest if a < b]
        s = nan_reduce(np.nanmean, np.stack(pairs), 0)
        sb, sg = s[bad][np.isfinite(s[bad])], s[good][np.isfinite(s[good])]
        if sb.size and sg.size and np.median(sb) > OTHERS_RATIO * np.median(sg):
            return None, (
                f"the epipolar distances of every camera pair rise over {where} "
                f"({np.median(sg):.1f} -> {np.median(sb):.1f} px without camera "
                f"'{cams[c].name}'): not one camera's move"
            )
    at_good, at_bad = _rig_level(x, cams, good), _rig_level(x, cams, bad)
    fits = []
    for k in range(C):  # every camera's turn: which one explains the step
        Q = fit_rotation(x, cams, k, [d for d in range(C) if d != k], bad)
        xq = x.copy()
        xq[bad, :, k] = rotate(x[bad, :, k], Q)
        fits.append((_rig_level(xq, cams, bad), k, Q))
    fits.sort(key=lambda f: f[0])
    level, k, Q = fits[0]
    if not level - at_good <= 0.5 * (at_bad - at_good):
        return None, (
            f"the epipolar distances of camera '{cams[c].name}' rise over {where} "
            f"({min(m0, m1):.1f} -> {max(m0, m1):.1f} px) and no turn of a camera explains it "
            f"(the rig's {at_good:.1f} -> {at_bad:.1f} px, turned back at best {level:.1f} px)"
        )
    log.debug("camera move fits: %s", [(cams[f[1]].name, round(f[0], 3)) for f in fits])
    alike = [f for f in fits if f[0] <= TELL_RATIO * level]
    # the step was placed among the frames whose distances told (a pair seeing two parts, in
    # the sample) by the mean over camera c's pairs: each candidate places it again among
    # every frame in between and `PLACE_FRAMES` about it, by its own turn's fit
    told = np.flatnonzero(np.isfinite(series))
    lo = int(frames[told[told < b0][-1]]) if b0 > 0 and (told < b0).any() else None
    last, hi = int(frames[told[told < b1][-1]]), int(frames[b1]) if b1 < N else None
    placed = {}
    for _, kk, QQ in alike:
        f0 = first if lo is None else _refine(det, cams, kk, QQ, min(lo, first - PLACE_FRAMES),
                                             first + PLACE_FRAMES, True)  # fmt: skip
        f1 = end if hi is None else _refine(det, cams, kk, QQ, min(last, end - PLACE_FRAMES),
                                           hi + PLACE_FRAMES, False)  # fmt: skip
        placed[kk] = (f0, f1)
    jumps = {}
    if len(alike) > 1:  # the parts' continuity at the step tells which camera turned
        for _, kk, QQ in alike:
            f0, f1 = placed[kk]
            step = f0 if lo is not None else f1  # where the calibration's state meets the turn
            move = {"camera": cams[kk].name, "first_frame": f0, "end_frame": f1,
                    "rotvec": _rotvec(QQ)}  # fmt: skip
            jumps[kk] = jump_mm(apply_moves(_near(det, step), cams, [move]), cams, step)
        order = sorted(jumps, key=lambda kk: (not np.isfinite(jumps[kk]), jumps[kk]))
        k = order[0]
        Q = next(f[2] for f in alike if f[1] == k)
        level = next(f[0] for f in alike if f[1] == k)
    first, end = placed[k]
    here = same_place(x, cams, k, good, bad)
    if here is None or not (here[1] >= SAME_RATIO * here[0] and here[1] - here[0] >= SAME_PX):
        return None, (
            f"the epipolar distances of camera '{cams[k].name}' rise over {where}, but not "
            f"against frames where the parts were at the same places in the images "
            f"({'too few of them' if here is None else f'{here[0]:.1f} -> {here[1]:.1f} px'}): "
            "the calibration's error differs from place to place, not a move"
        )
    moved = {
        "camera": cams[k].name,
        "first_frame": first,
        "end_frame": end,
        "rotvec": [float(v) for v in _rotvec(Q)],
        "degrees": float(np.degrees(np.linalg.norm(_rotvec(Q)))),
        "others_px": round(at_good, 3),
        "before_px": round(at_bad, 3),
        "after_px": round(level, 3),
    }
    if jumps:
        moved["jump_mm"] = {cams[kk].name: round(v, 3) for kk, v in jumps.items()}
        ranked = sorted(jumps.values(), key=lambda v: (not np.isfinite(v), v))
        if not (np.isfinite(ranked[0]) and ranked[1] >= JUMP_RATIO * ranked[0] + JUMP_MM):
            moved["ambiguous"] = [cams[f[1]].name for f in alike]
    return moved, None


def _since_calibration(x, cams) -> tuple[dict | None, str | None]:
    """A camera turned before the session, after its calibration (bumped between the two), in
    the sampled rows (normalised points x (N, K, C, 2)): (move, None) with the move's camera,
    rotvec and distances (its frames: the whole session); (None, why) where a camera lies off
    and no turn, or more than one camera's, explains it; (None, None) where none lies off.
    Three cameras or more: a camera is off where the median over the frames of the mean over
    its pairs of `pair_series` is `STEP_RATIO` times and `STEP_PX` above that of the pairs
    without it, and that series has no such step in time (a camera moved during the session,
    off over most of it, is `_find`'s); every camera's turn is fitted over the session
    (`fit_rotation`), and the best must cut the rig's excess over those pairs by half, by a
    turn of at most `MAX_BUMP_DEG` (the real SLEAP mouse's `side` camera, given `top`'s pose,
    fits to 2.8 px turned by 44 degrees: a wrong pose, the camera check's), no other camera's
    excess coming within `TELL_RATIO` times and `TELL_PX` of its own (with no step in time,
    the parts' continuity cannot tell; excesses, not levels: the right camera's turn leaves
    about none, a wrong one 0.1-0.2 px at three cameras, 0.4 px at four, over 1.6 px)."""
    C = len(cams)
    if C < 3:
        return None, None
    rows = np.arange(x.shape[0])
    off = []
    for c in range(C):
        rest = [d for d in range(C) if d != c]
        own = _mean_series(x, cams, c, rest)
        pairs = [pair_series(x, cams, a, b) for a in rest for b in rest if a < b]
        without = nan_reduce(np.nanmean, np.stack(pairs), 0)
        if not (np.isfinite(own).any() and np.isfinite(without).any()):
            continue
        m_own, m_rest = float(np.nanmedian(own)), float(np.nanmedian(without))
        sp = split(own)
        lo, hi = (min(sp[1:]), max(sp[1:])) if sp is not None else (0.0, 0.0)
        if hi >= STEP_RATIO * lo and hi - lo >= STEP_PX:
            continue  # a step in time: a move during the session (`_find`'s)
        if m_own >= STEP_RATIO * m_rest and m_own - m_rest >= STEP_PX:
            off.append((m_own / max(m_rest, 1e-9), c, m_rest))
    if not off:
        return None, None
    _, c, at_good = max(off)
    at_bad = _rig_level(x, cams, rows)
    fits = []
    for k in range(C):
        Q = fit_rotation(x, cams, k, [d for d in range(C) if d != k], rows)
        xq = x.copy()
        xq[:, :, k] = rotate(x[:, :, k], Q)
        fits.append((_rig_level(xq, cams, rows), k, Q))
    fits.sort(key=lambda f: f[0])
    level, k, Q = fits[0]
    log.debug("camera turn fits: %s", [(cams[f[1]].name, round(f[0], 3)) for f in fits])
    name = cams[c].name
    if np.degrees(np.linalg.norm(_rotvec(Q))) > MAX_BUMP_DEG:
        return None, (
            f"the detections of camera '{name}' lie off the other cameras' epipolar lines "
            f"over the whole session (the rig's {at_bad:.1f} px, {at_good:.1f} px without it); "
            f"camera '{cams[k].name}' turned by "
            f"{np.degrees(np.linalg.norm(_rotvec(Q))):.0f} deg would fit: no bump, a wrong "
            "pose (the camera check judges it)"
        )
    if not level - at_good <= 0.5 * (at_bad - at_good):
        return None, (
            f"the detections of camera '{name}' lie off the other cameras' epipolar lines "
            f"over the whole session (the rig's {at_bad:.1f} px, {at_good:.1f} px without it) "
            f"and no turn of a camera explains it (turned back at best {level:.1f} px): its "
            "calibration is off in another way (intrinsics, lens model)?"
        )
    excess = max(level - at_good, 0.0)
    alike = [cams[f[1]].name for f in fits if f[0] - at_good <= TELL_RATIO * excess + TELL_PX]
    moved = {
        "camera": cams[k].name,
        "first_frame": None,  # the whole session (set by the caller)
        "end_frame": None,
        "rotvec": [float(v) for v in _rotvec(Q)],
        "degrees": float(np.degrees(np.linalg.norm(_rotvec(Q)))),
        "others_px": round(at_good, 3),
        "before_px": round(at_bad, 3),
        "after_px": round(level, 3),
        "since_calibration": True,
    }
    if len(alike) > 1:
        moved["ambiguous"] = alike
    return moved, None


def _refine(det, cameras, c: int, Q: np.ndarray, lo: int, hi: int, entering: bool) -> int:
    """Where in (lo, hi] (frame numbers) camera c's detections start (`entering`) or stop
    fitting its turn Q better than its calibration: every frame of `det` there weighs in for
    the state that fits it better, by at most 1 px (as `adjust.sync` places a change). Returns
    the new state's first frame."""
    frames = frame_numbers(det)
    rows = np.flatnonzero((frames > lo) & (frames <= hi))
    rows = rows[np.argsort(frames[rows], kind="stable")]
    others = [d for d in range(len(cameras)) if d != c]
    x = normalised_points(det.xy[rows], cameras)
    raw = _mean_series(x, cameras, c, others, 1)  # every part seen by a pair has a say
    x[:, :, c] = rotate(x[:, :, c], Q)
    score = np.nan_to_num(np.clip(raw - _mean_series(x, cameras, c, others, 1), -1.0, 1.0))
    prefix = np.r_[0.0, np.cumsum(score if entering else -score)]
    i = int(np.argmin(prefix))  # before i the old state fits better, from i the new one
    return int(frames[rows[i]]) if i < rows.size else int(hi)


def _rotvec(Q: np.ndarray) -> np.ndarray:
    return matrix_to_rodrigues(torch.as_tensor(Q)).numpy()


def _undo(x: np.ndarray, frames: np.ndarray, c: int, move: dict) -> None:
    """Turn camera c's normalised points x (N, K, C, 2) of the rows whose frame numbers
    `frames` (N,) the `move` spans back into its calibrated view, in place."""
    sel = np.flatnonzero(frames >= move["first_frame"])
    if move["end_frame"] is not None:
        sel = sel[frames[sel] < move["end_frame"]]
    Q = rodrigues_to_matrix(torch.as_tensor(np.asarray(move["rotvec"]))).numpy()
    x[sel, :, c] = rotate(x[sel, :, c], Q)


def _named(det: Detections, which) -> str:
    """Cameras `which` as a warning names them: 'name' (file), ..."""
    return ", ".join(f"'{n}' ({det.files[det.cameras.index(n)]})" for n in which)


def _say(mode: str, msg: str, fix: str, done: str) -> None:
    """A finding `msg`: an `InputError` with the way out `fix` (mode error), else a warning
    with what was `done` about it."""
    if mode == "error":
        raise InputError(msg + fix)
    log.warning("%s; %s (input.camera_check=warn)", msg, done)


def check_moves(
    cameras: Sequence[Camera], det: Detections, max_moves: int = 3, mode: str = "warn"
) -> tuple[Detections, dict]:
    """Find and undo cameras that moved during the session (module doc). Returns the (mapped)
    detections and the report {"max_moves", "moves": [{camera, first_frame, end_frame (None:
    the end), rotvec, degrees, others_px, before_px, after_px[, jump_mm]}, ...], and where
    found: "unresolved" (a move that more than one camera's turn explains: not mapped),
    "unexplained" [why] (a step that no turn explains)}."""
    report: dict = {"max_moves": int(max_moves), "moves": []}
    frames = frame_numbers(det)
    if mode == "off" or max_moves <= 0 or len(cameras) < 2 or frames is None:
        return det, report
    order = np.argsort(frames, kind="stable")
    rows = order[_sample_rows(det.num_frames)]
    x = normalised_points(det.xy[rows], cameras)
    now = det  # the moves found so far undone
    names = [cam.name for cam in cameras]
    bump, why = _since_calibration(x, cameras)
    if why is not None:
        report.setdefault("unexplained", []).append(why)
        log.info("camera move check: %s", why)
    if bump is not None:
        bump["first_frame"] = int(frames.min())
        c = names.index(bump["camera"])
        if "ambiguous" in bump:
            which = bump.pop("ambiguous")
            files = _named(det, which)
            msg = (
                f"the cameras do not fit their calibration from the session's start: the "
                f"detections lie {bump['before_px']:.1f} px from each other's epipolar lines "
                f"({bump['others_px']:.1f} px without camera '{bump['camera']}'); a turn since "
                f"the calibration of any of cameras {files} explains it (to "
                f"{bump['after_px']:.1f} px), and nothing tells which, so the tracks rest on "
                "a calibration that does not hold"
            )
            _say(mode, msg, "; recalibrate (input.camera_check=warn: tracked as calibrated, "
                 "with a warning)", "NOT mapped back")  # fmt: skip
            report["unresolved"] = {**bump, "cameras": which}
        else:
            msg = (
                f"camera '{bump['camera']}' ({det.files[c]}) does not fit its calibration from "
                f"the session's start: turned by {bump['degrees']:.2f} deg about its centre "
                f"since it was calibrated (the detections lie {bump['before_px']:.1f} px from "
                f"each other's epipolar lines, {bump['others_px']:.1f} px without it; turned "
                f"back, {bump['after_px']:.1f} px; a camera bumped between its calibration "
                "and the recording?)"
            )
            _say(mode, msg, "; recalibrate it, or set input.camera_check=warn to map its "
                 "detections back (input.max_camera_moves=0: no check)",
                 "its detections MAPPED back")  # fmt: skip
            report["moves"].append(bump)
            _undo(x, frames[rows], c, bump)
            now = apply_moves(now, cameras, [bump])
    for _ in range(int(max_moves) - len(report["moves"])):
        move, why = _find(x, cameras, frames[rows], now)
        if move is None:
            if why is not None:
                report.setdefault("unexplained", []).append(why)
                log.info("camera move check: %s", why)
            break
        c = names.index(move["camera"])
        span = (
            f"from frame {move['first_frame']}"
            if move["end_frame"] is None
            else f"over frames {move['first_frame']}-{move['end_frame'] - 1}"
        )
        if "ambiguous" in move:
            which = move.pop("ambiguous")
            files = _named(det, which)
            msg = (
                f"a camera moved {span}: the detections lie {move['before_px']:.1f} px from "
                f"the other cameras' epipolar lines there against {move['others_px']:.1f} px "
                f"elsewhere; a turn of any of cameras {files} explains it, and the parts' "
                f"continuity at the move does not tell which (they jump by {move['jump_mm']} "
                "mm), so the tracks there rest on a calibration that no longer holds"
            )
            _say(mode, msg, "; recalibrate for the frames after the move, or track the frames "
                 "before it (input.camera_check=warn: tracked as calibrated, with a warning)",
                 "NOT mapped back")  # fmt: skip
            report["unresolved"] = {**move, "cameras": which}
            break
        msg = (
            f"camera '{move['camera']}' ({det.files[c]}) moved {span}: turned by "
            f"{move['degrees']:.2f} deg about its centre (its detections lie "
            f"{move['before_px']:.1f} px from the other cameras' epipolar lines there, "
            f"{move['others_px']:.1f} px elsewhere; turned back, {move['after_px']:.1f} px; a "
            "camera bumped or its mount slipped?)"
        )
        _say(mode, msg, "; recalibrate it for those frames, or set input.camera_check=warn to "
             "map its detections back (input.max_camera_moves=0: no check)",
             "its detections there MAPPED back")  # fmt: skip
        report["moves"].append(move)
        _undo(x, frames[rows], c, move)
        now = apply_moves(now, cameras, [move])
    return now, report
