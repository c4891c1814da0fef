"""Clocks: find a camera whose frames do not keep the others' time one for one, and read its
detections at the others' times.

    det, report = check_clocks(cameras, det, max_offset=30)

Detection files are matched by frame number. Two kinds of camera break that and are not
`adjust.rates`' (a whole multiple of the others' frame rate), `adjust.sync`'s (a whole number
of frames out of step, or steps of dropped frames) or `adjust.subframe`'s (a constant fraction
of a frame):

- a frame rate that is not a whole multiple of the others' (a camera set to 25 fps beside
  others at 30): its lag grows by a sixth of a frame every frame;
- a clock that drifts: free-running cameras (webcams, no common trigger) whose rates differ a
  little (29.9 against 30 fps, a low-light exposure), so that one camera's lag grows through
  the session (a file with a few frames fewer than the others' for the same session). A
  webcam that drops a frame now and then (one in 150) reads as one too: its lag is a
  staircase of single frames, which the line follows to within a frame.

Both are a time map: the camera's detections at the others' frame f are its own at its
(fractional) frame g = rate f + offset. How it is found:

1. A first map (`first_map`), for each candidate rate (1, and the ratio of the camera's frame
   span to the others' where they differ by `MIN_SPAN_GAP` and not by a whole multiple): the
   others' frames are cut into blocks of `BLOCK` frames (at most `MAX_BLOCKS`, spread over the
   session); in each block the offset is searched within +-``max_offset`` frames (whole
   frames, then `STEP` about the best), the camera's detections read at rate f + offset
   (linear between its rows) against the other cameras' epipolar lines: the median symmetric
   distance of each pair, the median over its pairs (`block_curve`). A block counts where its
   curve has a clear minimum (`CONTRAST` times below the curve's median, not at the edge: a
   still animal gives a flat curve); the minimum is refined by a parabola, and a robust line
   through the counted blocks (`fit_line`) is the first map. Where fewer than `MIN_BLOCKS`
   count (two cameras, or a slow animal: shallow curves), the candidate rate itself is.
2. Refined (`refine`): read with the map, the camera's remaining lag is regressed on the
   velocity of its points across the other cameras' epipolar lines, as a line in time, by
   `adjust.subframe`'s instrumental-variables terms (a late camera's points lie its lag
   times that velocity off the lines; the sandwich variance over clusters of frames gives the
   rate's standard error); the line is folded into the map until it changes the lag by under
   `CONVERGED` frames.
3. Taken (`decide`) where it is a clock: its rate differs from 1 by `Z` standard errors and by
   `MIN_DRIFT` frames over the session (less is the constant fraction's of
   `adjust.subframe`), the standard error the larger of the regression's and the one from
   the scatter of the blocks' lags about a line (`in_step`: a calibration a little off
   biases the lag by where the animal is, which the regression's short clusters do not
   see); read with it, the camera keeps the others' time block by block
   (`in_step`: the blocks' lags of `CHECK_BLOCK` frames rms `MAX_SCATTER` frames, and no step
   in them: a lag that steps is dropped frames, `adjust.sync`'s); and its detections so read
   lie closer to the others' epipolar lines than as numbered, within `PLAUSIBLE_PX` (or twice
   the other pairs' median).

With three or more cameras each is fitted against the others and the one whose map brings it
closest is taken first, then the rest again (the majority keeps its time); with two the first
keeps the session's time. Done (`retime`): the rows become the others' frames, the camera read
at rate f + offset (`adjust.subframe.read_at`: on the line between its two rows, the other
where one is a spike). Not looked for: sessions under `MIN_FRAMES` frames, labelled images; a
clock whose rate wanders (not a line) is left to the sync check's steps. A long session
tracked in chunks finds the map on its sample and reads each chunk with it
(`read_clocked`, `window`: `adjust.chunks`). Runs after
`adjust.rates`, before the sync check (`adjust.camera_check`); ``input.rate_check`` (the one
setting for both) false: not looked for. Detections: ``Detections`` (T, K, C, 2) px."""

from __future__ import annotations

