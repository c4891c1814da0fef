"""DeepLabCut 2D tables (CSV and H5), independent of any body model.

DeepLabCut writes one table per video: columns a MultiIndex with levels ``scorer``,
``bodyparts``, ``coords`` (``x``, ``y``, ``likelihood``) -- multi-animal projects add an
``individuals`` level after ``scorer`` -- and rows indexed by frame number. The CSV has one
header row per level (its first cell the level's name) and the frame index as first column; the
H5 holds the same DataFrame under the key ``df_with_missing``. Missing values are empty CSV cells
(NaN).

`read_dlc` returns a `DLCTable` with the file's own part names (in file order); tables without a
``likelihood`` coordinate (e.g. hand labels) get likelihood 1 where x and y are present
(`adjust.io.scene` says so in a warning naming the file and camera).
"""

from __future__ import annotations

import csv
import itertools
import logging
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from adjust.io.errors import InputError
from deformnet.atomic import atomic_path
from deformnet.paths import regular_file

log = logging.getLogger(__name__)

H5_KEY = "df_with_missing"
_LEVELS = ("scorer", "individuals", "bodyparts", "coords")
_COORDS = ("x", "y", "likelihood")
_NAN_WORDS = frozenset({"", "nan", "NaN", "NAN", "NA", "N/A", "null", "None", "-nan"})


@dataclass(frozen=True)
class DLCTable:
    """One camera's DeepLabCut detections.

    parts: K part names in file order; xy: (T, K, 2) float64 px, NaN where absent; likelihood:
    (T, K) float64 as in the file (NaN where the cell is empty); scorer: the network's name;
    frames: (T,) the file's row index (ints for video output, strings for labelled images);
    individual: the chosen individual of a multi-animal file (None for single-animal files);
    no_likelihood: the parts without a likelihood column (given likelihood 1 where x and y are);
    unusable: (T, K) bool, x or y given but not a finite number (inf, or only one of the two),
    read as absent (NaN) in ``xy``; None: none.
    """

    parts: tuple[str, ...]
    xy: np.ndarray
    likelihood: np.ndarray
    scorer: str = ""
    frames: np.ndarray | None = None
    individual: str | None = None
    path: Path | None = None
    no_likelihood: tuple[str, ...] = ()
    unusable: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return int(self.xy.shape[0])


# --- reading ------------------------------------------------------------------------------


def read_dlc(path: str | os.PathLike, individual: str | None = None) -> DLCTable:
    """Read a DeepLabCut CSV (``.csv``) or H5 (``.h5``/``.hdf5``) table.

    individual: which individual of a multi-animal file to take; required when the file has more
    than one (the error lists them), ignored (with a warning) for single-animal files.
    """
    path = regular_file(path, "DeepLabCut file", InputError)
    suffix = path.suffix.lower()
    if suffix == ".csv":
        columns, values, frames = _read_csv(path)
    elif suffix in (".h5", ".hdf5"):
        columns, values, frames = _read_h5(path)
    else:
        raise InputError(f"{path}: unknown DeepLabCut file type '{path.suffix}' (use .csv or .h5)")
    return _assemble(path, columns, values, frames, individual)


def _read_csv(path: Path) -> tuple[list[tuple], np.ndarray, np.ndarray]:
    (block,) = _csv_blocks(path, None)
    return block


def iter_dlc(
    path: str | os.PathLike, individual: str | None = None, block_rows: int = 50_000
) -> Iterator[DLCTable]:
    """`read_dlc` in consecutive blocks of at most `block_rows` rows (a CSV is parsed as it is
    read: a long session's file is never held whole; an H5 file comes as one block). The
    blocks' tables concatenated are `read_dlc`'s table; errors name the file's line as there."""
    path = regular_file(path, "DeepLabCut file", InputError)
    if path.suffix.lower() != ".csv":
        yield read_dlc(path, individual)
        return
    for columns, values, frames in _csv_blocks(path, block_rows):
        yield _assemble(path, columns, values, frames, individual)


def _csv_lines(fh, path: Path) -> Iterator[list[str]]:
    """The CSV's rows; a read error is an InputError naming the file."""
    reader = csv.reader(fh)
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except (OSError, UnicodeDecodeError, csv.Error) as exc:
            raise InputError(f"{path}: cannot read CSV: {exc}") from None
        yield row


