"""Config value checks shared by the scene's pieces (rig, occluders, detector)."""

from __future__ import annotations

from typing import Any

import numpy as np


def _vec(value: Any, n: int, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be {n} numbers, got {value!r}") from None
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be {n} finite numbers, got {value!r}")
    return arr


def _range(value: Any, what: str, lo: float = 0.0, hi: float = 1.0) -> tuple[float, float]:
    v = _vec(value, 2, what)
    if not (lo <= v[0] <= v[1] <= hi):
        raise ValueError(
            f"{what} must be [low, high] with {lo} <= low <= high <= {hi}, got {value!r}"
        )
    return float(v[0]), float(v[1])
