"""Camera check: a camera that disagrees with the others is named, diagnosed and excluded."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest
import torch
from helpers import projected_detections

from adjust.camera import Camera
from adjust.camera_check import check_cameras, check_from_config
from adjust.io import Detections, InputError, load_scene
from adjust.scene import camera_look_at, default_rig
from deformnet.paths import shared_dir

torch.set_num_threads(1)
SLEAP_MOUSE = shared_dir() / "data" / "real-mouse-sleap-4cam"


def _rig() -> list[Camera]:
    cams = default_rig()
    back = camera_look_at("back", (150.0, 870.0, 220.0), (150.0, 150.0, 0.0), focal_px=1800.0)
    return [*cams, back]


def _scene(cams, T=60, K=6, noise=0.5, seed=0) -> Detections:
    """A wandering cloud of K points in the arena, seen by every camera with pixel noise."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, T)
    centre = np.stack([150 + 60 * np.cos(t), 150 + 60 * np.sin(2 * t), 30 + 0 * t], -1)
    X = centre[:, None] + rng.normal(0, 20, (1, K, 3)) + rng.normal(0, 3, (T, K, 3))
    return projected_detections(cams, X, noise, rng)


def _with(det: Detections, c: int, xy: np.ndarray) -> Detections:
    new = det.xy.copy()
    new[:, :, c] = xy
    return dataclasses.replace(det, xy=new)


def test_consistent_cameras_are_kept():
    cams = _rig()
    det = _scene(cams)
    kept, d2, rep = check_cameras(cams, det)
    assert [c.name for c in kept] == ["top", "side", "front", "back"] and rep["excluded"] == {}
    assert max(rep["leave_one_out_px"].values()) < 2.0  # 0.5 px noise
    assert d2.xy.shape == det.xy.shape


def _case(kind: str):
    cams = _rig()
    det = _scene(cams)
    c = 1  # side
    if kind == "wrong pose":
        bad = camera_look_at("side", (-520.0, 350.0, 300.0), (130.0, 170.0, 10.0), focal_px=1800.0)
        cams = [*cams[:c], bad, *cams[c + 1 :]]
    elif kind == "reverse":
        det = _with(det, c, det.xy[::-1, :, c])
    elif kind == "offset":
        shifted = np.full_like(det.xy[:, :, c], np.nan)
        shifted[:-3] = det.xy[3:, :, c]  # its file lost its first 3 frames
        det = _with(det, c, shifted)
    elif kind == "swap":
        xy = det.xy.copy()
        xy[:, :, [1, 2]] = xy[:, :, [2, 1]]
        det = dataclasses.replace(det, xy=xy)
    return cams, det


@pytest.mark.parametrize(
    ("kind", "cause"),
    [
        ("wrong pose", "wrong pose"),
        ("reverse", "rows in reverse frame order"),
        ("offset", "frames offset by"),
        ("swap", "swapped with camera"),
    ],
)
def test_bad_camera_named_diagnosed_excluded(kind, cause, caplog):
    cams, det = _case(kind)
    with caplog.at_level(logging.WARNING):
        kept, d2, rep = check_cameras(cams, det)
    assert "side" in rep["excluded"], rep
    assert rep["excluded"]["side"]["cause"].startswith(cause), rep["excluded"]
    assert rep["excluded"]["side"]["error_px"] > 20.0
    assert "'side' (side.csv)" in caplog.text and "EXCLUDED" in caplog.text
    assert "side" not in [c.name for c in kept] and "side" not in d2.cameras
    if kind == "swap":  # both swapped cameras go, each diagnosed as swapped with the other
        assert set(rep["excluded"]) == {"side", "front"}
        assert "swapped with camera 'side'" in rep["excluded"]["front"]["cause"]
    else:
        assert len(kept) == 3
    with pytest.raises(InputError, match=r"cameras? 'side'.*disagree"):
        check_cameras(cams, det, mode="error")


def test_rotated_sign_camera_behind():
    """A camera whose rotation is negated sees the scene behind it."""
    cams = _rig()
    det = _scene(cams)
    c = 1
    flip = np.diag([-1.0, 1.0, -1.0])  # 180 degrees about the camera's y axis
    R = flip @ cams[c].R
    bad = Camera.from_matrices("side", cams[c].K, R, flip @ cams[c].tvec, size=cams[c].size)
    cams = [*cams[:c], bad, *cams[c + 1 :]]
    _, _, rep = check_cameras(cams, det)
    assert rep["excluded"]["side"]["cause"] == "scene behind the camera"


def test_swapped_files_with_three_cameras_is_an_error():
    """Three cameras, two files swapped: no camera can be left out (one good camera would be
    left); the swap is named instead of excluding the one good camera."""
    cams = default_rig()
    det = _scene(cams)
    xy = det.xy.copy()
    xy[:, :, [1, 2]] = xy[:, :, [2, 1]]
    with pytest.raises(InputError, match=r"'side'.*and 'front'.*look swapped"):
        check_cameras(cams, dataclasses.replace(det, xy=xy))


def test_settings_by_hand_and_off():
    cams, det = _case("wrong pose")
    kept, d2, rep = check_from_config(cams, det, {"exclude_cameras": ["side"]})
    assert [c.name for c in kept] == ["top", "front", "back"] and rep["excluded"] == {}
    assert rep["excluded_by_hand"] == ["side"]
    kept, _, rep = check_from_config(cams, det, {"camera_check": "off"})
    assert len(kept) == 4 and rep["mode"] == "off"
    with pytest.raises(InputError, match="input.camera_check must be one of"):
        check_from_config(cams, det, {"camera_check": "maybe"})
    with pytest.raises(InputError, match=r"unknown cameras \['nope'\]"):
        check_from_config(cams, det, {"exclude_cameras": "nope"})


def test_shared_sleap_mouse_side_excluded():
    assert SLEAP_MOUSE.is_dir(), f"shared data missing: {SLEAP_MOUSE}"
    cams, det = load_scene(
        SLEAP_MOUSE / "calibration.toml", SLEAP_MOUSE, None, 0.0, pattern="*.analysis.h5"
    )
    kept, d2, rep = check_cameras(cams, det)
    assert list(rep["excluded"]) == ["side"]
    side = rep["excluded"]["side"]
    assert side["error_px"] > 60 and side["cause"] == "wrong pose"  # measured 95.8 px
    assert "pose of camera ['top']" in side["detail"]
    assert [c.name for c in kept] == ["back", "mid", "top"]
