"""Config helpers for code that accepts both Hydra/OmegaConf nodes and plain mappings: plain
values (`to_plain`), a project config (`compose`), an integer setting (`int_setting`), a frame
rate (`check_fps`)."""

from __future__ import annotations

import math
from typing import Any

from deformnet.paths import CONF_DIR


def to_plain(cfg: Any) -> Any:
    """OmegaConf node -> plain dicts/lists (interpolations resolved); anything else unchanged."""
    try:
        from omegaconf import OmegaConf
    except ImportError:  # pragma: no cover - omegaconf ships with hydra-core
        return cfg
    return OmegaConf.to_container(cfg, resolve=True) if OmegaConf.is_config(cfg) else cfg


def compose(name: str, overrides: list[str] | tuple[str, ...] = ()) -> Any:
    """The project's Hydra config `name` with `overrides`, from inside a running Hydra app (its
    config search path is the project's) or from plain Python (a temporary initialisation)."""
    import hydra
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        return hydra.compose(name, overrides=list(overrides))
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose(name, overrides=list(overrides))


def int_setting(cfg: Any, key: str, minimum: int) -> int:
    """``cfg[key]``, an integer >= `minimum` (not a bool), or a ValueError naming the setting."""
    value = cfg.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{key} must be an integer >= {minimum}, got {value!r}")
    return value


def check_fps(fps: Any, what: str) -> float | None:
    """A frame rate from a config (Hz): None stays None; anything not a finite number > 0 is a
    ValueError naming `what`."""
    if fps is None:
        return None
    try:
        f = float(fps)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a frame rate in Hz (a number > 0), got {fps!r}") from None
    if not (math.isfinite(f) and f > 0):
        raise ValueError(f"{what} must be a frame rate in Hz (a number > 0), got {fps!r}")
    return f
