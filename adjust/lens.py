"""Lens check: find detections made on a video undistorted before the pose estimator while the
calibration still carries the lens's distortion, and map them into the calibrated images.

    det, report = check_lens(cameras, det)

A lab that undistorts its videos (``cv2.undistort``: the camera matrix kept) and then gives the
calibration made on the raw videos has its detections undistorted twice. Unnoticed, the error
grows with the distance from the image's centre and every camera errs alike, so the cameras
still agree to a pixel or two at the median: the real motion filmed through lenses like the
real SLEAP rig's (k1 -0.29) tracked up to 15x worse with exit 0 where the mouse reached the
images' margins (the validation segment; 1.00-1.08x on the test segment, where it kept nearer
their centres; `benchmarks/lens.py`).

The two readings of a camera's detections u: as the calibration reads them (undistorted with
its distortion) and as an undistorted video's pixels (normalised coordinates K^-1 u). They
differ only away from the image's centre, so the check looks only there: over the part-frames
of each camera pair where either camera's detection moves by `MOVE_PX` or more between the
readings, the pair's median symmetric epipolar distance for each pair of readings
(`pair_scores`); a rig's score is the geometric mean over its pairs (`rig_score`). Every set
of cameras (of those whose calibration has a distortion) read as undistorted is scored
against none. A set counts where each of its cameras' own pairs come `CAMERA_BETTER` closer
read so than as read, the set's other cameras read so either way (a camera beside an
undistorted one gains from its partner's reading, not its own), and none of the rig's pairs
`WORSE` (a camera whose calibration lacks its lens's distortion makes the others look
undistorted to it alone). The best set is kept where it lowers the rig's score by `BETTER`,
to within `PLAUSIBLE_PX` and `LEVEL` times the rig's distance over all part-frames, unless one
camera turned (`adjust.moves.fit_rotation`, fitted to all its part-frames) brings the margins
as close (`TELL`): a camera bumped since its calibration (with two cameras, its partner read
as undistorted fitted it 2x closer) is no lens; a warning then says so, and the move check
looks for the turn. Else its cameras' detections are mapped into their calibrated
(distorted) images, x = K distort(K^-1 u), with a warning. A calibration whose distortion is
much too strong for its lens fits the same way and is named beside it. Not looked for: an
undistortion with another camera matrix (``cv2.getOptimalNewCameraMatrix``: a zoom, which a
calibration a little off resembles); a calibration without the lens's distortion (the
distortion would have to be fitted).

Runs in the camera check before the move check (which took such a camera for one turned since
its calibration) and after the other checks (`adjust.camera_check`), under
``input.pixel_check``; ``input.camera_check=error`` stops instead. Detections: ``Detections``
(T, K, C, 2) px."""

from __future__ import annotations

import dataclasses
import itertools
import logging
from collections.abc import Sequence

import numpy as np
import torch

from adjust.camera import Camera
from adjust.distortion import distort_points, pixels_to_normalized
from adjust.io import Detections, InputError
from adjust.moves import fit_rotation, rotate
from adjust.rates import MIN_PAIRS as MIN_MEDIAN_PAIRS
from adjust.sync import (
    epipolar_medians,
    epipolar_px,
    essential,
    focal_px,
    normalised_points,
    spread_rows,
)

log = logging.getLogger(__name__)

MOVE_PX = 10.0  #: a detection the two readings place this far apart (ideal px) tells them apart
BETTER = 1.5  #: the rig's score must fall by this factor
CAMERA_BETTER = 1.25  #: ... and each camera read as undistorted its own pairs' by this one
WORSE = 1.1  #: ... and none of its pairs farther than this factor as read
PLAUSIBLE_PX = 5.0  #: ... to within this many px
LEVEL = 1.5  #: ... and to within this factor of the rig's distance over all part-frames
TELL = 1.0  #: a camera turned fitting the margins within this factor of the reading: not told
BROKEN_PX = 25.0  #: a camera pair this far apart over all part-frames is not scored (a wrong pose)
MIN_PAIRS = 30  #: part-frames a camera pair needs where the readings differ
MAX_ROWS = 3_000  #: rows the check uses (spread over the session)


def as_undistorted(xy: np.ndarray, cam: Camera) -> np.ndarray:
    """Normalised coordinates (..., 2) of pixels xy (..., 2) of camera `cam`'s video undistorted
    with its camera matrix kept: K^-1 xy (NaN stays NaN)."""
    return pixels_to_normalized(torch.as_tensor(xy), torch.as_tensor(cam.K)).numpy()


def undistorted_map(det: Detections, cam: Camera) -> Detections:
    """The detections with camera `cam`'s pixels u (its undistorted video's, the camera matrix
    K kept) mapped into its calibrated image: x = K distort(K^-1 u)."""
    c = det.cameras.index(cam.name)
    xy = det.xy.copy()
    ok = np.isfinite(xy[:, :, c]).all(-1)
    xy[:, :, c][ok] = distort_points(
        torch.as_tensor(xy[:, :, c][ok]),
        torch.as_tensor(cam.K),
        torch.as_tensor(cam.dist),
        fisheye=torch.tensor(cam.fisheye),
    ).numpy()
    return dataclasses.replace(det, xy=xy)


