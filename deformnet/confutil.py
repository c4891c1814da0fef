"""Config helpers for code that accepts both Hydra/OmegaConf nodes and plain mappings: plain
values (`to_plain`), a config block's checked fields (`checked_fields`) or the fields it gives
(`given_fields`), a project config
(`compose`), an integer setting (`int_setting`), a frame rate (`check_fps`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from typing import Any

from deformnet.paths import CONF_DIR


def to_plain(cfg: Any) -> Any:
    """OmegaConf node -> plain dicts/lists (interpolations resolved); anything else unchanged."""
    try:
        from omegaconf import OmegaConf
    except ImportError:  # pragma: no cover - omegaconf ships with hydra-core
        return cfg
    return OmegaConf.to_container(cfg, resolve=True) if OmegaConf.is_config(cfg) else cfg


def checked_fields(cls: type, cfg: Any, what: str, ignore: Iterable[str] = ()) -> dict[str, Any]:
    """A config block (OmegaConf node, mapping or None) as a plain dict of the dataclass `cls`'s
    fields: a key that is no field of `cls` (nor in `ignore`: read elsewhere) is a ValueError
    naming it as ``what.key`` and the known ones (`what`: the block, e.g. ``data.augment``)."""
    data = {} if cfg is None else dict(to_plain(cfg))
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names - set(ignore))
    if unknown:
        keys = [f"{what}.{k}" for k in unknown]
        raise ValueError(f"unknown {what} settings {keys}; known: {sorted(names)}")
    return {k: v for k, v in data.items() if k in names}


def as_kind(v, kind):
    """v as `kind`: int (a whole number), float, str, bool (only a bool: no other kind takes
    one) or list (of whole numbers); None where it is not one."""
    if kind is list:
        v = [as_kind(x, int) for x in v] if isinstance(v, (list, tuple)) else [None]
        return None if None in v else v
    if isinstance(v, bool) != (kind is bool):
        return None
    try:
        return v if kind is bool else None if kind is int and float(v) != int(v) else kind(v)
    except (TypeError, ValueError, OverflowError):
        return None


def check_fields(obj, block: str, **rules) -> None:
    """The fields of the frozen dataclass `obj` that `rules` names (key=(kind, test, what))
    coerced to their kind (`as_kind`) and checked by test(value) (test None: any value of the
    kind); else a ValueError: ``block.key`` must be `what`."""
    for key, (kind, test, what) in rules.items():
        v = as_kind(getattr(obj, key), kind)
        if v is None or (test is not None and not test(v)):
            raise ValueError(f"{block}.{key} must be {what}, got {getattr(obj, key)!r}")
        object.__setattr__(obj, key, v)


def given_fields(cls: type, cfg: Any) -> dict[str, Any]:
    """The keys of a config node (OmegaConf or a mapping; None: none) that are fields of the
    dataclass `cls`, unresolved values as they stand: the fields absent keep `cls`'s defaults,
    the one copy of a YAML default in the code (other keys are read elsewhere)."""
    if cfg is None:
        return {}
    return {f.name: cfg[f.name] for f in dataclasses.fields(cls) if f.name in cfg}


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
