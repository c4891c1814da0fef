"""Helpers shared by the `adjust` Hydra apps (adjust-triangulate, adjust-track)."""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from deformnet import project
from deformnet.atomic import finite_or_none  # noqa: F401  (apps: adjust.app.finite_or_none)

log = logging.getLogger(__name__)


def _output_or(given, default: str) -> str:
    """Hydra run folder: ``output.dir`` when it is set and usable (an existing folder, or one
    that can be created, writable); else `default` (under runs/) when it is not set, or, when it
    is set but unusable, `default` under the system's temporary folder, so that the app itself
    reports the unusable folder in one line (`prepare_output`) instead of Hydra failing with a
    traceback, and nothing lands in the working directory. Used as
    ``hydra.run.dir: ${output_or:${oc.select:output.dir,null},runs/...}``."""
    if given is None or str(given) in ("", "None", "null"):
        return default
    p = Path(str(given))
    try:  # Hydra creates it next anyway; a real write test (access() is always true for root)
        p.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".write-test.", dir=p)
        os.close(fd)
        os.unlink(tmp)
    except OSError:  # Hydra's files go to a scratch folder, not the working directory
        return str(Path(tempfile.gettempdir()) / "mousetrack" / default)
    return str(p)


if not OmegaConf.has_resolver("output_or"):
    OmegaConf.register_new_resolver("output_or", _output_or)


@contextlib.contextmanager
def _terminate_as_exit() -> Iterator[None]:
    """SIGTERM (a `kill`, a job scheduler's time limit) raises SystemExit in the main thread,
    so atomic writers remove their temporary files on the way out (SIGKILL cannot be caught)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):  # noqa: ARG001
        raise SystemExit(128 + signum)

    before = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)


def run_or_exit(run: Callable[[DictConfig], dict], cfg: DictConfig) -> dict:
    """Call an app's `run(cfg)`; bad input or config (ValueError, whose message names the file,
    camera, part or frame, or an OmegaConf error about a setting) is one logged line and exit
    status 2, an unwritable output folder (OSError) too, never a traceback. Settings
    (`check_settings`) and ``output.dir`` (`prepare_output`) are checked before `run`; the
    per-project settings the console script added are logged first (`deformnet.project`)."""
    project.announce()
    try:
        with _terminate_as_exit():
            check_settings(cfg)
            if OmegaConf.select(cfg, "output.dir", default=None):
                prepare_output(cfg)  # an unusable output folder before any computing
            return run(cfg)
    except (ValueError, OmegaConfBaseException) as exc:
        log.error("%s", str(exc).strip().splitlines()[0] if str(exc).strip() else exc)
        raise SystemExit(2) from None
    except OSError as exc:
        log.error("cannot write the outputs: %s", exc)
        raise SystemExit(2) from None


def hydra_app(run: Callable[[DictConfig], dict], config_name: str) -> Callable[[], None]:
    """An app's console-script entry point: Hydra composes ``conf/<config_name>.yaml`` with
    the command line, then `run_or_exit` calls `run`."""
    import hydra

    from deformnet.paths import CONF_DIR

    def main(cfg: DictConfig) -> None:
        run_or_exit(run, cfg)

    main.__wrapped__ = run  # Hydra names the job (and its log file) after run's module
    return hydra.main(config_path=str(CONF_DIR), config_name=config_name, version_base=None)(main)


_KINDS = {"int": "an integer", "float": "a number", "bool": "true or false"}


def setting(
    cfg,
    key: str,
    kind: str,
    default=None,
    *,
    lo: float | None = None,
    hi: float | None = None,
    allow_none: bool = False,
    prefix: str = "",
):
    """The value of config `key` (dotted) as `kind` ("int", "float", "bool"), or a ValueError
    naming the setting and what it accepts (``solver.max_iterations=abc``, ``=2.5``, ``=-3``).
    lo/hi: inclusive bounds. None (or absent) gives `default`; None is allowed only with
    allow_none (or a non-None default). prefix: how the messages name `cfg` (``"input."``)."""
    name = prefix + key
    value = OmegaConf.select(cfg, key, default=None) if isinstance(cfg, DictConfig) else None
    if value is None and not isinstance(cfg, DictConfig) and hasattr(cfg, "get"):
        value = cfg
        for part in key.split("."):
            value = value.get(part) if hasattr(value, "get") else None
    if value is None:
        if default is None and not allow_none:
            raise ValueError(f"{name} must be set ({_KINDS[kind]})")
        return default
    accepts = _KINDS[kind]
    if lo is not None and hi is not None:
        accepts += f" from {lo:g} to {hi:g}"
    elif lo is not None:
        accepts += f" >= {lo:g}"
    elif hi is not None:
        accepts += f" <= {hi:g}"
    bad = ValueError(f"{name}={value!r} is not valid: {name} accepts {accepts}")
    if kind == "bool":
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false"):
            return value.lower() == "true"
        raise bad
    if isinstance(value, bool):
        raise bad
    if kind == "int":
        if isinstance(value, int):
            out = int(value)
        elif isinstance(value, float) and value.is_integer():
            out = int(value)
        elif isinstance(value, str) and value.strip().lstrip("+-").isdigit():
            out = int(value)
        else:
            raise bad
    else:
        try:
            out = float(value)
        except (TypeError, ValueError):
            raise bad from None
        if not math.isfinite(out):
            raise bad
    if (lo is not None and out < lo) or (hi is not None and out > hi):
        raise bad
    return out


#: typed settings of the apps, checked before any work: key -> (kind, lo, hi, may be null)
SETTINGS = {
    "threads": ("int", 0, None, True),
    "progress": ("bool", None, None, False),
    "input.likelihood_threshold": ("float", 0.0, 1.0, False),
    "input.ignore_unknown_parts": ("bool", None, None, False),
    "input.allow_missing_parts": ("bool", None, None, False),
    "triangulate.robust": ("bool", None, None, False),
    "triangulate.max_error_px": ("float", 0.0, None, False),
    "triangulate.min_views": ("int", 2, None, False),
    "deform.max_error_px": ("float", 0.0, None, False),
    "deform.gate_mm": ("float", 0.0, None, False),
    "deform.batch_size": ("int", 1, None, False),
    "deform.max_iterations": ("int", 0, None, True),
    "deform.rigid_first": ("bool", None, None, False),
}
#: lower bounds of solver settings beyond ">= 0" (SolverConfig checks the rest)
_SOLVER_LO = {"grid_size": 3}


def check_settings(cfg) -> None:
    """Settings of the wrong type or range (``solver.max_iterations=abc``, ``=2.5``, ``=-3``,
    ``threads=abc``) are a ValueError naming the setting and what it accepts. Checks the keys of
    `SETTINGS` and every number of the ``solver`` node (typed by `adjust.lsq.SolverConfig`)."""
    if not isinstance(cfg, DictConfig):
        return
    for key, (kind, lo, hi, nullable) in SETTINGS.items():
        if OmegaConf.select(cfg, key, default="<absent>") == "<absent>":
            continue
        if OmegaConf.select(cfg, key, default=None) is None:
            if not nullable:
                raise ValueError(f"{key} must be set ({_KINDS[kind]})")
            continue
        setting(cfg, key, kind, lo=lo, hi=hi)
    solver = cfg.get("solver")
    if solver is None or not hasattr(solver, "keys"):
        return
    import dataclasses

    from adjust.lsq.config import SolverConfig

    for f in dataclasses.fields(SolverConfig):
        if f.name not in solver:
            continue
        kind = {"int": "int", "float": "float", "float | None": "float", "bool": "bool"}.get(
            str(f.type)
        )
        if kind is None:
            continue
        lo = _SOLVER_LO.get(f.name, 0) if kind != "bool" else None
        setting(solver, f.name, kind, lo=lo, allow_none=True, prefix="solver.")


def prepare_output(cfg) -> Path:
    """The app's output folder (`deformnet.paths.output_dir`), checked before any computing:
    a file in its place, a folder that cannot be created or written is a ValueError naming it."""
    from deformnet.paths import output_dir

    given = (
        OmegaConf.select(cfg, "output.dir", default=None) if isinstance(cfg, DictConfig) else None
    )
    if given:
        p = Path(str(given))
        probe = p
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        if probe.exists() and not probe.is_dir():
            raise ValueError(f"output.dir={p}: {probe} is a file, not a folder")
    try:
        out = output_dir(cfg)
    except OSError as exc:
        raise ValueError(f"output folder cannot be created: {exc}") from None
    try:
        fd, tmp = tempfile.mkstemp(prefix=".write-test.", dir=out)
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        raise ValueError(f"output folder {out} is not writable: {exc.strerror or exc}") from None
    return out


def file_digest(path: str | os.PathLike) -> str:
    """sha256 of a file's bytes (hex): how a summary names the exact outputs it describes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_outputs(out: Path, write_points: Callable[[Path], Path], summary: dict) -> dict:
    """Write ``points3d.csv`` and ``summary.json`` into `out` so that a reader never sees a new
    one beside an old other: the old summary is removed first, the points written (atomically),
    then the summary (atomically, last), which records the points file's sha256 and size
    (``outputs.points3d_sha256``). A summary present is therefore always the one of the points
    beside it. Returns the summary as written."""
    import json

    from deformnet.atomic import write_text

    summary_path = out / "summary.json"
    summary_path.unlink(missing_ok=True)
    points_path = write_points(out / "points3d.csv")
    summary = dict(summary)
    outputs = dict(summary.get("outputs") or {})
    outputs.update(
        points3d=str(points_path),
        summary=str(summary_path),
        points3d_sha256=file_digest(points_path),
        points3d_bytes=points_path.stat().st_size,
    )
    summary["outputs"] = outputs
    summary = finite_or_none(summary)
    write_text(summary_path, json.dumps(summary, indent=2) + "\n")
    return summary