def pair_scores(cameras: Sequence[Camera], read: np.ndarray, alt: dict[int, np.ndarray]) -> dict:
    """{(a, b): {(ma, mb): median px, "n": count, "far": (N, K) mask}} for each camera pair:
    the median symmetric epipolar distance over the part-frames ("far") where either camera's
    readings differ by `MOVE_PX` or more, with camera a read as undistorted if ma (b if mb);
    read: (N, K, C, 2) normalised as the calibration reads them, alt: {c: (N, K, 2)} as
    undistorted (the candidate cameras); pairs with fewer than `MIN_PAIRS` such part-frames are
    left out."""
    C = len(cameras)
    f = [focal_px(c) for c in cameras]
    moved = np.zeros(read.shape[:-1])  # (N, K, C) px
    for c, n in alt.items():
        moved[:, :, c] = np.linalg.norm(n - read[:, :, c], axis=-1) * f[c]
    moved = np.nan_to_num(moved)
    out = {}
    for a, b in itertools.combinations(range(C), 2):
        if a not in alt and b not in alt:
            continue
        both = np.isfinite(read[:, :, a]).all(-1) & np.isfinite(read[:, :, b]).all(-1)
        far = both & (np.maximum(moved[:, :, a], moved[:, :, b]) >= MOVE_PX)
        if far.sum() < MIN_PAIRS:
            continue
        E = essential(cameras[a], cameras[b])
        got: dict = {"n": int(far.sum()), "far": far}
        for ma, mb in itertools.product((False, True), repeat=2):
            if (ma and a not in alt) or (mb and b not in alt):
                continue
            xa = (alt[a] if ma else read[:, :, a])[far]
            xb = (alt[b] if mb else read[:, :, b])[far]
            got[(ma, mb)] = float(np.median(epipolar_px(E, xa, xb, f[a], f[b])))
        out[(a, b)] = got
    return out


def rig_score(scores: dict, chosen: frozenset) -> float:
    """The geometric mean over the scored pairs of their median distance with the cameras
    `chosen` read as undistorted (inf where no pair is scored)."""
    v = [s[(a in chosen, b in chosen)] for (a, b), s in scores.items()]
    return float(np.exp(np.mean(np.log(np.maximum(v, 1e-9))))) if v else float("inf")


def camera_score(scores: dict, c: int, chosen: frozenset) -> float:
    """`rig_score` over camera c's pairs only."""
    return rig_score({k: v for k, v in scores.items() if c in k}, chosen)


def turned_score(cameras: Sequence[Camera], read: np.ndarray, scores: dict, broken: set):
    """(camera, the rig's score, degrees) of the camera whose turn (`adjust.moves.fit_rotation`
    against its unbroken pairs, on all part-frames) brings the scored pairs' margins closest,
    read as the calibration reads them; None where no camera has a pair to fit to."""
    best = None
    f = [focal_px(cam) for cam in cameras]
    for c in range(len(cameras)):
        others = [o for o in range(len(cameras)) if o != c and tuple(sorted((c, o))) not in broken]
        if not others:
            continue
        Q = fit_rotation(read, cameras, c, others, np.arange(len(read)))
        x = read.copy()
        x[:, :, c] = rotate(read[:, :, c], Q)
        v = []
        for (a, b), s in scores.items():
            E = essential(cameras[a], cameras[b])
            m = s["far"] & np.isfinite(x[:, :, a]).all(-1) & np.isfinite(x[:, :, b]).all(-1)
            v.append(float(np.median(epipolar_px(E, x[:, :, a][m], x[:, :, b][m], f[a], f[b]))))
        got = float(np.exp(np.mean(np.log(np.maximum(v, 1e-9))))) if v else float("inf")
        deg = float(np.degrees(np.arccos(np.clip((np.trace(Q) - 1) / 2, -1.0, 1.0))))
        if best is None or got < best[1]:
            best = (c, got, deg)
    return best


def best_set(scores: dict, cand: Sequence[int], limit: float):
    """(the best set of cameras read as undistorted, the closest one whatever the rules), each
    (ratio: the rig's score as read / read so, the set, the rig's score read so) or None: of
    the sets of `cand` where each camera's own pairs come `CAMERA_BETTER` closer (the set's
    others read so either way), no pair `WORSE`, the rig `BETTER` closer and within `limit`
    px, the one with the highest ratio."""
    none = rig_score(scores, frozenset())
    best, closest = None, None
    for k in range(1, len(cand) + 1) if scores else ():
        for chosen in map(frozenset, itertools.combinations(cand, k)):
            got = rig_score(scores, chosen)
            each = [camera_score(scores, c, chosen - {c}) / camera_score(scores, c, chosen)
                    for c in chosen]  # fmt: skip
            worse = [
                s[(a in chosen, b in chosen)] > WORSE * s[(False, False)]
                for (a, b), s in scores.items()
            ]
            trial = (none / max(got, 1e-9), chosen, got)
            if closest is None or trial[0] > closest[0]:
                closest = trial
            if not all(e >= CAMERA_BETTER for e in each) or any(worse) or trial[0] < BETTER:
                continue
            if got <= limit and (best is None or trial[0] > best[0]):
                best = trial
    return best, closest


