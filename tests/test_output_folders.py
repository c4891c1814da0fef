"""Whole output folders (issue 46): a lock on output.dir, a run's outputs committed as one set
(a folder holds the previous complete run or the new one, whenever a run is killed), Ctrl-C
exit 130 with the folder whole, and no Hydra run folder in the working directory."""

from __future__ import annotations

import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from adjust.apps.common import OutputBusy, OutputSet, recover_outputs, write_outputs
from deformnet.atomic import file_digest
from deformnet.outputs import (
    JOURNAL_NAME,
    LOCK_NAME,
    STAGING_PREFIX,
    hold_output,
    output_lock,
    release_output,
)

BIN = Path(sys.executable).parent
ENV = {**os.environ, "HYDRA_FULL_ERROR": "0"}


# --- the set ----------------------------------------------------------------------------------


def _whole(folder: Path) -> dict | None:
    """The summary of `folder` when the folder holds one complete set: every file its
    ``outputs.files`` lists present with that sha256 (else None)."""
    try:
        summary = json.loads((folder / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    files = summary["outputs"]["files"]
    for name, facts in files.items():
        p = folder / name
        if not p.is_file() or file_digest(p) != facts["sha256"]:
            return None
    return summary


def _write_set(folder: Path, tag: str, names=("points3d.csv", "accepted.npz")) -> dict:
    with OutputSet(folder) as s:
        for n in names:
            s.path(n).write_text(f"{n} of run {tag}\n")
        return s.commit({"run": tag, "outputs": {}})


def test_a_set_is_committed_whole_and_replaces_the_previous_one(tmp_path):
    first = _write_set(tmp_path, "1", ("points3d.csv", "accepted.npz", "tracks.nwb"))
    assert _whole(tmp_path) == first
    assert sorted(first["outputs"]["files"]) == ["accepted.npz", "points3d.csv", "tracks.nwb"]
    assert first["outputs"]["points3d_sha256"] == file_digest(tmp_path / "points3d.csv")
    _write_set(tmp_path, "2")  # without tracks.nwb: the previous run's one goes
    assert _whole(tmp_path)["run"] == "2"
    assert not (tmp_path / "tracks.nwb").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "accepted.npz",
        "points3d.csv",
        "summary.json",
    ]


def test_a_failed_run_leaves_the_previous_set(tmp_path):
    _write_set(tmp_path, "1")
    for exc in (ValueError("bad input"), KeyboardInterrupt()):
        with pytest.raises(type(exc)), OutputSet(tmp_path) as s:
            s.path("points3d.csv").write_text("half of run 2")
            raise exc
        assert _whole(tmp_path)["run"] == "1"
        assert not list(tmp_path.glob(STAGING_PREFIX + "*"))


@pytest.mark.parametrize("kill_at", range(6))
def test_a_commit_killed_at_any_step_leaves_one_whole_set(tmp_path, monkeypatch, kill_at):
    """A kill at each rename of a commit (0: the staged summary, 1: the journal, the commit
    point, 2-4: the moves into place, 5: none): the folder holds the previous set, or the new
    one once the next OutputSet (or recover_outputs) has completed the moves; never a mix, and
    never a summary beside files it does not describe."""
    import deformnet.outputs as outputs

    _write_set(tmp_path, "1")
    real = os.replace
    done = []

    def replace(src, dst):
        if len(done) == kill_at:
            raise SystemExit(137)  # the process dies here
        done.append(dst)
        real(src, dst)

    monkeypatch.setattr(outputs.os, "replace", replace)
    with pytest.raises(SystemExit) if kill_at < 5 else contextlib.nullcontext():
        with OutputSet(tmp_path) as s:
            for n in ("points3d.csv", "accepted.npz"):
                s.path(n).write_text(f"{n} of run 2\n")
            s.commit({"run": "2", "outputs": {}})
    monkeypatch.setattr(outputs.os, "replace", real)
    if (tmp_path / JOURNAL_NAME).exists():  # killed while moving: no summary until completed
        assert not (tmp_path / "summary.json").exists()
    else:
        assert _whole(tmp_path)["run"] == ("1" if kill_at < 2 else "2")
    assert recover_outputs(tmp_path) == (2 <= kill_at < 5)
    assert _whole(tmp_path)["run"] == ("1" if kill_at < 2 else "2")
    assert not (tmp_path / JOURNAL_NAME).exists()
    assert not list(tmp_path.glob(STAGING_PREFIX + "*"))


def test_a_staging_folder_of_a_dead_run_is_removed(tmp_path):
    _write_set(tmp_path, "1")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()  # fmt: skip
    stale = tmp_path / f"{STAGING_PREFIX}{dead}-x"
    stale.mkdir()
    (stale / "points3d.csv").write_text("killed before its commit")
    _write_set(tmp_path, "2")
    assert not stale.exists() and _whole(tmp_path)["run"] == "2"


def test_write_outputs_pairs_points_and_summary(tmp_path):
    def points(path: Path) -> Path:
        path.write_text("a_x,a_y,a_z,fnum\n1,2,3,0\n")
        return path

    s = write_outputs(tmp_path, points, {"completeness": 1.0})
    assert s["outputs"]["points3d"] == str(tmp_path / "points3d.csv")
    assert s["outputs"]["points3d_sha256"] == file_digest(tmp_path / "points3d.csv")
    assert _whole(tmp_path) == s


# --- the lock ---------------------------------------------------------------------------------

_HOLD = """
import sys, time
from deformnet.outputs import hold_output
hold_output(sys.argv[1])
print("held", flush=True)
time.sleep(float(sys.argv[2]))
"""


def _holder(folder: Path, seconds: float) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", _HOLD, str(folder), str(seconds)],
                         stdout=subprocess.PIPE, text=True)  # fmt: skip
    assert p.stdout.readline().strip() == "held"
    return p


