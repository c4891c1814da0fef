"""Camera check: find a camera whose detections disagree with the others, say why, drop it.

    cameras, det, report = check_cameras(cameras, det, mode="warn", exclude=())

After loading, each camera is tested against the consensus of the others, leave one camera out:
the parts are triangulated from the other cameras and projected into this one; its robust error
is the median pixel distance between those projections and its own detections. A camera is
*off* when that error exceeds ``min_px`` (25 px) and either ``ratio`` (3) times the median of
the other cameras' leave-one-out errors (the consensus) or ``fit_ratio`` (10) times the error
to which the other cameras fit each other (with three cameras, one bad camera spoils two of the
three leave-one-out errors, but not the fit of the good pair). The camera with the largest
ratio of its error to the others' fit is judged first, and the check is repeated on the rest
while at least three cameras remain.

For a camera that is off, the likely cause is diagnosed from the others' points:

- ``scene behind the camera``: most of the points lie behind it (a sign or rotation error);
- ``rows in reverse frame order`` / ``frames offset by N``: its detections fit after reversing
  or shifting its rows in time (a wrong or truncated file, a wrong frame rate);
- ``swapped with camera X``: its detections fit camera X's projection (two files swapped); when
  there is no consensus at all (the median leave-one-out error above ``min_px``), every pair of
  cameras is swapped back in turn, and a pair whose swap makes every camera agree is named (an
  error when fewer than two cameras would be left, e.g. with three cameras);
- ``wrong pose``: a pose resected from the others' points with its own intrinsics
  (`adjust.resection.resect`) fits it to a few pixels (the calibration's extrinsics are off);
- else ``detections or intrinsics inconsistent``.

Before that, detections made on scaled or cropped videos are mapped into the calibrated images
(`adjust.pixels`, ``input.pixel_check``; the report's ``pixels``), a camera recorded at a whole
multiple or fraction of the others' frame rate has its frames renumbered to theirs
(`adjust.rates`, ``input.rate_check``; the report's ``rates``), a camera whose clock runs at
another rate than theirs (a non-whole ratio, a drift) is read at their times (`adjust.clocks`,
``input.rate_check`` too; the report's ``clocks``), a camera whose left/right parts
are named the other way round from the others' has them swapped back (`adjust.sides`,
``input.side_check``; the report's ``sides``), detections made on a video undistorted while
the calibration keeps the lens's distortion are mapped into the calibrated image
(`adjust.lens`, ``input.pixel_check`` too; the report's ``lens``), a camera out of step in time
with the others (its video started a few frames early or late) is found from the epipolar
geometry and shifted back (`adjust.sync`, up to ``input.max_frame_offset`` frames; the report's
``sync``), and a camera turned during the session (bumped) has its detections after the move
mapped back (`adjust.moves`, up to ``input.max_camera_moves`` moves; the report's ``moved``).
After it, a kept camera whose exposures fall a fraction of a frame before or after the others'
(no common trigger) has its detections interpolated in time to their
frames (`adjust.subframe`, ``input.subframe_sync``; the report's ``subframe``).

Modes (``input.camera_check``): ``warn`` (default): a camera that is off is excluded and a
warning names it with its error and likely cause (one out of step is shifted back); ``error``:
an `InputError` instead; ``off``: no check. ``input.exclude_cameras=[name, ...]`` drops
cameras by hand before the check. The returned report (the apps put it in ``summary.json`` as
``camera_check``) lists every camera's leave-one-out error, the threshold, the excluded cameras
with error and cause, and the cameras shifted in time (``sync``, ``subframe``).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np
import torch

from adjust.camera import Camera, CameraTensors, project_cameras
from adjust.clocks import check_clocks
from adjust.io import Detections, InputError
from adjust.lens import check_lens
from adjust.moves import check_moves, rig_px
from adjust.pixels import check_pixels
from adjust.rates import check_rates, pair_medians
from adjust.resection import resect
from adjust.settings import InputConfig
from adjust.sides import check_sides, combine
from adjust.subframe import check_subframe
from adjust.sync import check_sync
from adjust.triangulate import triangulate

log = logging.getLogger(__name__)

MODES = ("error", "warn", "off")
MIN_PX = 25.0  #: a camera is off only above this median error (px) ...
RATIO = 3.0  #: ... and above this multiple of the other cameras' (leave-one-out) errors ...
FIT_RATIO = 10.0  #: ... or this multiple of the error to which the others fit each other
MIN_POINTS = 10  #: fewer jointly usable points than this: the camera is not judged
MAX_SHIFT = 5  #: frame offsets tried when diagnosing
FIT_FRACTION = 0.35  #: a diagnosis must bring the camera's error below this fraction of it
RESECTION_POINTS = 100  #: points (spread over the frames) a diagnostic resection uses


def _tri(det: Detections, cams: Sequence[Camera], idx: Sequence[int]) -> np.ndarray:
    """(T, K, 3) points triangulated from cameras `idx` (NaN where < 2 of them saw a part)."""

    ct = CameraTensors.from_cameras([cams[i] for i in idx], dtype=torch.float64)
    with torch.no_grad():
        res = triangulate(
            torch.as_tensor(det.xy[:, :, list(idx)]),
            torch.as_tensor(det.weight()[:, :, list(idx)]),
            ct,
            robust=len(idx) >= 3,
        )
    return res.points.numpy()


def _project(X: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(T, K, 2) pixels and (T, K) depths of points X (T, K, 3) in one camera."""
    ct = CameraTensors.from_cameras([cam], dtype=torch.float64)
    with torch.no_grad():
        uv = project_cameras(torch.as_tensor(np.nan_to_num(X)), ct)[..., 0, :]
    depth = X @ cam.R[2] + cam.tvec[2]
    return uv.numpy(), depth


