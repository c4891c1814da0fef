"""benchmarks/real_motion.py end to end on a tiny configuration (150 frames, one 3-camera
8-part scene, dlt and rigid, no stability table)."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

from adjust.scene.motion import MOTION_PAPER8, MOTION_PARTS22, part_set

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "benchmarks" / "real_motion.py"


def _load(name: str = "real_motion"):
    """benchmarks/NAME.py as a module (skipped where the real motion is not present)."""
    spec = importlib.util.spec_from_file_location(f"{name}_bench", SCRIPT.parent / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)  # puts benchmarks/ on sys.path for its own imports
    if not mod.DATA.is_file():
        pytest.skip(f"{mod.DATA} not present")
    return mod


def test_tiny_run(tmp_path, one_thread):
    rm = _load()
    if not rm.DATA.is_file():
        pytest.skip(f"{rm.DATA} not present")
    out = tmp_path / "x.json"
    rm.main(
        ["--frames", "150", "--cameras", "3", "--parts", "8", "--seeds", "0",
         "--methods", "dlt,rigid", "--no-stability", "--work", str(tmp_path / "work"),
         "--out", str(out), "-o", "body_fit.scale_factor=1.05"]
    )  # fmt: skip
    res = json.loads(out.read_text())
    assert res["split"] == "test" and res["frames"] == [2400, 2550]
    rows = {r["method"]: r for r in res["rows"]}
    assert set(rows) == {"dlt", "rigid"}
    for r in rows.values():
        assert r["cameras"] == 3 and r["parts"] == 8 and r["seed"] == 0
        assert "error" not in r
        for k in ("rmse_all", "rmse_seen2", "rmse_occluded"):
            assert r[k] is not None and math.isfinite(r[k]) and r[k] > 0
    assert rows["dlt"]["completeness"] < 1.0
    assert rows["rigid"]["completeness"] == 1.0
    assert rows["rigid"]["diverged"] is False
    assert res["overrides"] == ["body_fit.scale_factor=1.05"]  # -o: every tracker run's
    assert rows["rigid"]["scale_factor"] == 1.05
    per = rows["rigid"]["calib_per_part"]  # the calibration part by part
    assert list(per) == list(MOTION_PAPER8)
    seen = [d["seen"] for d in per.values() if d["seen"] is not None]
    assert len(seen) >= 4 and all(0.1 < v < 10 for v in seen)
    assert "c3_p8" in res["aggregate"]
    assert res["stability"] is None


def test_part_sets_and_constraints():
    rm = _load()
    parts = tuple(f"p{i}" for i in range(34))
    src, names = part_set(8, parts)
    assert names == list(MOTION_PAPER8) and src == list(MOTION_PAPER8.values())
    assert part_set(22, parts)[0] == list(MOTION_PARTS22)
    assert part_set(34, parts)[1] == list(parts)
    with pytest.raises(ValueError, match="part set must be 8, 22 or 34"):
        part_set(12, parts)
    skeleton = Path(rm.DATA).parent / "skeleton.csv"
    strong, weak = rm.skeleton_constraints(skeleton, list(MOTION_PARTS22))
    assert set(strong) == set(rm.HEAD_TRIANGLE)
    assert ("Neck", "Trunk") in weak or not skeleton.is_file()
    assert all(a in MOTION_PARTS22 and b in MOTION_PARTS22 for a, b in strong + weak)
    assert rm.target_ratio(2, 8) == 0.6 and rm.target_ratio(4, 8) == 0.8
    assert rm.target_ratio(3, 22) == 0.8


def test_calibrated_parts_counts_the_parts_within_the_range():
    rm = _load()
    per = {
        "a": {"seen": 1.0, "occluded": 0.5, "unseen": float("nan")},
        "b": {"seen": 1.3, "occluded": 1.1, "unseen": 1.0},
        "c": {"seen": 0.9, "occluded": float("nan"), "unseen": float("nan")},
    }
    assert rm.calibrated_parts(per) == {"seen": [2, 3], "occluded": [1, 2]}


def test_stride_films_every_nth_frame(tmp_path):
    """--stride N: the scene is every Nth frame of the segment (a camera at 1/N of the
    recording's rate), cached under its own key, and --frames stays within the segment."""
    rm = _load()
    if not rm.DATA.is_file():
        pytest.skip(f"{rm.DATA} not present")
    motion = rm.Motion(rm.DATA)
    key = rm.scene_key("val", 1200, 40, 3, 8, 0, stride=3)
    assert key == "val_1200-1320_c3_p8_s0_x3" and rm.scene_key("val", 1200, 40, 3, 8, 0) == (
        "val_1200-1240_c3_p8_s0"
    )
    scene = rm.film_scene(tmp_path / key, motion, 1200, 40, 3, 8, 0, stride=3)
    truth = np.load(scene / "truth.npz")
    src = [motion.parts.index(p) for p in MOTION_PAPER8.values()]
    np.testing.assert_allclose(truth["points"], motion.points[1200:1320:3][:, src], atol=1e-6)
    with pytest.raises(SystemExit):
        rm.main(["--stride", "3", "--frames", "400", "--work", str(tmp_path / "w")])


def test_units_benchmark_tiny_run(tmp_path, one_thread):
    """benchmarks/units.py on 120 frames: the files in cm and m with the unit declared track as
    the mm file does (its check), and read as mm they do not."""
    units = _load("units")
    res = units.main(
        ["--frames", "120", "--cameras", "3", "--methods", "rigid",
         "--work", str(tmp_path / "work"), "--out", str(tmp_path / "u.json")]
    )  # fmt: skip
    line = res["table"]["3 cameras, rigid"]
    assert res["checks"]["declared_within_2pct"], line
    assert line["m as mm / mm"] > 1.1, line


def test_sync_benchmark_tiny_run(tmp_path, one_thread):
    """benchmarks/sync.py on 150 frames: a camera moved by 5 frames is found and shifted back
    (its check), the real recordings show no offset."""
    sync = _load("sync")
    res = sync.main(
        ["--frames", "150", "--cameras", "3", "--lags", "5", "--drops", "",
         "--work", str(tmp_path / "work"), "--out", str(tmp_path / "s.json")]
    )  # fmt: skip
    assert res["checks"]["every_offset_found"] and res["checks"]["no_offset_on_real"], res
    (row,) = res["rows"]
    assert row["found"] == 5 and row["checked"]["rmse_all"] < row["unchecked"]["rmse_all"]


def test_moves_benchmark_tiny_run(tmp_path, one_thread):
    """benchmarks/moves.py on 300 frames (3 cameras, each turned 1 deg at frame 150 in turn):
    every move mapped to the camera that turned, the tracks as unmoved (its checks), worse
    unchecked."""
    moves = _load("moves")
    res = moves.main(
        ["--split", "val", "--frames", "300", "--cameras", "3", "--degrees", "1", "--axes", "y",
         "--at", "150", "--no-peer", "--work", str(tmp_path / "work"),
         "--out", str(tmp_path / "m.json")]
    )  # fmt: skip
    checks = res["checks"]
    assert checks["mapped_moves_right_camera"] and checks["mapped_within_5pct_of_unmoved"], res
    assert checks["no_move_on_unmoved"] and checks["mapped"] == "3 of 3", checks
    assert all(r["unchecked_all"] > 1.1 * r["unmoved_all"] for r in res["rows"]), res["rows"]


def test_subframe_benchmark_tiny_run(tmp_path, one_thread):
    """benchmarks/subframe.py on 400 frames (3 cameras, the front one half a frame late): the
    offset found on the late camera, none in step (its checks), and the seen part-frames
    tracked better checked than unchecked."""
    sub = _load("subframe")
    res = sub.main(
        ["--split", "val", "--frames", "400", "--cameras", "3", "--late", "0.5",
         "--strides", "1", "--late-cameras", "front", "--no-peer",
         "--work", str(tmp_path / "work"), "--out", str(tmp_path / "s.json")]
    )  # fmt: skip
    checks = res["checks"]
    assert checks["found_right_camera_within_0.1"] and checks["no_offset_in_step"], res
    (row,) = res["rows"]
    assert set(row["found"]) == {"front"}, row
    assert row["checked_seen"] < row["unchecked_seen"], row


def test_rates_benchmark_tiny_run(tmp_path, one_thread):
    """benchmarks/rates.py on 400 frames (3 cameras, the front one at twice and at half the
    others' frame rate): found with the right ratio, tracked as the scene at one rate (its
    checks), and worse unchecked."""
    rates = _load("rates")
    res = rates.main(
        ["--split", "val", "--frames", "400", "--cameras", "3", "--ratios", "2,-2",
         "--rate-cameras", "front", "--no-peer",
         "--work", str(tmp_path / "work"), "--out", str(tmp_path / "r.json")]
    )  # fmt: skip
    assert res["checks"]["found_every_camera"], res
    assert res["checks"]["checked_within_5pct_of_one_rate"], res
    assert all(r["unchecked_all"] > 1.1 * r["checked_all"] for r in res["rows"]), res["rows"]


def test_pixels_benchmark_tiny_run(tmp_path, one_thread):
    """benchmarks/pixels.py on 300 frames (3 cameras: every video downsampled 2x, each camera
    cropped in turn): the spoilt cameras mapped, none other, tracked as calibrated (its
    checks); unchecked worse."""
    px = _load("pixels")
    res = px.main(
        ["--split", "val", "--frames", "300", "--cameras", "3", "--no-peer",
         "--work", str(tmp_path / "work"), "--out", str(tmp_path / "p.json")]
    )  # fmt: skip
    assert res["checks"]["mapped_the_spoilt_cameras"], res
    assert res["checks"]["checked_within_5pct_of_calibrated"], res
    assert all(r["unchecked_all"] > 1.2 * r["checked_all"] for r in res["rows"].values()), res


def test_sides_benchmark_tiny_run(tmp_path, one_thread):
    """benchmarks/sides.py on 300 frames (2 cameras, each with every pair or all but the first
    swapped in turn): the swapped pairs found, nothing else, tracked as labelled (its checks);
    unchecked worse."""
    sd = _load("sides")
    res = sd.main(
        ["--split", "val", "--frames", "300", "--cameras", "2", "--no-peer",
         "--work", str(tmp_path / "work"), "--out", str(tmp_path / "s.json")]
    )  # fmt: skip
    n = res["checks"]["runs"]
    assert n == 4 and res["checks"]["found_the_swapped_pairs"] == n, res
    assert res["checks"]["checked_within_2pct_of_labelled"] == n, res
    assert all(r["unchecked_all"] > 1.2 * r["checked_all"] for r in res["rows"].values()), res


def test_clocks_benchmark_tiny_run(tmp_path, one_thread):
    """benchmarks/clocks.py on 600 frames (3 cameras, the front one at 25 against the others'
    30 fps): its clock found, its lag within half a frame, none in step (its checks), and it
    tracks far better checked than unchecked."""
    ck = _load("clocks")
    res = ck.main(
        ["--split", "val", "--frames", "600", "--cameras", "3", "--rates", "0.8333",
         "--drops", "", "--clock-cameras", "front", "--no-peer",
         "--work", str(tmp_path / "work"), "--out", str(tmp_path / "c.json")]
    )  # fmt: skip
    checks = res["checks"]
    assert checks["found_right"] == "1 of 1", res
    assert checks["every_found_right"] and checks["no_map_in_step"], res
    (row,) = res["rows"]
    assert row["unchecked_all"] > 1.5 * row["checked_all"], row


def test_lens_benchmark_tiny_run(tmp_path, one_thread):
    """benchmarks/lens.py on 300 frames (3 cameras through wide lenses, every camera's video
    undistorted): no camera mapped but those (two of the three: the side camera's detections
    stay near its image's centre, where the readings differ little), none as filmed; tracked
    within 10% of the scene as filmed, unchecked 8x worse."""
    ln = _load("lens")
    res = ln.main(
        ["--split", "val", "--frames", "300", "--cameras", "3", "--cases", "every", "--no-peer",
         "--work", str(tmp_path / "work"), "--out", str(tmp_path / "l.json")]
    )  # fmt: skip
    assert res["checks"]["no_other_camera_mapped"], res
    assert res["checks"]["none_mapped_as_filmed"], res
    (row,) = res["rows"].values()
    assert len(row["mapped"]) >= 2 and row["checked_all"] <= 1.1 * row["filmed_all"], row
    assert row["unchecked_all"] > 5 * row["checked_all"], row
