"""Frame offsets between cameras (`adjust.sync`): a camera out of step in time with the others
is found from the epipolar geometry, named and shifted back; cameras in step, a still animal
and the real recordings get no offset."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest
import torch
from helpers import projected_detections

from adjust.camera_check import check_from_config
from adjust.io import Detections, InputError, load_scene
from adjust.scene import default_rig
from adjust.sync import check_sync, epipolar_px, essential, row_offsets, shift_cameras
from deformnet.paths import shared_dir

torch.set_num_threads(1)
DATA = shared_dir() / "data"


def _points(T: int, K: int = 6, seed: int = 0, still: bool = False) -> np.ndarray:
    """(T, K, 3) mm: K points about a centre that wanders round the arena, each moving 1 mm rms
    about it, or standing still."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 4 * np.pi, T) * (0.0 if still else 1.0)
    centre = np.stack([150 + 60 * np.cos(t), 150 + 60 * np.sin(2 * t), 30 + 0 * t], -1)
    jitter = rng.normal(0, 0.0 if still else 1.0, (T, K, 3))
    return centre[:, None] + rng.normal(0, 20, (1, K, 3)) + jitter


def _detections(cams, X: np.ndarray, noise: float = 0.5, seed: int = 1) -> Detections:
    return projected_detections(cams, X, noise, np.random.default_rng(seed))


def _out_of_step(det: Detections, c: int, lag: int) -> Detections:
    """Camera c's rows moved so that its frame f + lag holds what the others see at frame f."""
    xy = det.xy.copy()
    src = det.xy[:, :, c]
    xy[:, :, c] = np.nan
    if lag > 0:
        xy[lag:, :, c] = src[:-lag]
    else:
        xy[:lag, :, c] = src[-lag:]
    return dataclasses.replace(det, xy=xy)


def test_epipolar_distance_of_true_and_wrong_matches():
    """A point's two projections lie on each other's epipolar lines (0 px); another point's
    do not; the distance grows with a detection's move across its line."""
    a, b = default_rig()[:2]
    X = _points(40, K=3)
    det = _detections([a, b], X, noise=0.0)
    E = essential(a, b)
    # normalised coordinates of distortion-free cameras
    na = (det.xy[:, :, 0].reshape(-1, 2) - a.K[:2, 2]) / np.diag(a.K)[:2]
    nb = (det.xy[:, :, 1].reshape(-1, 2) - b.K[:2, 2]) / np.diag(b.K)[:2]
    fa, fb = float(a.K[0, 0]), float(b.K[0, 0])
    assert np.abs(epipolar_px(E, na, nb, fa, fb)).max() < 1e-6
    wrong = epipolar_px(E, na, nb[::-1], fa, fb)
    assert np.median(wrong) > 20.0
    line = np.concatenate([na, np.ones((len(na), 1))], 1) @ E.T  # b's epipolar lines
    normal = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    moved = epipolar_px(E, na, nb + 2.0 / fb * normal, fa, fb)  # 2 px across b's line
    assert np.all((moved > 0.9) & (moved < 3.1))  # b's 2 px, a's share of the mean


def test_shift_reads_by_frame_number():
    """Camera 1 shifted by +2 reads frame f + 2 at frame f, by frame numbers (rows 10-19 are
    frames 20-29: frame 9 has no frame 11, frame 20 reads frame 22)."""
    cams = default_rig()[:2]
    det = _detections(cams, _points(20, K=2))
    det = dataclasses.replace(det, frames=np.r_[np.arange(10), np.arange(20, 30)])
    out = shift_cameras(det, {cams[1].name: 2})
    np.testing.assert_array_equal(out.xy[:, :, 0], det.xy[:, :, 0])
    np.testing.assert_array_equal(out.xy[5, :, 1], det.xy[7, :, 1])
    assert np.isnan(out.xy[8:10, :, 1]).all() and (out.likelihood[8:10, :, 1] == 0).all()
    np.testing.assert_array_equal(out.xy[10, :, 1], det.xy[12, :, 1])
    assert np.isnan(out.xy[18:, :, 1]).all()
    assert shift_cameras(det, {cams[1].name: 0}) is det


