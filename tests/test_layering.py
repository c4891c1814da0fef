"""The layering contract (run by `make lint` and `make test`).

- `deformnet` never imports `adjust` (not at the top of a module, not inside a function, not by
  ``importlib.import_module``): the learning half stands alone; `adjust` may import `deformnet`.
- The library never imports an app: no module of `adjust` outside `adjust/apps/` (one module
  per console script) imports `adjust.apps`, and `adjust/entry.py` names only app modules;
  `adjust/io` imports no behavior code.
- At most 40 function-local imports of adjust / deformnet, each with its reason in a comment.
- Every module of `adjust` and of `deformnet.sim` imports without Lightning (only training,
  `deformnet.lit` / `deformnet.train` / ..., needs it), and so do the `deformnet` modules that
  `adjust-track` loads at run time outside training (`RUNTIME`).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIGHTNING = ("lightning", "pytorch_lightning", "lightning_fabric")
RUNTIME = [
    "deformnet.deformation",
    "deformnet.pretrained",
    "deformnet.sessions",
    "deformnet.windows",
    "deformnet.heldout",
]


def _imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in a file, wherever it stands."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module))
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute | ast.Name)
            and getattr(node.func, "attr", getattr(node.func, "id", "")) == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            out.append((node.lineno, node.args[0].value))
    return out


def _imports_where(files: list[Path], wanted) -> list[str]:
    """``path:line imports module`` for each import in `files` whose module is `wanted`."""
    return [
        f"{p.relative_to(ROOT)}:{line} imports {mod}"
        for p in files
        for line, mod in _imported_modules(p)
        if wanted(mod)
    ]


def test_deformnet_never_imports_adjust():
    files = sorted((ROOT / "deformnet").rglob("*.py"))
    assert files
    bad = _imports_where(files, lambda mod: mod == "adjust" or mod.startswith("adjust."))
    assert not bad, "deformnet must never import adjust:\n" + "\n".join(bad)


def test_the_library_never_imports_an_app():
    apps = ROOT / "adjust" / "apps"
    files = [p for p in sorted((ROOT / "adjust").rglob("*.py")) if apps not in p.parents]
    assert len(files) > 20 and (apps / "track.py").is_file()
    bad = _imports_where(files, lambda mod: mod == "adjust.apps" or mod.startswith("adjust.apps."))
    assert not bad, "the library (adjust outside adjust/apps) must not import an app:\n" + (
        "\n".join(bad)
    )


def test_deformnet_never_imports_its_apps():
    """deformnet/apps/ holds one thin module per console script; no other deformnet module
    imports one (the library never imports an app)."""
    apps = ROOT / "deformnet" / "apps"
    files = [p for p in sorted((ROOT / "deformnet").rglob("*.py")) if apps not in p.parents]
    assert len(files) > 20 and (apps / "classify.py").is_file()
    bad = _imports_where(
        files, lambda mod: mod == "deformnet.apps" or mod.startswith("deformnet.apps.")
    )
    assert not bad, "the library (deformnet outside deformnet/apps) must not import an app:\n" + (
        "\n".join(bad)
    )
    import re

    targets = re.findall(
        r'console_script\("\w+", "([\w.]+):main"\)',
        (ROOT / "deformnet" / "entry.py").read_text(encoding="utf-8"),
    )
    assert len(targets) == 3 and all(t.startswith("deformnet.apps.") for t in targets), targets


BEHAVIOR = ("deformnet.behavior", "deformnet.classify", "deformnet.heads", "deformnet.pseudo",
            "deformnet.sequence")  # fmt: skip


def test_the_readers_never_import_behavior_code():
    """adjust/io (the files' readers and writers) uses no behavior module (it took the frame
    rate check from deformnet.behavior_labels; now deformnet.confutil.check_fps)."""
    files = sorted((ROOT / "adjust" / "io").rglob("*.py"))
    assert files
    bad = _imports_where(files, lambda mod: mod.startswith(BEHAVIOR))
    assert not bad, "adjust/io must not import behavior code:\n" + "\n".join(bad)


def test_the_windows_never_import_the_simulator():
    """deformnet.windows (the masked windows adjust-track checks a net on) and the other modules
    adjust-track loads at run time import no simulator: simulated training sequences are
    deformnet.data's (`simulate_sequences`, `load_sequences`)."""
    files = [ROOT / (m.replace(".", "/") + ".py") for m in RUNTIME]
    files = [p if p.is_file() else p.with_suffix("") / "__init__.py" for p in files]
    assert all(p.is_file() for p in files), files
    bad = _imports_where(
        files, lambda mod: mod == "deformnet.sim" or mod.startswith("deformnet.sim.")
    )
    assert not bad, "the run-time modules must not import the simulator:\n" + "\n".join(bad)


