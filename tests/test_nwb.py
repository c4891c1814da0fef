"""NWB export (adjust.export, adjust-export, adjust-track output.nwb=true): the file reads back
with pynwb and its values are those of points3d.csv; calibration, skeleton, bouts and events."""

from __future__ import annotations

from pathlib import Path

import hydra
import numpy as np
import pytest

from adjust.io import InputError, load_calibration, read_points3d
from deformnet.paths import CONF_DIR

pynwb = pytest.importorskip("pynwb")
ndx_pose = pytest.importorskip("ndx_pose")

FPS = 30.0


def _cfg(name: str, overrides: list[str]):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose(name, overrides=overrides)


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A 60-frame simulated scene tracked by adjust-track with output.nwb=true."""
    from adjust.scene_cli import run as simulate
    from adjust.track import run as track

    scene = tmp_path_factory.mktemp("scene")
    simulate(_cfg("scene", [f"output.dir={scene}", "num_frames=60", "seed=3"]))
    out = tmp_path_factory.mktemp("track")
    summary = track(
        _cfg(
            "track",
            [
                f"input.calibration={scene / 'calibration.toml'}",
                f"input.detections={scene / 'detections'}",
                f"output.dir={out}",
                "progress=false",
                "solver.max_iterations=6",
                "output.nwb=true",
                f"output.fps={FPS}",
            ],
        )
    )
    return scene, out, summary


def _bouts_events(tmp: Path) -> tuple[Path, Path]:
    bouts = tmp / "bouts.csv"
    bouts.write_text("start,stop,label,probability\n0,12,rear,0.9\n13,40,groom,0.75\n")
    events = tmp / "events.csv"
    events.write_text(
        "start,stop,part,mechanism,min_distance_mm\n5,9,left_front_paw,lever,1.5\n"
        "30,44,nose_tip,door,0.25\n"
    )
    return bouts, events


def test_track_nwb_matches_points3d(tracked):
    scene, out, summary = tracked
    path = Path(summary["outputs"]["nwb"])
    assert path == out / "tracks.nwb" and path.is_file()
    d = read_points3d(out / "points3d.csv")
    cams = load_calibration(scene / "calibration.toml")
    with pynwb.NWBHDF5IO(str(path), "r") as io:
        nwb = io.read()
        behavior = nwb.processing["behavior"]
        pose = behavior["PoseEstimation3D"]
        assert list(pose.skeleton.nodes[:]) == list(d["parts"])
        edges = np.asarray(pose.skeleton.edges[:])
        assert edges.shape == (len(d["parts"]) - 1, 2)  # a spanning tree of the parts
        # every part connected: union-find over the edges
        root = list(range(len(d["parts"])))

        def find(i):
            while root[i] != i:
                i = root[i]
            return i

        for a, b in edges:
            root[find(int(a))] = find(int(b))
        assert len({find(i) for i in range(len(root))}) == 1
        for k, part in enumerate(d["parts"]):
            s = pose.pose_estimation_series[part]
            assert s.unit == "mm"
            np.testing.assert_array_equal(s.data[:], d["points"][:, k])
            np.testing.assert_array_equal(s.confidence[:], d["ncams"][:, k] / len(cams))
            np.testing.assert_allclose(s.timestamps[:], d["fnum"] / FPS, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(behavior["ncams"].data[:], d["ncams"])
        np.testing.assert_array_equal(behavior["reprojection_error_px"].data[:], d["error"])
        np.testing.assert_array_equal(behavior["score"].data[:], d["score"])
        sig = np.stack([d["extra"][f"{p}_sigma"] for p in d["parts"]], -1)
        np.testing.assert_array_equal(behavior["sigma_mm"].data[:], sig)
        pose_cols = ("pose_rx", "pose_ry", "pose_rz", "pose_tx", "pose_ty", "pose_tz")
        want = np.stack([d["extra"][c] for c in pose_cols], -1)
        np.testing.assert_array_equal(behavior["body_pose"].data[:], want)
        np.testing.assert_array_equal(behavior["frame_number"].data[:], d["fnum"])
        # the calibration as metadata: one CalibratedCamera per camera, linked per view
        assert sorted(nwb.devices) == sorted(c.name for c in cams)
        for c in cams:
            dev = nwb.devices[c.name]
            np.testing.assert_array_equal(dev.intrinsic_matrix[:], c.K)
            np.testing.assert_array_equal(dev.rotation_matrix[:], c.R)
            np.testing.assert_array_equal(dev.translation_vector[:], c.tvec)
            np.testing.assert_array_equal(dev.distortion_coefficients[:], c.dist)
            assert pose.pose_estimations[f"camera_{c.name}"].device is dev


def test_nwb_validates(tracked):
    _, out, _ = tracked
    assert list(pynwb.validate(path=str(out / "tracks.nwb"))) == []


def test_export_cli_with_bouts_and_events(tracked, tmp_path):
    from adjust.export import read_nwb_tracks
    from adjust.export_cli import run

    scene, out, _ = tracked
    bouts, events = _bouts_events(tmp_path)
    target = tmp_path / "session.nwb"
    res = run(
        _cfg(
            "export",
            [
                f"tracks={out / 'points3d.csv'}",
                f"calibration={scene / 'calibration.toml'}",
                "fps=50",
                f"bouts={bouts}",
                f"events={events}",
                f"output={target}",
                "edges=[[nose_tip,left_ear],[nose_tip,right_ear]]",
                "session_start_time=2026-03-01T09:30:00",
                "subject_id=m01",
            ],
        )
    )
    assert Path(res["output"]) == target
    r = read_nwb_tracks(target)
    d = read_points3d(out / "points3d.csv")
    np.testing.assert_array_equal(r["points"], d["points"])
    np.testing.assert_allclose(r["timestamps"], d["fnum"] / 50.0, rtol=0, atol=1e-12)
    assert r["skeleton_edges"] == [(0, 1), (0, 2)]
    b = r["intervals"]["behavior_bouts"]
    np.testing.assert_allclose(b["start_time"], [0 / 50, 13 / 50])
    np.testing.assert_allclose(b["stop_time"], [12 / 50, 40 / 50])
    assert list(b["label"]) == ["rear", "groom"]
    np.testing.assert_allclose(b["probability"], [0.9, 0.75])
    e = r["intervals"]["lockbox_events"]
    np.testing.assert_allclose(e["start_time"], [5 / 50, 30 / 50])
    assert list(e["part"]) == ["left_front_paw", "nose_tip"]
    assert list(e["mechanism"]) == ["lever", "door"]
    np.testing.assert_allclose(e["min_distance_mm"], [1.5, 0.25])
    with pynwb.NWBHDF5IO(str(target), "r") as io:
        nwb = io.read()
        assert nwb.subject.subject_id == "m01"
        assert nwb.session_start_time.isoformat().startswith("2026-03-01T09:30:00")


def test_export_bad_inputs(tracked, tmp_path):
    from adjust.export import write_nwb

    scene, out, _ = tracked
    tracks = out / "points3d.csv"
    with pytest.raises(InputError, match="fps"):
        write_nwb(tmp_path / "a.nwb", tracks, scene / "calibration.toml")
    bad = tmp_path / "bouts.csv"
    bad.write_text("start,end,label\n0,3,rear\n")
    with pytest.raises(InputError, match=r"bouts\.csv: missing column\(s\) \['stop'\]"):
        write_nwb(tmp_path / "a.nwb", tracks, fps=FPS, bouts=bad)
    bad.write_text("start,stop,label\n0,3,rear\n9,4,groom\n")
    with pytest.raises(InputError, match="stop before start at row 1"):
        write_nwb(tmp_path / "a.nwb", tracks, fps=FPS, bouts=bad)
    bad.write_text("start,stop,part,mechanism\nx,3,nose_tip,lever\n")
    with pytest.raises(InputError, match="non-numeric start 'x' at row 0"):
        write_nwb(tmp_path / "a.nwb", tracks, fps=FPS, events=bad)
    with pytest.raises(InputError, match="unknown part 'tail'"):
        write_nwb(tmp_path / "a.nwb", tracks, fps=FPS, edges=[["tail", "nose_tip"]])
    assert not (tmp_path / "a.nwb").exists()  # nothing half-written
