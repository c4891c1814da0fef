"""Console scripts whose ``--help`` page comes at once.

Hydra prints an app's help page (conf/hydra/help/<config>.yaml's template) only after
composing the config and listing every config group with its options, and the app's module
imports torch first: 3-4 s for a page of text. Each page of ours is plain text (no ``$``
substitutions), so a bare ``--help`` / ``-h`` prints the template as Hydra would, without
importing the app; any other command line (overrides with ``--help``, ``--cfg``, a run) goes to
the app's own entry point, with the per-project settings (``mousetrack.yaml``,
`deformnet.project`) in front of its overrides. `adjust.entry` and `deformnet.entry` hold the
console scripts (pyproject.toml's ``[project.scripts]``).
"""

from __future__ import annotations

import importlib
import logging
import sys
from collections.abc import Callable

from deformnet import paths, project

log = logging.getLogger(__name__)


def help_page(config_name: str) -> str | None:
    """The ``--help`` page of the app whose primary config is conf/<config_name>.yaml, as
    Hydra prints it (conf/hydra/help/<config_name>.yaml's template), or None when the template
    substitutes Hydra's variables (then only Hydra can make the page)."""
    from omegaconf import OmegaConf

    path = paths.CONF_DIR / "hydra" / "help" / f"{config_name}.yaml"
    template = OmegaConf.load(path).get("template")
    if not isinstance(template, str) or "$" in template:
        return None
    return template


def console_script(config_name: str, target: str) -> Callable[[], None]:
    """A console script's entry point: a bare ``--help`` / ``-h`` prints `help_page`
    (config_name: the app's primary config); anything else calls `target`
    ("package.module:function", imported only then) with the project settings
    (`deformnet.project.apply`) in front of the command line's overrides; a settings file that
    cannot be used is one logged line and exit status 2, Ctrl-C before the app's own handler
    (`deformnet.apprun`) runs one line and exit status 130."""

    def main() -> None:
        if sys.argv[1:] in (["--help"], ["-h"]):
            page = help_page(config_name)
            if page is not None:
                print(page)
                return
        script = project.script_of(config_name)
        try:
            if script is not None:  # one of ours (pyproject.toml): the project settings
                sys.argv = project.apply(script, sys.argv)
            module, func = target.split(":")
            getattr(importlib.import_module(module), func)()
        except project.SettingsError as exc:
            log.error("%s", exc)
            raise SystemExit(2) from None
        except KeyboardInterrupt:  # Ctrl-C while importing or composing (the app's own
            # handler, deformnet.apprun, says it once the run started)
            log.error("interrupted (Ctrl-C) before the run started; exit status 130")
            raise SystemExit(130) from None

    main.__doc__ = f"Console script: {target} (bare --help: conf/hydra/help/{config_name}.yaml)."
    return main
