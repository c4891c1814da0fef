"""A calibration plus a folder of per-camera 2D detection files -> one (T, K, C, 2) array.

A camera's file is a DeepLabCut table (``.csv``, ``.h5``; Lightning Pose writes the same CSV
layout), a SLEAP analysis file (``*.analysis.h5``, or any HDF5 file with SLEAP's ``tracks``
and ``node_names``) or a SLEAP ``.slp`` file (`adjust.io.sleap`). Files are matched to cameras
by name: a file belongs to the camera whose name appears in the file name (without suffix, and
without SLEAP's ``.analysis`` / ``.predictions``); when several camera names appear, the longest
wins (``cam10`` over ``cam1``), and two equally long matches are an error. Only ``.csv``,
``.h5``, ``.hdf5`` and ``.slp`` files are considered (hidden files, e.g. half-written
temporaries, are skipped). When one camera
has both a ``.h5`` and a ``.csv`` with the same stem (DeepLabCut writes the CSV as a copy of the
H5), the H5 is used; any other second file for a camera is an error (narrow the choice with
``pattern``, e.g. ``"*_filtered.h5"``).

Part names map to a body model through its aliases (`BodyModel.resolve`); with ``body=None`` the
parts are the files' own names (in the first camera's file order). A likelihood below the
threshold (or a non-finite one) makes the detection missing (NaN).

Validation (each problem names the file, camera, part and frame):

- a likelihood outside [0, 1] (DeepLabCut's are probabilities) is an error;
- a non-finite coordinate, or one absurdly far from the image (more than one image width or
  height outside it; without an image size, beyond 1e6 px), is a missing detection, with one
  warning per camera counting them (one bad cell never spoils the other frames);
- no usable detection at all (e.g. every likelihood below the threshold) is an error; the
  apps refuse a session where fewer than two cameras have one (`check_cameras_usable`);
- a file without a likelihood column (or SLEAP scores), and detections with x and y but an
  empty likelihood cell, are read at likelihood 1, each with a warning naming the file and
  camera; a camera file that loses most (> 50%) of its detections on reading says why (how
  many below the threshold, not finite, far outside the image), and one without any detection
  says so; the log gives the usable detections per camera;
- rows are matched by the files' frame numbers, never by position: when the files' integer
  frame indices differ, the output covers their union (sorted), a camera without a row for a
  frame has no detection there (with a warning); a frame number twice in one file, or labelled
  image names that differ between files, is an error. `Detections.frames` holds the frame
  numbers (the ``fnum`` column of every app's output).
"""

from __future__ import annotations

import fnmatch
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from adjust.camera import Camera
from adjust.io.calibration import load_calibration
from adjust.io.dlc import DLCTable, read_dlc
from adjust.io.errors import InputError, UnknownPartsError
from adjust.io.sleap import is_sleap_file, read_sleap
from deformnet.body import BodyModel

log = logging.getLogger(__name__)

SUFFIXES = (".csv", ".h5", ".hdf5", ".slp")
#: a coordinate beyond this (px) is absurd when the camera's image size is unknown
MAX_ABS_PX = 1e6


def file_stem(f: Path) -> str:
    """The part of a file name matched against camera names (SLEAP's ``.analysis`` and
    ``.predictions`` dropped)."""
    stem = f.stem
    for tail in (".analysis", ".predictions"):
        if stem.lower().endswith(tail):
            return stem[: -len(tail)]
    return stem


def read_table(path: Path, individual: str | None = None) -> DLCTable:
    """One camera's file: a SLEAP analysis HDF5 or .slp file, or a DeepLabCut CSV/H5 table."""
    if is_sleap_file(path):
        return read_sleap(path, individual)
    return read_dlc(path, individual)