def test_lock_refuses_a_second_run_and_takes_over_a_stale_one(tmp_path, caplog):
    p = _holder(tmp_path, 60)
    try:
        with pytest.raises(OutputBusy, match=f"output.dir={tmp_path} is in use by another run "
                           f"\\(process {p.pid} on "):  # fmt: skip
            hold_output(tmp_path)
    finally:
        p.kill()  # SIGKILL: the lock file stays, with the dead process's id
        p.wait()
    assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == p.pid
    with output_lock(tmp_path):  # stale: taken over, with a warning naming it
        assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == os.getpid()
        with output_lock(tmp_path):  # re-entrant in one process
            pass
        assert (tmp_path / LOCK_NAME).exists()
    assert f"a stale lock of process {p.pid}" in caplog.text and "no longer running" in caplog.text
    assert not (tmp_path / LOCK_NAME).exists()  # released: the file goes
    release_output(tmp_path)  # not held: nothing to do


def test_a_second_app_run_into_a_busy_folder_is_one_line_and_leaves_it_alone(tmp_path):
    """Refused before Hydra writes anything there: the running one's .hydra/ and log stay."""
    out = tmp_path / "out"
    (out / ".hydra").mkdir(parents=True)
    (out / ".hydra" / "config.yaml").write_text("the running one's\n")
    p = _holder(out, 120)
    cwd = tmp_path / "lab"
    cwd.mkdir()
    try:
        r = subprocess.run(
            [str(BIN / "adjust-triangulate"), "input.calibration=c.toml", "input.detections=d",
             f"output.dir={out}"], cwd=cwd, capture_output=True, text=True, env=ENV, timeout=300,
        )  # fmt: skip
    finally:
        p.kill()
        p.wait()
    text = r.stdout + r.stderr
    errors = [ln for ln in text.splitlines() if "[ERROR]" in ln]
    assert r.returncode == 2 and "Traceback" not in text, text[-2000:]
    assert len(errors) == 1 and "is in use by another run (process" in errors[0], errors
    assert (out / ".hydra" / "config.yaml").read_text() == "the running one's\n"
    assert sorted(x.name for x in out.iterdir()) == [".hydra", LOCK_NAME]
    assert not list(cwd.iterdir())