import dataclasses
import logging
import warnings
from collections.abc import Sequence

import numpy as np

from adjust.camera import Camera
from adjust.io import Detections, InputError
from adjust.rates import SPAN_TOL, camera_px, pair_medians, ratio_of, spans
from adjust.subframe import MIN_CLUSTERS, pair_terms, read_at, regress, term_rows
from adjust.sync import (
    epipolar_px,
    essential,
    focal_px,
    frame_numbers,
    normalised_points,
)

log = logging.getLogger(__name__)

MIN_FRAMES = 500  #: sessions of fewer frames (the others') are not looked at
BLOCK = 100  #: the others' consecutive frames per block
MAX_BLOCKS = 40  #: ... at most this many blocks, spread over the session
STEP = 0.25  #: frames: the fine grid about a block's best whole frame
MIN_PAIRS = 30  #: part-frames a camera pair needs in a block for its median to count
CONTRAST = 2.0  #: a block's curve minimum must lie this many times below its median
MIN_BLOCKS = 5  #: counted blocks a first line needs
CUT = 4.0  #: blocks beyond this many MADs (1.4826 MAD, at least `SCATTER_FLOOR`) left out
SCATTER_FLOOR = 0.1  #: frames: the least scatter assumed of a block's offset
ITERATIONS = 6  #: refinements of the map by the velocity regression (`refine`)
CONVERGED = 0.02  #: frames: a refinement's change of the lag below this everywhere: done
CHECK_BLOCK = 100  #: the others' frames per block of the final check (`in_step`)
CHECK_CLUSTERS = 5  #: ... clusters (`adjust.subframe.CLUSTER` frames) a block needs
MAX_SCATTER = 0.5  #: frames: the checked blocks' rms lag after the map
STEP_CHI2 = 25.0  #: one step in the checked blocks' lags this much more likely: a step
Z = 6.0  #: the rate must differ from 1 by this many standard errors
MIN_DRIFT = 1.5  #: ... and by this many frames over the session
MIN_SPAN_GAP = 0.002  #: a span ratio this far from 1 is a candidate rate of its own
PLAUSIBLE_PX = 5.0  #: the retimed camera's median epipolar distance (px; or 2x the others')


@dataclasses.dataclass(frozen=True)
class ClockMap:
    """A camera's time map g = rate f + offset (its frame g at the others' frame f): rate,
    offset (frames) and the rate's standard error."""

    rate: float
    offset: float
    rate_se: float = float("inf")

    def drift(self, span: float) -> float:
        """Frames the map's lag changes by over `span` of the others' frames."""
        return (self.rate - 1.0) * span


def _dense(x: np.ndarray, frames: np.ndarray) -> tuple[int, np.ndarray]:
    """(first frame, (F, K, 2)) camera points x (T, K, 2) by frame number (NaN where none)."""
    first = int(frames.min())
    arr = np.full((int(frames.max()) - first + 1, *x.shape[1:]), np.nan)
    arr[frames - first] = x
    return first, arr


