"""One error handler for every app: bad input is one log line and exit status 2.

`run_app(run, cfg)` calls an app's plain ``run(cfg)`` (the console scripts of both halves:
`adjust.apps.common.run_or_exit` adds adjust's settings checks):

- bad input or config (a ValueError, whose message names the file, camera, part or frame, or an
  OmegaConf error about a setting): one ERROR line, exit status 2, never a traceback;
- an unusable output folder, or one another run is using (`deformnet.outputs.OutputBusy`), and
  any other OSError: one line, exit status 2;
- Ctrl-C (KeyboardInterrupt): one line, exit status 130; SIGTERM (a `kill`, a scheduler's time
  limit): exit status 143. Atomic writers (`deformnet.atomic`, `deformnet.outputs.OutputSet`)
  remove their temporary files on the way out, so the output folder keeps the previous run's
  outputs whole.

The per-project settings the console script added are logged first (`deformnet.project`), and a
given ``output.dir`` is checked and locked (`deformnet.outputs.prepare_output`) before `run`.
`hydra_app(run, config_name)` is a console script's Hydra entry point over `run_app`.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from deformnet import project
from deformnet.outputs import hold_output, prepare_output, release_output
from deformnet.paths import CONF_DIR
from deformnet.quiet import quiet_lightning

log = logging.getLogger(__name__)

#: exit status of a run stopped by Ctrl-C (128 + SIGINT), as shells report it
EXIT_INTERRUPTED = 130


@contextlib.contextmanager
def terminate_as_exit() -> Iterator[None]:
    """SIGTERM (a `kill`, a job scheduler's time limit) raises SystemExit(143) in the main
    thread, so atomic writers remove their temporary files on the way out (SIGKILL cannot be
    caught: `deformnet.outputs` covers it)."""
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


def first_line(exc: BaseException) -> str:
    """The first non-empty line of an exception's message (its type when it has none)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def run_app(
    run: Callable[[DictConfig], dict],
    cfg: DictConfig,
    check: Callable[[DictConfig], None] | None = None,
) -> dict:
    """Call ``run(cfg)`` as the module doc says; `check(cfg)`: settings checks first."""
    project.announce()
    locked: Path | None = None
    try:
        with terminate_as_exit():
            if check is not None:
                check(cfg)
            if OmegaConf.select(cfg, "output.dir", default=None):
                out = prepare_output(cfg)  # an unusable or busy folder before any computing
                hold_output(out)
                locked = out
            return run(cfg)
    except KeyboardInterrupt:
        where = f" (the outputs in {locked} are the previous run's)" if locked else ""
        log.error("interrupted (Ctrl-C)%s; exit status %d", where, EXIT_INTERRUPTED)
        raise SystemExit(EXIT_INTERRUPTED) from None
    except (ValueError, OmegaConfBaseException) as exc:
        log.error("%s", first_line(exc))
        raise SystemExit(2) from None
    except OSError as exc:
        if exc.filename is not None:
            log.error("cannot read or write %s: %s", exc.filename, exc.strerror or exc)
        else:
            log.error("cannot write the outputs: %s", exc)
        raise SystemExit(2) from None
    finally:
        if locked is not None:
            release_output(locked)


def hydra_app(
    run: Callable[[DictConfig], dict],
    config_name: str,
    check: Callable[[DictConfig], None] | None = None,
    quiet: bool = False,
) -> Callable[[], None]:
    """An app's console-script entry point: Hydra composes ``conf/<config_name>.yaml`` with the
    command line, then `run_app` calls ``run`` (after ``check``); ``quiet``: within
    `deformnet.quiet.quiet_lightning` (no Lightning tips or deprecations on the console)."""

    def quiet_run(cfg: DictConfig) -> dict:
        with quiet_lightning():
            return run(cfg)

    def main(cfg: DictConfig) -> None:
        run_app(quiet_run if quiet else run, cfg, check)
        # done and committed: a Ctrl-C during Hydra's and Python's teardown changes nothing
        # (it killed the process with Python's own exit, -2, after a complete run)
        signal.signal(signal.SIGINT, signal.SIG_IGN)

    main.__wrapped__ = run  # Hydra names the job (and its log file) after run's module
    return hydra.main(config_path=str(CONF_DIR), config_name=config_name, version_base=None)(main)
