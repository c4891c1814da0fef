"""`adjust-export`: existing tracks in the formats labs publish and anipose users expect.

    adjust-export nwb tracks=OUT/points3d.csv [calibration=calibration.toml] fps=100 \
        session_start_time=2026-03-01T09:30:00+01:00 subject.subject_id=m01 \
        subject.species='Mus musculus' subject.sex=F subject.age=P90D \
        [bouts=bouts.csv] [events=events.csv] [skeleton=skeleton.csv] output=OUT/session.nwb
    adjust-export anipose tracks=OUT/points3d.csv axes.x=[a,b] axes.y=[a,c]
    adjust-export anipose tracks=OUT/points3d.csv calibration=calibration.toml \
        axes.board.detections=board.csv axes.board.rows=5 axes.board.columns=7 \
        axes.board.square_mm=30
    adjust-export angles tracks=OUT/points3d.csv +angles.knee=[hip,knee,ankle]

The first bare word is the format (``nwb``, ``anipose``, ``angles``; also ``format=...``).
`run(cfg) -> dict` is the plain function behind the Hydra app; it returns what was written.
Layouts: `adjust.export` (NWB, anipose's points3d.csv), `adjust.kinematics` (angles, axes).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from adjust.apps.common import hydra_app
from adjust.export import write_anipose, write_nwb
from adjust.io.errors import InputError
from adjust.kinematics import alignment_kwargs, angles_csv
from adjust.nwb_metadata import FILE_KEYS, SUBJECT_KEYS
from adjust.settings import required
from deformnet.paths import regular_file

log = logging.getLogger(__name__)

FORMATS = ("nwb", "anipose", "angles")
#: the output beside the tracks when ``output`` is null
DEFAULT_OUTPUT = {"nwb": "{stem}.nwb", "anipose": "{stem}_anipose.csv", "angles": "angles.csv"}


def _opt(cfg: DictConfig, key: str):
    v = cfg.get(key)
    return None if v is None or str(v) == "" else v


def _plain(value):
    return OmegaConf.to_container(value) if OmegaConf.is_config(value) else value


def axes_kwargs(cfg: DictConfig) -> dict:
    """``axes`` and ``origin`` of `adjust.kinematics.align_tracks` from the ``axes`` node: named
    points or a calibration board (`adjust.kinematics.alignment_kwargs`); {} without one."""
    return alignment_kwargs(_plain(cfg.get("axes")), _opt(cfg, "calibration"))


def nwb_kwargs(cfg: DictConfig) -> dict:
    """`adjust.export.write_nwb` keyword arguments (all but path and tracks) from a config node
    with the keys of conf/export.yaml (absent keys: the defaults)."""
    subject = _plain(cfg.get("subject")) or {}
    metadata = {k: _plain(cfg.get(k)) for k in FILE_KEYS if cfg.get(k) is not None}
    unknown = [k for k in subject if k not in SUBJECT_KEYS]
    if unknown:
        raise ValueError(f"subject: unknown setting(s) {unknown} (known: {list(SUBJECT_KEYS)})")
    return {
        "calibration": _opt(cfg, "calibration"),
        "fps": _opt(cfg, "fps"),
        "bouts": _opt(cfg, "bouts"),
        "events": _opt(cfg, "events"),
        "intervals_unit": str(cfg.get("intervals_unit") or "frames"),
        "edges": _plain(_opt(cfg, "edges")),
        "skeleton": _opt(cfg, "skeleton"),
        "detections": _opt(cfg, "detections"),
        "session_description": str(
            cfg.get("session_description") or "3D mouse tracks (mousetrack adjust-track)"
        ),
        "identifier": _opt(cfg, "identifier"),
        "session_start_time": _opt(cfg, "session_start_time"),
        "subject": subject,
        "starting_time": float(cfg.get("starting_time") or 0.0),
        "metadata": metadata,
        **axes_kwargs(cfg),
    }


def run(cfg: DictConfig) -> dict:
    """Export ``cfg.tracks`` in ``cfg.format``; returns {"format", "tracks", "output"}."""
    fmt = str(cfg.get("format") or "nwb")
    if fmt not in FORMATS:
        raise ValueError(f"adjust-export: unknown format {fmt!r} (known: {list(FORMATS)})")
    tracks = regular_file(required(cfg, "tracks", "export"), "tracks file", InputError)
    out = _opt(cfg, "output")
    out = (
        Path(str(out))
        if out is not None
        else tracks.parent / DEFAULT_OUTPUT[fmt].format(stem=tracks.stem)
    )
    if fmt == "nwb":
        path = write_nwb(out, tracks, **nwb_kwargs(cfg))
    elif fmt == "anipose":
        path = write_anipose(
            out, tracks, keep_extra=bool(cfg.get("keep_extra") or False), **axes_kwargs(cfg)
        )
    else:
        path = angles_csv(out, tracks, _plain(cfg.get("angles")))
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