@dataclass(frozen=True)
class Detections:
    """2D detections of K parts in C cameras over T frames.

    cameras: C names (calibration order); parts: K names (body model order, or the files' order
    when no body model is given); xy: (T, K, C, 2) float64 px, NaN where missing or below the
    likelihood threshold; likelihood: (T, K, C) float64 as in the files (0 where absent);
    files: the C files read, in camera order; threshold: the likelihood threshold applied.
    """

    cameras: tuple[str, ...]
    parts: tuple[str, ...]
    xy: np.ndarray
    likelihood: np.ndarray
    files: tuple[Path, ...]
    threshold: float = 0.5
    frames: np.ndarray | None = None
    #: what validation set aside: {"absurd_or_nonfinite": {camera: count}, ...}
    notes: dict = field(default_factory=dict, compare=False)

    @property
    def num_frames(self) -> int:
        return int(self.xy.shape[0])

    @property
    def num_parts(self) -> int:
        return int(self.xy.shape[1])

    @property
    def num_cameras(self) -> int:
        return int(self.xy.shape[2])

    @property
    def observed(self) -> np.ndarray:
        """(T, K, C) bool: a usable detection (finite xy at or above the threshold)."""
        return np.isfinite(self.xy).all(-1)

    def weight(self) -> np.ndarray:
        """(T, K, C) float64 weights: the likelihood where observed, 0 where missing."""
        return np.where(self.observed, self.likelihood, 0.0)

    def usable_per_camera(self) -> dict[str, int]:
        """{camera: number of usable detections} (finite x, y at or above the threshold)."""
        counts = self.observed.sum(axis=(0, 1))
        return {c: int(n) for c, n in zip(self.cameras, counts)}


#: fewer cameras than this with a usable detection cannot triangulate anything
MIN_CAMERAS = 2


def check_cameras_usable(det: Detections, where: str, min_cameras: int = MIN_CAMERAS) -> None:
    """An InputError when fewer than `min_cameras` cameras have any usable detection: nothing
    can be triangulated and a track would rest on one view (depth unobserved) while looking
    precise. The message names every camera with its count of usable detections (and its
    file); `where` names the session (e.g. the detections folder). Call it after cameras are
    excluded (`adjust.camera_check`)."""
    counts = det.usable_per_camera()
    have = [c for c, n in counts.items() if n > 0]
    if len(have) >= min_cameras:
        return
    listed = ", ".join(
        f"'{c}' {n}" + (f" ({Path(f).name})" if f else "")
        for (c, n), f in zip(counts.items(), list(det.files) + [None] * len(counts))
    )
    raise InputError(
        f"{where}: only {len(have)} of {len(counts)} cameras have a usable detection (usable "
        f"detections per camera: {listed}); at least {min_cameras} cameras must see the animal "
        f"(check the files, input.likelihood_threshold={det.threshold:g} and "
        "input.exclude_cameras)"
    )


