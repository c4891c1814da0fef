"""Sub-frame offsets between cameras: find a camera whose exposures fall a fraction of a frame
before or after the others' (cameras without a common trigger, e.g. webcams started one after
the other) and interpolate its detections in time to the others' frames.

    det, report = check_subframe(cameras, det)

Whole frames are `adjust.sync`'s; this runs after it (and after `adjust.moves`), on what is
left. Offsets follow `adjust.sync`'s convention: a camera with offset o shows at its row for
frame f + o what the others show at frame f (o = -0.4: its exposures come 0.4 of a frame after
theirs).

How it is found (`pair_fit`): for a camera pair (a, b), the signed distance d of b's detection from
the epipolar line of a's at the same frame moves, to first order, by the offset times the velocity v
of b's point across that line: d = (o_a - o_b) v + noise. Each pair's o_a - o_b is the
instrumental-variables regression of d on v, v from b's detections one frame before and after, the
instrument from two frames before and after (independent of both d's and v's noise, so the noise of
v does not bias the estimate towards 0); only where the two velocities agree (`SMOOTH`: the
first-order model holds; a head shake at 20 Hz breaks it); robust (residuals beyond `CUT` MADs left
out, re-fitted); both directions of the pair pooled. Its variance is the sandwich over blocks of
`CLUSTER` consecutive frames (the residuals of neighbouring frames are not independent: a
calibration a little off errs alike where the animal stays), plus `FLOOR` squared (what the
first-order model leaves); a pair needs `MIN_CLUSTERS` blocks (a session of 300 frames or more). The
cameras' offsets are the pairs' weighted least squares (`combine`), referred to the camera whose
offset is the median (the majority keeps its time; two cameras: the first, as in `adjust.sync`). A
camera is shifted only where its offset is `Z` (5) standard errors or more, at least `MIN_SHIFT`
frames, at most `MAX_SHIFT` (beyond, the first-order model does not hold: whole frames are the sync
check's), and the pairs agree (`MAX_DISAGREEMENT`: chi-square over its degrees of freedom). A clock
that drifts is not modelled: the offset is the session's mean.

How it is undone (`resample`): the camera's detections at frame f are read at its fractional
row f + o, on the line between the two rows that bracket it (a cubic through four rows was
farther from the truth: it weights the detector's noise more); where one of the two is a
spike (`spikes`: an outlier or a swap, which the line would spread into the neighbouring
frame), the other row; where only one has a detection, that one if it is the nearer, else
none (a detection from farther off in time, at the edge of an occlusion, tracked worse).
Detections: ``Detections`` (T, K, C, 2) px."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np

from adjust.camera import Camera
from adjust.io import Detections, InputError
from adjust.sync import (
    block_rows,
    epipolar_lines,
    essential,
    focal_px,
    frame_numbers,
    homog,
    normalised_points,
    rows_at,
)

log = logging.getLogger(__name__)

CUT = 4.0  #: residuals beyond this many MADs (1.4826 MAD) are left out of a pair's fit
SMOOTH, SMOOTH_PX = (
    0.25,
    2.0,
)  #: velocities over 2 and 4 frames agree: 25% of them + 2 px
CLUSTER = 10  #: consecutive frames whose residuals count as one in the variance
FLOOR = 0.05  #: frames of error beyond the noise in each pair's offset (the model's)
MIN_TERMS = 200  #: part-frames a pair needs to count
MIN_CLUSTERS = 30  #: ... in this many clusters (300 frames; fewer make the variance too small)
Z = 5.0  #: a camera's offset is taken from this many standard errors on
MIN_SHIFT = 0.1  #: ... and this many frames
MAX_SHIFT = 1.0  #: ... to this many (whole frames: `adjust.sync`)
MAX_DISAGREEMENT = 4.0  #: pairs whose offsets disagree beyond this chi2 / dof: nothing taken
SPIKE_PX = 8.0  #: a row this far (px) from its neighbours' mean, beyond half their step, is a spike
MAX_ROWS = 20_000  #: rows the offsets are measured on (in blocks spread over the session)
BLOCK_ROWS = 1_000  #: ... of this many consecutive rows


def _along(x: np.ndarray, i: np.ndarray, j: np.ndarray, n: np.ndarray, span: float):
    """n . (x[j] - x[i]) / span where both rows exist (NaN else); x (T, K, 2), n (N, K, 2)."""
    ok = (i >= 0) & (j >= 0)
    out = np.full(n.shape[:2], np.nan)
    out[ok] = (n[ok] * (x[j[ok]] - x[i[ok]])).sum(-1) / span
    return out


def pair_terms(x, frames, rows, nb, a: int, b: int, cameras: Sequence[Camera]):
    """The regression's terms of pair (a, b), both directions: (d, v, z, frame) flat, px and
    px / frame, signed so that d = (o_a - o_b) v. x: (T, K, C, 2) normalised points; rows:
    the rows measured; nb: the rows of their frames -2, -1, +1, +2 (-1: none)."""
    E = essential(cameras[a], cameras[b])
    m2, m1, p1, p2 = nb
    out = []
    for p, q, M, sign in (
        (a, b, E.T, 1.0),
        (b, a, E, -1.0),
    ):  # lines in q from p's points
        fq = focal_px(cameras[q])
        line, inv = epipolar_lines(homog(x[rows, :, p]), M)
        n = line[..., :2] * inv[..., None]  # (N, K, 2) unit normals
        d = (homog(x[rows, :, q]) * line).sum(-1) * inv * fq
        xq = x[:, :, q]
        v = _along(xq, m1, p1, n, 2.0) * fq
        z = _along(xq, m2, p2, n, 4.0) * fq
        f = np.broadcast_to(frames[rows][:, None], d.shape)
        with np.errstate(invalid="ignore"):
            smooth = np.abs(v - z) <= SMOOTH * 0.5 * (np.abs(v) + np.abs(z)) + SMOOTH_PX
        ok = np.isfinite(d) & smooth
        out.append((sign * d[ok], v[ok], z[ok], f[ok]))
    return tuple(np.concatenate([o[i] for o in out]) for i in range(4))


def regress(d, X, W, f, min_clusters: int = MIN_CLUSTERS):
    """Instrumental-variables regression d = X beta (N,) on X (N, P), instruments W (N, P),
    robust (residuals beyond `CUT` MADs left out, refitted): beta (P,) and its covariance, the
    sandwich over clusters of `CLUSTER` frames (f: each term's frame) plus `FLOOR` squared;
    None with fewer than `MIN_TERMS` terms or `min_clusters` clusters, or no leverage (the
    least singular value of W^T X, each column scaled to unit norm, under 1e-9)."""
    if d.size < MIN_TERMS:
        return None
    norms = np.sqrt(np.outer((W**2).sum(0), (X**2).sum(0)))
    keep = np.ones(d.size, bool)
    for _ in range(5):
        A = W[keep].T @ X[keep]
        with np.errstate(all="ignore"):
            An = A / norms
        if not np.isfinite(An).all() or np.linalg.svd(An, compute_uv=False).min() < 1e-9:
            return None
        beta = np.linalg.solve(A, W[keep].T @ d[keep])
        r = d - X @ beta
        mad = 1.4826 * float(np.median(np.abs(r[keep])))
        new = np.abs(r) <= CUT * max(mad, 1e-9)
        if (new == keep).all():
            break
        keep = new
    clusters, g = np.unique((f[keep] // CLUSTER).astype(np.int64), return_inverse=True)
    if keep.sum() < MIN_TERMS or clusters.size < min_clusters:
        return None
    Ai = np.linalg.inv(W[keep].T @ X[keep])
    sums = np.stack([np.bincount(g, weights=W[keep][:, j] * r[keep]) for j in range(W.shape[1])])
    return beta, Ai @ (sums @ sums.T) @ Ai.T + FLOOR**2 * np.eye(W.shape[1])


def pair_fit(d, v, z, f) -> tuple[float, float] | None:
    """(offset, variance) of o_a - o_b from `pair_terms`' (d, v, z, f) (`regress` on v with
    the instrument z); None with fewer than `MIN_TERMS` terms or no leverage."""
    got = regress(d, v[:, None], z[:, None], f)
    return None if got is None else (float(got[0][0]), float(got[1][0, 0]))


def combine(fits: dict, C: int):
    """The cameras' offsets (C,) and their covariance (C, C) from the pairs' fits {(a, b):
    (offset, variance)} of o_a - o_b, camera 0's fixed at 0 (weighted least squares), and the
    pairs' chi2 / dof (NaN without redundancy); None where a camera is in no pair."""
    N, h = np.zeros((C - 1, C - 1)), np.zeros(C - 1)
    for (a, b), (o, var) in fits.items():
        D = np.zeros(C)
        D[a], D[b] = 1.0, -1.0
        D = D[1:]
        N += np.outer(D, D) / var
        h += D * o / var
    if np.linalg.matrix_rank(N) < C - 1:
        return None
    cov = np.zeros((C, C))
    cov[1:, 1:] = np.linalg.inv(N)
    theta = np.concatenate([[0.0], cov[1:, 1:] @ h])
    chi2 = sum((o - (theta[a] - theta[b])) ** 2 / var for (a, b), (o, var) in fits.items())
    dof = len(fits) - (C - 1)
    return theta, cov, (chi2 / dof if dof > 0 else float("nan"))