def _csv_blocks(
    path: Path, block_rows: int | None
) -> Iterator[tuple[list[tuple], np.ndarray, np.ndarray]]:
    """(columns, values, frames) of the CSV's data rows in blocks of at most `block_rows` rows
    (None: one block), read as the file is parsed; a file without data rows gives one empty
    block."""
    try:
        fh = open(path, newline="", encoding="utf-8-sig")
    except OSError as exc:
        raise InputError(f"{path}: cannot read CSV: {exc}") from None
    with fh:
        lines = _csv_lines(fh, path)
        # header rows: first cells scorer, [individuals], bodyparts, coords
        levels: dict[str, list[str]] = {}
        n_header = 0
        first_line: list[str] | None = None
        first_body: list[str] | None = None
        for row in lines:
            if first_line is None:
                first_line = row
            first = row[0].strip() if row else ""
            if first not in _LEVELS:
                first_body = row
                break
            if first in levels:
                raise InputError(
                    f"{path}: header row '{first}' appears twice (line {n_header + 1})"
                )
            levels[first] = row
            n_header += 1
        names = tuple(levels)
        if names not in (("scorer", "bodyparts", "coords"), _LEVELS):
            raise InputError(
                f"{path}: not a DeepLabCut table: expected header rows starting with 'scorer', "
                f"['individuals',] 'bodyparts', 'coords' in the first column, found {list(names)} "
                f"(first line: "
                f"{','.join(first_line[:4]) if first_line is not None else '<empty file>'}...)"
            )
        width = len(levels["scorer"])
        for name, row in levels.items():
            if len(row) != width:
                raise InputError(
                    f"{path}: header row '{name}' has {len(row)} cells, the 'scorer' row {width}"
                )
        # index columns: the first, plus leading columns with empty header cells (labelled data)
        n_index = 1
        while n_index < width and all(levels[n][n_index].strip() == "" for n in names):
            n_index += 1
        if n_index >= width:
            raise InputError(f"{path}: no data columns after the index column(s)")
        columns = [
            tuple(
                (levels[n][j].strip() if n in levels else None)
                for n in ("scorer", "individuals", "bodyparts", "coords")
            )
            for j in range(n_index, width)
        ]
        body = lines if first_body is None else itertools.chain([first_body], lines)
        # pandas writes a row with the index name (and empty cells) when the index is named
        if (
            first_body is not None
            and all(c.strip() == "" for c in first_body[n_index:])
            and not _is_number(first_body[0])
        ):
            next(body)
            n_header += 1
        line0 = n_header + 1  # 1-based line number of the first data row
        kept: list[tuple[int, list[str]]] = []
        given = 0
        for i, row in enumerate(body):
            if not row or all(c.strip() == "" for c in row):
                continue  # blank line
            if len(row) != width:
                raise InputError(
                    f"{path}: line {line0 + i} has {len(row)} cells, the header {width} "
                    "(truncated or malformed row)"
                )
            kept.append((line0 + i, row))
            if block_rows is not None and len(kept) >= block_rows:
                yield columns, *_csv_values(path, columns, kept, n_index)
                given += 1
                kept = []
        if kept or not given:
            yield columns, *_csv_values(path, columns, kept, n_index)


def _csv_values(
    path: Path, columns: list[tuple], kept: list[tuple[int, list[str]]], n_index: int
) -> tuple[np.ndarray, np.ndarray]:
    """The (line, row) pairs' values (rows, columns) float64 (NaN: an empty cell) and frames."""
    if not kept:
        return np.zeros((0, len(columns))), np.zeros(0, dtype=np.int64)
    cells = np.array([r[n_index:] for _, r in kept], dtype=object)
    index = [r[0] if n_index == 1 else "/".join(r[:n_index]) for _, r in kept]
    flat = pd.Series(cells.reshape(-1), dtype=object)
    values = pd.to_numeric(flat, errors="coerce").to_numpy(np.float64).reshape(cells.shape)
    bad = np.isnan(values)
    if bad.any():  # NaN from an empty/'nan' cell is missing data; from anything else an error
        blank = pd.Series(cells[bad], dtype=object).str.strip().isin(_NAN_WORDS).to_numpy()
        bad[bad] = ~blank
    if bad.any():
        r, c = np.argwhere(bad)[0]
        line, _ = kept[r]
        raise InputError(
            f"{path}: non-numeric value {cells[r, c]!r} at line {line} (frame {index[r]}), "
            f"column {n_index + c + 1} ({_column_name(columns[c])})"
            + (f"; {int(bad.sum()) - 1} more non-numeric cells" if bad.sum() > 1 else "")
        )
    return values, _frames(index, path)


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