def _median_error(X: np.ndarray, xy: np.ndarray, cam: Camera) -> tuple[float, int]:
    """Median pixel distance between the projections of X (T, K, 3) and detections xy
    (T, K, 2) where both exist, and how many pairs that is."""
    uv, depth = _project(X, cam)
    ok = np.isfinite(X).all(-1) & np.isfinite(xy).all(-1) & (depth > 0)
    if not ok.any():
        return float("inf"), 0
    return float(np.median(np.linalg.norm(uv - xy, axis=-1)[ok])), int(ok.sum())


def _diagnose(det, cams, active, c, X, err) -> tuple[str, str]:
    """(cause, detail) for camera c whose detections disagree with points X of the others."""
    cam, xy = cams[c], det.xy[:, :, c]
    seen = np.isfinite(X).all(-1) & det.observed[:, :, c]
    _, depth = _project(X, cam)
    if seen.any() and (depth[seen] <= 0).mean() > 0.5:
        return "scene behind the camera", (
            f"{100 * (depth[seen] <= 0).mean():.0f}% of the other cameras' points lie behind it "
            "(a sign or rotation error in its extrinsics?)"
        )
    good = FIT_FRACTION * err  # an explanation must cut the error to this
    rev, _ = _median_error(X, xy[::-1], cam)
    if rev < good:
        return "rows in reverse frame order", f"reversing its rows gives {rev:.1f} px"
    T = xy.shape[0]
    best = (float("inf"), 0)
    for s in range(-MAX_SHIFT, MAX_SHIFT + 1):
        if s == 0 or abs(s) >= T - MIN_POINTS:
            continue
        shifted = np.full_like(xy, np.nan)
        if s > 0:
            shifted[s:] = xy[:-s]  # its row t is frame t + s
        else:
            shifted[:s] = xy[-s:]
        e, n = _median_error(X, shifted, cam)
        if n >= MIN_POINTS and e < best[0]:
            best = (e, s)
    if best[0] < good:
        return f"frames offset by {best[1]}", (
            f"shifting its rows by {best[1]} frames gives {best[0]:.1f} px (a missing or extra "
            "frame at the start of its file?)"
        )
    for d in range(len(cams)):  # excluded cameras too: the other half of a swap may be gone
        if d == c:
            continue
        rest = [i for i in active if i not in (c, d)]
        if len(rest) < 2:
            continue
        Xr = _tri(det, cams, rest)
        e_cd, n = _median_error(Xr, xy, cams[d])
        if n >= MIN_POINTS and e_cd < good:
            e_dc, _ = _median_error(Xr, det.xy[:, :, d], cam)
            both = e_dc < good
            return f"swapped with camera '{cams[d].name}'" if both else (
                f"holds camera '{cams[d].name}''s detections"
            ), (
                f"its detections fit camera '{cams[d].name}' to {e_cd:.1f} px"
                + (f" and '{cams[d].name}''s fit it to {e_dc:.1f} px" if both else "")
            )
    if seen.sum() >= 6:
        idx = np.flatnonzero(seen.reshape(-1))
        if idx.size > RESECTION_POINTS:
            idx = idx[np.linspace(0, idx.size - 1, RESECTION_POINTS).astype(int)]
        Xs, xs = X.reshape(-1, 3)[idx], xy.reshape(-1, 2)[idx]
        quiet = logging.getLogger("adjust.resection")
        level = quiet.level
        quiet.setLevel(logging.ERROR)  # its "large error" warning is expected here
        try:
            fit = resect(
                Xs, xs, K=cam.K, dist=cam.dist, name=cam.name, size=cam.size, max_iter=30,
                fisheye=cam.fisheye,
            )  # fmt: skip
        except ValueError:
            fit = None
        finally:
            quiet.setLevel(level)
        if fit is not None:
            e, _ = _median_error(X, xy, fit)
            if e < good:
                moved = float(np.linalg.norm(fit.center - cam.center))
                dR = fit.R @ cam.R.T
                angle = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
                twins = [
                    o.name
                    for o in cams
                    if o is not cam and np.allclose(o.center, cam.center, rtol=0, atol=1e-6)
                ]
                return "wrong pose", (
                    f"a pose resected from the other cameras' points fits it to {e:.1f} px; "
                    f"the calibration's is {moved:.0f} mm and {angle:.0f} deg away from it"
                    + (f"; it has the pose of camera {twins} (copied extrinsics?)" if twins else "")
                    + "; recalibrate its extrinsics"
                )
    return "detections or intrinsics inconsistent", "no simple fix found"