def test_the_deformation_nets_never_import_behavior_code():
    """The deformation side of deformnet (outside deformnet/behavior/ and the apps; e.g.
    deformnet.lit, which once imported the behavior heads) uses no behavior module."""
    skip = (ROOT / "deformnet" / "behavior", ROOT / "deformnet" / "apps")
    files = [
        p
        for p in sorted((ROOT / "deformnet").rglob("*.py"))
        if not any(s in p.parents for s in skip) and p.name != "entry.py"
    ]
    assert (ROOT / "deformnet" / "lit.py") in files
    bad = _imports_where(files, lambda mod: mod.startswith(BEHAVIOR))
    assert not bad, "deformation code must not import behavior code:\n" + "\n".join(bad)


def test_every_console_script_is_an_app_module():
    """pyproject's adjust-* scripts go through adjust/entry.py to a module of adjust/apps/."""
    import re

    targets = re.findall(
        r'console_script\("\w+", "([\w.]+):main"\)',
        (ROOT / "adjust" / "entry.py").read_text(encoding="utf-8"),
    )
    assert len(targets) >= 8
    for t in targets:
        assert t.startswith("adjust.apps."), t
        assert (ROOT / (t.replace(".", "/") + ".py")).is_file(), t


def test_the_scan_sees_every_kind_of_import(tmp_path):
    f = tmp_path / "m.py"
    f.write_text(
        "import adjust.camera\nfrom adjust import io\n"
        "def g():\n    from adjust.lsq import lm\n    importlib.import_module('adjust.track')\n"
        "from . import sibling\n"
    )
    assert [m for _, m in _imported_modules(f)] == [
        "adjust.camera",
        "adjust",
        "adjust.lsq",
        "adjust.track",
    ]


#: the most function-local imports of adjust / deformnet in the two packages (issue 50)
MAX_LOCAL_IMPORTS = 40


def _local_first_party_imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import of adjust or deformnet (or a relative one) that stands
    inside a function body of the file."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    out = set()
    for fn in ast.walk(tree):
        if not isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        for node in ast.walk(fn):
            if isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                mods = [node.module or ""] if node.level == 0 else ["."]
            else:
                continue
            out |= {(node.lineno, m) for m in mods if m == "." or m.split(".")[0] in FIRST_PARTY}
    return sorted(out)


FIRST_PARTY = ("adjust", "deformnet")


def test_function_local_first_party_imports_are_few_and_give_their_reason():
    """At most `MAX_LOCAL_IMPORTS` imports of adjust / deformnet inside functions (they hid
    import circles: 150 before issue 50), each with a comment on its line or the line above
    saying why it is not at the top (Lightning or torch kept off a light path, an optional
    package)."""
    found, silent = [], []
    for pkg in FIRST_PARTY:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            lines = p.read_text(encoding="utf-8").splitlines()
            for line, mod in _local_first_party_imports(p):
                where = f"{p.relative_to(ROOT)}:{line} imports {mod}"
                found.append(where)
                if "#" not in lines[line - 1] and not lines[line - 2].strip().startswith("#"):
                    silent.append(where)
    assert len(found) <= MAX_LOCAL_IMPORTS, "\n".join(found)
    assert not silent, "function-local imports without a reason:\n" + "\n".join(silent)


def test_the_local_import_count_sees_nested_and_relative_imports(tmp_path):
    f = tmp_path / "m.py"
    f.write_text(
        "import adjust.camera\n"
        "def g():\n    import numpy\n    from deformnet import body\n"
        "    def h():\n        from . import sibling\n        import adjust.lsq\n"
    )
    assert _local_first_party_imports(f) == [(4, "deformnet"), (6, "."), (7, "adjust.lsq")]


_IMPORT_ALL = f"""
import importlib, pkgutil, sys

class _NoLightning:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {LIGHTNING!r}:
            raise ImportError("lightning is blocked: " + name)
        return None

sys.meta_path.insert(0, _NoLightning())
import adjust, deformnet.sim
failed = []
names = [
    info.name
    for pkg in (adjust, deformnet.sim)
    for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + ".")
]
# what adjust-track loads at run time (a net, its held-out check on the session's tokens)
names += {RUNTIME!r}
for name in names:
    try:
        importlib.import_module(name)
    except ImportError as exc:
        failed.append(name + ": " + str(exc))
loaded = sorted(m for m in sys.modules if m.split(".")[0] in {LIGHTNING!r})
print("\\n".join(failed + loaded))
sys.exit(1 if failed or loaded else 0)
"""


def test_adjust_and_sim_import_without_lightning():
    proc = subprocess.run(
        [sys.executable, "-c", _IMPORT_ALL],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, (
        "these need Lightning (adjust and deformnet.sim must not):\n"
        + proc.stdout[-3000:]
        + proc.stderr[-3000:]
    )
