"""Pixel frames: find detections made on videos other than the calibrated ones, scaled (the
videos downsampled for the pose estimator), shifted (cropped: DeepLabCut's ``cropping``),
flipped or turned by a quarter turn, and map them back into the calibrated images.

    det, report = check_pixels(cameras, det)

A camera whose detections u (px) are the calibrated image's pixels x = s u + d (a scale s, an
offset d) lies far from the other cameras' epipolar lines. Unnoticed, a cropped camera was
excluded with a wrong cause ("wrong pose"), and a rig whose every video was downsampled read
as "all cameras agree" at 100-150 px and tracked garbage with exit 0. Where the cameras already
agree (every camera's median symmetric epipolar distance within `PLAUSIBLE_PX`) nothing is
looked for. Else:

- every camera scaled alike about the top-left pixel's corner (a downsampled rig, x = s u +
  (s - 1) / 2), for each s of `SCALES`;
- then the camera farthest from the others' lines, and the next, each once (two cameras: the
  second; the first keeps its frame): s and d fitted to the epipolar lines of the cameras that
  agree among themselves without it (`fit_camera`: the lines in its ideal pixels, each
  detection's residual linear in (s, dx, dy), least squares, residuals beyond `CUT` MADs left
  out). Against one camera's lines (two cameras) the scale is not told (they meet at the
  epipole: any scale about it fits) and is held at 1: a crop; an offset along nearly parallel
  lines is not told either, and is not fitted;
- then, for a camera still far from the others' lines, its video flipped (`FLIPS`: left to
  right, upside down, by a half turn; x = W - 1 - u along each flipped axis): a view from
  below mirrored to look like one from above before the pose estimator; or turned (`TURNS`: a
  quarter turn either way, a camera mounted on its side and its video turned upright; or its
  x and y swapped, a transpose, as a converter that writes the columns the other way round
  gives; x = A u + d, A a signed permutation, `edit_map`). The edit that brings its camera
  closest to the others is kept if it does so by `BETTER` and to within `PLAUSIBLE_PX` itself
  (two camera files swapped with each other came 3x closer flipped by a half turn, to 60 px);
  with two cameras either camera may be the edited one (a flip or a turn, unlike a crop, is
  told by the geometry).

A scale-and-offset map must be a video edit: its scale within `SNAP` of 1 or of a `SCALES` ratio
(then refitted with that scale; a scale of 1 needs an offset of `MIN_CROP_PX` or more): a
calibration a little off (a focal length 2% off is a scale about the principal point) is not
mapped. A camera's map is kept where it brings its median distance (`adjust.rates.pair_medians`)
down by `BETTER` (3x) and to within `PLAUSIBLE_PX` or twice the other pairs'; its detections are
mapped, with a warning naming the scale and offset. Runs first in the camera check
(`adjust.camera_check`); ``input.camera_check=error`` stops instead, ``input.pixel_check=
false`` does not look.
Detections: ``Detections`` (T, K, C, 2) px."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np

from adjust.camera import Camera
from adjust.io import Detections, InputError
from adjust.rates import camera_px, pair_medians
from adjust.sync import essential, focal_px, normalised_points, spread_rows

log = logging.getLogger(__name__)

SCALES = (0.25, 1 / 3, 0.5, 2 / 3, 0.75, 4 / 3, 1.5, 2.0, 3.0, 4.0)  #: downsampled rigs tried
PLAUSIBLE_PX = 5.0  #: a camera within this median epipolar distance agrees
BETTER = 3.0  #: a map must bring the camera's median distance down by this factor
CUT = 4.0  #: residuals beyond this many MADs are left out of a fit
MAX_ROWS = 3_000  #: rows a fit uses (spread over the session)
MAX_SE_PX = 1.0  #: an offset fitted to one camera's lines must be this well fixed (px)
SNAP = 0.005  #: a fitted scale within this fraction of 1 or of a `SCALES` ratio is that ratio
MIN_CROP_PX = 10.0  #: a crop (scale 1) moves the image by at least this many px
TELL_RATIO = 1.05  #: another camera's map fitting the rig to within this factor: not told
#: a video mirrored (how: the per-axis scale s of x = s u + d)
FLIPS = {"left to right": (-1.0, 1.0), "upside down": (1.0, -1.0), "by a half turn": (-1.0, -1.0)}
#: a video turned or transposed (how: A of x = A u + d; ffmpeg's ``transpose`` 1, 2, 0, 3)
TURNS = {
    "a quarter turn clockwise": ((0.0, 1.0), (-1.0, 0.0)),
    "a quarter turn counter-clockwise": ((0.0, -1.0), (1.0, 0.0)),
    "transposed (its x and y swapped)": ((0.0, 1.0), (1.0, 0.0)),
    "transposed about the other diagonal": ((0.0, -1.0), (-1.0, 0.0)),
}


def edit_map(how: str, size) -> tuple:
    """The map (s, d) back into the calibrated image, its `size` (W, H) px, of a video flipped
    (`FLIPS`: x = W - 1 - u along each flipped axis) or turned (`TURNS`: x = A u + d, the turned
    video H px wide) `how`; pixel centres."""
    s = FLIPS[how] if how in FLIPS else TURNS[how]
    rows = np.diag(s) if how in FLIPS else np.array(s)
    W, H = size
    return s, tuple(float(n - 1) if r.sum() < 0 else 0.0 for n, r in zip((W, H), rows))


def _edit_words(how: str) -> tuple[str, str]:
    """How a flip or turn `how` reads in a warning: the edit, and its likely cause."""
    if how in FLIPS:
        return f"flipped {how}", "video flipped before the pose estimator?"
    if "turn" in how:
        return f"turned {how}", "video turned upright before the pose estimator?"
    return how, "its x and y columns swapped, or its video transposed before the pose estimator?"


def apply(det: Detections, maps: dict) -> Detections:
    """The detections with camera ``name``'s pixels u mapped to s u + d, ``maps[name]`` = (s,
    (dx, dy)); s a number, (sx, sy) per axis (a flip), or a 2 x 2 matrix (a turn)."""
    if not maps:
        return det
    xy = det.xy.copy()
    for name, (s, d) in maps.items():
        c = det.cameras.index(name)
        s = np.asarray(s, dtype=np.float64)
        u = det.xy[:, :, c]
        xy[:, :, c] = (u @ s.T if s.ndim == 2 else s * u) + np.asarray(d, dtype=np.float64)
    return dataclasses.replace(det, xy=xy)


def _ideal(xy: np.ndarray, cam: Camera) -> np.ndarray:
    """Ideal (undistorted) pixels of xy (N, K, 2) in `cam` (NaN stays NaN)."""
    n = normalised_points(xy[:, :, None], [cam])[:, :, 0]
    return n @ cam.K[:2, :2].T + cam.K[:2, 2]


def fit_camera(cameras: Sequence[Camera], det: Detections, c: int, refs: Sequence[int], scale=None):
    """(s, (dx, dy)) mapping camera c's pixels into its calibrated image, fitted to the
    epipolar lines of cameras `refs` (their detections as they are in `det`); ``scale`` given:
    s fixed, the offset alone (one reference camera: its lines meet at the epipole, and a
    scale about it fits any of them); None where too few part-frames tell or the lines'
    directions do not fix the offset."""
    rows = np.arange(det.num_frames)
    cam = cameras[c]
    u = det.xy[rows, :, c]  # (N, K, 2) as the files have them
    Kc_inv = np.linalg.inv(cam.K)
    A_rows, b_rows = [], []
    for o in refs:
        xo = _ideal(det.xy[rows, :, o], cameras[o])
        both = np.isfinite(u).all(-1) & np.isfinite(xo).all(-1)
        if not both.any():
            continue
        Ko_inv = np.linalg.inv(cameras[o].K)
        F = Kc_inv.T @ essential(cameras[o], cam) @ Ko_inv  # x_c^T F x_o = 0 (ideal px)
        h = np.concatenate([xo[both], np.ones((both.sum(), 1))], 1)
        line = h @ F.T  # (n, 3) in camera c's ideal pixels
        norm = np.linalg.norm(line[:, :2], axis=1)
        line = line / np.maximum(norm, 1e-12)[:, None]
        uu = u[both]
        A_rows.append(np.stack([(line[:, :2] * uu).sum(1), line[:, 0], line[:, 1]], 1))
        b_rows.append(-line[:, 2])
    if not A_rows:
        return None
    A, b = np.concatenate(A_rows), np.concatenate(b_rows)
    if len(b) < 30:
        return None
    if scale is not None:
        b, A = b - scale * A[:, 0], A[:, 1:]
    keep = np.ones(len(b), bool)
    p = None
    for _ in range(4):
        p, *_ = np.linalg.lstsq(A[keep], b[keep], rcond=None)
        r = A @ p - b
        mad = 1.4826 * float(np.median(np.abs(r[keep])))
        keep = np.abs(r) <= CUT * max(mad, 1e-6)
        if keep.sum() < 30:
            return None
    if scale is not None:  # nearly parallel lines leave the offset along them free
        sigma2 = float(np.mean(r[keep] ** 2))
        se = np.sqrt(sigma2 * np.diag(np.linalg.pinv(A[keep].T @ A[keep])))
        if not np.all(se <= MAX_SE_PX):
            return None
    s, dx, dy = (float(v) for v in p) if scale is None else (float(scale), *map(float, p))
    if not np.isfinite([s, dx, dy]).all() or s <= 0:
        return None
    return s, (dx, dy)


def _resized(s: float):
    """The map of a video resized by 1 / s (pixel centres: x = s u + (s - 1) / 2)."""
    return s, ((s - 1) / 2, (s - 1) / 2)


def _without(med: np.ndarray, o: int, c: int) -> float:
    """Camera o's median over its pairs' medians, camera c's pair left out (inf where none)."""
    v = np.array([med[o, q] for q in range(len(med)) if q not in (o, c)])
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else float("inf")


