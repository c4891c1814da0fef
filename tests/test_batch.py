"""Batch runs (adjust.apps.batch, adjust.session): ``adjust-track -m input.session=glob(...)`` over
three session folders, one broken; re-runs skip finished sessions; the SLURM launcher config
composes and the job survives pickling."""

from __future__ import annotations

import os
import pickle
import sys
import time
from pathlib import Path

import hydra
import pytest
from omegaconf import OmegaConf

from adjust.apps.batch import SUMMARY_COLUMNS, read_summary, run_session
from adjust.io import InputError
from adjust.session import expand_session_globs, resolve_session, session_name, with_session
from deformnet.paths import CONF_DIR

FAST = ["progress=false", "solver.max_iterations=6"]


def _cfg(name: str, overrides: list[str], hydra_config: bool = False):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose(name, overrides=overrides, return_hydra_config=hydra_config)


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> Path:
    """sessions/{a_ok, b_broken, c_ok}: 60-frame simulated scenes; b's calibration is broken."""
    from adjust.apps.simulate import run as simulate

    root = tmp_path_factory.mktemp("sessions")
    for seed, name in enumerate(("a_ok", "b_broken", "c_ok")):
        simulate(_cfg("scene", [f"output.dir={root / name}", "num_frames=60", f"seed={seed}"]))
    (root / "b_broken" / "calibration.toml").write_text('[cam_0]\nname = "top"\n')
    (root / "notes.txt").write_text("not a session folder\n")
    return root


def _multirun(monkeypatch, args: list[str]) -> int:
    """`adjust-track -m ARGS` in this process (the console script's own entry point); returns
    its exit status."""
    from adjust.apps.track import main

    monkeypatch.setattr(sys, "argv", ["adjust-track", "-m", *args, *FAST])
    try:
        main()
    except SystemExit as exc:
        return exc.code
    return 0


def _rows(batch: Path) -> dict[str, dict]:
    rows = read_summary(batch / "summary.csv")
    assert list(rows[0]) == list(SUMMARY_COLUMNS)
    return {Path(r["session"]).name: r for r in rows}


@pytest.fixture(scope="module")
def first_batch(sessions, tmp_path_factory):
    """The first batch, through the joblib launcher (in this process: n_jobs=1; two worker
    processes in the slow test below)."""
    batch = tmp_path_factory.mktemp("runs") / "batch1"
    mp = pytest.MonkeyPatch()
    try:
        code = _multirun(
            mp,
            [
                f"input.session=glob({sessions}/*)",
                f"hydra.sweep.dir={batch}",
                "hydra/launcher=joblib",
                "hydra.launcher.n_jobs=1",
            ],
        )
    finally:
        mp.undo()
    assert code == 1  # b_broken failed
    return batch


def test_batch_finishes_the_others_and_reports_the_broken_one(sessions, first_batch):
    rows = _rows(first_batch)
    assert sorted(rows) == ["a_ok", "b_broken", "c_ok"]  # notes.txt is not a session
    for name in ("a_ok", "c_ok"):
        r = rows[name]
        assert r["status"] == "ok" and r["error"] == ""
        assert int(r["frames"]) == 60 and float(r["completeness"]) == 1.0
        assert 0.0 < float(r["median_reprojection_error_px"]) < 5.0
        assert float(r["seconds"]) > 0
        assert Path(r["output"]) == first_batch / name  # one folder per session
        assert (first_batch / name / "points3d.csv").is_file()
    bad = rows["b_broken"]
    assert bad["status"] == "failed"
    assert "b_broken/calibration.toml" in bad["error"] and "missing keys" in bad["error"]
    assert bad["frames"] == "" and not (first_batch / "b_broken" / "points3d.csv").exists()