#: frame numbers must fit numpy's int64 (the ``fnum`` column of every output)
MAX_FRAME = np.iinfo(np.int64).max


def _frames(index: Sequence, path: Path | None = None) -> np.ndarray:
    """The row labels as int64 frame numbers, or as strings (labelled images' names); a frame
    number beyond int64 is an InputError naming it."""
    try:
        as_int = [int(str(v).strip()) for v in index]
    except ValueError:
        return np.array([str(v) for v in index], dtype=object)
    big = [v for v in as_int if abs(v) > MAX_FRAME]
    if big:
        raise InputError(
            f"{path}: frame number {big[0]} is beyond the int64 range (|frame| <= {MAX_FRAME})"
            + (f"; {len(big) - 1} more" if len(big) > 1 else "")
        )
    return np.array(as_int, dtype=np.int64)


def _column_name(col: tuple) -> str:
    _, ind, part, coord = col
    return "/".join(x for x in (ind, part, coord) if x is not None)


def _read_h5(path: Path) -> tuple[list[tuple], np.ndarray, np.ndarray]:
    try:
        with pd.HDFStore(path, mode="r") as store:
            keys = [k.lstrip("/") for k in store.keys()]
            if H5_KEY in keys:
                key = H5_KEY
            elif len(keys) == 1:
                key = keys[0]
            else:
                raise InputError(
                    f"{path}: no '{H5_KEY}' table (DeepLabCut's key); the file holds "
                    f"{keys or 'none'}"
                )
            df = store.get(key)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - PyTables/HDF5 raise many types
        raise InputError(f"{path}: cannot read HDF5 table: {type(exc).__name__}: {exc}") from None
    if not isinstance(df, pd.DataFrame):
        raise InputError(f"{path}: key '{key}' holds a {type(df).__name__}, not a DataFrame")
    cols = df.columns
    level_names = [str(n) if n is not None else None for n in getattr(cols, "names", [None])]
    if cols.nlevels == 3:
        order = ("scorer", "bodyparts", "coords")
    elif cols.nlevels == 4:
        order = _LEVELS
    else:
        raise InputError(
            f"{path}: not a DeepLabCut table: columns have {cols.nlevels} levels {level_names}, "
            "expected scorer/[individuals/]bodyparts/coords"
        )
    if all(n is not None for n in level_names) and tuple(level_names) != order:
        raise InputError(
            f"{path}: column levels are {level_names}, expected {list(order)} (DeepLabCut layout)"
        )
    columns = []
    for col in cols:
        d = dict(zip(order, (str(c) for c in col)))
        columns.append((d["scorer"], d.get("individuals"), d["bodyparts"], d["coords"]))
    values = np.empty(df.shape, dtype=np.float64)
    for j in range(df.shape[1]):
        raw = df.iloc[:, j]
        num = pd.to_numeric(raw, errors="coerce").to_numpy(np.float64, na_value=np.nan)
        bad = np.isnan(num) & raw.notna().to_numpy()
        if bad.any():
            r = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"{path}: non-numeric value {raw.iloc[r]!r} at row {r} (frame {df.index[r]}), "
                f"column {_column_name(columns[j])}"
            )
        values[:, j] = num
    frames = df.index
    if isinstance(frames, pd.MultiIndex):
        frames = ["/".join(map(str, f)) for f in frames]
    return columns, values, _frames(list(frames), path)


