"""Per-project settings (`deformnet.project`): a ``mousetrack.yaml`` in the working directory,
the session folder or named by ``MOUSETRACK_CONFIG`` adds its overrides in front of every
console script's command line (the command line wins); a malformed file is one error, exit 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import hydra
import pytest
from hydra._internal.utils import get_args_parser

from deformnet import project
from deformnet.paths import CONF_DIR, REPO_DIR

BIN = Path(sys.executable).parent
SETTINGS = """\
all:
  - input.likelihood_threshold=0.6
  - input.pattern='*.analysis.h5'
  - threads=2
  - +lab=ours
adjust-track:
  - body=auto
  - deformation=rigid
adjust-simulate:
  - seed=5
"""


def _composed(script: str, argv: list[str]):
    """The config the app composes from a command line (Hydra's parser, then its compose API)."""
    args = get_args_parser().parse_args(argv[1:])
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose(project.SCRIPTS[script], overrides=args.overrides)


def _run(cwd: Path, app: str, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items() if k != project.ENV}
    return subprocess.run(
        [str(BIN / app), *args],
        cwd=cwd,
        env={**base, "HYDRA_FULL_ERROR": "0", **(env or {})},
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.fixture
def lab(tmp_path, monkeypatch):
    """A project folder with mousetrack.yaml as the working directory."""
    monkeypatch.delenv(project.ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    (tmp_path / project.FILE_NAME).write_text(SETTINGS)
    return tmp_path


def test_every_console_script_is_known():
    scripts = tomllib.loads((REPO_DIR / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == set(project.SCRIPTS)
    for script, config in project.SCRIPTS.items():
        assert (CONF_DIR / f"{config}.yaml").is_file()
        assert project.script_of(config) == script
    assert project.script_of("no_such_app") is None


def test_file_in_the_working_directory_sets_and_the_command_line_wins(lab):
    argv = project.apply("adjust-track", ["adjust-track", "input.likelihood_threshold=0.7"])
    cfg = _composed("adjust-track", argv)
    assert cfg.input.pattern == "*.analysis.h5" and cfg.threads == 2  # from the file
    assert cfg.deformation == "rigid"  # the app's own section
    assert cfg.input.likelihood_threshold == 0.7  # the command line wins
    assert cfg.lab == "ours"  # +key: added where the app lacks it
    done = project.announce()
    assert done["file"] == str(lab / project.FILE_NAME)
    assert done["overrides"][-2:] == ["body=auto", "deformation=rigid"]
    assert project.announce() is None  # logged once
    # a group choice from the file, and the command line choosing another
    args = get_args_parser().parse_args(project.apply("adjust-track", ["t", "body=mouse"])[1:])
    assert args.overrides.index("body=auto") < args.overrides.index("body=mouse")
    # adjust-plot has input.pattern but no threads, body or deformation: those are skipped
    cfg = _composed("adjust-plot", project.apply("adjust-plot", ["adjust-plot"]))
    assert cfg.input.pattern == "*.analysis.h5" and cfg.input.likelihood_threshold == 0.6
    assert "threads" not in cfg and "deformation" not in cfg
    assert project.announce()["skipped"] == ["threads=2"]
    # nothing to add: the command line as given
    (lab / project.FILE_NAME).write_text("adjust-export: [fps=30]\n")
    assert project.apply("adjust-track", ["adjust-track", "a=1"]) == ["adjust-track", "a=1"]


@pytest.mark.parametrize(
    "argv",
    [
        ["p"],
        ["p", "x=1"],
        ["p", "-m", "x=1", "y=2"],
        ["p", "x=1", "-m"],
        ["p", "--cfg", "job", "x=1"],
        ["p", "--cfg", "job"],
        ["p", "--info"],
        ["p", "-cd", "lab/conf", "x=1", "--resolve"],
    ],
)
def test_overrides_go_in_front_of_the_command_lines(argv):
    new = project.insert_overrides(argv, ["a=1", "b='c d'"])
    parser = get_args_parser()
    before, after = vars(parser.parse_args(argv[1:])), vars(parser.parse_args(new[1:]))
    assert after.pop("overrides") == ["a=1", "b='c d'", *before.pop("overrides")]
    assert after == before  # -m, --cfg, --info, -cd: as given


def test_mousetrack_config_and_the_session_folder(lab, tmp_path_factory, monkeypatch):
    other = tmp_path_factory.mktemp("elsewhere") / "settings.yaml"
    other.write_text("adjust-track: [deformation=interp]\n")
    session = tmp_path_factory.mktemp("session")
    (session / project.FILE_NAME).write_text("adjust-track: [deformation=self]\n")
    here = ["adjust-track", f"input.session={session}"]
    # the session folder's file before the working directory's
    assert _composed("adjust-track", project.apply("adjust-track", here)).deformation == "self"
    # a batch's list of sessions: not a session's own file
    batch = ["adjust-track", "-m", f"input.session={session},{session}_2"]
    assert "deformation=rigid" in project.apply("adjust-track", batch)
    # MOUSETRACK_CONFIG before both: a file, or a folder holding mousetrack.yaml
    monkeypatch.setenv(project.ENV, str(other))
    assert _composed("adjust-track", project.apply("adjust-track", here)).deformation == "interp"
    monkeypatch.setenv(project.ENV, str(session))
    assert project.find_file() == session / project.FILE_NAME
    monkeypatch.setenv(project.ENV, str(other.parent / "nope.yaml"))
    with pytest.raises(project.SettingsError, match="MOUSETRACK_CONFIG=.*nope.yaml"):
        project.apply("adjust-track", here)


@pytest.mark.parametrize(
    "text, message",
    [
        ("all: [a=1\n", "not valid YAML \\(line 2"),
        ("- a=1\n", "expected a mapping"),
        ("adjust-trak: [deformation=rigid]\n", "unknown section 'adjust-trak'"),
        ("adjust-track: deformation=rigid\n", "expected a list of overrides"),
        ("adjust-track:\n  - deformation: rigid\n", "not an override \\(write `- key=value`"),
        ("adjust-track: ['a=[1,2']\n", "'a=\\[1,2'"),
        ("adjust-track: [deformaton=rigid]\n", "adjust-track: Could not override 'deformaton'"),
        ("adjust-track: [body=rat]\n", "adjust-track: .*body"),
    ],
)
def test_a_malformed_file_is_one_error_naming_it(lab, text, message):
    (lab / project.FILE_NAME).write_text(text)
    with pytest.raises(project.SettingsError, match=message) as exc:
        project.apply("adjust-track", ["adjust-track"])
    assert str(exc.value).startswith(str(lab / project.FILE_NAME))


def test_console_scripts_use_it(lab, tmp_path_factory):
    """The console scripts themselves: the settings in a composed config, an app's log line
    and its outputs, a batch (-m), and a malformed file (one line, exit 2, no traceback)."""
    res = _run(lab, "adjust-track", "--cfg", "job", "input.likelihood_threshold=0.7")
    assert res.returncode == 0, res.stderr[-2000:]
    assert "pattern: '*.analysis.h5'" in res.stdout and "likelihood_threshold: 0.7" in res.stdout
    out = tmp_path_factory.mktemp("runs")
    res = _run(lab, "adjust-simulate", "num_frames=60", f"output.dir={out / 'scene'}")
    assert res.returncode == 0, res.stderr[-2000:]
    assert json.loads((out / "scene" / "scene.json").read_text())["seed"] == 5  # from the file
    lines = [ln for ln in res.stdout.splitlines() if "project settings" in ln]
    assert len(lines) == 1 and f"{lab / project.FILE_NAME}: added +lab=ours seed=5" in lines[0]
    # a batch: every session's job gets the file's overrides
    (lab / project.FILE_NAME).write_text(
        "adjust-track: [progress=false, solver.max_iterations=6, input.likelihood_threshold=0.4]"
    )
    res = _run(
        lab, "adjust-track", "-m", f"input.session={out / 'scene'}", f"output.dir={out / 'b'}"
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    job = (out / "b" / "scene" / ".hydra" / "overrides.yaml").read_text()
    assert "input.likelihood_threshold=0.4" in job and "solver.max_iterations=6" in job
    assert (out / "b" / "summary.csv").is_file()
    assert "project settings" in res.stdout
    (lab / project.FILE_NAME).write_text("adjust-plot: {tracks: x.csv}\n")
    res = _run(lab, "adjust-plot", "tracks=t.csv")
    text = res.stdout + res.stderr
    assert res.returncode == 2 and "Traceback" not in text
    assert text.strip().splitlines() == [
        f"{lab / project.FILE_NAME}: adjust-plot: expected a list of overrides (- key=value), "
        "got dict"
    ]
