"""Detections made on videos undistorted before the pose estimator while the calibration keeps
the lens's distortion (`adjust.lens`): the cameras so read are found from the epipolar geometry
away from the image's centre and their detections mapped back into the calibrated images; a
rig as filmed, one a little off, one whose calibration lacks a camera's distortion, and the real
recordings are left alone."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from helpers import projected_detections
from scipy.spatial.transform import Rotation

import adjust.lens as lens
from adjust.camera import Camera
from adjust.camera_check import check_from_config
from adjust.chunks import ChunkHooks, SessionModel
from adjust.distortion import undistort_points
from adjust.io import InputError, load_scene
from adjust.lens import (
    as_undistorted,
    check_lens,
    pair_scores,
    rig_score,
    turned_score,
    undistorted_map,
)
from adjust.scene import default_rig
from adjust.sync import normalised_points
from deformnet.paths import shared_dir

torch.set_num_threads(1)
DATA = shared_dir() / "data"


def _cams(n: int = 3, k1: float = -0.8, focal: float = 800.0):
    """The default rig's first n cameras with wide lenses (barrel distortion k1)."""
    out = []
    for cam in default_rig()[:n]:
        K = cam.K.copy()
        K[0, 0] = K[1, 1] = focal
        out.append(dataclasses.replace(cam, K=K, dist=np.array([k1, 0.0, 0.0, 0.0, 0.0])))
    return out


