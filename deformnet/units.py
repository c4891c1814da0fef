"""Length units of a calibration file. mousetrack works in mm; an anipose calibration.toml is in
whatever unit its board's square length was given in (mm, cm or m in practice). Its optional
``[metadata] units`` key says which (``"mm"``, ``"cm"`` or ``"m"``; absent: mm), and every
reader converts the file's lengths (camera translations, ``[metadata.mechanisms]`` positions)
to mm with `unit_mm`. Here, not in `adjust.io`, because `deformnet-classify` reads the
mechanisms of a calibration too (deformnet never imports adjust)."""

from __future__ import annotations

from collections.abc import Mapping

__all__ = ["LENGTH_UNITS", "unit_mm", "declared_unit"]

#: mm per unit of each length unit a calibration may declare
LENGTH_UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


def declared_unit(metadata: Mapping | None, where: str) -> str | None:
    """The ``units`` of a calibration's ``[metadata]`` table (lower case), None where absent;
    ValueError naming `where` (the file) for a unit that is not one of `LENGTH_UNITS`."""
    value = metadata.get("units") if isinstance(metadata, Mapping) else None
    if value is None:
        return None
    unit = value.strip().lower() if isinstance(value, str) else None
    if unit not in LENGTH_UNITS:
        raise ValueError(
            f"{where}: [metadata] units = {value!r} is not a length unit; one of "
            f"{sorted(LENGTH_UNITS)} (the unit of the camera translations and mechanism "
            "positions in this file)"
        )
    return unit


def unit_mm(metadata: Mapping | None, where: str) -> float:
    """mm per length unit of the calibration whose ``[metadata]`` table is `metadata` (1 where
    it declares none); ValueError naming `where` as `declared_unit`."""
    unit = declared_unit(metadata, where)
    return LENGTH_UNITS[unit] if unit is not None else 1.0
