"""Detections made on videos other than the calibrated ones (`adjust.pixels`): a rig whose
videos were all downsampled, and a camera whose video was cropped, are found from the epipolar
geometry and mapped back into the calibrated images; cameras as calibrated, and the real
recordings, are left alone."""

from __future__ import annotations

import dataclasses
import itertools
import logging

import numpy as np
import pytest
import torch
from helpers import projected_detections

from adjust.camera import Camera
from adjust.camera_check import check_from_config, drop_cameras
from adjust.chunks import ChunkHooks, SessionModel
from adjust.io import InputError, load_scene
from adjust.moves import check_moves
from adjust.pixels import TURNS, apply, check_pixels, edit_map
from adjust.scene import default_rig
from adjust.scene.motion import (
    MOTION_FEET,
    MOTION_PAPER8,
    floor_frame,
    load_motion,
    motion_rig,
    write_motion_scene,
)
from deformnet.paths import real_mouse_motion_dir, shared_dir

torch.set_num_threads(1)
DATA = shared_dir() / "data"


def _det(cams, T: int = 400, seed: int = 0):
    """Detections (0.5 px noise) of parts wandering round the arena, and the noiseless ones."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 4 * np.pi, T)
    centre = np.stack([150 + 60 * np.cos(t), 150 + 60 * np.sin(2 * t), 30 + 10 * np.sin(3 * t)], -1)
    X = centre[:, None] + rng.normal(0, 20, (1, 8, 3))
    return (projected_detections(cams, X, 0.5, np.random.default_rng(seed + 1)),
            projected_detections(cams, X, 0.0, np.random.default_rng(0)))  # fmt: skip


def _edit(det, c: int | None, fn):
    xy = det.xy.copy()
    for k in range(det.num_cameras) if c is None else [c]:
        xy[:, :, k] = fn(xy[:, :, k])
    return dataclasses.replace(det, xy=xy)


def _downsampled(xy: np.ndarray, f: float = 2.0) -> np.ndarray:
    """Pixels of a video resized by 1/f (pixel centres: u = (x + 0.5) / f - 0.5)."""
    return (xy + 0.5) / f - 0.5


def test_a_downsampled_rig_is_mapped_back(caplog):
    cams = default_rig()
    det, truth = _det(cams)
    small = _edit(det, None, _downsampled)
    with caplog.at_level(logging.WARNING, logger="adjust.pixels"):
        out, rep = check_pixels(cams, small)
    assert set(rep["mapped"]) == {c.name for c in cams}, rep
    for m in rep["mapped"].values():
        assert abs(m["scale"] - 2.0) < 0.01 and np.allclose(m["offset"], 0.5, atol=1.0), m
        assert m["epipolar_px"][1] < 2.0 < 20 < m["epipolar_px"][0]
    assert np.nanmedian(np.abs(out.xy - truth.xy)) < 1.0
    assert "downsampled" in caplog.text and "MAPPED" in caplog.text


@pytest.mark.parametrize("ncams", [2, 3])
def test_a_cropped_camera_is_mapped_back_alone(ncams):
    """The last camera's video cropped at (200, 150): that camera alone is mapped, by the
    crop's offset (within a pixel) and scale 1 (within 0.5%)."""
    cams = default_rig()[:ncams]
    det, truth = _det(cams)
    crop = _edit(det, ncams - 1, lambda xy: xy - np.array([200.0, 150.0]))
    out, rep = check_pixels(cams, crop)
    name = cams[-1].name
    assert set(rep["mapped"]) == {name}, rep
    m = rep["mapped"][name]
    assert abs(m["scale"] - 1) < 0.005 and np.allclose(m["offset"], [200, 150], atol=1.0), m
    assert np.nanmedian(np.abs(out.xy[:, :, -1] - truth.xy[:, :, -1])) < 1.0


@pytest.mark.parametrize(("ncams", "c", "axes"), [(3, 1, "x"), (3, 0, "y"), (3, 2, "xy"),
                                                 (2, 0, "x"), (2, 1, "x")])  # fmt: skip
def test_a_flipped_camera_is_mapped_back(ncams, c, axes, caplog):
    """Camera c's video mirrored left to right (x), upside down (y) or both (a half turn)
    before the pose estimator: that camera alone is mapped back (either of two cameras: a
    flip is no crop, the geometry tells which)."""
    cams = default_rig()[:ncams]
    det, truth = _det(cams)
    W, H = cams[c].size
    flip = np.array([-1.0 if "x" in axes else 1.0, -1.0 if "y" in axes else 1.0])
    offset = np.array([W - 1.0 if "x" in axes else 0.0, H - 1.0 if "y" in axes else 0.0])
    bad = _edit(det, c, lambda xy: flip * xy + offset)
    with caplog.at_level(logging.WARNING, logger="adjust.pixels"):
        out, rep = check_pixels(cams, bad)
    name = cams[c].name
    assert set(rep["mapped"]) == {name}, rep
    m = rep["mapped"][name]
    assert m["scale"] == flip.tolist() and np.allclose(m["offset"], offset), m
    np.testing.assert_allclose(out.xy, det.xy, atol=1e-9)
    assert "flipped" in caplog.text and "MAPPED" in caplog.text


@pytest.mark.parametrize(("ncams", "c", "how"), [(3, 1, 0), (3, 2, 1), (4, 0, 2), (3, 0, 3),
                                                (2, 0, 0), (2, 1, 2)])  # fmt: skip
