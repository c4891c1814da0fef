"""Session folders: ``input.session=DIR`` and the session lists of batch runs.

A session folder holds one recording as `adjust-simulate` writes it and a lab keeps it:
``DIR/calibration.toml`` (anipose) and one DeepLabCut/SLEAP file per camera, in
``DIR/detections/`` when that folder exists, else in ``DIR`` itself.

- `resolve_session`: DIR -> (calibration, detections), with a one-line error for a folder that is
  not a session;
- `with_session`: an app config with ``input.session`` set -> the same config with
  ``input.calibration`` / ``input.detections`` filled in from it (values given explicitly win:
  e.g. one shared ``input.calibration`` for sessions that have none);
- `expand_session_globs`: command-line ``input.session=glob(PATTERN, ...)`` -> the comma list of
  matching folders, the form Hydra's sweeper enumerates (Hydra's own ``glob`` only enumerates
  config-group options);
- the ``session_name`` OmegaConf resolver (the batch's per-session folder names).
"""

from __future__ import annotations

import glob as _glob
import os
import re
from collections.abc import Sequence
from fnmatch import fnmatch
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict

from adjust.io.errors import InputError

CALIBRATION = "calibration.toml"
DETECTIONS = "detections"
SESSION_KEY = "input.session"


def resolve_session(session: str | os.PathLike) -> tuple[Path, Path]:
    """(calibration file, detections folder) of a session folder."""
    d = Path(session)
    if not d.is_dir():
        raise InputError(f"session folder not found: {d}")
    calibration = d / CALIBRATION
    detections = d / DETECTIONS if (d / DETECTIONS).is_dir() else d
    return calibration, detections


def session_name(session, num=None) -> str:
    """A session's folder name in a batch: the folder's base name, made file-system safe (the
    job number when there is no session)."""
    if session is None or str(session) in ("", "None", "null"):
        return f"job{num}" if num is not None else "session"
    name = Path(str(session).rstrip("/\\")).name or str(session)
    return re.sub(r"[^A-Za-z0-9._+-]+", "_", name)


def _given(cfg: DictConfig, key: str) -> bool:
    if OmegaConf.is_missing(cfg, key):
        return False
    value = OmegaConf.select(cfg, key)
    return value is not None and str(value) != ""


def with_session(cfg: DictConfig) -> DictConfig:
    """``cfg`` with input.calibration / input.detections from ``input.session`` (when set and
    the keys are not given). Returns ``cfg`` itself when there is no session."""
    if not _given(cfg, SESSION_KEY):
        return cfg
    session = str(OmegaConf.select(cfg, SESSION_KEY))
    calibration, detections = resolve_session(session)
    cfg = cfg.copy()
    with open_dict(cfg):
        if not _given(cfg, "input.calibration"):
            if not calibration.is_file():
                raise InputError(
                    f"session {session}: no {CALIBRATION} (or set input.calibration=...)"
                )
            cfg.input.calibration = str(calibration)
        if not _given(cfg, "input.detections"):
            cfg.input.detections = str(detections)
    return cfg


def _quote(value: str) -> str:
    """A Hydra override value for a literal string (quoted, escapes for \\ and ')."""
    return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"


def find_sessions(include: Sequence[str], exclude: Sequence[str] = ()) -> list[str]:
    """Folders matching any ``include`` file-system glob and no ``exclude`` pattern, sorted."""
    found = set()
    for pattern in include:
        for path in _glob.glob(os.path.expanduser(pattern)):
            if Path(path).is_dir():
                found.add(path.rstrip("/\\") or path)
    keep = [p for p in found if not any(fnmatch(p, e) or fnmatch(Path(p).name, e) for e in exclude)]
    return sorted(keep)


def expand_session_globs(argv: Sequence[str]) -> list[str]:
    """Rewrite ``input.session=glob(...)`` arguments into the comma list of matching session
    folders. Raises InputError when nothing matches or two folders share a name (they would
    share a batch output folder)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import Glob

    out = []
    parser = None
    for arg in argv:
        key = arg.split("=", 1)[0].lstrip("+~")
        if key != SESSION_KEY or "glob(" not in arg:
            out.append(arg)
            continue
        parser = parser or OverridesParser.create()
        value = parser.parse_override(arg).value()
        if not isinstance(value, Glob):
            out.append(arg)
            continue
        sessions = find_sessions(value.include, value.exclude)
        if not sessions:
            raise InputError(f"{arg}: no session folder matches")
        names: dict[str, str] = {}
        for s in sessions:
            n = session_name(s)
            if n in names:
                raise InputError(
                    f"{arg}: sessions {names[n]} and {s} have the same name '{n}' (one output "
                    "folder per name): give them distinct folder names"
                )
            names[n] = s
        out.append(f"{arg.split('=', 1)[0]}=" + ",".join(_quote(s) for s in sessions))
    return out


def register_resolvers() -> None:
    """``${session_name:SESSION,NUM}`` for hydra.sweep.subdir (idempotent)."""
    if not OmegaConf.has_resolver("session_name"):
        OmegaConf.register_new_resolver("session_name", session_name)


register_resolvers()