def match_files(
    folder: str | os.PathLike, camera_names: Sequence[str], pattern: str | None = None
) -> dict[str, Path]:
    """Map each camera name to its DeepLabCut file in `folder` (see the module doc)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"detections folder not found: {folder}")
    names = [str(n) for n in camera_names]
    files = sorted(
        f
        for f in folder.iterdir()
        if f.is_file()
        and not f.name.startswith(".")
        and f.suffix.lower() in SUFFIXES
        and (pattern is None or fnmatch.fnmatch(f.name, pattern))
    )
    what = f"detection files ({', '.join(SUFFIXES)}"
    what += f", matching '{pattern}')" if pattern else ")"
    if not files:
        raise InputError(f"{folder}: no {what} found")
    by_camera: dict[str, list[Path]] = {n: [] for n in names}
    orphans = []
    for f in files:
        hits = [n for n in names if n and n in file_stem(f)]
        if not hits:
            orphans.append(f.name)
            continue
        longest = max(len(n) for n in hits)
        best = [n for n in hits if len(n) == longest]
        if len(best) > 1:
            raise InputError(
                f"{folder / f.name}: file name matches several cameras equally well {best}; "
                "rename the file so one camera name appears in it"
            )
        by_camera[best[0]].append(f)
    if orphans:
        raise InputError(
            f"{folder}: files without a camera: {orphans} (camera names: {names}); every file "
            "name must contain one camera's name (remove other files or set a pattern"
            + (
                ", e.g. input.pattern='*.analysis.h5')"
                if any(f.name.lower().endswith(".analysis.h5") for f in files)
                else ")"
            )
        )
    missing = [n for n, fs in by_camera.items() if not fs]
    if missing:
        raise InputError(
            f"{folder}: cameras without a file: {missing}; files found: {[f.name for f in files]} "
            "(a camera's file must contain its name)"
        )
    chosen: dict[str, Path] = {}
    for n, fs in by_camera.items():
        if len(fs) == 2 and len({f.stem for f in fs}) == 1:
            h5 = [f for f in fs if f.suffix.lower() != ".csv"]
            if len(h5) == 1:
                log.info("camera '%s': both %s and .csv; using the H5", n, h5[0].name)
                fs = h5
        if len(fs) > 1:
            raise InputError(
                f"{folder}: camera '{n}' matches several files {[f.name for f in fs]}; keep one "
                "or set a pattern (input.pattern='*_filtered.h5')"
            )
        chosen[n] = fs[0]
    return chosen


def _map_parts(
    table: DLCTable,
    camera: str,
    parts: tuple[str, ...] | None,
    body: BodyModel | None,
    ignore_unknown_parts: bool,
    allow_missing_parts: bool,
) -> tuple[tuple[str, ...], list[int | None]]:
    """Target part order and, for each target part, the file's column (None if absent)."""
    where = f"{table.path} (camera '{camera}')"
    if body is not None:
        try:
            resolved, unknown = body.match(table.parts)
        except ValueError as exc:  # two of the file's parts name one part of the model
            raise InputError(f"{where}: {exc}") from None
        if unknown:
            msg = (
                f"{where}: unknown parts {unknown} for body model '{body.name}' (parts: "
                f"{list(body.parts)}; aliases: {sorted(body.aliases)})"
            )
            if not ignore_unknown_parts:
                raise UnknownPartsError(
                    msg + "; add aliases, or use the files' own parts (body=auto)", unknown
                )
            log.warning("%s; ignored", msg)
        target_parts = body.parts
    else:
        resolved = {name: k for k, name in enumerate(table.parts)}
        target_parts = parts if parts is not None else table.parts
        unknown = [p for p in table.parts if p not in target_parts]
        if unknown:
            msg = (
                f"{where}: parts {unknown} are not in the other cameras' files {list(target_parts)}"
            )
            if not ignore_unknown_parts:
                raise InputError(msg)
            log.warning("%s; ignored", msg)
    missing = [p for p in target_parts if p not in resolved]
    if missing:
        msg = f"{where}: missing parts {missing} (the file has {list(table.parts)})"
        if body is not None:
            msg += f"; body model '{body.name}' needs {list(body.parts)}"
        if not allow_missing_parts:
            raise InputError(msg)
        log.warning("%s; they count as never detected", msg)
    return tuple(target_parts), [resolved.get(p) for p in target_parts]


