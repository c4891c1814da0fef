"""CSV tables read with one-line errors, and the points3d layout's part columns: shared by the
readers of both halves (`adjust.io.points3d`, `adjust.export`, `deformnet.behavior.tracks`).

A points3d file keeps anipose's columns only (so anipose's readers, movement's
``from_anipose_file`` among them, take it as it is); our further per-frame columns (body pose,
per-part sigmas) live in a sidecar beside it, ``<stem>.extra.csv`` (`extra_path`): a first line
``# extra columns of <name> sha256=<hex>`` naming the points3d file's bytes, then ``fnum`` and
the columns. `read_points3d_table` returns the two joined.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterable
from pathlib import Path

import pandas as pd

from deformnet.atomic import file_digest
from deformnet.paths import regular_file

log = logging.getLogger(__name__)

#: the sidecar of a points3d file ``X.csv``: ``X.extra.csv``
EXTRA_SUFFIX = ".extra.csv"
_EXTRA_HEADER = re.compile(r"^# extra columns of (.*) sha256=([0-9a-f]{64})\s*$")


def read_csv(
    path: str | os.PathLike, what: str, error: type[Exception] = ValueError, **kwargs
) -> pd.DataFrame:
    """``pd.read_csv(path, **kwargs)``; a missing file is ``error("<what> not found: PATH")``,
    an unreadable one ``error("PATH: cannot read CSV: ...")`` (`what`: e.g. ``"tracks file"``;
    `error`: the caller's error class, e.g. adjust's ``InputError``); a directory, FIFO or device
    is refused before opening (`deformnet.paths.regular_file`)."""
    path = regular_file(path, what, error)
    try:
        return pd.read_csv(path, **kwargs)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise error(f"{path}: cannot read CSV: {exc}") from None


def xyz_parts(columns: Iterable[str]) -> list[str]:
    """The parts that have ``{part}_x``, ``{part}_y`` and ``{part}_z`` columns, in column order."""
    names = [str(c) for c in columns]
    have = set(names)
    return [
        c[:-2]
        for c in names
        if c.endswith("_x") and f"{c[:-2]}_y" in have and f"{c[:-2]}_z" in have
    ]


def extra_path(path: str | os.PathLike) -> Path:
    """The sidecar of points3d file `path` (``points3d.csv`` -> ``points3d.extra.csv``)."""
    path = Path(path)
    return path.with_name(path.stem + EXTRA_SUFFIX)


def extra_header(path: str | os.PathLike, name: str | None = None) -> str:
    """The sidecar's first line for the points3d file now at `path` (its bytes' sha256);
    `name`: the file name to state (default `path`'s)."""
    path = Path(path)
    return f"# extra columns of {name or path.name} sha256={file_digest(path)}\n"


def read_points3d_table(
    path: str | os.PathLike, what: str = "points3d file", error: type[Exception] = ValueError
) -> pd.DataFrame:
    """A points3d CSV (`read_csv`) with its sidecar's columns (`extra_path`) appended when the
    sidecar exists and belongs to these bytes (its sha256 line) and frames (same ``fnum``); a
    sidecar that does not is left out with a warning naming both files. Columns the file itself
    has win over the sidecar's."""
    path = Path(path)
    df = read_csv(path, what, error)
    side = extra_path(path)
    if not side.is_file():
        return df
    try:
        with open(side, encoding="utf-8") as fh:
            first = fh.readline()
    except (OSError, UnicodeDecodeError) as exc:
        log.warning("%s: cannot read the extra columns of %s (%s): left out", side, path, exc)
        return df
    m = _EXTRA_HEADER.match(first)
    if m is None or m.group(2) != file_digest(path):
        log.warning(
            "%s: not the extra columns of %s as it is now (written for other bytes): left out",
            side,
            path,
        )
        return df
    extra = read_csv(side, "extra columns file", error, skiprows=1)
    same_frames = len(extra) == len(df) and (
        "fnum" not in df.columns
        or (
            "fnum" in extra.columns
            and list(extra["fnum"].astype(str)) == list(df["fnum"].astype(str))
        )
    )
    if not same_frames:
        log.warning("%s: its frames differ from those of %s: left out", side, path)
        return df
    new = [c for c in extra.columns if c != "fnum" and c not in df.columns]
    return pd.concat([df, extra[new].set_index(df.index)], axis=1) if new else df