def _loo(det: Detections, cams: Sequence[Camera], active: Sequence[int]) -> dict[int, float]:
    """{camera: median error of its detections against the others' points}."""
    out = {}
    for c in active:
        X = _tri(det, cams, [i for i in active if i != c])
        out[c] = _median_error(X, det.xy[:, :, c], cams[c])[0]
    return out


def _find_swap(det, cams, active, loo, min_px) -> tuple[int, int, float] | None:
    """Two cameras whose detection files are swapped: swapping their columns makes every
    camera agree (all leave-one-out errors below min_px and a third of today's median)."""
    now = float(np.median(list(loo.values())))
    best = None
    for a in active:
        for b in active:
            if b <= a:
                continue
            xy = det.xy.copy()
            xy[:, :, [a, b]] = xy[:, :, [b, a]]
            w = det.likelihood.copy()
            w[:, :, [a, b]] = w[:, :, [b, a]]
            after = _loo(dataclasses.replace(det, xy=xy, likelihood=w), cams, active)
            worst = max(after.values())
            if worst < min_px and worst < now / 3 and (best is None or worst < best[2]):
                best = (a, b, worst)
    return best


def _in_step_and_in_place(cams, det, max_offset: int, max_moves: int, mode: str):
    """`adjust.sync.check_sync` and `adjust.moves.check_moves` in the order that leaves the
    cameras agreeing best. Either can be fooled by what the other undoes: a bumped camera's
    detections lie off at every lag, and a lag that the animal's motion happens to fit better
    reads as an offset (two cameras); a camera out of step can look turned where the animal
    walks one way. Both orders are tried quietly and the one whose detections lie closest to
    the others' epipolar lines (`adjust.moves.rig_px`) is run (and said); where neither
    finds anything, that is the result. Returns (detections, sync report, moves report)."""
    quiet = [logging.getLogger(n) for n in ("adjust.sync", "adjust.moves")]
    levels = [q.level for q in quiet]
    for q in quiet:
        q.setLevel(logging.ERROR)
    try:
        a, a_sync = check_sync(cams, det, max_offset, "warn")
        a, a_moved = check_moves(cams, a, max_moves, "warn")
        b, b_moved = check_moves(cams, det, max_moves, "warn")
        b, b_sync = check_sync(cams, b, max_offset, "warn")
    finally:
        for q, level in zip(quiet, levels):
            q.setLevel(level)
    moves_first = b is not a and rig_px(cams, b) < rig_px(cams, a)
    if moves_first:
        det, moved = check_moves(cams, det, max_moves, mode)
        det, sync = check_sync(cams, det, max_offset, mode)
    else:
        det, sync = check_sync(cams, det, max_offset, mode)
        det, moved = check_moves(cams, det, max_moves, mode)
    return det, sync, moved