def test_a_turned_or_transposed_camera_is_mapped_back(ncams, c, how, caplog):
    """Camera c's video turned a quarter turn (a camera on its side, its video turned upright)
    or its x and y swapped: that camera alone is mapped back, by the turn, to the bit (either
    of two cameras); its pixels before lie in the turned video (H px wide), as a file has them."""
    how = list(TURNS)[how]
    cams = default_rig()[:ncams]
    det, _ = _det(cams)
    W, H = cams[c].size
    A, d = (np.array(v) for v in edit_map(how, (W, H)))
    bad = _edit(det, c, lambda xy: (xy - d) @ A)  # u = A^T (x - d): A is orthogonal
    u = bad.xy[:, :, c][np.isfinite(bad.xy[:, :, c]).all(-1)]
    assert (u.min(0) >= -0.5).all() and (u.max(0) <= np.array([H, W]) - 0.5).all()
    with caplog.at_level(logging.WARNING, logger="adjust.pixels"):
        out, rep = check_pixels(cams, bad)
    name = cams[c].name
    assert set(rep["mapped"]) == {name}, rep
    m = rep["mapped"][name]
    assert m["turn"] == how and m["scale"] == A.tolist() and np.allclose(m["offset"], d), m
    assert m["epipolar_px"][1] < 2.0 < 20 < m["epipolar_px"][0]
    np.testing.assert_allclose(out.xy, det.xy, atol=1e-9)
    assert how in caplog.text and "MAPPED" in caplog.text


def test_a_shift_that_more_than_one_camera_explains_is_not_mapped(tmp_path, caplog):
    """The real motion filmed by the 3-camera rig (the scene detector: occlusion, outliers):
    the front camera's principal point 15 px off is told (its shift mapped back); the top
    camera's is not: a shift of top or of front fits the rig alike (1.6 px), so neither is
    mapped, with a warning naming both (before, the front camera's detections were shifted and
    the tracks came out 2.2x the calibrated scene's); the move check leaves it unresolved too."""
    X, parts = load_motion(real_mouse_motion_dir() / "poses3d.csv")
    rig = motion_rig(floor_frame(X, parts, MOTION_FEET), 3)
    rename = {v: k for k, v in MOTION_PAPER8.items()}
    write_motion_scene(tmp_path, X[2400:2800], parts, rig, list(MOTION_PAPER8.values()), rename)
    cams, det = load_scene(tmp_path / "calibration.toml", tmp_path / "detections", None)

    def off(c: int) -> list:
        K = cams[c].K.copy()
        K[0, 2] += 15.0
        out = list(cams)
        out[c] = Camera.from_matrices(cams[c].name, K, cams[c].R, cams[c].tvec, cams[c].dist,
                                      cams[c].size)  # fmt: skip
        return out

    names = [c.name for c in cams]
    front, top = names.index("front"), names.index("top")
    _, rep = check_pixels(off(front), det)
    assert list(rep["mapped"]) == ["front"], rep
    assert np.allclose(rep["mapped"]["front"]["offset"], [15.0, 0.0], atol=0.5), rep
    with caplog.at_level(logging.WARNING, logger="adjust.pixels"):
        _, rep = check_pixels(off(top), det)
    assert rep["mapped"] == {}, rep
    assert "not told" in caplog.text and "'top'" in caplog.text and "'front'" in caplog.text
    assert sorted(check_moves(off(top), det, 3)[1]["unresolved"]["cameras"]) == ["front", "top"]


def test_cameras_as_calibrated_and_real_recordings_are_left_alone():
    cams = default_rig()
    det, _ = _det(cams)
    out, rep = check_pixels(cams, det)
    assert rep["mapped"] == {} and out is det
    for folder, pattern in (("real-hand-4cam", None), ("real-mouse-sleap-4cam", "*.analysis.h5")):
        root = DATA / folder
        dets = root / "trial_000" if folder == "real-hand-4cam" else root
        rc, rd = load_scene(root / "calibration.toml", dets, None, pattern=pattern)
        names = [c.name for c in rc]
        for k in range(2, len(names) + 1):  # the SLEAP mouse's wrong `side` pose too
            for keep in itertools.combinations(names, k):
                sc, sd = drop_cameras(rc, rd, [n for n in names if n not in keep])
                assert check_pixels(sc, sd)[1]["mapped"] == {}, keep


def test_error_mode_config_and_chunks():
    """Error mode names the camera and its file; ``input.pixel_check`` (default true) runs it
    first in the camera check (the cropped camera is no longer excluded), false does not; a
    long session's chunks map their rows as the sample found."""
    cams = default_rig()
    det, _ = _det(cams)
    crop = _edit(det, 1, lambda xy: xy - np.array([200.0, 150.0]))
    with pytest.raises(InputError, match=rf"camera '{cams[1].name}' \({cams[1].name}.csv\)"):
        check_pixels(cams, crop, "error")
    _, _, rep = check_from_config(cams, crop, {})
    assert set(rep["pixels"]["mapped"]) == {cams[1].name} and rep["excluded"] == {}
    _, _, off = check_from_config(cams, crop, {"pixel_check": False})
    assert "pixels" not in off and set(off["excluded"]) == {cams[1].name}
    model = SessionModel(None, None, None, None, (), rep, {})
    _, got, _ = ChunkHooks(None, 0, det.num_frames, model=model, keep=(0, det.num_frames)
                           ).check_cameras(cams, crop, {})  # fmt: skip
    m = rep["pixels"]["mapped"][cams[1].name]
    want = apply(crop, {cams[1].name: (m["scale"], m["offset"])})
    np.testing.assert_array_equal(got.xy, want.xy)