def test_rerun_skips_finished_sessions_unless_forced(sessions, first_batch, monkeypatch):
    runs = first_batch.parent
    code = _multirun(
        monkeypatch, [f"input.session=glob({sessions}/*)", f"hydra.sweep.dir={runs / 'b2'}"]
    )
    assert code == 1  # b_broken failed again
    rows = _rows(runs / "b2")
    for name in ("a_ok", "c_ok"):
        assert rows[name]["status"] == "skipped"
        assert Path(rows[name]["output"]) == first_batch / name  # where it was done
        assert int(rows[name]["frames"]) == 60
        assert not (runs / "b2" / name / "points3d.csv").exists()
    assert rows["b_broken"]["status"] == "failed"  # no outputs: tried again

    # force=true, new settings, or inputs whose contents changed: tracked again
    a = sessions / "a_ok"
    code = _multirun(
        monkeypatch, [f"input.session={a}", f"hydra.sweep.dir={runs / 'b3'}", "force=true"]
    )
    assert code == 0  # every session ok
    assert _rows(runs / "b3")["a_ok"]["status"] == "ok"
    assert (runs / "b3" / "a_ok" / "points3d.csv").is_file()
    c = sessions / "c_ok"
    ov = [f"input.session={c}", "input.likelihood_threshold=0.6"]
    _multirun(monkeypatch, [*ov, f"hydra.sweep.dir={runs / 'b4'}"])
    assert _rows(runs / "b4")["c_ok"]["status"] == "ok"
    # decided by contents, not file times: a newer time alone skips; a changed file with an
    # older time (rsync -a, cp -p) is tracked again
    det = sorted((c / "detections").iterdir())[0]
    future = time.time() + 60
    os.utime(det, (future, future))
    _multirun(monkeypatch, [*ov, f"hydra.sweep.dir={runs / 'b5'}"])
    assert _rows(runs / "b5")["c_ok"]["status"] == "skipped"
    old = det.stat().st_mtime - 3600
    lines = det.read_text().splitlines()
    cells = lines[-1].split(",")
    cells[1] = repr(float(cells[1]) + 0.5) if cells[1] else cells[1]  # one x moved half a pixel
    det.write_text("\n".join([*lines[:-1], ",".join(cells)]) + "\n")
    os.utime(det, (old, old))
    _multirun(monkeypatch, [*ov, f"hydra.sweep.dir={runs / 'b6'}"])
    assert _rows(runs / "b6")["c_ok"]["status"] == "ok"


def test_batch_into_output_dir_and_its_exit_status(sessions, tmp_path, monkeypatch, capfd):
    """output.dir: every session's outputs and Hydra's files in OUTPUT_DIR/<name>/, summary.csv
    in OUTPUT_DIR (this batch's sessions only), nothing in the working directory; a batch with
    a failed session, or whose glob matches none, exits non-zero."""
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out"
    ok = f"input.session={sessions / 'a_ok'},{sessions / 'c_ok'}"
    assert _multirun(monkeypatch, [ok, f"output.dir={out}"]) == 0
    rows = _rows(out)
    assert sorted(rows) == ["a_ok", "c_ok"]
    for name, r in rows.items():
        assert r["status"] == "ok" and Path(r["output"]) == out / name
        assert (out / name / "points3d.csv").is_file() and (out / name / ".hydra").is_dir()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no runs/ here
    # the same output.dir, one session: its summary.csv lists this batch's session only
    again = [f"input.session={sessions / 'a_ok'}", f"output.dir={out}", "force=true"]
    assert _multirun(monkeypatch, again) == 0
    assert sorted(_rows(out)) == ["a_ok"]
    capfd.readouterr()
    bad = [f"input.session={sessions / 'b_broken'}", f"output.dir={tmp_path / 'bad'}"]
    assert _multirun(monkeypatch, bad) == 1
    text = capfd.readouterr().out
    assert "batch: 1 of 1 sessions failed" in text and "exit status 1" in text
    assert _rows(tmp_path / "bad")["b_broken"]["status"] == "failed"
    none = [f"input.session=glob({tmp_path}/nothing*)", f"output.dir={tmp_path / 'none'}"]
    assert _multirun(monkeypatch, none) == 2  # before any job
    assert not (tmp_path / "none").exists()


def test_batch_without_status_rows_fails(tmp_path):
    from adjust.apps.batch import BatchSummary

    cfg = OmegaConf.create({"hydra": {"sweep": {"dir": str(tmp_path)}, "overrides": {"task": []}}})
    with pytest.raises(SystemExit) as exc:
        BatchSummary().on_multirun_end(config=cfg)
    assert exc.value.code == 1