def drop_cameras(
    cameras: Sequence[Camera], det: Detections, names: Sequence[str]
) -> tuple[list[Camera], Detections]:
    """The cameras and detections without the named cameras."""
    keep = [i for i, c in enumerate(cameras) if c.name not in set(names)]
    det = dataclasses.replace(
        det,
        cameras=tuple(det.cameras[i] for i in keep),
        xy=det.xy[:, :, keep],
        likelihood=det.likelihood[:, :, keep],
        files=tuple(det.files[i] for i in keep),
    )
    return [cameras[i] for i in keep], det


def check_cameras(
    cameras: Sequence[Camera],
    det: Detections,
    mode: str = "warn",
    exclude: Sequence[str] | None = (),
    *,
    min_px: float = MIN_PX,
    ratio: float = RATIO,
    fit_ratio: float = FIT_RATIO,
    max_offset: int = 0,
    max_moves: int = 0,
    subframe: bool = False,
    rates: bool = False,
    pixels: bool = False,
    sides: bool = False,
    reference=None,
) -> tuple[list[Camera], Detections, dict]:
    """Drop the cameras named in `exclude`, then (mode warn/error) shift back a camera out of
    step by up to `max_offset` frames (`adjust.sync.check_sync`; 0: none), map back up to
    `max_moves` cameras turned mid-session (`adjust.moves.check_moves`; 0: none), test each
    camera against the others (see the module doc) and, with `subframe`, interpolate in time
    a kept camera out of step by a fraction of a frame (`adjust.subframe.check_subframe`);
    first, with `pixels`, map detections made on scaled or cropped videos into the calibrated
    images (`adjust.pixels.check_pixels`) and, with `rates`, renumber a camera at a whole
    multiple or fraction of the others' frame rate (`adjust.rates.check_rates`) and read one
    whose clock runs at another rate at their times (`adjust.clocks.check_clocks`), with
    `sides` swap back a camera whose left/right parts are named the other way round
    (`adjust.sides.check_sides`; `reference`, a named body model, decides a tie), and with
    `pixels` map detections made on undistorted videos (`adjust.lens.check_lens`).
    Returns the kept cameras, their detections (T, K, C', 2) and the report for the summary."""
    if mode not in MODES:
        raise InputError(f"input.camera_check must be one of {list(MODES)}, got {mode!r}")
    names = [c.name for c in cameras]
    if list(det.cameras) != names:
        raise ValueError(f"detections' cameras {det.cameras} are not the cameras {names}")
    exclude = [str(n) for n in (exclude or [])]
    unknown = [n for n in exclude if n not in names]
    if unknown:
        raise InputError(f"input.exclude_cameras: unknown cameras {unknown} (cameras: {names})")
    report: dict = {"mode": mode, "excluded_by_hand": exclude, "excluded": {}}
    if exclude:
        log.warning("cameras %s excluded by hand (input.exclude_cameras)", exclude)
    cams, det = drop_cameras(cameras, det, exclude)
    if len(cams) < 2:
        raise InputError(f"fewer than 2 cameras left after excluding {exclude}: {names}")
    if mode == "off":
        return cams, det, report
    if pixels:
        det, report["pixels"] = check_pixels(cams, det, mode)
    if rates:
        det, report["rates"] = check_rates(cams, det, mode)
        det, report["clocks"] = check_clocks(cams, det, mode, max(max_offset, 2))
    if sides:
        det, report["sides"] = check_sides(cams, det, mode, reference)
    if pixels:  # undistorted videos (before the move check, which takes them for a turn)
        det, report["lens"] = check_lens(cams, det, mode)
    det, report["sync"], report["moved"] = _in_step_and_in_place(
        cams, det, max_offset, max_moves, mode
    )
    if sides:  # again: a camera out of step or turned is told once it is put right
        det, again = check_sides(cams, det, mode, reference)
        report["sides"] = combine(report["sides"], again)
    report.update(min_px=min_px, ratio=ratio, leave_one_out_px={}, others_px={})
    active = list(range(len(cams)))
    excluded: list[str] = []
    if len(cams) == 2:  # no camera to outvote the other: one beyond min_px leaves one camera
        px = float(pair_medians(cams, det)[0, 1])
        report["pair_px"] = px
        if px > min_px:
            raise InputError(
                f"cameras '{cams[0].name}' ({det.files[0]}) and '{cams[1].name}' "
                f"({det.files[1]}) disagree: their detections lie {px:.1f} px (median) from "
                f"each other's epipolar lines (more than {min_px:.0f} px), and with two "
                "cameras neither can be excluded: a calibration that does not belong to these "
                "detections, or videos cropped in a way the pixel check cannot tell? Fix the "
                "calibration or the files (input.camera_check=off tracks them anyway)"
            )
    while len(active) >= 3:
        loo, rest, npts, pts = {}, {}, {}, {}
        for c in active:
            others = [i for i in active if i != c]
            X = _tri(det, cams, others)
            loo[c], npts[c] = _median_error(X, det.xy[:, :, c], cams[c])
            own = [_median_error(X, det.xy[:, :, d], cams[d])[0] for d in others]
            rest[c] = float(np.median(own))
            pts[c] = X
            seen = np.isfinite(X).all(-1) & det.observed[:, :, c]
            if npts[c] < MIN_POINTS and seen.sum() >= MIN_POINTS:
                _, depth = _project(X, cams[c])
                if (depth[seen] <= 0).mean() > 0.5:  # the scene is behind it: judge it
                    loo[c], npts[c] = float("inf"), int(seen.sum())
        if not report["leave_one_out_px"]:
            report["leave_one_out_px"] = {cams[c].name: loo[c] for c in active}
            report["others_px"] = {cams[c].name: rest[c] for c in active}
        if float(np.median(list(loo.values()))) > min_px:  # no consensus: two files swapped?
            swap = _find_swap(det, cams, active, loo, min_px)
            if swap is not None:
                a, b, after = swap
                na, nb = cams[a].name, cams[b].name
                msg = (
                    f"cameras '{na}' ({det.files[a]}) and '{nb}' ({det.files[b]}) disagree with "
                    f"the others ({loo[a]:.1f} and {loo[b]:.1f} px median): their detection "
                    f"files look swapped (swapped back, every camera agrees to {after:.1f} px)"
                )
                if mode == "error" or len(active) - 2 < 2:
                    raise InputError(
                        msg
                        + "; swap the files (or rename them) and run again"
                        + ("" if mode == "error" else " (too few cameras would be left)")
                    )
                log.warning("%s; both EXCLUDED from the solve (input.camera_check=warn)", msg)
                for c, other in ((a, nb), (b, na)):
                    report["excluded"][cams[c].name] = {
                        "error_px": loo[c],
                        "others_px": rest[c],
                        "threshold_px": min_px,
                        "cause": f"swapped with camera '{other}'",
                        "detail": f"swapped back, every camera agrees to {after:.1f} px",
                        "points": npts[c],
                    }
                    excluded.append(cams[c].name)
                active = [i for i in active if i not in (a, b)]
                continue
        judged = [c for c in active if npts[c] >= MIN_POINTS and np.isfinite(rest[c])]
        if not judged:
            break
        c = max(judged, key=lambda i: loo[i] / max(rest[i], 0.5))
        consensus = float(np.median([loo[i] for i in active if i != c]))
        threshold = max(min_px, min(ratio * consensus, fit_ratio * max(rest[c], 0.5)))
        if not loo[c] > threshold:
            break
        cause, detail = _diagnose(det, cams, active, c, pts[c], loo[c])
        name = cams[c].name
        msg = (
            f"camera '{name}' ({det.files[c]}) disagrees with the others: its detections lie "
            f"{loo[c]:.1f} px (median) from the points the other cameras triangulate (they "
            f"fit each other to {rest[c]:.1f} px; each of them, left out, {consensus:.1f} px); "
            f"likely cause: {cause} ({detail})"
        )
        if mode == "error":
            raise InputError(
                msg + "; fix it, or exclude it (input.exclude_cameras=[" + name + "]) or set "
                "input.camera_check=warn"
            )
        log.warning("%s; EXCLUDED from the solve (input.camera_check=warn)", msg)
        report["excluded"][name] = {
            "error_px": loo[c],
            "others_px": rest[c],
            "consensus_px": consensus,
            "threshold_px": threshold,
            "cause": cause,
            "detail": detail,
            "points": npts[c],
        }
        excluded.append(name)
        active.remove(c)
    cams, det = drop_cameras(cams, det, excluded)
    kept = [c.name for c in cams]
    report["cameras_used"] = kept
    loo_px = report["leave_one_out_px"]
    unjudged = [k for k, v in loo_px.items() if not np.isfinite(v)]
    if not excluded and loo_px and not unjudged and max(loo_px.values()) > min_px:
        log.warning(
            "camera check: no camera agrees with the others to within %.0f px (leave-one-out "
            "median %s px): a calibration that does not belong to these detections? (videos "
            "downsampled or cropped before the pose estimator are looked for: "
            "input.pixel_check)",
            min_px,
            ", ".join(f"{k} {v:.1f}" for k, v in loo_px.items()),
        )
    elif not excluded and loo_px and not unjudged:
        log.info(
            "camera check: all %d cameras agree (leave-one-out median %s px)",
            len(kept),
            ", ".join(f"{k} {v:.1f}" for k, v in loo_px.items()),
        )
    elif not excluded and unjudged:  # e.g. a camera without detections: not "agreeing"
        log.info(
            "camera check: cameras %s not judged (too few of their detections seen by the "
            "others); the others agree (leave-one-out median %s px)",
            unjudged,
            ", ".join(f"{k} {v:.1f}" for k, v in loo_px.items() if k not in unjudged) or "-",
        )
    if subframe:
        det, report["subframe"] = check_subframe(cams, det, mode)
    return cams, det, report


def check_from_config(
    cameras: Sequence[Camera], det: Detections, inp, reference=None
) -> tuple[list[Camera], Detections, dict]:
    """`check_cameras` with the settings of an app's ``input`` node (an
    `adjust.settings.InputConfig` or the node it is read from): ``camera_check`` (error|warn|
    off), ``exclude_cameras`` (a list of names, or one name), ``max_frame_offset``,
    ``max_camera_moves``, ``subframe_sync``, ``rate_check``, ``pixel_check`` and
    ``side_check`` (`reference`: a named body model whose left and right decide a tie of the
    side check; None: the first camera keeps its labels)."""
    ic = InputConfig.from_config(inp)
    mode, exclude = ic.camera_check, list(ic.exclude_cameras)
    return check_cameras(
        cameras,
        det,
        mode,
        exclude,
        max_offset=ic.max_frame_offset,
        max_moves=ic.max_camera_moves,
        subframe=ic.subframe_sync,
        rates=ic.rate_check,
        pixels=ic.pixel_check,
        sides=ic.side_check,
        reference=reference,
    )