def _compose(outer, inner):
    """The map x = outer(inner(u)) of two maps (s, d)."""
    so, do = outer
    si, di = inner
    return so * si, (so * di[0] + do[0], so * di[1] + do[1])


def check_pixels(
    cameras: Sequence[Camera], det: Detections, mode: str = "warn"
) -> tuple[Detections, dict]:
    """Find and undo scaled or shifted pixel frames (module doc). ``mode`` as the camera
    check's: warn = map the detections and say so, error = an `InputError` naming the camera,
    off = nothing. Returns the (mapped) detections and the report {"mapped": {name: {"scale",
    "offset", "epipolar_px": [as read, mapped]}}}."""
    report: dict = {"mapped": {}}
    C = len(cameras)
    if mode == "off" or C < 2:
        return det, report
    rows = spread_rows(det.num_frames, MAX_ROWS)
    sub = dataclasses.replace(det, xy=det.xy[rows], likelihood=det.likelihood[rows], frames=None)
    base = pair_medians(cameras, sub)
    before = np.array([camera_px(base, c) for c in range(C)])
    if not np.isfinite(before).any() or np.nanmax(before) <= PLAUSIBLE_PX:
        return det, report
    names = [cam.name for cam in cameras]
    identity = (1.0, (0.0, 0.0))
    maps = {n: identity for n in names}

    def score(m: dict) -> np.ndarray:
        med = pair_medians(cameras, apply(sub, {n: v for n, v in m.items() if v != identity}))
        return np.array([camera_px(med, c) for c in range(C)])

    best, best_px = maps, before
    for s in SCALES:  # a downsampled rig: every camera alike
        trial = {n: _resized(s) for n in names}
        px = score(trial)
        if np.nanmedian(px) * BETTER <= np.nanmedian(best_px):
            best, best_px = trial, px
    maps = dict(best)

    def fitted(c: int, cur: Detections, med: np.ndarray, maps: dict, px_now: np.ndarray):
        """Camera c's map fitted to the cameras that agree without it (`fit_camera`; the
        detections `cur` as mapped by `maps`, their pair medians `med`): (the maps with it,
        the cameras' distances then, or None where it does not bring c closer by `BETTER`);
        None where no map is fitted."""
        refs = [o for o in range(C) if o != c and (C < 3 or _without(med, o, c) <= PLAUSIBLE_PX)]
        refs = refs or [o for o in range(C) if o != c]
        fit = fit_camera(cameras, cur, c, refs, scale=1.0 if len(refs) == 1 else None)
        if fit is None:
            return None
        trial = dict(maps)
        trial[names[c]] = _compose(fit, maps[names[c]])
        px = score(trial)
        return trial, px if px[c] * BETTER <= px_now[c] else None

    tried: set[int] = set()
    for _ in range(C):  # the worst camera first, fitted to the cameras that agree without it
        px_now = score(maps)
        bad = [c for c in (range(1, C) if C == 2 else range(C))
               if c not in tried and px_now[c] > PLAUSIBLE_PX]  # fmt: skip
        if not bad:
            break
        c = max(bad, key=lambda i: px_now[i])
        tried.add(c)
        cur = apply(sub, {n: v for n, v in maps.items() if v != identity})
        med = pair_medians(cameras, cur)

        got = fitted(c, cur, med, maps, px_now)
        if got is None or got[1] is None:
            continue
        fits = {c: got}  # the other cameras far off too: does one of their maps fit better?
        for o in (o for o in bad if o != c) if C >= 3 else ():
            other = fitted(o, cur, med, maps, px_now)
            if other is not None and other[1] is not None:
                fits[o] = other
        level = {o: float(np.nanmax(f[1])) for o, f in fits.items()}
        best = min(level, key=level.get)
        alike = [o for o in level if o != best and level[o] <= TELL_RATIO * level[best]]
        if alike:
            tried.update(fits)
            log.warning(
                "cameras %s lie off each other's epipolar lines (%s px) and a shift of any "
                "of them fits (to %s px): which one is off (its video cropped, or the "
                "camera moved since its calibration) is not told, and none is mapped",
                [names[o] for o in (best, *alike)],
                ", ".join(f"{px_now[o]:.1f}" for o in (best, *alike)),
                ", ".join(f"{level[o]:.1f}" for o in (best, *alike)),
            )
            continue
        tried.add(best)
        maps = fits[best][0]
    for c in range(C):  # a video edit: a resize by a plain ratio, or a crop (snapped, refitted)
        m = maps[names[c]]
        if m == identity or m == _resized(m[0]):  # the rig's resize: a plain ratio already
            continue
        nice = min((1.0, *SCALES), key=lambda v: abs(m[0] / v - 1))
        fit = None
        if abs(m[0] / nice - 1) <= SNAP:
            others = apply(sub, {n: v for n, v in maps.items() if v != identity and n != names[c]})
            fit = fit_camera(cameras, others, c, [o for o in range(C) if o != c], scale=nice)
        if fit is None or (nice == 1.0 and max(abs(v) for v in fit[1]) < MIN_CROP_PX):
            log.info(
                "camera '%s' fits the others better as x = %.4g u + (%.1f, %.1f) px, which is "
                "no resize by a plain ratio nor a crop (a calibration a little off?): left as "
                "it is",
                names[c],
                m[0],
                *m[1],
            )
            maps[names[c]] = identity
        else:
            maps[names[c]] = fit
    edited: dict[str, str] = {}  # camera -> how its video was flipped or turned
    for _ in range(C):  # a flipped or turned video: the edit that best brings a camera back
        px_now = score(maps)
        trials = [(name, how) for c, name in enumerate(names) for how in (*FLIPS, *TURNS)
                  if maps[name] == identity and px_now[c] > PLAUSIBLE_PX
                  and min(cameras[c].size) > 0]  # fmt: skip
        if not trials:
            break
        got = []
        for name, how in trials:
            trial = dict(maps)
            trial[name] = edit_map(how, cameras[names.index(name)].size)
            got.append((float(score(trial)[names.index(name)]), name, how, trial))
        px, name, how, trial = min(got, key=lambda g: g[0])
        if not (px * BETTER <= px_now[names.index(name)] and px <= PLAUSIBLE_PX):
            break
        maps, edited[name] = trial, how
    after = score(maps)
    for c in range(C):
        rest = np.delete(np.delete(base, c, 0), c, 1)
        rest_px = float(np.nanmedian(rest)) if np.isfinite(rest).any() else float("nan")
        plausible = max(PLAUSIBLE_PX, 2 * rest_px) if np.isfinite(rest_px) else PLAUSIBLE_PX
        if names[c] in edited:  # a flip or turn brings its camera to the rig, not near it
            plausible = PLAUSIBLE_PX
        m = maps[names[c]]
        if m == identity or not (after[c] <= plausible and after[c] * BETTER <= before[c]):
            maps[names[c]] = identity
            continue
        s, (dx, dy) = m
        far = f"they lie {before[c]:.1f} px from the other cameras' epipolar lines as read"
        how = edited.get(names[c])
        if how is not None:
            edit, why = _edit_words(how)
            msg = (
                f"camera '{names[c]}' ({det.files[c]}): its detections fit the calibration's "
                f"image {edit} ({far}, {after[c]:.1f} px mapped back; {why})"
            )
        else:
            what = "downsampled" if s > 1.01 else "upsampled" if s < 0.99 else "cropped"
            turn = float(np.degrees(np.arctan(np.hypot(dx, dy) / focal_px(cameras[c]))))
            bump = f" or the camera turned {turn:.1f} deg since its calibration?"
            bump = bump if what == "cropped" else ""
            if abs(s - 1) > 0.01 and max(abs(dx), abs(dy)) > abs(s - 1):
                what += " or cropped"
            msg = (
                f"camera '{names[c]}' ({det.files[c]}): its detections fit the calibration's "
                f"image as x = {s:.4g} u + ({dx:.1f}, {dy:.1f}) px ({far}, {after[c]:.1f} px "
                f"mapped; videos {what} before the pose estimator?{bump})"
            )
        if mode == "error":
            raise InputError(
                msg + "; give detections in the calibrated videos' pixels, or set "
                "input.camera_check=warn to map them (input.pixel_check=false: no check)"
            )
        log.warning("%s; its detections MAPPED into the calibrated image", msg)
        report["mapped"][names[c]] = {
            "scale": np.asarray(s, dtype=float).tolist() if how is not None else round(s, 6),
            "offset": [round(dx, 3), round(dy, 3)],
            "epipolar_px": [round(float(before[c]), 3), round(float(after[c]), 3)],
            **({"flip" if how in FLIPS else "turn": how} if how is not None else {}),
        }
    kept = {n: maps[n] for n in report["mapped"]}
    return apply(det, kept), report