def _read(first: int, arr: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Points (..., K, 2) of `_dense` at fractional frames p (...): linear between the rows
    (NaN where either is missing or outside)."""
    i = np.floor(p).astype(np.int64) - first
    w = (p - np.floor(p))[..., None, None]
    ok = (i >= 0) & (i + 1 < len(arr))
    j = np.clip(i, 0, len(arr) - 2)
    out = (1 - w) * arr[j] + w * arr[j + 1]
    out[~ok] = np.nan
    return out


def block_curve(cams, x, c, others, rows, frames, first, arr, rate, offsets) -> np.ndarray:
    """(G,) camera c's median over its pairs of each pair's median symmetric epipolar distance
    (px) on block rows `rows`, c read at rate f + o for each o of `offsets` (G,); NaN where
    no pair has `MIN_PAIRS` part-frames. x: (T, K, C, 2) normalised points."""
    p = rate * frames[rows][None, :] + np.asarray(offsets)[:, None]  # (G, N)
    xc = _read(first, arr, p)  # (G, N, K, 2)
    fc = focal_px(cams[c])
    meds = []
    for d in others:
        xd = np.broadcast_to(x[rows][:, :, d], xc.shape)
        ok = np.isfinite(xc).all(-1) & np.isfinite(xd).all(-1)  # (G, N, K)
        fd = focal_px(cams[d])
        e = np.full(ok.shape, np.nan)
        if ok.any():
            e[ok] = epipolar_px(essential(cams[c], cams[d]), xc[ok], xd[ok], fc, fd)
        n = ok.reshape(len(p), -1).sum(1)
        meds.append(np.where(n >= MIN_PAIRS, _nanmedian(e.reshape(len(p), -1)), np.nan))
    return _nanmedian(np.stack(meds).T)


def _nanmedian(a: np.ndarray) -> np.ndarray:
    """The median of each row of a (G, N) over its finite entries (NaN where none)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN row: NaN is the answer
        return np.nanmedian(a, axis=1)


def block_offset(cams, x, c, others, rows, frames, first, arr, rate, max_offset) -> float | None:
    """The offset (frames) at which camera c's block `rows` agrees best with the others
    (`block_curve`: whole frames within +-max_offset, then `STEP` about the best, a parabola
    through the least three); None without a clear minimum (`CONTRAST`) or at the edge."""
    whole = np.arange(-max_offset, max_offset + 1, dtype=np.float64)
    curve = block_curve(cams, x, c, others, rows, frames, first, arr, rate, whole)
    if not np.isfinite(curve).any():
        return None
    k = int(np.nanargmin(curve))
    if k == 0 or k == len(whole) - 1:
        return None
    if not curve[k] * CONTRAST <= float(np.nanmedian(curve)):
        return None
    fine = whole[k] + np.arange(-4, 5) * STEP
    cf = block_curve(cams, x, c, others, rows, frames, first, arr, rate, fine)
    if not np.isfinite(cf).any():
        return None
    j = int(np.nanargmin(cf))
    if 0 < j < len(fine) - 1 and np.isfinite(cf[j - 1 : j + 2]).all():
        y0, y1, y2 = cf[j - 1 : j + 2]
        den = y0 - 2 * y1 + y2
        if den > 0:
            return float(fine[j] + np.clip(0.5 * (y0 - y2) / den, -1, 1) * STEP)
    return float(fine[j])


def fit_line(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Robust line y = b + s t through the blocks (centre frames t, offsets y): blocks beyond
    `CUT` MADs of the residuals left out, refitted. Returns (s, b)."""
    keep = np.ones(len(t), bool)
    s, b = 0.0, float(np.median(y))
    for _ in range(5):
        tk, yk = t[keep], y[keep]
        tm = float(tk.mean())
        sxx = float(((tk - tm) ** 2).sum())
        s = float(((tk - tm) * (yk - yk.mean())).sum() / sxx) if sxx > 0 else 0.0
        b = float(yk.mean()) - s * tm
        r = y - (b + s * t)
        mad = 1.4826 * float(np.median(np.abs(r[keep])))
        new = np.abs(r) <= CUT * max(mad, SCATTER_FLOOR)
        if (new == keep).all() or new.sum() < 3:
            break
        keep = new
    return s, b


def first_map(cams, det, x, c: int, rate: float, max_offset: int) -> ClockMap | None:
    """Camera c's first time map with the candidate `rate`: a line through the blocks'
    offsets (`block_offset`, module doc); None with fewer than `MIN_BLOCKS` counted blocks.
    x: (T, K, C, 2) normalised points."""
    frames = frame_numbers(det)
    others = [d for d in range(det.num_cameras) if d != c]
    has = np.isfinite(det.xy).all(-1).any(1)  # (T, C): a usable detection in the row
    own = has[:, c]
    if own.sum() < MIN_PAIRS or frames is None:
        return None
    first, arr = _dense(x[own][:, :, c], frames[own])
    ref = np.flatnonzero(has[:, others].any(1))
    ref = ref[np.argsort(frames[ref], kind="stable")]
    nblocks = min(len(ref) // BLOCK, MAX_BLOCKS)
    if nblocks < MIN_BLOCKS:
        return None
    starts = np.linspace(0, len(ref) - BLOCK, nblocks).astype(np.int64)
    t, y = [], []
    for s0 in starts:
        rows = ref[s0 : s0 + BLOCK]
        o = block_offset(cams, x, c, others, rows, frames, first, arr, rate, max_offset)
        if o is not None:
            t.append(float(frames[rows].mean()))
            y.append(o)
    if len(t) < MIN_BLOCKS:
        return None
    s, b = fit_line(np.asarray(t), np.asarray(y))
    return ClockMap(rate + s, b)


def velocity_terms(cams, det: Detections, c: int):
    """`adjust.subframe.pair_terms` of camera c against every other camera, pooled: (d, v, z,
    frame) with d = o v, o camera c's lag (its row f + o matches the others' f)."""
    frames = frame_numbers(det)
    x, rows, nb = term_rows(cams, det, frames)
    terms = [pair_terms(x, frames, rows, nb, c, d, cams) for d in range(len(cams)) if d != c]
    return tuple(np.concatenate([t[i] for t in terms]) for i in range(4))


def refine(cams, det: Detections, c: int, m: ClockMap, f0: float, span: float):
    """Camera c's map `m` refined (`ITERATIONS`): read with it, camera c's remaining lag is
    regressed on the points' velocities across the other cameras' epipolar lines as a line
    in time o(f) = a + b (f - f0) / span (`velocity_terms`, `regress`), folded into the map;
    until it changes the lag by under `CONVERGED` frames. Returns the refined `ClockMap` (with
    the rate's standard error) or None where the regression cannot tell."""
    rate, offset = m.rate, m.offset
    cov = None
    for _ in range(ITERATIONS):
        d, v, z, f = velocity_terms(cams, retime(det, c, rate, offset), c)
        u = (f - f0) / span
        fit = regress(d, np.stack([v, u * v], 1), np.stack([z, u * z], 1), f, MIN_CLUSTERS)
        if fit is None:
            return None
        (a, b), cov = fit
        # the retimed row f + o(f) is the camera's frame rate (f + o(f)) + offset
        offset += rate * (a - b * f0 / span)
        rate *= 1.0 + b / span
        if abs(a) < CONVERGED and abs(a + b) < CONVERGED:
            break
    return ClockMap(rate, offset, rate * float(np.sqrt(cov[1, 1])) / span)


def in_step(cams, det: Detections, c: int) -> tuple[float, bool, float]:
    """How camera c keeps the others' time in blocks of `CHECK_BLOCK` frames: the rms of the
    blocks' lags (frames; `regress` on each block's velocity terms), whether one step in them
    fits `STEP_CHI2` better than none (dropped frames, not a clock), and the standard error
    of a drift (frames per frame) from the blocks' scatter about a line (inf with fewer than
    3 blocks): what moves the lag from block to block besides the clock (a calibration a
    little off biases each place the animal goes alike) is in it, as it is not in the
    regression's clusters of a few frames."""
    d, v, z, f = velocity_terms(cams, det, c)
    o, w, t = [], [], []
    for lo in np.arange(f.min(), f.max() + 1, CHECK_BLOCK) if f.size else []:
        k = (f >= lo) & (f < lo + CHECK_BLOCK)
        fit = regress(d[k], v[k, None], z[k, None], f[k], CHECK_CLUSTERS)
        if fit is not None:
            o.append(float(fit[0][0]))
            w.append(1.0 / float(fit[1][0, 0]))
            t.append(float(f[k].mean()))
    if len(o) < 3:
        return 0.0, False, float("inf")
    o, w, t = np.asarray(o), np.asarray(w), np.asarray(t)
    flat = float((w * o**2).sum())
    step = min(
        float((w[:k] * (o[:k] - np.average(o[:k], weights=w[:k])) ** 2).sum())
        + float((w[k:] * (o[k:] - np.average(o[k:], weights=w[k:])) ** 2).sum())
        for k in range(1, len(o))
    )
    sxx = float(((t - t.mean()) ** 2).sum())
    slope = float(((t - t.mean()) * o).sum()) / sxx
    r = o - o.mean() - slope * (t - t.mean())
    sd = max(float(np.sqrt((r**2).sum() / (len(o) - 2))), SCATTER_FLOOR)
    return float(np.sqrt((o**2).mean())), flat - step > STEP_CHI2, sd / np.sqrt(sxx)


def retime(det: Detections, c: int, rate: float, offset: float) -> Detections:
    """The detections on the other cameras' frames, camera c read at its fractional frame
    rate f + offset (`adjust.subframe.read_at`); frames only camera c had are left out."""
    frames = frame_numbers(det)
    if frames is None:
        raise ValueError("labelled images (frames by name) have no time order to retime")
    order = np.argsort(frames, kind="stable")
    has = (det.likelihood > 0).any(1) | np.isfinite(det.xy).all(-1).any(1)  # (T, C)
    others = [d for d in range(det.num_cameras) if d != c]
    keep = np.flatnonzero(has[:, others].any(1))
    keep = keep[np.argsort(frames[keep], kind="stable")]
    xy = det.xy[keep].copy()
    lik = det.likelihood[keep].copy()
    xy[:, :, c], lik[:, :, c] = read_at(det, c, rate * frames[keep] + offset, frames, order)
    new = None if det.frames is None else np.asarray(det.frames)[keep]
    return dataclasses.replace(det, xy=xy, likelihood=lik, frames=new)


def read_clocked(det: Detections, wide: Detections, maps: dict) -> Detections:
    """`det` with each camera of `maps` ({name: (rate, offset)}) read from `wide` (the same
    cameras and parts, that camera's rows over the frames the map reads) at its fractional
    frame rate f + offset for each of det's frames f (`adjust.subframe.read_at`): a long
    session's chunk read at the others' times, as `retime` read the sample."""
    frames = frame_numbers(det)
    wf = frame_numbers(wide)
    if frames is None or wf is None:
        raise ValueError("labelled images (frames by name) have no time order to retime")
    order = np.argsort(wf, kind="stable")
    xy, lik = det.xy.copy(), det.likelihood.copy()
    for name, (rate, offset) in maps.items():
        c = det.cameras.index(name)
        xy[:, :, c], lik[:, :, c] = read_at(wide, c, rate * frames + offset, wf, order)
    return dataclasses.replace(det, xy=xy, likelihood=lik)


def window(rate: float, offset: float, first: int, last: int) -> tuple[int, int]:
    """The camera frames a map (rate, offset) reads for the others' frames first..last (the
    two rows about each, and one more for `adjust.subframe.spikes`)."""
    lo, hi = sorted((rate * first + offset, rate * last + offset))
    return int(np.floor(lo)) - 2, int(np.ceil(hi)) + 2


def decide(m: ClockMap, span: float, scatter: float, stepped: bool, before: float,
           after: float, plausible: float) -> str | None:  # fmt: skip
    """None where map `m` is a clock to undo (module doc), else why not."""
    drift = abs(m.drift(span))
    if drift < MIN_DRIFT or abs(m.rate - 1.0) < Z * m.rate_se:
        return f"no drift beyond the noise ({drift:.2f} frames, se {m.rate_se * span:.2f})"
    if scatter > MAX_SCATTER or stepped:
        return (
            f"read with it, its blocks do not keep time (rms lag {scatter:.2f} frames"
            f"{', one step in them' if stepped else ''}): dropped frames?"
        )
    closer = not np.isfinite(before) or after < before
    if not (np.isfinite(after) and after <= plausible and closer):
        return f"read so it does not agree ({before:.1f} px as numbered, {after:.1f} px retimed)"
    return None


def check_clocks(
    cameras: Sequence[Camera], det: Detections, mode: str = "warn", max_offset: int = 30
) -> tuple[Detections, dict]:
    """Find and undo a camera whose clock runs at another rate than the others' (module doc).
    ``mode`` as the camera check's: warn = retime its detections and say so, error = an
    `InputError` naming it, off = nothing; ``max_offset``: the frames a block's lag is
    searched within (``input.max_frame_offset``). Returns the (retimed) detections and the
    report {"retimed": {name: {"rate", "offset", "rate_se", "drift_frames" (over the
    session), "epipolar_px": [as numbered, retimed]}}}."""
    report: dict = {"retimed": {}}
    C = len(cameras)
    frames = frame_numbers(det)
    if mode == "off" or C < 2 or frames is None or det.num_frames < MIN_FRAMES:
        return det, report
    done: set[int] = set()
    while True:
        sp = spans(det)
        frames = frame_numbers(det)
        seen = np.isfinite(det.xy).all(-1).any((1, 2))
        if not seen.any():
            return det, report
        f0 = float(frames[seen].min())
        x = normalised_points(det.xy, cameras)
        base = pair_medians(cameras, det)
        best = None
        for c in range(C):
            if c in done or (C == 2 and c == 0):  # two cameras: the first keeps the time
                continue
            others = np.delete(sp, c)
            ref_span = float(np.median(others[others > 0])) if (others > 0).any() else 0.0
            if ref_span < MIN_FRAMES or sp[c] <= 0:
                continue
            rates = [1.0]
            r_span = float(sp[c]) / ref_span
            if abs(r_span - 1) > MIN_SPAN_GAP and ratio_of(int(sp[c]), ref_span) is None:
                rates.append(r_span)
            before = camera_px(base, c)
            rest = np.delete(np.delete(base, c, 0), c, 1)
            rest_px = float(np.nanmedian(rest)) if np.isfinite(rest).any() else float("nan")
            plausible = max(PLAUSIBLE_PX, 2 * rest_px) if np.isfinite(rest_px) else PLAUSIBLE_PX
            for r in rates:
                m = first_map(cameras, det, x, c, r, max_offset) or ClockMap(r, 0.0)
                m = refine(cameras, det, c, m, f0, ref_span)
                if m is None:
                    continue
                cand = retime(det, c, m.rate, m.offset)
                scatter, stepped, slope_se = in_step(cameras, cand, c)
                m = dataclasses.replace(m, rate_se=max(m.rate_se, m.rate * slope_se))
                after = camera_px(pair_medians(cameras, cand), c)
                why = decide(m, ref_span, scatter, stepped, before, after, plausible)
                if why is not None:
                    log.info("camera '%s': clock not retimed (rate %.5f): %s", cameras[c].name,
                             m.rate, why)  # fmt: skip
                    continue
                if best is None or after < best[2]:
                    best = (c, m, after, before, cand, ref_span)
        if best is None:
            return det, report
        c, m, after, before, cand, ref_span = best
        name = cameras[c].name
        drift = m.drift(ref_span)
        msg = (
            f"camera '{name}' ({det.files[c]}) does not keep the others' time frame for frame: "
            f"its frame {m.rate:.5f} f {m.offset:+.2f} matches their frame f (a frame rate "
            f"{m.rate:.4f}x theirs: {drift:+.1f} frames over the session's {ref_span:.0f}; "
            f"its detections lie {before:.1f} px from the other cameras' epipolar lines as "
            f"numbered, {after:.1f} px so read; "
            + (
                "a clock that drifts: cameras without a common trigger?)"
                if abs(m.rate - 1) < SPAN_TOL
                else "set to another frame rate than theirs?)"
            )
        )
        if mode == "error":
            raise InputError(
                msg + "; resample its file to the others' frames, or set input.camera_check=warn "
                "to read it at their times (input.rate_check=false: no check)"
            )
        log.warning("%s; its detections RETIMED to theirs (input.camera_check=warn)", msg)
        report["retimed"][name] = {
            "rate": round(float(m.rate), 7),
            "offset": round(float(m.offset), 4),
            "rate_se": float(f"{m.rate_se:.3g}"),
            "drift_frames": round(float(drift), 3),
            "epipolar_px": [round(float(before), 3), round(float(after), 3)],
        }
        det = cand
        done.add(c)
