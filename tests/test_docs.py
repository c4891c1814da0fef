"""The documentation: the README is for users (at most 200 lines, the two set-up commands, links
that resolve), the mkdocs site (mkdocs.yml, docs/) builds with --strict, and every console-script
command line in the fenced code blocks of README.md and docs/ composes with Hydra's compose API
under the app's primary config."""

from __future__ import annotations

import ast
import importlib.util
import os
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Glob

from deformnet.paths import CONF_DIR, REPO_DIR

README = REPO_DIR / "README.md"
DOCS = REPO_DIR / "docs"
MAX_README_LINES = 200

#: Command lines not composed, each with its reason: (substring of the line, reason). Every
#: entry must still match a documented line (test_skip_list_is_in_use).
SKIP = (("--config-dir lab/conf", "the user's own config folder, shown in docs/configuration.md"),)

#: flags that take no part in the composed config (the second value: takes an argument)
IGNORED_FLAGS = {"--help": False, "-h": False, "--hydra-help": False, "--cfg": True, "-c": True}


def _console_scripts() -> dict[str, str]:
    """Console script -> its primary config name, as the code wires them: pyproject.toml's
    [project.scripts] entry points and each entry module's ``console_script("<config>", ...)``."""
    scripts = tomllib.loads((REPO_DIR / "pyproject.toml").read_text())["project"]["scripts"]
    configs: dict[str, dict[str, str]] = {}
    out = {}
    for script, target in scripts.items():
        module, func = target.split(":")
        if module not in configs:
            spec = importlib.util.find_spec(module)
            assert spec is not None and spec.origin, module
            tree = ast.parse(Path(spec.origin).read_text())
            configs[module] = {
                t.id: node.value.args[0].value
                for node in tree.body
                if isinstance(node, ast.Assign)
                and isinstance(node.value, ast.Call)
                and getattr(node.value.func, "id", None) == "console_script"
                for t in node.targets
            }
        out[script] = configs[module][func]
    return out


APPS = _console_scripts()


def _doc_files() -> list[Path]:
    return [README, *sorted(DOCS.rglob("*.md"))]


def _command_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, command) for every console-script line in the file's fenced code blocks
    (python and yaml blocks excluded), continuation lines joined, and the block's own shell
    assignments (``D=...``) substituted."""
    found = []
    lines = path.read_text().splitlines()
    fence = None
    variables: dict[str, str] = {}
    i = 0
    while i < len(lines):
        line = lines[i]
        stripped = line.strip()
        if stripped.startswith("```"):
            fence = None if fence is not None else (stripped[3:].strip() or "text")
            variables = {}
            i += 1
            continue
        if fence is None or fence in ("python", "yaml", "toml"):
            i += 1
            continue
        start = i + 1
        while line.endswith("\\") and i + 1 < len(lines):
            i += 1
            line = line[:-1].rstrip() + " " + lines[i].strip()
        i += 1
        assignment = re.fullmatch(r"([A-Za-z_]\w*)=(\S+)", line.strip())
        if assignment:
            variables[assignment[1]] = assignment[2]
            continue
        for name, value in variables.items():
            line = re.sub(rf"\$(\{{{name}\}}|{name}\b)", value, line)
        words = line.split()
        if words and words[0] in APPS:
            found.append((start, line.strip()))
    return found


def _all_commands() -> list[tuple[str, str]]:
    out = []
    for path in _doc_files():
        for number, line in _command_lines(path):
            out.append((f"{path.relative_to(REPO_DIR)}:{number}", line))
    return out


COMMANDS = _all_commands()


def _skip_reason(line: str) -> str | None:
    return next((reason for text, reason in SKIP if text in line), None)


def _overrides(line: str) -> tuple[str, list[str], bool]:
    """A documented command line -> (config name, overrides, multirun)."""
    words = shlex.split(line, comments=True)
    app, args = words[0], words[1:]
    overrides, multirun = [], False
    k = 0
    while k < len(args):
        arg = args[k]
        k += 1
        if arg == "...":  # "the command above, plus": the listed overrides alone
            continue
        if arg in ("-m", "--multirun"):
            multirun = True
        elif arg in IGNORED_FLAGS:
            k += IGNORED_FLAGS[arg]
        elif "=" in arg:
            overrides.append(arg)
        elif app == "adjust-export" and not overrides and arg.isidentifier():
            overrides.append(f"format={arg}")  # `adjust-export nwb ...`: the first bare word
        else:
            raise AssertionError(f"{line!r}: {arg!r} is neither an override nor a known flag")
    assert "$" not in " ".join(overrides), f"{line!r}: an unresolved shell variable (add to SKIP)"
    if multirun:  # compose one job of the sweep: its first value
        parser = OverridesParser.create()
        one = []
        for text in overrides:
            o = parser.parse_override(text)
            if not o.is_sweep_override():
                one.append(text)
            elif isinstance(o.value(), Glob):  # input.session=glob(...) (adjust.session)
                one.append(f"{o.get_key_element()}={o.value().include[0]}")
            else:
                one.append(f"{o.get_key_element()}={next(o.sweep_string_iterator())}")
        overrides = one
    return APPS[app], overrides, multirun


def test_readme_is_for_users():
    text = README.read_text()
    assert len(text.splitlines()) <= MAX_README_LINES
    assert "make demo" in text and "make test" in text
    assert "torch==2.13.0" in text  # installed first by the Makefile (a bare torch pulls CUDA)
    assert "![key figure](docs/demo_key.png)" in text


def test_readme_links_resolve():
    text = README.read_text()
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    assert targets
    for target in targets:
        if "://" not in target:
            assert (REPO_DIR / target).exists(), target


def test_every_console_script_has_its_page():
    assert len(APPS) == 11
    for script in APPS:
        page = DOCS / "commands" / f"{script}.md"
        assert page.is_file(), f"{script}: no {page.relative_to(REPO_DIR)}"
        assert any(line.split()[0] == script for _, line in _command_lines(page)), script


def test_skip_list_is_in_use():
    for text, _ in SKIP:
        assert any(text in line for _, line in COMMANDS), f"SKIP entry {text!r} matches no line"


def test_commands_were_found():
    readme = [c for c in COMMANDS if c[0].startswith("README.md")]
    assert len(readme) >= 5 and len(COMMANDS) >= 70, (len(readme), len(COMMANDS))
    assert {line.split()[0] for _, line in COMMANDS} == set(APPS)


@pytest.mark.parametrize("where,line", COMMANDS, ids=[f"{w} {c.split()[0]}" for w, c in COMMANDS])
def test_documented_command_composes(where, line):
    reason = _skip_reason(line)
    if reason:
        pytest.skip(reason)
    name, overrides, _ = _overrides(line)
    hydra_keys = any(o.lstrip("+~").startswith("hydra") for o in overrides)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        try:
            cfg = compose(name, overrides=overrides, return_hydra_config=hydra_keys)
        except Exception as e:  # noqa: BLE001 - name the documented line
            raise AssertionError(f"{where}: {line!r} does not compose: {e}") from e
    assert cfg is not None


def test_mkdocs_builds_strictly(tmp_path):
    if importlib.util.find_spec("mkdocs") is None:
        pytest.skip("mkdocs is not installed (pip install -e '.[docs]')")
    site = tmp_path / "site"
    res = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=REPO_DIR,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    assert res.returncode == 0, res.stdout + res.stderr
    assert (site / "index.html").is_file()
    for script in APPS:
        assert (site / "commands" / script / "index.html").is_file(), script