# --- killed and interrupted runs of the apps --------------------------------------------------


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A 400-frame simulated session (adjust-simulate)."""
    import hydra

    from adjust.apps.simulate import run
    from deformnet.paths import CONF_DIR

    folder = tmp_path_factory.mktemp("scene")
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra.compose("scene", [f"output.dir={folder}", "num_frames=400", "seed=3"])
    run(cfg)
    return folder


def _track_args(scene: Path, out: Path, *extra: str) -> list[str]:
    return [str(BIN / "adjust-track"), f"input.session={scene}", f"output.dir={out}",
            "progress=false", "solver.max_iterations=6", *extra]  # fmt: skip


TRACK_SET = ["accepted.npz", "points3d.csv", "points3d.extra.csv", "tokens.npz"]


@pytest.mark.slow  # fast: test_a_commit_killed_at_any_step_leaves_one_whole_set
def test_track_killed_at_any_moment_leaves_one_whole_run(scene, tmp_path):
    """SIGKILL at random moments of a re-run: the folder holds the earlier run whole (its
    summary lists and matches every output) or the new one, never a mix."""
    out = tmp_path / "out"
    r = subprocess.run(_track_args(scene, out), capture_output=True, text=True, env=ENV)
    assert r.returncode == 0, r.stdout[-2000:]
    first = _whole(out)
    assert first is not None and sorted(first["outputs"]["files"]) == TRACK_SET
    elapsed = first["time_s"]["total_s"] + 3.0  # + the imports
    rng = random.Random(46)
    seen = set()
    for i in range(4):
        args = _track_args(scene, out, f"solver.max_iterations={7 + i}")
        p = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV)
        time.sleep(rng.uniform(0.5, elapsed))
        p.send_signal(signal.SIGKILL)
        p.wait()
        recover_outputs(out)  # what the next run does first
        now = _whole(out)
        assert now is not None, sorted(x.name for x in out.iterdir())
        assert sorted(now["outputs"]["files"]) == TRACK_SET
        seen.add(now["settings"]["solver"]["max_iterations"])
    assert seen  # the previous run or a new one, whole, every time


@pytest.mark.slow  # fast: test_a_commit_killed_at_any_step_leaves_one_whole_set
def test_triangulate_killed_at_any_moment_leaves_one_whole_run(scene, tmp_path):
    out = tmp_path / "out"
    args = [str(BIN / "adjust-triangulate"), f"input.calibration={scene / 'calibration.toml'}",
            f"input.detections={scene / 'detections'}", f"output.dir={out}"]  # fmt: skip
    r = subprocess.run(args, capture_output=True, text=True, env=ENV)
    assert r.returncode == 0, r.stdout[-2000:]
    first = _whole(out)
    assert first is not None
    rng = random.Random(7)
    for thr in (0.3, 0.4, 0.6):
        again = [*args, f"input.likelihood_threshold={thr}"]
        p = subprocess.Popen(again, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV)
        time.sleep(rng.uniform(2.0, 6.0))
        p.send_signal(signal.SIGKILL)
        p.wait()
        recover_outputs(out)
        now = _whole(out)
        assert now is not None, sorted(x.name for x in out.iterdir())
        assert now["likelihood_threshold"] in (0.5, 0.3, 0.4, 0.6)


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_exits_130_with_the_folder_whole(scene, tmp_path):
    out = tmp_path / "out"
    r = subprocess.run(_track_args(scene, out), capture_output=True, text=True, env=ENV)
    assert r.returncode == 0, r.stdout[-2000:]
    first = _whole(out)
    args = _track_args(scene, out, "solver.max_iterations=30")
    p = subprocess.Popen(  # SIGINT as at a terminal (a pytest-xdist worker ignores it, and a
        args,  # child inherits an ignored signal across exec)
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=ENV,
        preexec_fn=_default_sigint,
    )
    for line in p.stdout:  # interrupted while it computes
        if "read 400 frames" in line:
            break
    time.sleep(0.5)
    p.send_signal(signal.SIGINT)
    text = p.communicate(timeout=120)[0]
    assert p.returncode == 130, text[-2000:]
    assert "Traceback" not in text
    errors = [ln for ln in text.splitlines() if "[ERROR]" in ln]
    assert len(errors) == 1 and "interrupted (Ctrl-C)" in errors[0], errors
    assert _whole(out) == first  # the earlier run's outputs, untouched
    assert not list(out.glob(STAGING_PREFIX + "*")) and not (out / LOCK_NAME).exists()


def test_events_and_export_write_nothing_into_the_working_directory(scene, tmp_path):
    """With an output given, Hydra's run folder is the output's folder, not runs/<app>/."""
    from adjust.io import write_points3d

    tracks = tmp_path / "t" / "points3d.csv"
    rng = np.random.default_rng(0)
    T, K = 30, 2
    write_points3d(tracks, ["nose_tip", "tail_base"], rng.normal(0, 5, (T, K, 3)),
                   np.zeros((T, K)), np.full((T, K), 2), np.ones((T, K)))  # fmt: skip
    (tracks.parent / ".hydra").mkdir()
    (tracks.parent / ".hydra" / "config.yaml").write_text("the track's\n")
    cwd = tmp_path / "lab"
    cwd.mkdir()
    runs = [
        ["adjust-events", f"tracks={tracks}", "mechanisms={lever: [0.0, 0.0, 0.0]}",
         "parts=[nose_tip]", f"output.dir={tmp_path / 'ev'}"],
        ["adjust-export", "anipose", f"tracks={tracks}", f"output={tmp_path / 'exp' / 'a.csv'}"],
        ["adjust-export", "anipose", f"tracks={tracks}"],  # beside the tracks
    ]  # fmt: skip
    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT, "text": True, "env": ENV}
    procs = [subprocess.Popen([str(BIN / a[0]), *a[1:]], cwd=cwd, **pipes) for a in runs]
    for p in procs:
        text = p.communicate(timeout=300)[0]
        assert p.returncode == 0, text[-2000:]
    assert not list(cwd.iterdir())  # no runs/events/..., runs/export/...
    assert (tmp_path / "ev" / "events.csv").is_file() and (tmp_path / "ev" / ".hydra").is_dir()
    assert (tmp_path / "exp" / "a.csv").is_file()
    assert (tracks.parent / "points3d_anipose.csv").is_file()
    assert (tracks.parent / ".hydra" / "config.yaml").read_text() == "the track's\n"


def test_ctrl_c_while_importing_is_one_line_and_130(monkeypatch, caplog):
    """Ctrl-C in the seconds a console script spends importing torch: no traceback either."""
    import importlib

    from deformnet.quickhelp import console_script

    def interrupted(name):
        raise KeyboardInterrupt

    monkeypatch.setattr(importlib, "import_module", interrupted)
    monkeypatch.setattr(sys, "argv", ["adjust-track", "input.session=x"])
    with pytest.raises(SystemExit) as exc:
        console_script("track", "adjust.apps.track:main")()
    assert exc.value.code == 130
    assert "interrupted (Ctrl-C) before the run started" in caplog.text
