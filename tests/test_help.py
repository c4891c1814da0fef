"""Every app's `--help` (as a new user runs it, a subprocess): what the app does first, its
required arguments, an example, and only the config groups it uses, with their real options
(conf/hydra/help/<app>.yaml, selected in each app's primary config)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from deformnet.paths import CONF_DIR, REPO_DIR

#: console script -> its primary config (conf/<name>.yaml)
APPS = {
    "deformnet-simulate": "simulate",
    "deformnet-train": "train",
    "adjust-simulate": "scene",
    "adjust-triangulate": "triangulate",
    "adjust-track": "track",
    "adjust-calibrate": "calibrate",
    "adjust-export": "export",
    "adjust-events": "events",
    "deformnet-classify": "classify",
    "adjust-plot": "plot",
    "adjust-demo": "demo",
}


def _script(name: str) -> str:
    for folder in (REPO_DIR / ".venv" / "bin", Path(sys.executable).parent):
        if (folder / name).exists():
            return str(folder / name)
    raise AssertionError(f"console script {name} is not installed (pip install -e .)")


@pytest.fixture(scope="module")
def helps() -> dict[str, subprocess.CompletedProcess]:
    """All the apps' --help, run side by side."""
    procs = {
        app: subprocess.Popen(
            [_script(app), "--help"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for app in APPS
    }
    out = {}
    for app, p in procs.items():
        stdout, stderr = p.communicate(timeout=120)
        out[app] = subprocess.CompletedProcess(p.args, p.returncode, stdout, stderr)
    return out


def test_every_console_script_has_a_help_page():
    import tomllib

    scripts = tomllib.loads((REPO_DIR / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == set(APPS)
    for name in APPS.values():
        assert (CONF_DIR / "hydra" / "help" / f"{name}.yaml").is_file()


def _required(node, prefix: str = "") -> list[str]:
    """Keys whose value is ``???`` (mandatory), dotted."""
    keys = []
    for k, v in node.items():
        if k in ("hydra", "defaults"):
            continue
        if v == "???":
            keys.append(prefix + str(k))
        elif isinstance(v, dict):
            keys += _required(v, f"{prefix}{k}.")
    return keys


def _groups(name: str) -> dict[str, set[str]]:
    """The config groups conf/<name>.yaml's defaults list uses -> the options in conf/."""
    cfg = OmegaConf.load(CONF_DIR / f"{name}.yaml")
    groups = {}
    for entry in cfg.get("defaults") or []:
        if isinstance(entry, str):
            continue
        (key,) = list(entry.keys())
        if key.startswith("override"):
            continue
        groups[key] = {p.stem for p in (CONF_DIR / key).glob("*.yaml")}
    return groups


@pytest.mark.parametrize("app", list(APPS))
def test_help_says_what_needs_and_uses(app, helps):
    res = helps[app]
    assert res.returncode == 0, res.stderr
    text = res.stdout
    first = text.strip().splitlines()[0]
    assert first.startswith(f"{app}:") or first.startswith(f"{app} ("), first
    assert len(text.splitlines()) < 45  # a page, not a dump of the whole config
    assert "Required arguments:" in text
    name = APPS[app]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose(name)  # with the groups' files (conf/input/default.yaml's input.*)
    required = _required(OmegaConf.to_container(cfg, resolve=False))
    for key in required:
        assert f"{key}=" in text, f"{app} --help does not name its required {key}"
    if not required and app not in ("deformnet-classify",):
        assert "Required arguments: none" in text or "Required arguments:\n" in text
    assert "Example" in text and f"\n  {app} " in text  # an example command line
    # the groups: exactly those of the app's defaults list, each with its real options
    section = text.split("Config groups", 1)[1]
    listed = dict(re.findall(r"^ {2}([a-z_]+)=([\w|]+)\s", section, re.M))
    groups = _groups(name)
    assert set(listed) == set(groups), (app, listed, groups)
    for g, options in listed.items():
        assert set(options.split("|")) == groups[g], (app, g)
    if not groups:
        assert "Config groups: none" in text
    # not the default template: no list of every group in conf/, no config dump
    assert "== Config ==" not in text and "Powered by Hydra" not in text


def test_readme_lists_the_config_groups_as_they_are():
    """README's "Configuration groups" table: every group in conf/ with its real options."""
    text = (REPO_DIR / "README.md").read_text()
    section = text.split("## Configuration groups", 1)[1].split("\n## ", 1)[0]
    rows = dict(re.findall(r"^\| `([a-z_/]+)` \| ([\w, ]+) \|", section, re.M))
    groups = {  # nested groups too (solver/constraint, ...)
        p.relative_to(CONF_DIR).as_posix(): {f.stem for f in p.glob("*.yaml")}
        for p in CONF_DIR.rglob("*")
        if p.is_dir() and p.relative_to(CONF_DIR).parts[0] != "hydra"
    }
    assert set(rows) == set(groups) | {"hydra/launcher"}
    for g, options in groups.items():
        assert {o.strip() for o in rows[g].split(",")} == options, g
    # joblib comes with hydra-joblib-launcher; slurm is ours
    launchers = {f.stem for f in (CONF_DIR / "hydra" / "launcher").glob("*.yaml")} | {"joblib"}
    assert {o.strip() for o in rows["hydra/launcher"].split(",")} == launchers


def _hydra_help(app: str) -> subprocess.Popen:
    """The app's help page as Hydra itself makes it (the app's module, not the console
    script's quick path)."""
    import tomllib

    scripts = tomllib.loads((REPO_DIR / "pyproject.toml").read_text())["project"]["scripts"]
    module = {
        "adjust-track": "adjust.apps.track",
        "deformnet-classify": "deformnet.apps.classify",
        "adjust-events": "adjust.apps.events",
    }[app]
    assert scripts[app].split(":")[0] in ("adjust.entry", "deformnet.entry")
    code = f"import sys; sys.argv = [{app!r}, '--help']; from {module} import main; main()"
    return subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def test_quick_help_is_hydras_page_without_importing_torch(helps):
    """A bare --help is printed without composing the config or importing torch, and is the
    very page Hydra prints (one app of each kind of entry point)."""
    procs = {
        app: _hydra_help(app) for app in ("adjust-track", "deformnet-classify", "adjust-events")
    }
    for app, p in procs.items():
        stdout, stderr = p.communicate(timeout=120)
        assert p.returncode == 0, stderr
        assert helps[app].stdout == stdout, app
    code = (
        "import sys; sys.argv = ['adjust-track', '-h']; from adjust.entry import track; "
        "track(); assert 'torch' not in sys.modules and 'hydra' not in sys.modules"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("adjust-track:")


def test_console_script_falls_through_to_the_app(tmp_path, monkeypatch, capsys):
    """Anything but a bare --help, or a page that substitutes Hydra's variables, goes to the
    app's entry point."""
    import deformnet.paths
    from deformnet.quickhelp import console_script, help_page

    (tmp_path / "hydra" / "help").mkdir(parents=True)
    (tmp_path / "hydra" / "help" / "plain.yaml").write_text("template: |\n  plain: a page\n")
    (tmp_path / "hydra" / "help" / "subst.yaml").write_text("template: |\n  $APP_CONFIG_GROUPS\n")
    monkeypatch.setattr(deformnet.paths, "CONF_DIR", tmp_path)
    assert help_page("plain") == "plain: a page\n"
    assert help_page("subst") is None
    calls = []
    monkeypatch.setattr(sys.modules[__name__], "_app", lambda: calls.append(list(sys.argv)),
                        raising=False)  # fmt: skip
    for name, argv, called in [
        ("plain", ["x", "--help"], False),
        ("plain", ["x", "-h"], False),
        ("plain", ["x", "--help", "body=mouse"], True),
        ("plain", ["x", "seed=1"], True),
        ("subst", ["x", "--help"], True),
    ]:
        monkeypatch.setattr(sys, "argv", argv)
        calls.clear()
        console_script(name, f"{__name__}:_app")()
        assert bool(calls) == called, (name, argv)
        out = capsys.readouterr().out
        assert (out == "plain: a page\n\n") == (not called), (name, argv, out)
