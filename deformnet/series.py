"""Small time-series helpers shared by the apps (NumPy only)."""

from __future__ import annotations

import numpy as np


def interpolate_gaps(x: np.ndarray) -> np.ndarray:
    """Fill NaN runs of each column of x (T, ...) by linear interpolation in time (ends held)."""
    flat = x.reshape(len(x), -1).copy()
    t = np.arange(len(x))
    for j in range(flat.shape[1]):
        ok = np.isfinite(flat[:, j])
        if ok.any() and not ok.all():
            flat[:, j] = np.interp(t, t[ok], flat[ok, j])
    return flat.reshape(x.shape)
