"""movement's anipose loader (``load_poses.from_anipose_file``, default arguments) reads every
points3d.csv the project writes: adjust-track's, adjust-triangulate's and adjust-export
anipose's (aligned, with and without ``keep_extra``); the values are those of `read_points3d`,
which still joins our extra columns (body pose, sigmas) back from the sidecar."""

from __future__ import annotations

from pathlib import Path

import hydra
import numpy as np
import pytest
from movement.io import load_poses

from adjust.export import write_anipose
from adjust.io import read_points3d
from deformnet.behavior.tracks import POSE_COLUMNS
from deformnet.paths import CONF_DIR


def _cfg(name: str, overrides: list[str]):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose(name, overrides=overrides)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A 40-frame simulated scene tracked by adjust-track and triangulated by
    adjust-triangulate."""
    from adjust.apps.simulate import run as simulate
    from adjust.apps.track import run as track
    from adjust.apps.triangulate import run as triangulate

    scene = tmp_path_factory.mktemp("scene")
    simulate(_cfg("scene", [f"output.dir={scene}", "num_frames=40", "seed=5"]))
    inputs = [
        f"input.calibration={scene / 'calibration.toml'}",
        f"input.detections={scene / 'detections'}",
    ]
    tracked = tmp_path_factory.mktemp("track")
    track(
        _cfg(
            "track",
            [*inputs, f"output.dir={tracked}", "progress=false", "solver.max_iterations=6"],
        )
    )
    dlt = tmp_path_factory.mktemp("dlt")
    triangulate(_cfg("triangulate", [*inputs, f"output.dir={dlt}"]))
    return tracked / "points3d.csv", dlt / "points3d.csv"


def _check_movement_reads(path: Path) -> dict:
    """movement's values (default arguments) equal read_points3d's; returns the latter."""
    ds = load_poses.from_anipose_file(path)
    d = read_points3d(path)
    names = [str(k) for k in ds.coords["keypoints"].values]
    assert sorted(names) == sorted(d["parts"])
    order = [names.index(p) for p in d["parts"]]
    pos = ds["position"].values[:, :, order, 0]  # (T, 3, K)
    np.testing.assert_array_equal(pos.transpose(0, 2, 1), d["points"])
    conf = ds["confidence"].values[:, order, 0]
    np.testing.assert_array_equal(conf, d["score"])
    assert ds.sizes["time"] == len(d["fnum"])
    return d


def test_movement_reads_adjust_track_output(runs):
    tracked, _ = runs
    d = _check_movement_reads(tracked)
    assert np.isfinite(d["points"]).all()  # adjust-track fills every part
    # our columns are not lost: the sidecar holds them and read_points3d joins them back
    side = tracked.with_name("points3d.extra.csv")
    assert side.is_file()
    assert all(c in d["extra"] for c in POSE_COLUMNS)
    assert all(f"{p}_sigma" in d["extra"] for p in d["parts"])
    assert np.isfinite(np.stack([d["extra"][c] for c in POSE_COLUMNS])).all()
    np.testing.assert_array_equal(d["M"], np.eye(3))
    np.testing.assert_array_equal(d["center"], np.zeros(3))


def test_movement_reads_adjust_triangulate_output(runs):
    _, dlt = runs
    d = _check_movement_reads(dlt)
    assert np.isfinite(d["points"]).any()
    assert not dlt.with_name("points3d.extra.csv").exists()


def test_movement_reads_adjust_export_anipose(runs, tmp_path):
    tracked, _ = runs
    parts = read_points3d(tracked)["parts"]
    axes = {"x": [parts[0], parts[1]], "y": [parts[0], parts[2]]}
    for keep in (False, True):
        out = write_anipose(tmp_path / f"aligned_{keep}.csv", tracked, axes=axes, keep_extra=keep)
        d = _check_movement_reads(out)
        assert not np.allclose(d["M"], np.eye(3))  # the alignment is in the axes columns
        assert (set(POSE_COLUMNS) <= set(d["extra"])) == keep
        assert out.with_name(out.stem + ".extra.csv").is_file() == keep


def test_stale_sidecar_is_left_out(runs, tmp_path, caplog):
    """A sidecar written for other bytes (the points3d file rewritten by another tool) is not
    joined to the new file: its values would be silently wrong."""
    tracked, _ = runs
    d = read_points3d(tracked)
    copy = tmp_path / "points3d.csv"
    copy.write_bytes(tracked.read_bytes())
    side = tmp_path / "points3d.extra.csv"
    side.write_bytes(tracked.with_name("points3d.extra.csv").read_bytes())
    assert set(read_points3d(copy)["extra"]) == set(d["extra"])
    text = copy.read_text().splitlines(keepends=True)
    copy.write_text("".join(text[:-1]))  # another file (one frame fewer)
    with caplog.at_level("WARNING"):
        again = read_points3d(copy)
    assert again["extra"] == {}
    assert "points3d.extra.csv" in caplog.text and "left out" in caplog.text
