"""CSV tables read with one-line errors, and the points3d layout's part columns: shared by the
readers of both halves (`adjust.io.points3d`, `adjust.export`, `deformnet.classify`)."""

from __future__ import annotations

import os
from collections.abc import Iterable

import pandas as pd

from deformnet.paths import regular_file


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
