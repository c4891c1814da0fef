"""A non-editable install ships the Hydra configs (conf/ as the package mousetrack_conf)."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

from deformnet.paths import CONF_DIR

ROOT = CONF_DIR.parent


def test_wheel_ships_every_config(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            str(ROOT),
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    (whl,) = tmp_path.glob("mousetrack-*.whl")
    names = set(zipfile.ZipFile(whl).namelist())
    want = {
        "mousetrack_conf/" + str(p.relative_to(CONF_DIR)).replace(os.sep, "/")
        for p in CONF_DIR.rglob("*.yaml")
    }
    assert want and want <= names, sorted(want - names)
    assert "adjust/apps/track.py" in names and "deformnet/paths.py" in names
    # installed without the checkout, the apps find their configs in the package
    target = tmp_path / "site"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--no-deps",
            "-q",
            "--target",
            str(target),
            str(whl),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    env = {**os.environ, "PYTHONPATH": str(target)}
    out = subprocess.run(
        [sys.executable, "-c", "import deformnet.paths as p; print(p.CONF_DIR)"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=120,
    )
    assert Path(out.stdout.strip()) == target / "mousetrack_conf", out.stderr
