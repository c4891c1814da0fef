"""One helper for code that accepts both Hydra/OmegaConf nodes and plain mappings."""

from __future__ import annotations

from typing import Any


def to_plain(cfg: Any) -> Any:
    """OmegaConf node -> plain dicts/lists (interpolations resolved); anything else unchanged."""
    try:
        from omegaconf import OmegaConf
    except ImportError:  # pragma: no cover - omegaconf ships with hydra-core
        return cfg
    return OmegaConf.to_container(cfg, resolve=True) if OmegaConf.is_config(cfg) else cfg
