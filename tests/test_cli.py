"""The console scripts as a user runs them: exit codes, one-line errors without a traceback,
outputs only in output.dir (Hydra's files too), nothing in the working directory.

The processes start together (each spends most of its time importing torch)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from deformnet.paths import shared_dir

BIN = Path(sys.executable).parent
SLEAP_MOUSE = shared_dir() / "data" / "real-mouse-sleap-4cam"


def _start(cwd: Path, app: str, *args: str) -> subprocess.Popen:
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    return subprocess.Popen(
        [str(BIN / app), *args],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )


def test_console_scripts(tmp_path):
    assert SLEAP_MOUSE.is_dir(), f"shared data missing: {SLEAP_MOUSE}"
    cal, det = SLEAP_MOUSE / "calibration.toml", SLEAP_MOUSE
    sleap = [f"input.calibration={cal}", f"input.detections={det}", "input.pattern=*.analysis.h5"]
    (tmp_path / "afile").write_text("x")
    cwd = tmp_path / "lab"
    cwd.mkdir()
    good = tmp_path / "good"
    cases = {
        # name: (app, args, expected exit code, text the one error line must hold)
        "ok": ("adjust-triangulate", [*sleap, "input.likelihood_threshold=0", f"output.dir={good}"],
               0, None),
        "out_is_file": ("adjust-triangulate", [*sleap, f"output.dir={tmp_path / 'afile'}"], 2,
                        "is a file, not a folder"),
        "track_setting": ("adjust-track", [*sleap, "body=auto", "solver.max_iterations=2.5",
                          f"output.dir={tmp_path / 'o1'}"], 2,
                          "solver.max_iterations=2.5 is not valid"),
    }  # fmt: skip
    procs = {k: _start(cwd, app, *args) for k, (app, args, _, _) in cases.items()}
    outs = {k: p.communicate(timeout=300)[0] for k, p in procs.items()}
    for k, (_, _, code, text) in cases.items():
        out = outs[k]
        assert procs[k].returncode == code, (k, out[-2000:])
        assert "Traceback" not in out, (k, out[-2000:])
        if text is not None:
            errors = [ln for ln in out.splitlines() if "[ERROR]" in ln]
            assert len(errors) == 1 and text in errors[0], (k, errors)
            assert not list(tmp_path.glob("o*/points3d.csv"))
    assert not list(cwd.iterdir())  # nothing in the working directory (no runs/)
    # the good run: outputs and Hydra's own files in output.dir; side excluded, in the summary
    assert (good / "points3d.csv").is_file() and (good / ".hydra" / "config.yaml").is_file()
    summary = json.loads((good / "summary.json").read_text())
    assert summary["cameras"] == ["back", "mid", "top"]
    assert list(summary["camera_check"]["excluded"]) == ["side"]
    assert summary["camera_check"]["excluded"]["side"]["cause"] == "wrong pose"
    assert summary["reprojection_error_px"]["median"] < 5.0  # measured 3.1 px
    import hashlib

    digest = hashlib.sha256((good / "points3d.csv").read_bytes()).hexdigest()
    assert summary["outputs"]["points3d_sha256"] == digest
    assert not [f for f in good.iterdir() if f.name.startswith(".") and f.name != ".hydra"]
