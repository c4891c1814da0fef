"""anipose's everyday features (adjust.kinematics, adjust-export angles / anipose): joint angles
from part triplets, the world frame aligned to named points, recorded in points3d.csv's M and
center columns."""

from __future__ import annotations

from pathlib import Path

import hydra
import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from adjust.apps.export import run as export
from adjust.export import write_anipose
from adjust.io import InputError, read_points3d, write_points3d
from adjust.kinematics import (
    align_tracks,
    apply_axes,
    axes_frame,
    joint_angles,
    parse_angles,
)
from deformnet.behavior.tracks import POSE_COLUMNS
from deformnet.paths import CONF_DIR

PARTS = ["hip", "knee", "ankle", "toe"]


def _cfg(overrides: list[str]):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose("export", overrides=overrides)


def _leg(T: int = 5) -> np.ndarray:
    """(T, 4, 3) mm: hip above knee; the ankle swings so the knee angle is 90 + 10 t degrees."""
    X = np.zeros((T, 4, 3))
    X[:, 0] = [0, 0, 20]
    X[:, 1] = [0, 0, 0]
    for t in range(T):
        a = np.radians(90 + 10 * t)  # the angle at the knee between hip and ankle
        X[t, 2] = 15 * np.array([np.sin(a), 0, np.cos(a)])
    X[:, 3] = X[:, 2] + [5, 0, 0]
    return X


def test_joint_angles_anipose_semantics():
    X = _leg()
    out = joint_angles(X, PARTS, {"knee": ["hip", "knee", "ankle"]})
    np.testing.assert_allclose(out["knee"], 90 + 10 * np.arange(5), atol=1e-9)
    X[2, 2] = np.nan  # a missing point
    X[3, 2] = X[3, 1]  # the ankle on the knee: no direction
    out = joint_angles(X, PARTS, {"knee": ["hip", "knee", "ankle"]})
    assert np.isnan(out["knee"][2]) and np.isnan(out["knee"][3])
    assert np.isfinite(out["knee"][[0, 1, 4]]).all()
    straight = np.array([[[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 0, 0]]], float)
    assert joint_angles(straight, PARTS, [["hip", "knee", "ankle"]])["knee"][0] == 180.0
    with pytest.raises(InputError, match="unknown part"):
        joint_angles(X, PARTS, {"elbow": ["hip", "elbow", "ankle"]})


def test_parse_angles_forms():
    assert parse_angles({"k": ["a", "b", "c"]}) == {"k": ("a", "b", "c")}
    assert parse_angles([["a", "b", "c"], ["b", "c", "d"]]) == {
        "b": ("a", "b", "c"),
        "c": ("b", "c", "d"),
    }
    assert set(parse_angles([["a", "b", "c"], ["d", "b", "e"]])) == {"a_b_c", "d_b_e"}
    with pytest.raises(ValueError, match="three part names"):
        parse_angles({"k": ["a", "b"]})


def test_export_angles_csv(tmp_path):
    X = _leg()
    T = len(X)
    nan = np.full((T, 4), np.nan)
    tracks = write_points3d(
        tmp_path / "points3d.csv", PARTS, X, nan, nan, nan, fnum=np.arange(T) + 7
    )
    res = export(
        _cfg(["format=angles", f"tracks={tracks}", "+angles.knee=[hip,knee,ankle]",
              "+angles.ankle=[knee,ankle,toe]"])
    )  # fmt: skip
    assert Path(res["output"]) == tmp_path / "angles.csv"
    df = pd.read_csv(res["output"])
    assert list(df.columns) == ["knee", "ankle", "fnum"]  # anipose's angles.csv
    np.testing.assert_allclose(df["knee"], 90 + 10 * np.arange(T), atol=1e-9)
    assert df["fnum"].tolist() == list(range(7, 7 + T))
    # the list form, named after the middle part
    res = export(_cfg(["format=angles", f"tracks={tracks}", "angles=[[hip,knee,ankle]]"]))
    assert list(pd.read_csv(res["output"]).columns) == ["knee", "fnum"]
    with pytest.raises(ValueError, match=r"\+angles.knee="):
        export(_cfg(["format=angles", f"tracks={tracks}"]))


# --- axes alignment ---------------------------------------------------------------------------
def _floor_scene(T: int = 30, seed: int = 0):
    """Arena corners c0, c1, c2 on a tilted, shifted floor plane, and a body above it: the world
    frame of a calibration that knows nothing about the floor."""
    rng = np.random.default_rng(seed)
    R = Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix()  # floor -> world
    shift = np.array([100.0, -50.0, 400.0])
    floor = {"c0": [0, 0, 0], "c1": [300, 0, 0], "c2": [0, 200, 0], "nose": [150, 100, 30]}
    parts = list(floor)
    P = np.array([floor[p] for p in parts], float)
    X = np.repeat(P[None], T, 0) + rng.normal(0, 0.1, (T, len(parts), 3))
    X[:, 3] += rng.normal(0, 5, (T, 3))
    return parts, X @ R.T + shift, R, shift