def test_session_folders(sessions, tmp_path):
    calib, det = resolve_session(sessions / "a_ok")
    assert (
        calib == sessions / "a_ok" / "calibration.toml" and det == sessions / "a_ok" / "detections"
    )
    flat = tmp_path / "flat"  # detections beside the calibration
    flat.mkdir()
    assert resolve_session(flat) == (flat / "calibration.toml", flat)
    with pytest.raises(InputError, match="session folder not found"):
        resolve_session(tmp_path / "nope")
    with pytest.raises(InputError, match="no calibration.toml"):
        with_session(_cfg("track", [f"input.session={flat}"]))
    shared = sessions / "a_ok" / "calibration.toml"
    cfg = with_session(_cfg("track", [f"input.session={flat}", f"input.calibration={shared}"]))
    assert cfg.input.calibration == str(shared) and cfg.input.detections == str(flat)
    # glob expansion: sorted folders only, quoted; a pattern matching nothing is an error
    argv = expand_session_globs(["x", f"input.session=glob({sessions}/*,exclude=b_*)", "y=1"])
    assert argv[0] == "x" and argv[2] == "y=1"
    assert argv[1] == f"input.session='{sessions}/a_ok','{sessions}/c_ok'"
    with pytest.raises(InputError, match="no session folder matches"):
        expand_session_globs([f"input.session=glob({tmp_path}/none*)"])
    assert session_name("/data/m 1/") == "m_1" and session_name(None, 3) == "job3"


def test_slurm_launcher_config_composes():
    from hydra.utils import get_class

    cfg = _cfg("track", ["hydra/launcher=slurm", "input.session=/x/s1"], hydra_config=True)
    launcher = cfg.hydra.launcher
    cls = get_class(launcher._target_)
    assert cls.__name__ == "SlurmLauncher"
    assert launcher.timeout_min > 0 and launcher.cpus_per_task == 1 and launcher.mem_gb >= 1
    assert launcher.max_num_timeout == 0
    assert str(launcher.submitit_folder).endswith(".submitit/%j")
    subdir = OmegaConf.to_container(cfg.hydra.sweep)["subdir"]  # resolved per job
    assert subdir == "${session_name:${input.session},${hydra.job.num}}"
    assert session_name(cfg.input.session, 0) == "s1"  # the session's own folder
    assert cfg.hydra.callbacks.batch_summary._target_ == "adjust.apps.batch.BatchSummary"
    joblib = _cfg("track", ["hydra/launcher=joblib"], hydra_config=True).hydra.launcher
    assert get_class(joblib._target_).__name__ == "JoblibLauncher"


def test_job_is_picklable_and_runs_after_unpickling(sessions, tmp_path):
    cloudpickle = pytest.importorskip("cloudpickle")
    import adjust.apps.track

    # submitit pickles the launcher's task function (the undecorated Hydra main) with cloudpickle
    task = cloudpickle.loads(cloudpickle.dumps(adjust.apps.track._main.__wrapped__))
    assert callable(task)
    job = pickle.loads(pickle.dumps(run_session))
    cfg = pickle.loads(pickle.dumps(_cfg("track", [f"input.session={sessions / 'c_ok'}", *FAST])))
    row = job(cfg, job_dir=tmp_path / "job")
    assert row["status"] == "ok" and row["frames"] == 60
    assert (tmp_path / "job" / "points3d.csv").is_file()
    bad = OmegaConf.merge(cfg, {"input": {"session": str(sessions / "b_broken")}})
    row = job(bad, job_dir=tmp_path / "bad")
    assert row["status"] == "failed" and "calibration.toml" in row["error"]


@pytest.mark.slow
@pytest.mark.parametrize(
    "launcher",
    [
        # the submitit path SLURM uses (pickled job, a separate process), run locally
        ["hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10"],
        ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"],  # two worker processes
    ],
    ids=["submitit_local", "joblib"],
)
def test_launchers_in_other_processes(sessions, tmp_path, monkeypatch, launcher):
    code = _multirun(
        monkeypatch,
        [
            f"input.session={sessions / 'a_ok'},{sessions / 'b_broken'}",
            f"hydra.sweep.dir={tmp_path / 'sub'}",
            "force=true",
            *launcher,
        ],
    )
    rows = _rows(tmp_path / "sub")
    assert code == 1
    assert rows["a_ok"]["status"] == "ok" and rows["b_broken"]["status"] == "failed"
    assert (tmp_path / "sub" / "a_ok" / "points3d.csv").is_file()