def required(cfg: DictConfig, key: str, config_name: str) -> str:
    """The string value of a required config key, or a ValueError saying how to set it."""
    value = OmegaConf.select(cfg, key, throw_on_missing=False)
    if value is None or OmegaConf.is_missing(cfg, key) or str(value) == "":
        raise ValueError(f"set {key}=... (see conf/{config_name}.yaml)")
    return str(value)


def stats(values: np.ndarray) -> dict:
    """count, median, mean, p90 and max of the finite values (None when there are none): the
    summary.json view of `adjust.metrics.error_summary`, the one statistics summary."""
    from adjust.metrics import error_summary

    s = error_summary(values)
    if s["n"] == 0:
        return {"count": 0, "median": None, "mean": None, "p90": None, "max": None}
    return {"count": s["n"], **{k: s[k] for k in ("median", "mean", "p90", "max")}}


def load_kwargs(inp: DictConfig) -> dict:
    """`adjust.io.load_scene` keyword arguments from an app's `input` config node (settings of
    the wrong type or range are a ValueError naming them)."""
    individual = inp.get("individual")
    pattern = inp.get("pattern")
    return {
        "likelihood_threshold": setting(inp, "likelihood_threshold", "float", 0.5, lo=0.0, hi=1.0),
        "individual": None if individual is None else str(individual),
        "pattern": None if pattern is None else str(pattern),
        "ignore_unknown_parts": setting(
            inp, "ignore_unknown_parts", "bool", False, prefix="input."
        ),
        "allow_missing_parts": setting(inp, "allow_missing_parts", "bool", False, prefix="input."),
    }
