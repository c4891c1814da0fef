"""Per-project settings: ``mousetrack.yaml``, read by every console script.

A lab keeps the overrides it repeats on every command line in one file, a YAML mapping from
``all`` (every app) or a console script's name (``adjust-track``, ``deformnet-train``, ...) to a
list of Hydra overrides::

    all:                              # every app that has the key
      - input.likelihood_threshold=0.6
      - input.pattern='*.analysis.h5'
    adjust-track:
      - body=auto
      - deformation=interp

The file used is the first of: the file (or folder holding ``mousetrack.yaml``) named by the
environment variable ``MOUSETRACK_CONFIG``; ``mousetrack.yaml`` in the session folder given on
the command line (``input.session=DIR``; not for a batch's list or glob); ``mousetrack.yaml`` in
the working directory. Its overrides go in front of the command line's (`apply`), so they are
merged after the app's defaults and the command line wins; ``all`` first, then the app's own.
An ``all`` override whose key (or config group) the app's composed config does not have is
skipped for that app (logged at DEBUG); an app's own overrides must all apply. A file that is
not such a mapping, an unknown section, an item that is not an override or overrides that do
not compose are a `SettingsError` naming the file (the console scripts: one line, exit 2).

The console scripts (`deformnet.quickhelp.console_script`) call `apply` before the app parses
its command line; the app logs which file it used and what it added (`announce`), and Hydra
records the overrides in the run's ``.hydra/overrides.yaml``. Hydra is imported only when a
file is found (a bare ``--help`` stays fast).
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import yaml

from deformnet.paths import CONF_DIR

log = logging.getLogger(__name__)

FILE_NAME = "mousetrack.yaml"
ENV = "MOUSETRACK_CONFIG"
ALL = "all"
#: console script -> its primary config (conf/<name>.yaml); pyproject.toml's [project.scripts]
SCRIPTS = {
    "adjust-simulate": "scene",
    "adjust-triangulate": "triangulate",
    "adjust-track": "track",
    "adjust-calibrate": "calibrate",
    "adjust-events": "events",
    "adjust-export": "export",
    "adjust-demo": "demo",
    "adjust-plot": "plot",
    "deformnet-simulate": "simulate",
    "deformnet-train": "train",
    "deformnet-classify": "classify",
}
_SESSION_KEY = "input.session"

#: what `apply` added in this process, for `announce`: {"file", "overrides", "skipped", "script"}
_applied: dict | None = None


class SettingsError(ValueError):
    """A per-project settings file that cannot be used (the message names the file)."""


def script_of(config_name: str) -> str | None:
    """The console script whose primary config is conf/<config_name>.yaml (None: none)."""
    return next((script for script, name in SCRIPTS.items() if name == config_name), None)


# ---------------------------------------------------------------------------------------------
# finding and reading the file
# ---------------------------------------------------------------------------------------------
def _session_dir(overrides: Sequence[str]) -> Path | None:
    """The folder of the last plain ``input.session=DIR`` override (None for a batch's list or
    glob, or when there is none)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = None
    found = None
    for arg in overrides:
        if arg.split("=", 1)[0].lstrip("+~") != _SESSION_KEY or "=" not in arg:
            continue
        parser = parser or OverridesParser.create()
        try:
            o = parser.parse_override(arg)
        except Exception:  # noqa: BLE001 - Hydra reports a bad override itself
            continue
        value = None if o.is_sweep_override() else o.value()
        found = Path(value) if isinstance(value, str) and value else None
    return found