def load_detections(
    folder: str | os.PathLike,
    cameras: Sequence[Camera],
    body: BodyModel | None,
    likelihood_threshold: float = 0.5,
    individual: str | None = None,
    *,
    pattern: str | None = None,
    ignore_unknown_parts: bool = False,
    allow_missing_parts: bool = False,
    tables: Sequence[DLCTable] | None = None,
) -> Detections:
    """Read one DeepLabCut file per camera from `folder` into `Detections`.

    body: map file parts to this model's parts (through its aliases), in model order; None: use
    the files' own part names. individual: for multi-animal files. pattern: a glob the file names
    must match. ignore_unknown_parts: drop file parts the model does not know (default: error).
    allow_missing_parts: model parts absent from a file count as never detected (default: error).
    tables: the cameras' tables (in camera order) already read from their files, e.g. a long
    session's frame range (`adjust.chunks`), instead of reading the files.
    """
    if not cameras:
        raise ValueError("no cameras given")
    try:
        thr = float(likelihood_threshold)
    except (TypeError, ValueError):
        thr = float("nan")
    if not (0.0 <= thr <= 1.0):
        raise InputError(
            f"input.likelihood_threshold must be a number from 0 to 1, got {likelihood_threshold!r}"
        )
    names = [c.name for c in cameras]
    paths = match_files(folder, names, pattern)
    if tables is None:
        tables = [read_table(paths[n], individual) for n in names]
    frames, rows = _align_frames(Path(folder), tables)
    T = len(frames)
    if T == 0:
        raise InputError(f"{Path(folder)}: the files have no frames (header rows only)")
    parts: tuple[str, ...] | None = None
    columns = []
    for name, t in zip(names, tables):
        parts, cols = _map_parts(t, name, parts, body, ignore_unknown_parts, allow_missing_parts)
        columns.append(cols)
    assert parts is not None
    K, C = len(parts), len(cameras)
    xy = np.full((T, K, C, 2), np.nan)
    lik = np.zeros((T, K, C))
    for c, (t, cols, r) in enumerate(zip(tables, columns, rows)):
        _check_likelihoods(t, names[c])
        for k, j in enumerate(cols):
            if j is None:
                continue
            xy[r, k, c] = t.xy[:, j]
            lik[r, k, c] = t.likelihood[:, j]
    files = [paths[n] for n in names]
    unusable = np.zeros((T, K, C), dtype=bool)
    for c, (t, cols, r) in enumerate(zip(tables, columns, rows)):
        _state_likelihoods(t, names[c], [t.parts[j] for j in cols if j is not None])
        if t.unusable is not None:
            for k, j in enumerate(cols):
                if j is not None:
                    unusable[r, k, c] = t.unusable[:, j]
    no_lik = np.isnan(lik) & np.isfinite(xy).all(-1)  # empty likelihood cells, x and y given
    for c in np.flatnonzero(no_lik.any(axis=(0, 1))):
        t_, k_ = np.argwhere(no_lik[:, :, c])[0]
        log.warning(
            "camera '%s' (%s): %d detections have x and y but an empty likelihood cell (first: "
            "part '%s' at frame %s); read as likelihood 1, as a hand-placed label (empty their "
            "x and y if they are not detections)",
            names[c],
            files[c],
            int(no_lik[:, :, c].sum()),
            parts[k_],
            frames[t_],
        )
    lik[no_lik] = 1.0
    lik = np.where(np.isfinite(lik), lik, 0.0)
    given = np.isfinite(xy).all(-1) | unusable  # x and y given in the file
    absurd = _drop_absurd(xy, lik, cameras, files, parts, frames)
    below = np.isfinite(xy).all(-1) & (lik < thr)
    xy[(lik < thr) | ~np.isfinite(xy).all(-1)] = np.nan
    notes = {"absurd_or_nonfinite": absurd} if any(absurd.values()) else {}
    det = Detections(tuple(names), tuple(parts), xy, lik, tuple(files), thr, frames, notes)
    obs = det.observed
    _state_losses(det, given, below, unusable, absurd)
    if not obs.any():
        present = lik[np.isfinite(lik) & (lik > 0)]
        raise InputError(
            f"{Path(folder)}: no usable detection in any file: every likelihood is below "
            f"input.likelihood_threshold={thr:g}"
            + (f" (the highest is {present.max():.3g})" if present.size else " (all are 0)")
        )
    _check_in_image(det, cameras)
    log.info(
        "read %d frames x %d parts x %d cameras from %s; %.1f%% of detections at likelihood >= %g; "
        "usable detections per camera: %s",
        T,
        K,
        C,
        folder,
        100.0 * obs.mean() if obs.size else 0.0,
        thr,
        ", ".join(f"{c} {n}" for c, n in det.usable_per_camera().items()),
    )
    return det


