"""`adjust-export`: existing tracks in the formats labs publish (NWB with ndx-pose).

    adjust-export nwb tracks=OUT/points3d.csv [calibration=calibration.toml] fps=100 \
        [bouts=bouts.csv] [events=events.csv] [intervals_unit=frames] output=OUT/session.nwb

The first bare word is the format (``nwb``, also ``format=nwb``). `run(cfg) -> dict` is the
plain function behind the Hydra app; it returns what was written. Layout: `adjust.export`.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from adjust.app import hydra_app, required
from adjust.io.errors import InputError

log = logging.getLogger(__name__)

FORMATS = ("nwb",)


def _opt(cfg: DictConfig, key: str):
    v = cfg.get(key)
    return None if v is None or str(v) == "" else v


def nwb_kwargs(cfg: DictConfig) -> dict:
    """`adjust.export.write_nwb` keyword arguments (all but path and tracks) from a config node
    with the keys of conf/export.yaml (absent keys: the defaults)."""
    edges = _opt(cfg, "edges")
    if edges is not None:
        edges = OmegaConf.to_container(edges) if OmegaConf.is_config(edges) else list(edges)
    return {
        "calibration": _opt(cfg, "calibration"),
        "fps": _opt(cfg, "fps"),
        "bouts": _opt(cfg, "bouts"),
        "events": _opt(cfg, "events"),
        "intervals_unit": str(cfg.get("intervals_unit") or "frames"),
        "edges": edges,
        "session_description": str(
            cfg.get("session_description") or "3D mouse tracks (mousetrack adjust-track)"
        ),
        "identifier": _opt(cfg, "identifier"),
        "session_start_time": _opt(cfg, "session_start_time"),
        "subject_id": _opt(cfg, "subject_id"),
        "starting_time": float(cfg.get("starting_time") or 0.0),
    }


def run(cfg: DictConfig) -> dict:
    """Export ``cfg.tracks`` in ``cfg.format``; returns {"format", "tracks", "output"}."""
    from adjust.export import write_nwb

    fmt = str(cfg.get("format") or "nwb")
    if fmt not in FORMATS:
        raise ValueError(f"adjust-export: unknown format {fmt!r} (known: {list(FORMATS)})")
    tracks = Path(required(cfg, "tracks", "export"))
    if not tracks.is_file():
        raise InputError(f"tracks file not found: {tracks}")
    out = _opt(cfg, "output")
    out = Path(str(out)) if out is not None else tracks.with_suffix(".nwb")
    path = write_nwb(out, tracks, **nwb_kwargs(cfg))
    return {"format": fmt, "tracks": str(tracks), "output": str(path)}


_main = hydra_app(run, "export")


def main() -> None:
    """Console script: a first bare word (``adjust-export nwb ...``) is ``format=...``."""
    first = sys.argv[1] if len(sys.argv) > 1 else ""
    if first and "=" not in first and not first.startswith("-"):
        sys.argv[1] = f"format={first}"
    _main()


if __name__ == "__main__":  # pragma: no cover
    main()