def _det(cams, T: int = 400, seed: int = 0):
    """Detections (0.5 px noise) of parts wandering over the arena, into the lenses' margins."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 4 * np.pi, T)
    c = np.stack([150 + 150 * np.cos(t), 150 + 150 * np.sin(2 * t), 30 + 10 * np.sin(3 * t)], -1)
    X = c[:, None] + rng.normal(0, 25, (1, 8, 3))
    return projected_detections(cams, X, 0.5, np.random.default_rng(seed + 1))


def _undistorted(det, cams, which):
    """The detections of cameras `which` as on their videos undistorted (cv2.undistort: the
    camera matrix kept)."""
    xy = det.xy.copy()
    for c in which:
        K, d = torch.as_tensor(cams[c].K), torch.as_tensor(cams[c].dist)
        xy[:, :, c] = undistort_points(torch.as_tensor(xy[:, :, c]), K, d, pixels=True).numpy()
    return dataclasses.replace(det, xy=xy)


@pytest.mark.parametrize(
    "ncams,which", [(3, [0]), (3, [2]), (3, [0, 1, 2]), (2, [0]), (2, [1]), (2, [0, 1])]
)
def test_cameras_on_undistorted_videos_are_mapped_back(ncams, which, caplog):
    cams = _cams(ncams)
    det = _det(cams)
    with caplog.at_level("WARNING", logger="adjust.lens"):
        out, rep = check_lens(cams, _undistorted(det, cams, which))
    assert sorted(rep["undistorted"]) == sorted(cams[c].name for c in which), rep
    for m in rep["undistorted"].values():
        assert m["epipolar_px"][1] < 1.0 < 2.0 < m["epipolar_px"][0] and m["part_frames"] > 100
    np.testing.assert_allclose(out.xy, det.xy, atol=1e-6)  # the map undoes the undistortion
    assert "undistorted" in caplog.text and "MAPPED" in caplog.text


def test_rigs_as_filmed_or_a_little_off_are_left_alone():
    cams = _cams(3)
    det = _det(cams)
    for rig in (
        cams,
        [dataclasses.replace(c, K=c.K * [[1.02], [1.02], [1]]) if i == 1 else c
         for i, c in enumerate(cams)],  # a focal length 2% off
        # a camera whose calibration lacks its lens's distortion: reading the others as
        # undistorted brings them to it, and away from each other
        [dataclasses.replace(c, dist=np.zeros(5)) if i == 0 else c for i, c in enumerate(cams)],
    ):  # fmt: skip
        out, rep = check_lens(rig, det)
        assert rep["undistorted"] == {} and out is det
    plain = [dataclasses.replace(c, dist=np.zeros(5)) for c in cams]  # nothing to read twice
    _, rep = check_lens(plain, _det(plain))
    assert rep["undistorted"] == {}


def test_error_mode_and_the_camera_check():
    cams = _cams(3)
    det = _det(cams)
    bad = _undistorted(det, cams, [1])
    with pytest.raises(InputError, match=f"camera '{cams[1].name}'.*undistorted"):
        check_lens(cams, bad, mode="error")
    _, got, rep = check_from_config(cams, bad, {})
    assert sorted(rep["lens"]["undistorted"]) == [cams[1].name] and rep["excluded"] == {}
    np.testing.assert_allclose(got.xy, det.xy, atol=1e-6)
    _, _, off = check_from_config(cams, bad, {"pixel_check": False})
    assert "lens" not in off
    # a long session's chunks are mapped as the sample's check said
    model = SessionModel(None, None, None, None, (), rep, {})
    _, chunk, _ = ChunkHooks(None, 0, det.num_frames, model=model, keep=(0, det.num_frames)
                             ).check_cameras(cams, bad, {})  # fmt: skip
    np.testing.assert_array_equal(chunk.xy, undistorted_map(bad, cams[1]).xy)


def _real(name: str):
    folder = DATA / name
    assert folder.is_dir(), f"shared data missing: {folder}"
    pattern = {"pattern": "*.analysis.h5"} if "sleap" in name else {}
    src = folder / "trial_000" if "hand" in name else folder
    return load_scene(folder / "calibration.toml", src, None, **pattern)


@pytest.mark.parametrize("name", ["real-mouse-sleap-4cam", "real-hand-4cam", "real-fly-3cam"])
def test_real_recordings_are_left_alone(name):
    cams, det = _real(name)
    _, _, rep = check_from_config(cams, det, {})
    assert rep["lens"]["undistorted"] == {}


def test_the_real_sleap_mouse_undistorted_is_mapped_back():
    """The real SLEAP mouse's lenses (k1 -0.29 / -0.30): each kept camera's detections, and every
    camera's, undistorted as on undistorted videos, are found and mapped back (its `side`
    camera, whose pose is wrong, is excluded by the camera check as it is without this)."""
    cams, det = _real("real-mouse-sleap-4cam")
    names = [c.name for c in cams]
    for which in ([names.index("back")], [names.index("top")], list(range(len(cams)))):
        _, _, rep = check_from_config(cams, _undistorted(det, cams, which), {})
        want = sorted(names[c] for c in which if names[c] != "side")
        assert sorted(rep["lens"]["undistorted"]) == want, (which, rep["lens"])
        assert sorted(rep["excluded"]) == ["side"]


def test_a_turned_camera_is_no_lens(monkeypatch, caplog):
    """A camera turned since its calibration is fitted as a turn (`turned_score`); where a turn
    fits the margins as well as the undistorted reading, nothing is mapped and the report says
    why (with two cameras of the real motion, a turned one looked like its partner on an
    undistorted video)."""
    cams = _cams(2)
    det = _det(cams)
    turned = list(cams)
    w = np.radians(1.0) * np.array([0.0, 1.0, 0.0])
    R = Rotation.from_rotvec(w).as_matrix()
    turned[1] = Camera.from_matrices(
        cams[1].name, cams[1].K, R @ cams[1].R, R @ cams[1].tvec, cams[1].dist, cams[1].size
    )
    read = normalised_points(det.xy, turned)
    alt = {c: as_undistorted(det.xy[:, :, c], cams[c]) for c in range(2)}
    scores = pair_scores(turned, read, alt)
    c, px, deg = turned_score(turned, read, scores, set())
    assert px < 0.5 * rig_score(scores, frozenset()) and 0.7 < deg < 1.3, (c, px, deg)
    bad = _undistorted(det, cams, [1])
    monkeypatch.setattr(lens, "turned_score", lambda *a: (0, 0.1, 1.0))
    with caplog.at_level("WARNING", logger="adjust.lens"):
        out, rep = check_lens(cams, bad)
    assert rep["undistorted"] == {} and out is bad
    assert rep["unresolved"]["cameras"] == [cams[1].name] and "turned" in caplog.text