def _state_likelihoods(t: DLCTable, camera: str, used: Sequence[str]) -> None:
    """A warning for a file without likelihoods of the parts used (the file's names): their
    detections are taken at likelihood 1."""
    missing = [p for p in t.no_likelihood if p in set(used)]
    if not missing:
        return
    what = "no likelihood column" if t.scorer != "SLEAP" else "no point_scores"
    log.warning(
        "camera '%s' (%s): %s for %s; every detection with x and y is taken at likelihood 1 "
        "(input.likelihood_threshold cannot drop any of them)",
        camera,
        t.path,
        what,
        "any part" if len(missing) == len(used) else f"parts {missing}",
    )


#: a camera file that loses more than this share of its detections on reading says why
LOSS_WARNING = 0.5


def _state_losses(
    det: Detections,
    given: np.ndarray,
    below: np.ndarray,
    unusable: np.ndarray,
    absurd: dict[str, int],
) -> None:
    """One warning per camera whose file loses most (> `LOSS_WARNING`) of its detections (x and
    y given) on reading, with the reasons counted; one for a camera left without any."""
    obs = det.observed
    for c, cam in enumerate(det.cameras):
        n_given = int(given[:, :, c].sum())
        n_used = int(obs[:, :, c].sum())
        lost = n_given - n_used
        if n_given == 0:
            log.warning(
                "camera '%s' (%s): no detection at all (every x and y cell is empty); it adds "
                "nothing to the tracks",
                cam,
                det.files[c],
            )
            continue
        if lost <= LOSS_WARNING * n_given:
            continue
        reasons = {
            f"below input.likelihood_threshold={det.threshold:g}": int(below[:, :, c].sum()),
            "not finite numbers (inf, or x without y)": int(unusable[:, :, c].sum()),
            "far outside the image": int(absurd.get(cam, 0)),
        }
        log.warning(
            "camera '%s' (%s): %d of its %d detections (%.0f%%) are not used: %s",
            cam,
            det.files[c],
            lost,
            n_given,
            100.0 * lost / n_given,
            ", ".join(f"{n} {why}" for why, n in reasons.items() if n) or "unknown reason",
        )


def _align_frames(folder: Path, tables: Sequence[DLCTable]) -> tuple[np.ndarray, list]:
    """The output's frame numbers and, per table, the output row of each of its rows.

    Integer frame indices: their sorted union (rows matched by number). Labelled-image names:
    the same set in every file (rows matched by name, in the first file's order), else an error.
    """
    frames = [
        t.frames if t.frames is not None else np.arange(t.num_frames, dtype=np.int64)
        for t in tables
    ]
    for t, f in zip(tables, frames):
        if len(f) != t.num_frames:
            raise InputError(f"{t.path}: {len(f)} frame labels for {t.num_frames} rows")
        uniq, counts = np.unique(f.astype(str) if f.dtype == object else f, return_counts=True)
        if (counts > 1).any():
            raise InputError(
                f"{t.path}: frame {uniq[counts > 1][0]} appears {counts[counts > 1][0]} times "
                "(each frame number must appear once)"
            )
    if all(f.dtype.kind in "iu" for f in frames):
        union = np.unique(np.concatenate(frames)).astype(np.int64)
        rows = [np.searchsorted(union, f) for f in frames]
        same = all(np.array_equal(frames[0], f) for f in frames[1:])
        if not same:
            lack = {t.path.name: int(len(union) - len(f)) for t, f in zip(tables, frames)}
            log.warning(
                "%s: the files' frame numbers differ; rows are matched by frame number over "
                "the %d frames %d..%d (frames a file lacks have no detection in that camera: %s)",
                folder,
                len(union),
                int(union[0]) if len(union) else 0,
                int(union[-1]) if len(union) else 0,
                ", ".join(f"{k}: {v}" for k, v in lack.items()),
            )
        elif len(union) and not np.array_equal(union, frames[0]):
            log.warning("%s: rows are not in frame order; sorted by frame number", folder)
        return union, rows
    labels = [f.astype(str) for f in frames]
    first = labels[0]
    index = {v: i for i, v in enumerate(first)}
    rows = []
    for t, f in zip(tables, labels):
        if len(f) != len(first) or set(f) != set(first):
            only = sorted(set(f) ^ set(first))[:3]
            raise InputError(
                f"{t.path} and {tables[0].path} label different frames (e.g. {only}); rows "
                "cannot be matched"
            )
        rows.append(np.array([index[v] for v in f], dtype=np.int64))
    return np.array(first, dtype=object), rows