def test_axes_frame_puts_the_floor_at_z0():
    parts, Xw, R, shift = _floor_scene()
    M, c = axes_frame(Xw, parts, {"x": ["c0", "c1"], "y": ["c0", "c2"]})
    np.testing.assert_allclose(M @ M.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(M) == pytest.approx(1.0)
    np.testing.assert_allclose(M, R.T, atol=2e-3)  # the floor's own axes
    Xa = apply_axes(Xw, M, c)
    np.testing.assert_allclose(np.median(Xa[:, 0], 0), 0, atol=0.1)  # c0 at the origin
    assert np.abs(Xa[:, :3, 2]).max() < 1.0  # the corners on z = 0
    assert 20 < np.median(Xa[:, 3, 2]) < 40  # the nose 30 mm above the floor
    # anipose's semantics: the first axis exact, the second made orthogonal
    M2, _ = axes_frame(Xw, parts, {"y": ["c0", "c2"], "x": ["c0", "c1"]})
    d = np.median(Xw[:, 2], 0) - np.median(Xw[:, 0], 0)  # each point: its median position
    np.testing.assert_allclose(M2[1], d / np.linalg.norm(d), atol=1e-12)
    # points as coordinates, an explicit origin
    M3, c3 = axes_frame(
        Xw, parts, {"x": [[0, 0, 0], [1, 0, 0]], "z": [[0, 0, 0], [0, 0, 1]]}, origin="nose"
    )
    np.testing.assert_allclose(M3, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(c3, np.median(Xw[:, 3], 0))
    for bad, msg in (
        ({"x": ["c0", "c1"]}, "exactly two"),
        ({"x": ["c0", "c1"], "w": ["c0", "c2"]}, "unknown axis"),
        ({"x": ["c0", "c1"], "y": ["c0", "c0"]}, "coincide"),
        ({"x": ["c0", "c1"], "y": ["c0", "tail"]}, "unknown part 'tail'"),
    ):
        with pytest.raises(ValueError, match=msg):
            axes_frame(Xw, parts, bad)


def test_aligned_points3d_records_m_and_center(tmp_path):
    parts, Xw, _, _ = _floor_scene()
    T, K = Xw.shape[:2]
    rng = np.random.default_rng(1)
    err, nc, sc = rng.uniform(0, 2, (T, K)), np.full((T, K), 3), rng.uniform(0.5, 1, (T, K))
    model = np.array([[0, 0, 0], [10, 0, 0], [0, 5, 0], [3, 3, 3]], float)  # a rigid body
    pose = np.concatenate([Rotation.random(T, random_state=2).as_rotvec(), Xw[:, 3]], -1)
    extra = {c: pose[:, i] for i, c in enumerate(POSE_COLUMNS)}
    extra["{part}_sigma"] = rng.uniform(0, 1, (T, K))
    src = write_points3d(tmp_path / "points3d.csv", parts, Xw, err, nc, sc, extra=extra)
    d = read_points3d(src)
    np.testing.assert_array_equal(d["M"], np.eye(3))  # written unaligned: identity, 0

    axes = ["axes.x=[c0,c1]", "axes.y=[c0,c2]"]
    res = export(_cfg(["format=anipose", f"tracks={src}", *axes, "keep_extra=true"]))
    a = read_points3d(res["output"])
    M, c = a["M"], a["center"]
    # anipose's convention: X_out = M X_world - center
    np.testing.assert_allclose(a["points"], Xw @ M.T - c, atol=1e-9)
    np.testing.assert_allclose((a["points"] + c) @ M, Xw, atol=1e-9)  # and back
    assert np.abs(a["points"][:, :3, 2]).max() < 1.0
    np.testing.assert_array_equal(a["error"], d["error"])  # distances unchanged
    np.testing.assert_array_equal(a["extra"]["c0_sigma"], d["extra"]["c0_sigma"])
    # the body pose moved with the points: model -> aligned frame
    pa = np.stack([a["extra"][k] for k in POSE_COLUMNS], -1)
    body_w = np.einsum("tij,kj->tki", Rotation.from_rotvec(pose[:, :3]).as_matrix(), model)
    body_w += pose[:, None, 3:]
    body_a = np.einsum("tij,kj->tki", Rotation.from_rotvec(pa[:, :3]).as_matrix(), model)
    body_a += pa[:, None, 3:]
    np.testing.assert_allclose(body_a, body_w @ M.T - c, atol=1e-9)
    # aligning an aligned file composes M and center: still relative to the world frame
    again = align_tracks(a, {"x": ["c1", "c0"], "y": ["c0", "c2"]})
    np.testing.assert_allclose(again["points"], Xw @ again["M"].T - again["center"], atol=1e-9)
    # anipose's layout alone (default): our other columns dropped
    plain = write_anipose(tmp_path / "plain.csv", src, axes={"x": ["c0", "c1"], "y": ["c0", "c2"]})
    header = plain.read_text().splitlines()[0].split(",")
    assert header[-13:] == [
        "M_00", "M_01", "M_02", "M_10", "M_11", "M_12", "M_20", "M_21", "M_22",
        "center_0", "center_1", "center_2", "fnum",
    ]  # fmt: skip
    assert not any(h.startswith("pose_") or h.endswith("_sigma") for h in header)