def check_lens(
    cameras: Sequence[Camera], det: Detections, mode: str = "warn"
) -> tuple[Detections, dict]:
    """Find and undo detections made on undistorted videos (module doc). ``mode`` as the camera
    check's: warn = map them and say so, error = an `InputError` naming the cameras, off =
    nothing. Returns the (mapped) detections and the report {"undistorted": {name:
    {"epipolar_px": [as read, mapped], "part_frames"}}}."""
    report: dict = {"undistorted": {}}
    cand = [c for c, cam in enumerate(cameras) if np.any(cam.dist != 0)]
    if mode == "off" or len(cameras) < 2 or not cand:
        return det, report
    rows = spread_rows(det.num_frames, MAX_ROWS)
    xy = det.xy[rows]
    read = normalised_points(xy, cameras)
    alt = {c: as_undistorted(xy[:, :, c], cameras[c]) for c in cand}
    parts = range(det.num_parts)
    med = epipolar_medians(cameras, read, parts, parts, MIN_MEDIAN_PAIRS)
    broken = {(a, b) for a, b in zip(*np.triu_indices(len(cameras), 1)) if med[a, b] > BROKEN_PX}
    scores = {k: v for k, v in pair_scores(cameras, read, alt).items() if k not in broken}
    none = rig_score(scores, frozenset())
    med = np.array([med[a, b] for a, b in scores])
    level = float(np.exp(np.mean(np.log(np.maximum(med, 1e-9))))) if med.size else 0.0
    best, closest = best_set(scores, sorted(alt), min(PLAUSIBLE_PX, LEVEL * level))
    if best is None:
        if closest is not None:
            log.info(
                "lens check: the detections fit the calibrations as read (read as undistorted "
                "videos at best %.2fx closer to the others' epipolar lines, %s, to %.1f px "
                "where the rig agrees to %.1f px)",
                closest[0],
                sorted(cameras[c].name for c in closest[1]),
                closest[2],
                level,
            )
        return det, report
    ratio, chosen, got = best
    turn = turned_score(cameras, read, scores, broken)
    if turn is not None and turn[1] <= TELL * got:
        log.warning(
            "lens check: cameras %s fit the others' epipolar lines %.1fx closer away from the "
            "image's centre read as on undistorted videos (%.1f -> %.1f px), but camera '%s' "
            "turned by %.2f deg fits them as well (%.1f px): not mapped as undistorted videos "
            "(a camera turned since its calibration? the move check looks for it)",
            sorted(cameras[c].name for c in chosen),
            ratio,
            none,
            got,
            cameras[turn[0]].name,
            turn[2],
            turn[1],
        )
        report["unresolved"] = {
            "cameras": sorted(cameras[c].name for c in chosen),
            "epipolar_px": [round(none, 3), round(got, 3)],
            "turned": {"camera": cameras[turn[0]].name, "degrees": round(turn[2], 3),
                       "epipolar_px": round(turn[1], 3)},
        }  # fmt: skip
        return det, report
    for c in sorted(chosen):
        cam = cameras[c]
        before = camera_score(scores, c, frozenset())
        after = camera_score(scores, c, chosen)
        n = sum(s["n"] for k, s in scores.items() if c in k)
        msg = (
            f"camera '{cam.name}' ({det.files[c]}): its detections fit the calibration as "
            f"pixels of its video undistorted (its camera matrix kept): where the two readings "
            f"differ by {MOVE_PX:.0f} px or more ({n} part-frames) they lie {before:.1f} px "
            f"from the other cameras' epipolar lines as read, {after:.1f} px read so (the rig "
            f"{none:.1f} -> {got:.1f} px); videos undistorted before the pose estimator, or a "
            "calibration whose distortion is much too strong for its lens?"
        )
        if mode == "error":
            raise InputError(
                msg + "; give the calibration of the videos the detections were made on "
                "(distortions 0 and the new camera matrix for undistorted videos), or set "
                "input.camera_check=warn to map them (input.pixel_check=false: no check)"
            )
        log.warning("%s; its detections MAPPED into the calibrated image", msg)
        report["undistorted"][cam.name] = {
            "epipolar_px": [round(before, 3), round(after, 3)],
            "part_frames": n,
        }
    for c in sorted(chosen):
        det = undistorted_map(det, cameras[c])
    return det, report


def apply_lens(det: Detections, cameras: Sequence[Camera], undistorted: dict) -> Detections:
    """The detections with the cameras of a report's ``undistorted`` mapped (a long session's
    chunks, from the sample's check)."""
    for cam in cameras:
        if cam.name in undistorted and cam.name in det.cameras:
            det = undistorted_map(det, cam)
    return det