def _check_likelihoods(t: DLCTable, camera: str) -> None:
    """A likelihood outside [0, 1] where x and y are given is an error naming part and frame."""
    lik = t.likelihood
    present = np.isfinite(t.xy).all(-1) & np.isfinite(lik)
    bad = present & ((lik < 0.0) | (lik > 1.0))
    if bad.any():
        r, k = np.argwhere(bad)[0]
        frame = t.frames[r] if t.frames is not None else r
        raise InputError(
            f"{t.path} (camera '{camera}'): likelihood {float(lik[r, k])} of part "
            f"'{t.parts[k]}' at frame {frame} is outside [0, 1]"
            + (f"; {int(bad.sum()) - 1} more outside [0, 1]" if bad.sum() > 1 else "")
            + " (likelihoods are probabilities; fix or rescale the file)"
        )


def _drop_absurd(
    xy: np.ndarray,
    lik: np.ndarray,
    cameras: Sequence[Camera],
    files: Sequence[Path],
    parts: Sequence[str],
    frames: np.ndarray,
) -> dict[str, int]:
    """Set detections (T, K, C, 2) that are non-finite or absurdly far outside the image to
    missing (in place, likelihood 0); one warning per camera. Returns {camera: count}."""
    counts = {}
    for c, cam in enumerate(cameras):
        v = xy[:, :, c]
        given = lik[:, :, c] > 0
        partial = np.isfinite(v).any(-1) & ~np.isfinite(v).all(-1)
        w, h = cam.size
        with np.errstate(invalid="ignore"):
            if w > 0 and h > 0:
                far = (
                    (v[..., 0] < -w) | (v[..., 0] > 2 * w) | (v[..., 1] < -h) | (v[..., 1] > 2 * h)
                )
            else:
                far = (np.abs(v) > MAX_ABS_PX).any(-1)
        bad = given & (far | partial | np.isinf(v).any(-1))
        counts[cam.name] = int(bad.sum())
        if bad.any():
            t, k = np.argwhere(bad)[0]
            log.warning(
                "camera '%s' (%s): %d detections are non-finite or far outside the %dx%d image "
                "(first: part '%s' at frame %s, %s); treated as missing",
                cam.name,
                files[c],
                int(bad.sum()),
                w,
                h,
                parts[k],
                frames[t],
                v[t, k].tolist(),
            )
            v[bad] = np.nan
            lik[:, :, c][bad] = 0.0
    return counts


def _check_in_image(det: Detections, cameras: Sequence[Camera]) -> None:
    """Warn when many detections lie outside a camera's image (a sign of mismatched files)."""
    for c, cam in enumerate(cameras):
        w, h = cam.size
        if w <= 0 or h <= 0:
            continue
        uv = det.xy[:, :, c][det.observed[:, :, c]]
        if uv.size == 0:
            continue
        out = (uv[:, 0] < -0.5) | (uv[:, 0] > w - 0.5) | (uv[:, 1] < -0.5) | (uv[:, 1] > h - 0.5)
        if out.mean() > 0.01:
            log.warning(
                "camera '%s' (%s): %.1f%% of detections lie outside its %dx%d image; is the file "
                "matched to the right camera?",
                cam.name,
                det.files[c],
                100.0 * out.mean(),
                w,
                h,
            )


def load_scene(
    calibration_path: str | os.PathLike,
    detections_dir: str | os.PathLike,
    body: BodyModel | None,
    likelihood_threshold: float = 0.5,
    individual: str | None = None,
    **kwargs,
) -> tuple[list[Camera], Detections]:
    """`load_calibration` then `load_detections` (keyword options as there)."""
    cameras = load_calibration(calibration_path)
    det = load_detections(detections_dir, cameras, body, likelihood_threshold, individual, **kwargs)
    return cameras, det
