"""NWB export (adjust.export, adjust-export, adjust-track output.nwb=true): the file reads back
with pynwb and its values are those of points3d.csv; calibration, skeleton, bouts and events;
DANDI-ready (nwbinspector: no CRITICAL, no BEST_PRACTICE_VIOLATION with the subject described);
read by movement with its default arguments."""

from __future__ import annotations

from pathlib import Path

import h5py
import hydra
import numpy as np
import nwbinspector
import pynwb
import pytest
from movement.io import load_poses

import adjust.export
from adjust.io import InputError, load_calibration, read_points3d
from deformnet.paths import CONF_DIR

FPS = 30.0
START = "2026-03-01T09:30:00+00:00"
SUBJECT = [
    "subject.subject_id=m01",
    "subject.species='Mus musculus'",
    "subject.sex=F",
    "subject.age=P90D",
]


def _cfg(name: str, overrides: list[str]):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose(name, overrides=overrides)


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A 60-frame simulated scene tracked by adjust-track with output.nwb=true."""
    from adjust.apps.simulate import run as simulate
    from adjust.apps.track import run as track

    scene = tmp_path_factory.mktemp("scene")
    simulate(_cfg("scene", [f"output.dir={scene}", "num_frames=60", "seed=3"]))
    # the recording's start, a stated source adjust-track's NWB takes it from
    calib = scene / "calibration.toml"
    text = calib.read_text()
    assert "[metadata]\n" in text
    calib.write_text(text.replace("[metadata]\n", f'[metadata]\nsession_start_time = "{START}"\n'))
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
        pose = behavior["PoseEstimation"]  # the name ndx-pose readers (movement) look for
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
            assert s.unit == "meters" and s.conversion == 0.001  # data in mm
            np.testing.assert_array_equal(s.data[:], d["points"][:, k])
            np.testing.assert_array_equal(s.confidence[:], d["ncams"][:, k] / len(cams))
            assert s.timestamps is None and s.rate == FPS  # regular frames: a rate
            np.testing.assert_allclose(s.get_timestamps(), d["fnum"] / FPS, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(behavior["ncams"].data[:], d["ncams"])
        np.testing.assert_array_equal(behavior["reprojection_error_px"].data[:], d["error"])
        np.testing.assert_array_equal(behavior["score"].data[:], d["score"])
        sig = np.stack([d["extra"][f"{p}_sigma"] for p in d["parts"]], -1)
        np.testing.assert_array_equal(behavior["sigma_mm"].data[:], sig)
        pose_cols = ("pose_rx", "pose_ry", "pose_rz", "pose_tx", "pose_ty", "pose_tz")
        want = np.stack([d["extra"][c] for c in pose_cols], -1)
        np.testing.assert_array_equal(behavior["body_pose"].data[:], want)
        np.testing.assert_array_equal(behavior["frame_number"].data[:], d["fnum"])
        assert nwb.session_start_time.isoformat() == START  # from the calibration's [metadata]
        assert nwb.subject is None
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
    from adjust.apps.export import run
    from adjust.export import read_nwb_tracks

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
                *SUBJECT,
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
        assert (nwb.subject.species, nwb.subject.sex, nwb.subject.age) == (
            "Mus musculus",
            "F",
            "P90D",
        )
        assert nwb.session_start_time.isoformat() == "2026-03-01T09:30:00+00:00"  # naive: UTC


def test_export_bad_inputs(tracked, tmp_path):
    from adjust.export import write_nwb

    scene, out, _ = tracked
    tracks = out / "points3d.csv"

    def refused(match: str, **settings) -> None:
        """write_nwb of the track at FPS from START with `settings` raises `match`."""
        settings = {"fps": FPS, "session_start_time": START, **settings}
        with pytest.raises(InputError, match=match):
            write_nwb(tmp_path / "a.nwb", tracks, **settings)

    refused("fps", calibration=scene / "calibration.toml", fps=None, session_start_time=None)
    # no start time from a setting or the calibration: refused, naming the setting
    refused("set session_start_time=", session_start_time=None)
    refused("ISO 8601", session_start_time="1 March 2026")
    refused("in the future", session_start_time="2999-01-01")
    refused(r"subject.sex must be one of \['M', 'F', 'U', 'O'\]", subject={"sex": "x"})
    refused("subject.age must be an ISO 8601 duration", subject={"age": "90 days"})
    bad = tmp_path / "bouts.csv"
    bad.write_text("start,end,label\n0,3,rear\n")
    refused(r"bouts\.csv: missing column\(s\) \['stop'\]", bouts=bad)
    bad.write_text("start,stop,label\n0,3,rear\n9,4,groom\n")
    refused("stop before start at row 1", bouts=bad)
    bad.write_text("start,stop,part,mechanism\nx,3,nose_tip,lever\n")
    refused("non-numeric start 'x' at row 0", events=bad)
    refused("unknown part 'tail'", edges=[["tail", "nose_tip"]])
    assert not (tmp_path / "a.nwb").exists()  # nothing half-written


# --- DANDI-ready: nwbinspector ----------------------------------------------------------------
def _inspect(path: Path) -> list:
    config = nwbinspector.load_config("dandi")  # DANDI's own importance levels
    return list(nwbinspector.inspect_nwbfile(nwbfile_path=str(path), config=config))


def _by_importance(messages) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for m in messages:
        out.setdefault(m.importance.name, []).append(f"{m.check_function_name}: {m.message}")
    return out


def test_export_passes_nwbinspector(tracked, tmp_path, caplog):
    from adjust.apps.export import run

    scene, out, _ = tracked
    base = [
        f"tracks={out / 'points3d.csv'}",
        f"calibration={scene / 'calibration.toml'}",
        f"fps={FPS}",
    ]
    described = tmp_path / "described.nwb"
    run(_cfg("export", [*base, f"output={described}", *SUBJECT]))
    found = _by_importance(_inspect(described))
    assert "CRITICAL" not in found and "BEST_PRACTICE_VIOLATION" not in found, found
    # with the metadata nwbinspector suggests too, nothing at all to report
    full = tmp_path / "full.nwb"
    run(
        _cfg(
            "export",
            [
                *base,
                f"output={full}",
                *SUBJECT,
                "subject.description='C57BL/6J, lock-box cohort'",
                "experimenter=['Doe, Jane']",
                "institution='A University'",
                "experiment_description='lock-box task'",
                "keywords=[mouse,pose,3D]",
            ],
        )
    )
    assert _inspect(full) == []
    # without a subject: written, and the log says what DANDI still needs (nothing assumed)
    bare = tmp_path / "bare.nwb"
    with caplog.at_level("WARNING", logger="adjust.export"):
        run(_cfg("export", [*base, f"output={bare}"]))
    assert "subject.species" in caplog.text and "DANDI" in caplog.text
    assert "check_subject_exists" in str(_by_importance(_inspect(bare)))
    with pynwb.NWBHDF5IO(str(bare), "r") as io:
        assert io.read().subject is None  # no species made up


# --- movement (the neuroinformatics toolbox) reads our files with its default arguments --------
def test_movement_reads_the_nwb(tracked):
    scene, out, summary = tracked
    ds = load_poses.from_nwb_file(summary["outputs"]["nwb"])  # default arguments
    d = read_points3d(out / "points3d.csv")
    cams = load_calibration(scene / "calibration.toml")
    assert ds.attrs["fps"] == FPS and ds.sizes["time"] == len(d["fnum"])
    assert sorted(ds.keypoints.values) == sorted(d["parts"])
    for k, part in enumerate(d["parts"]):
        pos = ds.position.sel(keypoints=part).values[..., 0]  # (time, space)
        np.testing.assert_array_equal(pos, d["points"][:, k])  # mm, as points3d.csv
        conf = ds.confidence.sel(keypoints=part).values[..., 0]
        np.testing.assert_array_equal(conf, d["ncams"][:, k] / len(cams))


def test_movement_reads_points3d(tracked, tmp_path):
    from adjust.apps.export import run as export
    from adjust.apps.triangulate import run as triangulate

    scene, out, _ = tracked
    # adjust-triangulate's points3d.csv as it is: anipose's columns, axes columns included
    tri = tmp_path / "tri"
    triangulate(
        _cfg(
            "triangulate",
            [
                f"input.calibration={scene / 'calibration.toml'}",
                f"input.detections={scene / 'detections'}",
                f"output.dir={tri}",
            ],
        )
    )
    # adjust-track's carries our pose and sigma columns, which movement refuses: export it
    res = export(_cfg("export", ["format=anipose", f"tracks={out / 'points3d.csv'}"]))
    assert Path(res["output"]) == out / "points3d_anipose.csv"
    for path in (tri / "points3d.csv", Path(res["output"])):
        d = read_points3d(path)
        ds = load_poses.from_anipose_file(path)  # default arguments
        assert ds.sizes["time"] == len(d["fnum"])
        for k, part in enumerate(d["parts"]):
            pos = ds.position.sel(keypoints=part).values[..., 0]
            np.testing.assert_array_equal(pos, d["points"][:, k])
            conf = ds.confidence.sel(keypoints=part).values[..., 0]
            np.testing.assert_array_equal(conf, d["score"][:, k])


# --- skeleton from the input --------------------------------------------------------------------
def test_nwb_skeleton_sources(tracked, tmp_path, caplog):
    import h5py

    from adjust.export import read_nwb_tracks, write_nwb

    _, out, _ = tracked
    tracks = out / "points3d.csv"
    parts = list(read_points3d(tracks)["parts"])
    kw = {"fps": FPS, "session_start_time": START}
    # a user's skeleton.csv; an edge naming a part the tracks lack is dropped (warned)
    csv = tmp_path / "skeleton.csv"
    csv.write_text("part_a,part_b\nnose_tip,left_ear\nleft_ear,right_ear\nnose_tip,whisker\n")
    with caplog.at_level("WARNING"):
        write_nwb(tmp_path / "a.nwb", tracks, skeleton=csv, **kw)
    assert "whisker" in caplog.text
    idx = {p: k for k, p in enumerate(parts)}
    want = [(idx["nose_tip"], idx["left_ear"]), (idx["left_ear"], idx["right_ear"])]
    assert read_nwb_tracks(tmp_path / "a.nwb")["skeleton_edges"] == want
    # the session's SLEAP files carry their edges (SLEAP's analysis export: edge_names)
    det = tmp_path / "detections"
    det.mkdir()
    with h5py.File(det / "top.analysis.h5", "w") as f:
        f["tracks"] = np.zeros((1, 2, 2, 3))
        f["node_names"] = np.array([b"nose_tip", b"tail_root"])
        f["edge_names"] = np.array([[b"nose_tip", b"tail_root"]])
    write_nwb(tmp_path / "b.nwb", tracks, detections=det, **kw)
    assert read_nwb_tracks(tmp_path / "b.nwb")["skeleton_edges"] == [
        (idx["nose_tip"], idx["tail_root"])
    ]
    # nothing given or found: the minimum spanning tree, said in the log
    caplog.clear()
    with caplog.at_level("INFO", logger="adjust.io.skeleton"):
        write_nwb(tmp_path / "c.nwb", tracks, **kw)
    assert "minimum spanning tree" in caplog.text
    assert len(read_nwb_tracks(tmp_path / "c.nwb")["skeleton_edges"]) == len(parts) - 1


# --- times: a rate for regular frames, timestamps otherwise -------------------------------------
def test_nwb_rate_and_timestamps(tracked, tmp_path):
    from adjust.export import read_nwb_tracks, write_nwb
    from adjust.io import write_points3d

    _, out, _ = tracked
    d = read_points3d(out / "points3d.csv")
    kw = {"fps": FPS, "session_start_time": START}
    for name, fnum in (("every_other", np.arange(len(d["fnum"])) * 2 + 10),
                       ("gaps", np.r_[0, 1, 5, np.arange(3, len(d["fnum"])) + 5])):  # fmt: skip
        src = write_points3d(
            tmp_path / f"{name}.csv", d["parts"], d["points"], d["error"], d["ncams"], d["score"],
            fnum=fnum,
        )  # fmt: skip
        path = write_nwb(tmp_path / f"{name}.nwb", src, starting_time=2.0, **kw)
        r = read_nwb_tracks(path)
        np.testing.assert_allclose(r["timestamps"], 2.0 + fnum / FPS, rtol=0, atol=1e-9)
        with pynwb.NWBHDF5IO(str(path), "r") as io:
            s = io.read().processing["behavior"]["PoseEstimation"].pose_estimation_series
            first = s[d["parts"][0]]
            if name == "every_other":
                assert first.timestamps is None and first.rate == FPS / 2
                assert first.starting_time == pytest.approx(2.0 + 10 / FPS)
            else:
                assert first.rate is None and first.timestamps is not None


# --- axes alignment on export --------------------------------------------------------------------
def test_nwb_axes_alignment_keeps_the_cameras_consistent(tracked, tmp_path):
    import cv2

    from adjust.export import read_nwb_tracks, write_nwb

    scene, out, _ = tracked
    tracks = out / "points3d.csv"
    d = read_points3d(tracks)
    cams = load_calibration(scene / "calibration.toml")
    path = write_nwb(
        tmp_path / "aligned.nwb",
        tracks,
        scene / "calibration.toml",
        fps=FPS,
        session_start_time=START,
        axes={"x": ["tail_root", "nose_tip"], "z": [[0, 0, 0], [0, 0, 1]]},
    )
    r = read_nwb_tracks(path)
    assert not np.allclose(r["points"], d["points"])

    # the aligned points seen by the aligned cameras land where the world points did
    def project(X, R, t, cam):
        uv, _ = cv2.projectPoints(X.reshape(-1, 3), cv2.Rodrigues(R)[0], t, cam.K, cam.dist)
        return uv.reshape(-1, 2)

    for c in cams:
        dev = r["cameras"][c.name]
        np.testing.assert_allclose(
            project(r["points"], dev["R"], dev["t"], c),
            project(d["points"], c.R, c.tvec, c),
            atol=1e-6,
        )


def _datasets(path: Path) -> dict[str, np.ndarray]:
    """Every dataset of an NWB file under /processing and /general/devices, read whole."""
    out = {}
    with h5py.File(path, "r") as f:
        for root in ("processing", "general/devices"):
            f[root].visititems(
                lambda name, obj, r=root: (
                    out.__setitem__(f"{r}/{name}", obj[()])
                    if isinstance(obj, h5py.Dataset)
                    else None
                )
            )
    return out


def test_chunked_track_writes_the_nwb_block_by_block(tmp_path, monkeypatch):
    """A session tracked in chunks (output.nwb=true): the NWB file is written from the chunks'
    numbers on disk, block by block (points3d.csv is never read back whole), and holds exactly
    what the whole-file writer makes of the same points3d.csv."""
    from adjust.apps.simulate import run as simulate
    from adjust.apps.track import run as track

    scene = tmp_path / "scene"
    simulate(_cfg("scene", [f"output.dir={scene}", "num_frames=300", "seed=3"]))
    calib = scene / "calibration.toml"
    calib.write_text(
        calib.read_text().replace("[metadata]\n", f'[metadata]\nsession_start_time = "{START}"\n')
    )

    def whole_file(*a, **k):
        raise AssertionError("points3d.csv read back whole")

    monkeypatch.setattr(adjust.export, "read_points3d", whole_file)
    out = tmp_path / "chunked"
    s = track(
        _cfg(
            "track",
            [
                f"input.session={scene}",
                f"output.dir={out}",
                "progress=false",
                "chunk_frames=128",
                "output.nwb=true",
                f"output.fps={FPS}",
            ],
        )
    )
    monkeypatch.undo()
    assert len(s["chunked"]["chunks"]) == 3 and s["outputs"]["nwb"] == str(out / "tracks.nwb")
    ref = adjust.export.write_nwb(
        tmp_path / "ref.nwb", out / "points3d.csv", calib, fps=FPS, detections=scene / "detections"
    )
    a, b = _datasets(out / "tracks.nwb"), _datasets(ref)
    assert set(a) == set(b) and len(a) > 20
    for name in a:
        x, y = np.asarray(a[name]), np.asarray(b[name])
        assert x.shape == y.shape, name
        if x.dtype.kind == "f":
            np.testing.assert_array_equal(x, y, err_msg=name)  # NaN == NaN here
        else:
            assert (x == y).all(), name
    d = read_points3d(out / "points3d.csv")
    with pynwb.NWBHDF5IO(str(out / "tracks.nwb"), "r") as io:
        pose = io.read().processing["behavior"]["PoseEstimation"]
        series = pose.pose_estimation_series[d["parts"][0]]
        np.testing.assert_array_equal(series.data[:], d["points"][:, 0])
    assert list(pynwb.validate(path=str(out / "tracks.nwb"))) == []
