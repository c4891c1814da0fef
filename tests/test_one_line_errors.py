"""Every failure is one line (issue 46): the inputs that raised tracebacks now give one ERROR
line and exit status 2, or work. The console scripts run as a user runs them, in parallel."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from adjust.export import read_nwb_tracks
from adjust.scene.defective import defective_tracks, tracks_file

BIN = Path(sys.executable).parent
NWB = ["fps=100", "session_start_time=2026-01-01T00:00:00", "subject.subject_id=m1",
       "subject.species=Mus musculus", "subject.sex=F", "subject.age=P90D"]  # fmt: skip


def test_the_tracebacks_of_issue_46_are_one_line(tmp_path):
    good = tracks_file(tmp_path / "good.csv", 3, T=20)
    bad = defective_tracks(tmp_path, good, T=20)
    empty, big, labelled, huge, bouts = (
        bad[k] for k in ("empty", "big", "labelled", "huge", "bouts")
    )
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "out"
    cwd = tmp_path / "lab"
    cwd.mkdir()
    cases = {
        # name: (console script, args, exit status, text of the one ERROR line; None: works)
        "export_empty": ("adjust-export", ["anipose", f"tracks={empty}", f"output={out}/e.csv"],
                         2, "empty.csv: no rows"),
        "plot_empty": ("adjust-plot", [f"tracks={empty}", f"output.dir={out}/pe"], 2,
                       "empty.csv: no rows"),
        "export_300_parts": ("adjust-export", ["nwb", f"tracks={big}", *NWB,
                             f"output={out}/big.nwb"], 0, None),
        "export_mixed_bouts": ("adjust-export", ["nwb", f"tracks={good}", *NWB,
                               f"bouts={bouts}", f"output={out}/b.nwb"], 0, None),
        "plot_labelled": ("adjust-plot", [f"tracks={labelled}", f"output.dir={out}/pl"], 0, None),
        "events_labelled": ("adjust-events", [f"tracks={labelled}", "parts=[p0]",
                            "mechanisms={lever: [0.0, 0.0, 0.0]}", f"output.dir={out}/ev"], 2,
                            "fnum holds labelled images' names"),
        "plot_beyond_int64": ("adjust-plot", [f"tracks={huge}", f"output.dir={out}/ph"], 2,
                              "is beyond the int64 range"),
        "events_beyond_int64": ("adjust-events", [f"tracks={huge}", "parts=[p0]",
                                "mechanisms={lever: [0.0, 0.0, 0.0]}", f"output.dir={out}/eh"],
                                2, "is beyond the int64 range"),
        "classify_output_dir_file": ("deformnet-classify", [f"output.dir={tmp_path}/afile/x"],
                                     2, "afile is a file, not a folder"),
        "train_output_dir_unusable": ("deformnet-train", ["output.dir=/proc/mousetrack/x"], 2,
                                      "output folder cannot be created"),
        "fifo_calibration": ("adjust-triangulate", ["input.calibration=/dev/zero",
                             f"input.detections={tmp_path}", f"output.dir={out}/t"], 2,
                             "/dev/zero is a device, not a regular file"),
        "threads_absurd": ("adjust-track", ["input.calibration=c.toml", "input.detections=d",
                           "threads=100000", f"output.dir={out}/tt"], 2,
                           "threads=100000 is not valid"),
        "sigma_absurd": ("adjust-track", ["input.calibration=c.toml", "input.detections=d",
                         "stochastic.sigma_det_px=1e-9", f"output.dir={out}/ts"], 2,
                         "stochastic.sigma_det_px=1e-09 is not valid"),
    }  # fmt: skip
    env = {**os.environ, "HYDRA_FULL_ERROR": "0"}
    procs = {
        k: subprocess.Popen([str(BIN / app), *args], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env)
        for k, (app, args, _, _) in cases.items()
    }  # fmt: skip
    outs = {k: p.communicate(timeout=600)[0] for k, p in procs.items()}
    for k, (_, _, code, text) in cases.items():
        o = outs[k]
        assert "Traceback" not in o, (k, o[-3000:])
        assert procs[k].returncode == code, (k, o[-3000:])
        errors = [ln for ln in o.splitlines() if "[ERROR]" in ln]
        if text is None:
            assert not errors, (k, errors)
        else:
            assert len(errors) == 1 and text in errors[0], (k, errors)
    assert not list(cwd.iterdir())  # nothing in the working directory
    assert "edges left out" not in outs["export_mixed_bouts"]
    assert "NWB skeleton lists the parts without edges" in outs["export_300_parts"]
    assert read_nwb_tracks(out / "big.nwb")["points"].shape == (20, 300, 3)
    files = sorted(p.name for p in (out / "pl").iterdir() if p.suffix == ".png")
    assert files == ["body3d.png", "confidence.png", "reprojection_error.png"]