def _assemble(
    path: Path,
    columns: list[tuple],
    values: np.ndarray,
    frames: np.ndarray,
    individual: str | None,
) -> DLCTable:
    inds = list(dict.fromkeys(c[1] for c in columns))
    if inds != [None]:
        if individual is None:
            if len(inds) > 1:
                raise InputError(
                    f"{path}: multi-animal DeepLabCut file with individuals {inds}; choose one "
                    "(input.individual=NAME)"
                )
            individual = inds[0]
            log.info("%s: the only individual '%s' is used", path, individual)
        elif str(individual) not in inds:
            raise InputError(f"{path}: individual '{individual}' is not in the file; it has {inds}")
        individual = str(individual)
    elif individual is not None:
        log.warning("%s: single-animal file; individual '%s' ignored", path, individual)
        individual = None
    sel = [j for j, c in enumerate(columns) if c[1] == individual]
    parts = list(dict.fromkeys(columns[j][2] for j in sel))
    where: dict[tuple[str, str], int] = {}
    for j in sel:
        _, _, part, coord = columns[j]
        if coord not in _COORDS:
            raise InputError(
                f"{path}: column {j + 2} ({_column_name(columns[j])}): unknown coordinate "
                f"'{coord}' (expected x, y, likelihood)"
            )
        if (part, coord) in where:
            raise InputError(f"{path}: column '{_column_name(columns[j])}' appears twice")
        where[(part, coord)] = j
    T, K = values.shape[0], len(parts)
    xy = np.full((T, K, 2), np.nan)
    lik = np.full((T, K), np.nan)
    no_lik = []
    for k, part in enumerate(parts):
        for a, coord in enumerate(("x", "y")):
            if (part, coord) not in where:
                raise InputError(f"{path}: part '{part}' has no '{coord}' column")
            xy[:, k, a] = values[:, where[(part, coord)]]
        if (part, "likelihood") in where:
            lik[:, k] = values[:, where[(part, "likelihood")]]
        else:
            no_lik.append(part)
            lik[:, k] = np.where(np.isfinite(xy[:, k]).all(-1), 1.0, np.nan)
    if no_lik:  # said as a warning naming the camera by adjust.io.scene
        log.debug("%s: no likelihood for %s; 1 where x and y are given", path, no_lik)
    finite = np.isfinite(xy).all(-1)
    unusable = ~finite & ~np.isnan(xy).all(-1)  # inf, or x without y
    xy[~finite] = np.nan
    scorers = list(dict.fromkeys(columns[j][0] for j in sel))
    if len(scorers) > 1:
        log.warning("%s: several scorers %s; reporting the first", path, scorers)
    table = DLCTable(
        tuple(parts),
        xy,
        lik,
        scorers[0] if scorers else "",
        frames,
        individual,
        path,
        tuple(no_lik),
        unusable if unusable.any() else None,
    )
    log.debug("read %s: %d frames, %d parts", path, T, K)
    return table


# --- writing ------------------------------------------------------------------------------


def write_dlc_csv(
    path: str | os.PathLike,
    parts: Sequence[str],
    xy: np.ndarray,
    likelihood: np.ndarray,
    scorer: str = "DLC_simulated",
    frames: Sequence | None = None,
) -> Path:
    """Write a single-animal DeepLabCut CSV (header rows scorer/bodyparts/coords, frame index
    first), atomically. xy: (T, K, 2) px with NaN for missing; likelihood: (T, K).

    NaN cells are written empty, as DeepLabCut (pandas) does; floats are written exactly.
    """
    parts = [str(p) for p in parts]
    xy = np.asarray(xy, dtype=np.float64)
    lik = np.asarray(likelihood, dtype=np.float64)
    T, K = len(xy), len(parts)
    if xy.shape != (T, K, 2) or lik.shape != (T, K):
        raise ValueError(
            f"xy must be (T, {K}, 2) and likelihood (T, {K}) for {K} parts, got {xy.shape}, "
            f"{lik.shape}"
        )
    if len(set(parts)) != K:
        raise ValueError(f"duplicate part names {parts}")
    index = pd.RangeIndex(T) if frames is None else pd.Index(list(frames))
    if len(index) != T:
        raise ValueError(f"{len(index)} frame labels for {T} frames")
    cols = pd.MultiIndex.from_product(
        [[str(scorer)], parts, list(_COORDS)], names=["scorer", "bodyparts", "coords"]
    )
    data = np.concatenate([xy, lik[..., None]], axis=-1).reshape(T, K * 3)
    df = pd.DataFrame(data, index=index, columns=cols)
    with atomic_path(path) as tmp:
        df.to_csv(tmp)
    return Path(path)