def find_file(
    overrides: Sequence[str] = (),
    cwd: str | os.PathLike | None = None,
    environ: Mapping[str, str] | None = None,
) -> Path | None:
    """The settings file of a run: ``$MOUSETRACK_CONFIG`` (a file, or a folder holding
    ``mousetrack.yaml``; one that does not exist is a SettingsError), else the session folder's
    ``mousetrack.yaml`` (``input.session=DIR`` among `overrides`), else the working directory's;
    None when there is none."""
    environ = os.environ if environ is None else environ
    given = environ.get(ENV, "")
    if given:
        p = Path(given).expanduser()
        if p.is_dir():
            p = p / FILE_NAME
        if not p.is_file():
            raise SettingsError(f"{ENV}={given}: no such settings file ({p})")
        return p
    session = _session_dir(overrides) if any(_SESSION_KEY in a for a in overrides) else None
    if session is not None and (session / FILE_NAME).is_file():
        return session / FILE_NAME
    here = Path(cwd) if cwd is not None else Path.cwd()
    return here / FILE_NAME if (here / FILE_NAME).is_file() else None


def read_file(path: str | os.PathLike) -> dict[str, list[str]]:
    """The file's sections: {"all" or a console script: [override, ...]}, or a SettingsError
    naming the file (not YAML, not a mapping, an unknown section, an item that is not a
    ``key=value`` override)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        at = f" (line {where.line + 1}, column {where.column + 1})" if where else ""
        what = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise SettingsError(f"{path}: not valid YAML{at}: {what}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SettingsError(f"{path}: cannot read the settings file: {exc}") from None
    if data is None:
        return {}
    known = [ALL, *SCRIPTS]
    if not isinstance(data, dict):
        raise SettingsError(
            f"{path}: expected a mapping of {', '.join(known)} to lists of overrides, "
            f"got {type(data).__name__}"
        )
    parser = OverridesParser.create()
    out: dict[str, list[str]] = {}
    for section, items in data.items():
        if section not in known:
            raise SettingsError(
                f"{path}: unknown section {section!r} (expected {ALL} or a console script: "
                f"{', '.join(SCRIPTS)})"
            )
        if items is None:
            continue
        if isinstance(items, str) or not isinstance(items, list):
            raise SettingsError(
                f"{path}: {section}: expected a list of overrides (- key=value), "
                f"got {type(items).__name__}"
            )
        for item in items:
            if not isinstance(item, str) or not ("=" in item or item.startswith("~")):
                hint = " (write `- key=value`, not `- key: value`)" * isinstance(item, dict)
                raise SettingsError(f"{path}: {section}: {item!r} is not an override{hint}")
            try:
                parser.parse_override(item)
            except Exception as exc:  # noqa: BLE001 - Hydra's parser errors
                first = str(exc).strip().splitlines()[0] if str(exc).strip() else exc
                raise SettingsError(f"{path}: {section}: {item!r}: {first}") from None
        out[str(section)] = [str(i) for i in items]
    return out


# ---------------------------------------------------------------------------------------------
# which overrides apply to an app
# ---------------------------------------------------------------------------------------------
def _has_key(cfg, dotted: str) -> bool:
    """Whether the composed config has the (dotted) key, missing values (???) included."""
    from omegaconf import DictConfig

    node = cfg
    for seg in dotted.split("."):
        if not isinstance(node, DictConfig) or seg not in node.keys():
            return False
        node = node._get_node(seg)
    return True


def _compose(config_name: str, overrides: list[str], config_dir: str | None):
    """The app's config composed with `overrides` (Hydra's compose API, the app's config
    search path; a Hydra already initialized in this process is left as it was)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.initialize import get_gh_backup, restore_gh_from_backup

    extra = [f"hydra.searchpath=[file://{Path(config_dir).resolve()}]"] if config_dir else []
    plain = [o for o in overrides if not _is_sweep(o)]  # a sweep (`-m`) does not compose
    backup = get_gh_backup()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
            return compose(config_name, overrides=[*extra, *plain], return_hydra_config=True)
    finally:
        restore_gh_from_backup(backup)


def _is_sweep(override: str) -> bool:
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return OverridesParser.create().parse_override(override).is_sweep_override()


