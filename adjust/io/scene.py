"""A calibration plus a folder of per-camera DeepLabCut files -> one (T, K, C, 2) detection array.

Files are matched to cameras by name: a file belongs to the camera whose name appears in the
file name (without suffix); when several camera names appear, the longest wins (``cam10`` over
``cam1``), and two equally long matches are an error. Only ``.csv``, ``.h5`` and ``.hdf5``
files are considered (hidden files, e.g. half-written temporaries, are skipped). When one camera
has both a ``.h5`` and a ``.csv`` with the same stem (DeepLabCut writes the CSV as a copy of the
H5), the H5 is used; any other second file for a camera is an error (narrow the choice with
``pattern``, e.g. ``"*_filtered.h5"``).

Part names map to a body model through its aliases (`BodyModel.resolve`); with ``body=None`` the
parts are the files' own names (in the first camera's file order). A likelihood below the
threshold (or a non-finite one) makes the detection missing (NaN).
"""

from __future__ import annotations

import fnmatch
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from adjust.camera import Camera
from adjust.io.calibration import load_calibration
from adjust.io.dlc import DLCTable, read_dlc
from adjust.io.errors import InputError
from deformnet.body import BodyModel

log = logging.getLogger(__name__)

SUFFIXES = (".csv", ".h5", ".hdf5")


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
    what = f"DeepLabCut files ({', '.join(SUFFIXES)}"
    what += f", matching '{pattern}')" if pattern else ")"
    if not files:
        raise InputError(f"{folder}: no {what} found")
    by_camera: dict[str, list[Path]] = {n: [] for n in names}
    orphans = []
    for f in files:
        hits = [n for n in names if n and n in f.stem]
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
            "name must contain one camera's name (remove other files or set a pattern)"
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
        resolved: dict[str, int] = {}
        unknown = []
        for k, name in enumerate(table.parts):
            target = body.resolve(name)
            if target is None:
                unknown.append(name)
                continue
            if target in resolved:
                raise InputError(
                    f"{where}: parts '{table.parts[resolved[target]]}' and '{name}' both map to "
                    f"body part '{target}' of model '{body.name}'"
                )
            resolved[target] = k
        if unknown:
            msg = (
                f"{where}: unknown parts {unknown} for body model '{body.name}' (parts: "
                f"{list(body.parts)}; aliases: {sorted(body.aliases)})"
            )
            if not ignore_unknown_parts:
                raise InputError(msg + "; add aliases or use the files' own parts")
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
) -> Detections:
    """Read one DeepLabCut file per camera from `folder` into `Detections`.

    body: map file parts to this model's parts (through its aliases), in model order; None: use
    the files' own part names. individual: for multi-animal files. pattern: a glob the file names
    must match. ignore_unknown_parts: drop file parts the model does not know (default: error).
    allow_missing_parts: model parts absent from a file count as never detected (default: error).
    """
    if not cameras:
        raise ValueError("no cameras given")
    thr = float(likelihood_threshold)
    if not np.isfinite(thr):
        raise ValueError(f"likelihood_threshold must be finite, got {likelihood_threshold!r}")
    names = [c.name for c in cameras]
    paths = match_files(folder, names, pattern)
    tables = [read_dlc(paths[n], individual) for n in names]
    counts = {t.path.name: t.num_frames for t in tables}
    if len(set(counts.values())) > 1:
        raise InputError(
            f"{Path(folder)}: files have different frame counts: "
            + ", ".join(f"{f}: {n}" for f, n in counts.items())
        )
    T = tables[0].num_frames
    if T == 0:
        raise InputError(f"{Path(folder)}: the files have no frames (header rows only)")
    frames = tables[0].frames
    for t in tables[1:]:
        if (
            frames is not None
            and t.frames is not None
            and frames.dtype == t.frames.dtype
            and not np.array_equal(frames, t.frames)
        ):
            log.warning(
                "%s and %s have the same frame count but different frame indices; rows are "
                "matched by position",
                tables[0].path,
                t.path,
            )
    parts: tuple[str, ...] | None = None
    columns = []
    for name, t in zip(names, tables):
        parts, cols = _map_parts(t, name, parts, body, ignore_unknown_parts, allow_missing_parts)
        columns.append(cols)
    assert parts is not None
    K, C = len(parts), len(cameras)
    xy = np.full((T, K, C, 2), np.nan)
    lik = np.zeros((T, K, C))
    for c, (t, cols) in enumerate(zip(tables, columns)):
        for k, j in enumerate(cols):
            if j is None:
                continue
            xy[:, k, c] = t.xy[:, j]
            lik[:, k, c] = t.likelihood[:, j]
    lik = np.where(np.isfinite(lik), lik, 0.0)
    xy[(lik < thr) | ~np.isfinite(xy).all(-1)] = np.nan
    det = Detections(
        tuple(names), tuple(parts), xy, lik, tuple(paths[n] for n in names), thr, frames
    )
    _check_in_image(det, cameras)
    obs = det.observed
    log.info(
        "read %d frames x %d parts x %d cameras from %s; %.1f%% of detections at likelihood >= %g",
        T,
        K,
        C,
        folder,
        100.0 * obs.mean() if obs.size else 0.0,
        thr,
    )
    return det


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
