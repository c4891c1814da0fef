"""Lock-box mechanisms: their positions as a validated table, and the ``[metadata.mechanisms]``
table of a calibration.toml (as `adjust-simulate` writes it). Read here for
`deformnet-classify`'s lock-box context and by `adjust-events` (adjust may import deformnet,
not the other way). Positions: global mm, {name: [x, y, z]}."""

from __future__ import annotations

import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from deformnet.units import unit_mm

__all__ = ["mechanism_table", "calibration_mechanisms"]


def mechanism_table(table: Any, source: str) -> dict[str, list[float]]:
    """{name: [x, y, z]} (floats, insertion order) from a mapping of mechanism names to
    positions; ValueError naming ``source`` and the mechanism when it is not one."""
    if not isinstance(table, Mapping) or not table:
        raise ValueError(f"{source}: expected a table name -> [x, y, z] (mm), got {table!r}")
    out = {}
    for name, pos in table.items():
        try:
            p = np.asarray(pos, dtype=np.float64)
        except (TypeError, ValueError):
            p = np.array([])
        if p.shape != (3,) or not np.isfinite(p).all():
            raise ValueError(f"{source}: mechanism '{name}' needs [x, y, z] (mm), got {pos!r}")
        out[str(name)] = p.tolist()
    return out


def calibration_mechanisms(path: str | os.PathLike) -> dict[str, list[float]]:
    """The ``[metadata.mechanisms]`` table of a calibration.toml, validated, in mm (the file's
    ``[metadata] units``, `deformnet.units`); ValueError naming the file when it is missing, not
    TOML, or has no such table."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"calibration file not found: {path}")
    try:
        meta = tomllib.loads(path.read_text()).get("metadata") or {}
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a TOML calibration file ({exc})") from None
    table = meta.get("mechanisms") if isinstance(meta, Mapping) else None
    if not table:
        raise ValueError(f"{path}: no [metadata.mechanisms] table")
    out = mechanism_table(table, f"{path} [metadata.mechanisms]")
    factor = unit_mm(meta, str(path))
    return {name: [factor * v for v in pos] for name, pos in out.items()}
