"""What every `adjust` console script shares: one error handler (`run_or_exit`), the Hydra
entry point (`hydra_app`), the outputs written as one set (`write_outputs`); the settings
checks live in the library (`adjust.settings`)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig

from adjust.settings import check_settings
from deformnet import apprun
from deformnet.atomic import finite_or_none  # noqa: F401  (apps: adjust.apps.common.*)
from deformnet.outputs import (  # noqa: F401  (apps: adjust.apps.common.*; registers ${output_or:...})
    OutputBusy,
    OutputSet,
    output_lock,
    prepare_output,
    recover_outputs,
)

log = logging.getLogger(__name__)


def run_or_exit(run: Callable[[DictConfig], dict], cfg: DictConfig) -> dict:
    """Call an app's `run(cfg)` through the one error handler of every app
    (`deformnet.apprun.run_app`): bad input or config (ValueError, whose message names the file,
    camera, part or frame, or an OmegaConf error about a setting) is one logged line and exit
    status 2, an unusable or busy output folder (OSError, `OutputBusy`) too, Ctrl-C exit status
    130, never a traceback. Settings (`check_settings`) and ``output.dir`` (`prepare_output`,
    which locks it) are checked before `run`; the per-project settings the console script added
    are logged first (`deformnet.project`)."""
    return apprun.run_app(run, cfg, check_settings)


def hydra_app(run: Callable[[DictConfig], dict], config_name: str) -> Callable[[], None]:
    """An app's console-script entry point (`deformnet.apprun.hydra_app`): Hydra composes
    ``conf/<config_name>.yaml`` with the command line, then `run` is called as `run_or_exit`
    calls it."""
    return apprun.hydra_app(run, config_name, check_settings)


def write_outputs(
    out: Path,
    write_points: Callable[[Path], Path],
    summary: dict,
    outputs: OutputSet | None = None,
) -> dict:
    """Write ``points3d.csv`` and ``summary.json`` into `out` as one set (`OutputSet`): a
    reader never sees a new one beside an old other, and a run stopped at any moment (SIGKILL
    included) leaves the previous pair. The summary, written last, records every file's sha256
    and size (``outputs.files``; ``outputs.points3d_sha256``). With `outputs` (an open
    `OutputSet` of `out` holding the run's other files) the points join that set and it is
    committed here. Returns the summary as written."""
    if outputs is None:
        with OutputSet(out) as staged:
            return write_outputs(out, write_points, summary, staged)
    write_points(outputs.path("points3d.csv"))
    summary = dict(summary)
    summary["outputs"] = {
        **dict(summary.get("outputs") or {}),
        "points3d": str(outputs.final("points3d.csv")),
    }
    return outputs.commit(summary)
