"""Helpers shared by the `adjust` Hydra apps (adjust-triangulate, adjust-track)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)


def run_or_exit(run: Callable[[DictConfig], dict], cfg: DictConfig) -> dict:
    """Call an app's `run(cfg)`; bad input or config (ValueError, whose message names the file,
    camera, part or frame) is one logged line and exit status 2, not a traceback."""
    try:
        return run(cfg)
    except ValueError as exc:
        log.error("%s", exc)
        raise SystemExit(2) from None


def required(cfg: DictConfig, key: str, config_name: str) -> str:
    """The string value of a required config key, or a ValueError saying how to set it."""
    value = OmegaConf.select(cfg, key, throw_on_missing=False)
    if value is None or OmegaConf.is_missing(cfg, key) or str(value) == "":
        raise ValueError(f"set {key}=... (see conf/{config_name}.yaml)")
    return str(value)


def stats(values: np.ndarray) -> dict:
    """count, median, mean, p90 and max of the finite values (None when there are none)."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"count": 0, "median": None, "mean": None, "p90": None, "max": None}
    return {
        "count": int(v.size),
        "median": float(np.median(v)),
        "mean": float(v.mean()),
        "p90": float(np.percentile(v, 90)),
        "max": float(v.max()),
    }


def finite_or_none(x):
    """JSON has no NaN: non-finite floats (recursively) -> None; numpy bools -> bool."""
    if isinstance(x, dict):
        return {k: finite_or_none(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [finite_or_none(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def load_kwargs(inp: DictConfig) -> dict:
    """`adjust.io.load_scene` keyword arguments from an app's `input` config node."""
    return {
        "likelihood_threshold": float(inp.get("likelihood_threshold", 0.5)),
        "individual": inp.get("individual"),
        "pattern": inp.get("pattern"),
        "ignore_unknown_parts": bool(inp.get("ignore_unknown_parts", False)),
        "allow_missing_parts": bool(inp.get("allow_missing_parts", False)),
    }