@pytest.mark.parametrize(("ncams", "lag"), [(3, 4), (3, -6), (4, 1), (2, 3)])
def test_out_of_step_camera_found_and_shifted_back(ncams, lag, caplog):
    """One camera's video started `lag` frames off: found (2 cameras too, and a single frame),
    named in a warning, and shifted back to the detections in step."""
    rig = default_rig()
    cams = (rig + [rig[0]])[:ncams] if ncams == 4 else rig[:ncams]
    if ncams == 4:  # a fourth camera: the first one moved along
        cams[3] = dataclasses.replace(rig[0], name="back", tvec=rig[0].tvec + [80.0, 0, 0])
    c = ncams - 1
    det = _detections(cams, _points(300))
    off = _out_of_step(det, c, lag)
    with caplog.at_level(logging.WARNING):
        back, rep = check_sync(cams, off, 30)
    assert rep["offsets"] == {cams[c].name: lag}, rep
    zero, at = rep["epipolar_px"][cams[c].name]
    assert at < 1.5 and zero > 1.1 * at
    assert f"camera '{cams[c].name}' ({cams[c].name}.csv) is {abs(lag)} frame" in caplog.text
    assert "SHIFTED back" in caplog.text
    ok = np.isfinite(back.xy[:, :, c]).all(-1)
    assert ok.mean() > 0.9
    np.testing.assert_array_equal(back.xy[:, :, c][ok], det.xy[:, :, c][ok])
    with pytest.raises(InputError, match=rf"'{cams[c].name}'.* out of step.*camera_check=warn"):
        check_sync(cams, off, 30, mode="error")
    same, rep0 = check_sync(cams, off, 0)  # not looked for
    assert rep0["offsets"] == {} and same is off


def test_in_step_or_still_no_offset():
    """Cameras in step: no offset. A still animal shows no lag at all: no offset either, even
    for a camera that is out of step (nothing can tell)."""
    cams = default_rig()
    det = _detections(cams, _points(300))
    back, rep = check_sync(cams, det, 30)
    assert rep["offsets"] == {} and back is det
    still = _out_of_step(_detections(cams, _points(300, still=True)), 2, 5)
    assert check_sync(cams, still, 30)[1]["offsets"] == {}


def test_camera_check_shifts_before_judging():
    """Through the camera check (input.max_frame_offset, default 30): the out-of-step camera is
    shifted back and kept; its report is the camera check's ``sync``."""
    cams = default_rig()
    det = _out_of_step(_detections(cams, _points(300)), 1, 7)
    kept, d2, rep = check_from_config(cams, det, {})
    assert rep["sync"]["offsets"] == {cams[1].name: 7} and len(kept) == 3
    assert rep["excluded"] == {}
    _, _, rep0 = check_from_config(cams, det, {"max_frame_offset": 0})
    assert rep0["sync"]["offsets"] == {}
    with pytest.raises(ValueError, match="input.max_frame_offset"):
        check_from_config(cams, det, {"max_frame_offset": -1})


@pytest.mark.parametrize(
    ("folder", "pattern"),
    [("real-hand-4cam", None), ("real-fly-3cam", None), ("real-mouse-sleap-4cam", "*.analysis.h5")],
)
def test_real_recordings_are_in_step(folder, pattern):
    """No offset on the real recordings (the fly barely moves: flat curves; the SLEAP mouse's
    `side` camera has a wrong pose: its pairs disagree on a lag)."""
    root = DATA / folder
    assert root.is_dir(), f"shared data missing: {root}"
    dets = root / "trial_000" if folder == "real-hand-4cam" else root
    cams, det = load_scene(root / "calibration.toml", dets, None, pattern=pattern)
    _, rep = check_sync(cams, det, 30)
    assert rep["offsets"] == {}, rep


def _dropped(det: Detections, c: int, at: int, k: int) -> Detections:
    """Camera c dropped k frames at frame `at`: its rows from there hold the frame k later."""
    xy = det.xy.copy()
    xy[at:, :, c] = np.nan
    xy[at:-k, :, c] = det.xy[at + k :, :, c]
    return dataclasses.replace(det, xy=xy)


@pytest.mark.parametrize("ncams", [3, 2])
def test_a_camera_that_drops_frames_is_shifted_back_piecewise(ncams, caplog):
    """A camera drops 5 frames at frame 600 of 1200: in step before, 5 frames behind after.
    The change is found block by block, placed within a few frames, and undone piecewise."""
    cams = default_rig()[:ncams]
    c = ncams - 1
    det = _detections(cams, _points(1200))
    drop = _dropped(det, c, 600, 5)
    with caplog.at_level(logging.WARNING):
        back, rep = check_sync(cams, drop, 30)
    (first, second) = rep["steps"][cams[c].name]
    assert first == [0, 0] and second[1] == -5 and abs(second[0] - 600) <= 10, rep
    assert rep["offsets"] == {} and "changes its step" in caplog.text
    assert "SHIFTED back piecewise" in caplog.text
    rows = np.r_[0:595, 615:1200]  # away from the change (and its frames dropped)
    ok = np.isfinite(back.xy[rows, :, c]).all(-1)
    assert ok.mean() > 0.95
    np.testing.assert_array_equal(back.xy[rows, :, c][ok], det.xy[rows, :, c][ok])
    # a change of one frame is not told from a broad minimum's jitter: left alone
    assert check_sync(cams, _dropped(det, c, 600, 1), 30)[1].get("steps") in (None, {})


def test_row_offsets_follow_the_steps():
    cams = default_rig()[:2]
    det = dataclasses.replace(_detections(cams, _points(10, K=1)), frames=np.arange(100, 110))
    np.testing.assert_array_equal(
        row_offsets(det, [(100, 0), (104, -2), (108, 3)]), [0, 0, 0, 0, -2, -2, -2, -2, 3, 3]
    )
