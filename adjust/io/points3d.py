"""3D tracks in anipose's ``points3d`` CSV layout.

One row per frame; for each part, in order, the columns ``{part}_x``, ``{part}_y``, ``{part}_z``
(mm), ``{part}_error`` (mean reprojection error over the views used, px), ``{part}_ncams``
(number of views used) and ``{part}_score`` (lowest likelihood among those views); then
anipose's axes columns ``M_00`` .. ``M_22`` and ``center_0`` .. ``center_2`` (the same value in
every row); then ``fnum`` (frame number). Values not estimated are NaN (empty cells, as pandas
and anipose write them); floats are written exactly. These are exactly the columns anipose
writes, so tools that read anipose's files (movement's ``load_poses.from_anipose_file``, which
refuses any other column) read ours with their default arguments.

Our further per-frame columns (e.g. ``pose_rx`` .. ``pose_tz``, ``pose_sigma_r``,
``{part}_sigma``) go to a sidecar beside the file, ``<stem>.extra.csv``
(`deformnet.tables.extra_path`): a first line ``# extra columns of <name> sha256=<hex>`` (the
points3d file's bytes), then ``fnum`` and the columns. `read_points3d` joins them back (a
sidecar written for other bytes or frames is left out with a warning); files of older versions
with those columns in the points3d file itself are read as well.

The axes columns say how the points' frame relates to the calibration's world frame, as anipose's
``triangulation.axes`` writes them: ``X_out = M X_world - center`` (M a (3, 3) rotation, center
(3,) mm in the output frame), so ``X_world = M^T (X_out + center)``. Without an axes alignment
(`adjust.kinematics.align_tracks`) M is the identity and center 0: the points are in the
calibration's world frame.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from adjust.io.errors import InputError
from deformnet.atomic import atomic_path
from deformnet.tables import extra_header, extra_path, read_points3d_table, xyz_parts

log = logging.getLogger(__name__)

FIELDS = ("x", "y", "z", "error", "ncams", "score")
#: anipose's axes columns, in the order anipose writes them: M (row-major), then center
AXES_COLUMNS = tuple(f"M_{i}{j}" for i in range(3) for j in range(3)) + tuple(
    f"center_{i}" for i in range(3)
)
ROWS_PER_BLOCK = 50_000  # write_points3d: rows formatted at a time
MAX_FRAME = int(np.iinfo(np.int64).max)


def write_points3d(
    path: str | os.PathLike,
    parts: Sequence[str],
    points: np.ndarray,
    error: np.ndarray,
    ncams: np.ndarray,
    score: np.ndarray,
    extra: Mapping[str, np.ndarray] | None = None,
    fnum: Sequence[int] | None = None,
    M: np.ndarray | None = None,
    center: np.ndarray | None = None,
) -> Path:
    """Write 3D tracks atomically (and their extra columns' sidecar, see the module doc).

    points: (T, K, 3) mm, NaN where not estimated; error, score: (T, K) float; ncams: (T, K)
    (written as integers when all finite). extra: column name -> (T,) array; a name containing
    ``{part}`` with a (T, K) array gives one column per part (``"{part}_sigma"``); written to
    ``<stem>.extra.csv`` beside `path` (without extra columns a sidecar there is removed: it
    belonged to an earlier file). fnum: (T,) frame numbers (default 0..T-1). M: (3, 3), center:
    (3,) mm: the axes columns (see the module doc; default identity and 0, the calibration's
    world frame). Returns `path`.
    """
    parts = [str(p) for p in parts]
    pts = np.asarray(points, dtype=np.float64)
    T, K = (pts.shape[0], len(parts))
    if pts.shape != (T, K, 3):
        raise ValueError(f"points must be (T, {K}, 3) for {K} parts, got {pts.shape}")
    if len(set(parts)) != K:
        raise ValueError(f"duplicate part names {parts}")
    per_part = {}
    for key, arr in (("error", error), ("ncams", ncams), ("score", score)):
        a = np.asarray(arr)
        if a.shape != (T, K):
            raise ValueError(f"{key} must be (T, K) = {(T, K)}, got {a.shape}")
        per_part[key] = a
    cols: dict[str, np.ndarray] = {}
    nc = per_part["ncams"].astype(np.float64)
    nc_int = bool(np.all(np.isfinite(nc)) and np.all(nc == np.round(nc)))
    for k, p in enumerate(parts):
        for a, axis in enumerate("xyz"):
            cols[f"{p}_{axis}"] = pts[:, k, a]
        cols[f"{p}_error"] = per_part["error"][:, k].astype(np.float64)
        cols[f"{p}_ncams"] = nc[:, k].astype(np.int64) if nc_int else nc[:, k]
        cols[f"{p}_score"] = per_part["score"][:, k].astype(np.float64)
    rot = np.eye(3) if M is None else np.asarray(M, dtype=np.float64)
    ctr = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64)
    if rot.shape != (3, 3) or ctr.shape != (3,):
        raise ValueError(f"M must be (3, 3) and center (3,), got {rot.shape} and {ctr.shape}")
    for n, v in zip(AXES_COLUMNS, np.concatenate([rot.ravel(), ctr])):
        cols[n] = np.full(T, float(v))
    f = np.arange(T) if fnum is None else np.asarray(fnum)
    if f.shape != (T,):
        raise ValueError(f"fnum must have shape ({T},), got {f.shape}")
    cols["fnum"] = f
    more: dict[str, np.ndarray] = {}
    for name, arr in (extra or {}).items():
        a = np.asarray(arr)
        names = {name: a} if "{part}" not in name else None
        if names is None:
            if a.shape != (T, K):
                raise ValueError(f"extra column '{name}' must be (T, K) = {(T, K)}, got {a.shape}")
            names = {name.format(part=p): a[:, k] for k, p in enumerate(parts)}
        for n, v in names.items():
            v = np.asarray(v)
            if v.shape != (T,):
                raise ValueError(f"extra column '{n}' must have shape (T,) = ({T},), got {v.shape}")
            if n in cols or n in more:
                raise ValueError(f"extra column '{n}' clashes with another column")
            more[n] = v
    path = Path(path)
    _write_table(path, cols, T)
    side = extra_path(path)
    if more:
        _write_table(side, {"fnum": f, **more}, T, first_line=extra_header(path))
    else:
        side.unlink(missing_ok=True)
    return path


def _write_table(path: Path, cols: Mapping[str, np.ndarray], T: int, first_line: str = "") -> None:
    """`cols` (name -> (T,)) as a CSV, atomically, after an optional `first_line`; streamed in
    blocks of rows: a long session's table is never built whole in memory."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        fh.write(first_line)
        pd.DataFrame(columns=list(cols)).to_csv(fh, index=False)
        for a in range(0, T, ROWS_PER_BLOCK):
            block = pd.DataFrame({n: v[a : a + ROWS_PER_BLOCK] for n, v in cols.items()})
            block.to_csv(fh, index=False, header=False)


def read_points3d(path: str | os.PathLike) -> dict:
    """Read a points3d CSV (ours or anipose's) and its extra columns' sidecar when there is one.

    Returns a dict: ``parts`` (tuple), ``points`` (T, K, 3), ``error``, ``ncams``, ``score``
    (T, K) float64 (NaN where a column is absent), ``fnum`` (T,) (the detection files' frame
    numbers; strings for labelled images), ``M`` (3, 3) and ``center`` (3,) (anipose's axes
    columns; identity and 0 when the file has none), ``extra`` {column: (T,)} for every other
    column (the file's, then the sidecar's), in file order.
    """
    path = Path(path)
    df = read_points3d_table(path, "points3d file", InputError)
    if len(df) == 0:
        raise InputError(f"{path}: no rows (a header without frames): nothing to read")
    for col in df.columns:
        if col == "fnum":  # a frame number, or a labelled image's name
            continue
        if not pd.api.types.is_numeric_dtype(df[col]):
            num = pd.to_numeric(df[col], errors="coerce")
            bad = num.isna() & df[col].notna()
            r = int(np.flatnonzero(bad.to_numpy())[0])
            raise InputError(
                f"{path}: non-numeric value {df[col].iloc[r]!r} in column '{col}' at row {r}"
            )
    names = list(df.columns)
    colset = set(names)
    parts = xyz_parts(names)
    if not parts:
        raise InputError(f"{path}: no part columns ({{part}}_x, _y, _z)")
    T, K = len(df), len(parts)
    used = set()
    out: dict = {"parts": tuple(parts), "points": np.full((T, K, 3), np.nan)}
    for key in ("error", "ncams", "score"):
        out[key] = np.full((T, K), np.nan)
    for k, p in enumerate(parts):
        for a, axis in enumerate("xyz"):
            out["points"][:, k, a] = df[f"{p}_{axis}"].to_numpy(np.float64)
            used.add(f"{p}_{axis}")
        for key in ("error", "ncams", "score"):
            if f"{p}_{key}" in colset:
                out[key][:, k] = df[f"{p}_{key}"].to_numpy(np.float64)
                used.add(f"{p}_{key}")
    out["fnum"] = _fnum(path, df["fnum"]) if "fnum" in colset else np.arange(T)
    used.add("fnum")
    out["M"], out["center"] = _axes(path, df, colset)
    used.update(AXES_COLUMNS)
    out["extra"] = {c: df[c].to_numpy() for c in names if c not in used}
    return out


_BEYOND = f"is beyond the int64 range (|frame| <= {MAX_FRAME})"
_NOT_A_FRAME = f"is not a frame number (an integer up to {MAX_FRAME})"


def _refuse_fnum(path: Path, values, rows, why: str, show=str) -> None:
    """An InputError at the first of `rows` (if any), naming its fnum value and row."""
    if len(rows):
        r = int(rows[0])
        raise InputError(f"{path}: fnum {show(values[r])} at row {r} {why}")


def _fnum(path: Path, col: pd.Series) -> np.ndarray:
    """The ``fnum`` column: int64 frame numbers, or strings (labelled images' names); an empty
    cell, a fraction or a number beyond int64 is an InputError naming the row."""
    missing = np.flatnonzero(col.isna().to_numpy())
    if missing.size:
        raise InputError(f"{path}: fnum is empty at row {int(missing[0])}")
    if col.dtype.kind == "i":
        return col.to_numpy(np.int64)
    if col.dtype.kind == "u":  # beyond int64, below 2**64
        _refuse_fnum(path, col.iloc, np.flatnonzero(col.to_numpy() > MAX_FRAME), _BEYOND)
        return col.to_numpy(np.int64)
    if col.dtype.kind == "f":
        v = col.to_numpy(np.float64)
        bad = np.flatnonzero(~np.isfinite(v) | (v != np.round(v)) | (np.abs(v) > MAX_FRAME))
        _refuse_fnum(path, col.iloc, bad, _NOT_A_FRAME, repr)
        return v.astype(np.int64)
    values = col.tolist()
    # integers beyond int64 (pandas keeps them as Python ints)
    big = [i for i, v in enumerate(values) if isinstance(v, int) and abs(v) > MAX_FRAME]
    _refuse_fnum(path, values, big, _BEYOND)
    return np.array([str(v) for v in values], dtype=object)


def _axes(path: Path, df: pd.DataFrame, colset: set) -> tuple[np.ndarray, np.ndarray]:
    """(M (3, 3), center (3,)) from anipose's axes columns (identity and 0 when absent); a file
    with only some of them, or with values that differ between rows, is an InputError."""
    have = [c for c in AXES_COLUMNS if c in colset]
    if not have:
        return np.eye(3), np.zeros(3)
    if len(have) != len(AXES_COLUMNS):
        missing = [c for c in AXES_COLUMNS if c not in colset]
        raise InputError(f"{path}: incomplete axes columns: {missing} missing")
    vals = df[list(AXES_COLUMNS)].to_numpy(np.float64)
    if not len(vals):
        return np.eye(3), np.zeros(3)
    if not np.isfinite(vals[0]).all() or np.any(vals != vals[0]):
        raise InputError(
            f"{path}: the axes columns (M_.., center_..) must hold one finite value per column"
        )
    return vals[0, :9].reshape(3, 3).copy(), vals[0, 9:].copy()