def term_rows(cameras: Sequence[Camera], det: Detections, frames: np.ndarray):
    """What `pair_terms` reads: the normalised points x (T, K, C, 2) (NaN but on the rows
    needed), the rows measured (at most `MAX_ROWS`, in blocks of `BLOCK_ROWS`) and their
    frames' -2, -1, +1, +2 rows (-1: none)."""
    rows = block_rows(det.num_frames, MAX_ROWS, BLOCK_ROWS)
    order = np.argsort(frames, kind="stable")
    nb = [rows_at(frames, frames[rows] + s, order) for s in (-2, -1, 1, 2)]
    need = np.unique(np.concatenate([rows, *[r[r >= 0] for r in nb]]))
    x = np.full(det.xy.shape, np.nan)
    x[need] = normalised_points(det.xy[need], cameras)
    return x, rows, nb


def measure(cameras: Sequence[Camera], det: Detections) -> dict | None:
    """Every camera's offset and its standard error, referred to the median camera (two
    cameras: the first): {"offset" (C,), "se" (C,), "disagreement"}; None where the pairs
    cannot tell (no time order, too few terms)."""
    frames = frame_numbers(det)
    C = len(cameras)
    if frames is None or C < 2:
        return None
    x, rows, nb = term_rows(cameras, det, frames)
    fits = {}
    for a in range(C):
        for b in range(a + 1, C):
            fit = pair_fit(*pair_terms(x, frames, rows, nb, a, b, cameras))
            if fit is not None:
                fits[(a, b)] = fit
    got = combine(fits, C) if fits else None
    if got is None:
        return None
    theta, cov, disagreement = got
    ref = 0 if C == 2 else int(np.argsort(theta, kind="stable")[(C - 1) // 2])
    var = np.diag(cov) + cov[ref, ref] - 2 * cov[:, ref]
    return {"offset": theta - theta[ref], "se": np.sqrt(np.maximum(var, 0.0)),
            "disagreement": disagreement}  # fmt: skip


def decide(m: dict, cameras: Sequence[Camera]) -> tuple[dict, dict]:
    """({name: offset} of the cameras `measure` shows out of step (module doc), {name:
    reason} of those it shows out of step but beyond `MAX_SHIFT` or whose pairs disagree)."""
    found, refused = {}, {}
    for c, cam in enumerate(cameras):
        o, se = float(m["offset"][c]), float(m["se"][c])
        if abs(o) < max(MIN_SHIFT, Z * se):
            continue
        if np.isfinite(m["disagreement"]) and m["disagreement"] > MAX_DISAGREEMENT:
            refused[cam.name] = f"its pairs disagree (chi2/dof {m['disagreement']:.1f})"
        elif abs(o) > MAX_SHIFT:
            refused[cam.name] = f"offset {o:+.2f} frames, beyond {MAX_SHIFT:g}"
        else:
            found[cam.name] = o
    return found, refused


def spikes(xy: np.ndarray, prev: np.ndarray, nxt: np.ndarray) -> np.ndarray:
    """(T, K) bool: the detection lies more than `SPIKE_PX` plus half its neighbours' step
    from their mean (an outlier or a swap in that frame; False where a neighbour is missing).
    xy, prev, nxt: (T, K, 2) px, the rows and their frames' -1 and +1 rows."""
    with np.errstate(invalid="ignore"):
        e = np.linalg.norm(xy - 0.5 * (prev + nxt), axis=-1)
        out = e > SPIKE_PX + 0.5 * np.linalg.norm(nxt - prev, axis=-1)
    return out & np.isfinite(e)


def _rows(src: np.ndarray, r: np.ndarray, fill) -> np.ndarray:
    """src[r] with `fill` where r is -1."""
    got = src[np.maximum(r, 0)]
    return np.where((r >= 0).reshape(-1, *[1] * (got.ndim - 1)), got, fill)


def read_at(
    det: Detections, c: int, p: np.ndarray, frames: np.ndarray, order: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Camera c's detections (N, K, 2) px and likelihoods (N, K) read at fractional frame
    numbers p (N,) of its own rows: the line between the two bracketing rows; where one of
    them is a spike (`spikes`), the other row; where only one has a detection, that one if it
    is the nearer, else none (module doc). The likelihood is the rows' lower one (or the
    row's taken). frames: the rows' frame numbers; order: their argsort."""
    src, srcl = det.xy[:, :, c], det.likelihood[:, :, c]
    spike = spikes(
        src,
        _rows(src, rows_at(frames, frames - 1, order), np.nan),
        _rows(src, rows_at(frames, frames + 1, order), np.nan),
    )
    p = np.asarray(p, dtype=np.float64)
    i = np.floor(p).astype(np.int64)
    s = (p - i)[:, None]
    r1, r2 = rows_at(frames, i, order), rows_at(frames, i + 1, order)
    p1, p2 = _rows(src, r1, np.nan), _rows(src, r2, np.nan)
    l1, l2 = _rows(srcl, r1, 0.0), _rows(srcl, r2, 0.0)
    s1, s2 = _rows(spike, r1, False), _rows(spike, r2, False)
    h1, h2 = np.isfinite(p1).all(-1), np.isfinite(p2).all(-1)
    first = np.broadcast_to(s < 0.5, h1.shape)
    both = h1 & h2
    line = both & (s1 == s2) & ~(s1 & s2)
    take1 = (both & ((s2 & ~s1) | (s1 & s2 & first))) | (~both & h1 & first)
    take2 = (both & ((s1 & ~s2) | (s1 & s2 & ~first))) | (~both & h2 & ~first)
    val = (1 - s[..., None]) * p1 + s[..., None] * p2
    val = np.where(take1[..., None], p1, np.where(take2[..., None], p2, val))
    xy = np.where((line | take1 | take2)[..., None], val, np.nan)
    lik = np.where(take1, l1, np.where(take2, l2, np.where(line, np.minimum(l1, l2), 0.0)))
    return xy, lik


def resample(det: Detections, offsets: dict[str, float]) -> Detections:
    """The detections with camera ``name`` read at frame f at its fractional row f +
    ``offsets[name]`` (`read_at`)."""
    offsets = {n: float(o) for n, o in offsets.items() if o}
    if not offsets:
        return det
    frames = frame_numbers(det)
    if frames is None:
        raise ValueError("labelled images (frames by name) have no time order to resample")
    order = np.argsort(frames, kind="stable")
    xy, lik = det.xy.copy(), det.likelihood.copy()
    for name, o in offsets.items():
        c = det.cameras.index(name)
        xy[:, :, c], lik[:, :, c] = read_at(det, c, frames + o, frames, order)
    return dataclasses.replace(det, xy=xy, likelihood=lik)


def check_subframe(
    cameras: Sequence[Camera], det: Detections, mode: str = "warn"
) -> tuple[Detections, dict]:
    """Find and undo sub-frame offsets between the cameras (module doc). ``mode`` as the
    camera check's: warn = interpolate the camera's detections and say so, error = an
    `InputError` naming it, off = nothing. Returns the (resampled) detections and the report
    {"offsets": {name: frames}, "se": {name: frames}, "not_undone": {name: reason}} (the
    last two only where there are any)."""
    report: dict = {"offsets": {}}
    if mode == "off" or len(cameras) < 2:
        return det, report
    m = measure(cameras, det)
    if m is None:
        return det, report
    found, refused = decide(m, cameras)
    names = [cam.name for cam in cameras]
    for name, why in refused.items():
        log.info(
            "camera '%s' (%s) may be out of step with the others by a fraction of a frame; "
            "not undone: %s",
            name,
            det.files[names.index(name)],
            why,
        )
    if refused:
        report["not_undone"] = refused
    for name, o in found.items():
        c = names.index(name)
        msg = (
            f"camera '{name}' ({det.files[c]}) is out of step with the others by a fraction "
            f"of a frame: its exposures come {abs(o):.2f} of a frame "
            f"{'after' if o < 0 else 'before'} theirs (+- {m['se'][c]:.2f}; its frame f "
            f"{o:+.2f} matches their frame f; cameras without a common trigger?)"
        )
        if mode == "error":
            raise InputError(
                msg + "; trigger the cameras together, or set input.camera_check=warn to "
                "interpolate its detections in time (input.subframe_sync=false: no check)"
            )
        log.warning(
            "%s; its detections are INTERPOLATED in time to the others' frames "
            "(input.camera_check=warn)",
            msg,
        )
        report["offsets"][name] = round(o, 4)
        report.setdefault("se", {})[name] = round(float(m["se"][c]), 4)
    return resample(det, report["offsets"]), report
