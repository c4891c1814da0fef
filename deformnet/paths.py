"""Where the project's Hydra configs live, and where a Hydra app writes its outputs."""

from __future__ import annotations

import os
import stat
from pathlib import Path

REPO_DIR = Path(__file__).resolve().parents[1]


def _conf_dir() -> Path:
    """conf/ of the checkout (editable install, development); in a non-editable install the
    configs ship as the package ``mousetrack_conf``."""
    if (REPO_DIR / "conf" / "track.yaml").is_file():
        return REPO_DIR / "conf"
    import importlib.util

    spec = importlib.util.find_spec("mousetrack_conf")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("mousetrack's Hydra configs are missing: reinstall the package")
    return Path(next(iter(spec.submodule_search_locations)))


CONF_DIR = _conf_dir()


def shared_dir() -> Path:
    """The project's shared folder (the paper, real data sets): `$MOUSETRACK_SHARED`, else the
    `shared/` folder beside the checkout (where CI and developers have it)."""
    env = os.environ.get("MOUSETRACK_SHARED")
    return Path(env) if env else REPO_DIR.parent / "shared"


def real_hand_dir() -> Path:
    """The real 4-camera DeepLabCut hand data set (anipose calibration + trial_000/ CSVs)."""
    return shared_dir() / "data" / "real-hand-4cam"


def real_mouse_poses_dir() -> Path:
    """The 91 hand-labelled real 3D mouse poses (22 keypoints, ``poses3d.csv``)."""
    return shared_dir() / "data" / "real-mouse-poses-3d"


def real_mouse_motion_dir() -> Path:
    """The real mouse's 3D motion (3600 frames, 34 keypoints, ``poses3d.csv``)."""
    return shared_dir() / "data" / "real-mouse-motion-3d"


def output_dir(cfg) -> Path:
    """The folder a Hydra app writes into.

    `cfg.output.dir` when it is set (tests and users pass it), else Hydra's run folder
    (`hydra.runtime.output_dir`, under `runs/`). Never the working directory.
    """
    out = cfg.get("output") if hasattr(cfg, "get") else None
    given = out.get("dir") if out is not None else None
    if given:
        path = Path(str(given))
    else:
        from hydra.core.hydra_config import HydraConfig

        if not HydraConfig.initialized():
            raise ValueError(
                "no output folder: set output.dir=... (Hydra's run folder exists only under "
                "@hydra.main)"
            )
        path = Path(HydraConfig.get().runtime.output_dir)
    path.mkdir(parents=True, exist_ok=True)
    return path


def regular_file(path: str | os.PathLike, what: str, error: type[Exception] = ValueError) -> Path:
    """`path` when it is a regular file (or a link to one), checked before anything opens it;
    else ``error`` naming it: not found, a directory, or not a regular file (a FIFO, device or
    socket, which would block or never end: ``/dev/zero``, ``/dev/stdin``, a named pipe).
    `what`: how the message names the file (``"calibration file"``); `error`: the caller's error
    class (adjust's ``InputError``)."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise error(f"{what} not found: {path}") from None
    except OSError as exc:
        raise error(f"{what} {path}: cannot be read: {exc.strerror or exc}") from None
    if stat.S_ISDIR(mode):
        raise error(f"{what} {path} is a directory, not a file")
    if not stat.S_ISREG(mode):
        kind = (
            "a named pipe (FIFO)"
            if stat.S_ISFIFO(mode)
            else "a device"
            if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
            else "a socket"
            if stat.S_ISSOCK(mode)
            else "not a regular file"
        )
        raise error(f"{what} {path} is {kind}, not a regular file; give a file")
    return path