def _applies(cfg, override: str) -> bool:
    """Whether an ``all`` override applies to the app of the composed config `cfg`: its key
    (or config group) is there; ``+key`` only where the key is not, ``++key`` always."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    o = OverridesParser.create().parse_override(override)
    if o.is_force_add():
        return True
    group = o.key_or_group
    choices = cfg.hydra.runtime.choices if _has_key(cfg, "hydra.runtime.choices") else {}
    present = group in choices or _has_key(cfg, group.replace("/", "."))
    return not present if o.is_add() else present


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def select(
    path: str | os.PathLike,
    script: str,
    sections: Mapping[str, Sequence[str]],
    config_dir: str | None = None,
    config_name: str | None = None,
) -> tuple[list[str], list[str]]:
    """(the overrides for `script`, the ``all`` overrides skipped for it): ``all``'s that the
    app's config has, then the app's own; a SettingsError naming the file when they do not
    compose (config_dir, config_name: the command line's ``--config-dir`` / ``--config-name``).
    """
    name = config_name or SCRIPTS[script]
    own = list(sections.get(script) or [])
    common = list(sections.get(ALL) or [])
    if not own and not common:
        return [], []
    try:
        base = _compose(name, own, config_dir)
    except Exception as exc:  # noqa: BLE001 - Hydra's composition errors, one line
        raise SettingsError(f"{path}: {script}: {_first_line(exc)}") from None
    kept = [o for o in common if _applies(base, o)]
    skipped = [o for o in common if o not in kept]
    chosen = [*kept, *own]
    if kept:
        try:
            _compose(name, chosen, config_dir)
        except Exception as exc:  # noqa: BLE001
            raise SettingsError(f"{path}: {ALL}: {_first_line(exc)}") from None
    return chosen, skipped


# ---------------------------------------------------------------------------------------------
# the command line
# ---------------------------------------------------------------------------------------------
def _parse(args: list[str]):
    """Hydra's own parse of a command line (None when it does not parse: Hydra says why)."""
    from hydra._internal.utils import get_args_parser

    parser = get_args_parser()
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            return parser.parse_args(args)
    except SystemExit:
        return None


def insert_overrides(argv: list[str], extra: list[str]) -> list[str]:
    """`argv` with `extra` overrides in front of its own (Hydra's parser takes the overrides as
    one run of words: they go just before the command line's first override, or after the
    program name when it has none)."""
    if not extra:
        return list(argv)
    args = list(argv[1:])
    parsed = _parse(args)
    if parsed is None:
        return list(argv)
    given = list(parsed.overrides)
    n = len(given)
    positions = [i for i in range(len(args) + 1) if args[i : i + n] == given] if n else [0]
    positions += [len(args)]
    want = {**vars(parsed), "overrides": [*extra, *given]}
    for i in positions:
        new = [*args[:i], *extra, *args[i:]]
        again = _parse(new)
        if again is not None and vars(again) == want:
            return [argv[0], *new]
    raise SettingsError(f"cannot add the project settings to the command line {args}")


def apply(script: str, argv: Sequence[str], environ: Mapping[str, str] | None = None) -> list[str]:
    """The console script's command line with the project settings in front of its overrides
    (unchanged when there is no settings file); remembers what it added for `announce`."""
    global _applied
    argv = list(argv)
    parsed = _parse(argv[1:])
    given = list(parsed.overrides) if parsed is not None else []
    path = find_file(given, environ=environ)
    if path is None:
        return argv
    sections = read_file(path)
    chosen, skipped = select(
        path,
        script,
        sections,
        config_dir=getattr(parsed, "config_dir", None),
        config_name=getattr(parsed, "config_name", None),
    )
    _applied = {"file": str(path), "script": script, "overrides": chosen, "skipped": skipped}
    return insert_overrides(argv, chosen)


def announce() -> dict | None:
    """Log (INFO, once) which settings file the console script used and the overrides it added
    (the ``all`` ones the app lacks at DEBUG); returns that record (None when none was used)."""
    global _applied
    done, _applied = _applied, None
    if done is None:
        return None
    added = " ".join(done["overrides"]) or "nothing"
    log.info("project settings %s: added %s", done["file"], added)
    if done["skipped"]:
        log.debug(
            "project settings %s: %s lacks %s (skipped)",
            done["file"],
            done["script"],
            " ".join(done["skipped"]),
        )
    return done
