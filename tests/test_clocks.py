"""A camera whose clock runs at another rate than the others' (`adjust.clocks`): a drift (its
lag grows through the session) or a frame rate that is not a whole multiple of theirs is
found, with its rate and offset, and the camera read at the others' times; cameras in step,
a constant fraction of a frame, a lag that steps (dropped frames) and short sessions are
left alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import own_clock_detections, projected_detections, wandering_path

from adjust.camera_check import check_from_config
from adjust.chunks import ChunkHooks
from adjust.clocks import check_clocks, fit_line, retime
from adjust.io import Detections, InputError
from adjust.scene import default_rig

torch.set_num_threads(1)
T = 1000


def _clocked(cams, c: int, times: np.ndarray) -> Detections:
    """Detections at frames 0..T-1, camera c's rows g = 0..len(times)-1 showing the times
    `times` instead (its own clock)."""
    return own_clock_detections(cams, T, c, times)


def _truth(cams) -> np.ndarray:
    X = wandering_path(np.arange(T, dtype=np.float64))
    return projected_detections(cams, X, 0.0, np.random.default_rng(0)).xy


@pytest.mark.parametrize(
    ("c", "rate", "offset"),
    [(2, 0.995, 0.0), (1, 1.004, 2.3), (2, 25 / 30, 0.0), (0, 1.2, -0.4)],
)
def test_a_camera_whose_clock_runs_otherwise_is_retimed(c, rate, offset, caplog):
    """Camera c's frame g shows the others' frame (g - offset) / rate: a drift of 0.4-0.5%
    (4-5 frames over the session) or another frame rate (25 against 30 fps; 1.2x). Named with
    its rate, read at the others' frames: its detections are theirs to within the noise."""
    cams = default_rig()
    n = int(np.floor((T - 1) * rate + offset)) + 1
    det = _clocked(cams, c, (np.arange(n) - offset) / rate)
    out, rep = check_clocks(cams, det)
    name = cams[c].name
    assert set(rep["retimed"]) == {name}, rep
    got = rep["retimed"][name]
    assert abs(got["rate"] - rate) < 2e-4 and abs(got["offset"] - offset) < 0.2, got
    assert got["epipolar_px"][1] < 1.5 and got["epipolar_px"][1] < got["epipolar_px"][0]
    assert out.num_frames == T and out.frames.tolist() == list(range(T))
    seen = np.isfinite(out.xy[:, :, c]).all(-1)
    assert seen.sum() >= 0.97 * T * det.num_parts
    err = np.linalg.norm(out.xy[:, :, c][seen] - _truth(cams)[:, :, c][seen], axis=-1)
    assert np.median(err) < 1.0
    assert name in caplog.text and "RETIMED" in caplog.text


def test_in_step_a_fraction_steps_and_short_sessions_are_left_alone():
    """No map where the cameras keep time (also a constant fraction of a frame, the sub-frame
    check's); where the lag steps by 3 frames at frame 500 (dropped frames: the sync check's);
    where the camera's file stops early (its span 0.85 of theirs: a candidate rate that does
    not fit); where the session is short."""
    cams = default_rig()
    for times in (np.arange(T), np.arange(T) - 0.4):
        out, rep = check_clocks(cams, _clocked(cams, 2, times.astype(np.float64)))
        assert rep["retimed"] == {}, rep
    stepped = np.where(np.arange(T) < 500, np.arange(T), np.arange(T) + 3).astype(np.float64)
    assert check_clocks(cams, _clocked(cams, 1, stepped))[1]["retimed"] == {}
    early = np.arange(int(0.85 * T), dtype=np.float64)  # its file stops early: no clock
    assert check_clocks(cams, _clocked(cams, 2, early))[1]["retimed"] == {}
    det = _clocked(cams, 2, np.arange(T) / 0.99)
    short = Detections(det.cameras, det.parts, det.xy[:400], det.likelihood[:400], det.files,
                       0.5, det.frames[:400])  # fmt: skip
    assert check_clocks(cams, short)[1]["retimed"] == {}


def test_retime_and_line():
    """`retime` reads the camera at rate f + offset on the others' frames; `fit_line` leaves an
    outlying block out."""
    cams = default_rig()
    det = _clocked(cams, 1, np.arange(T) / 1.0)
    same = retime(det, 1, 1.0, 0.0)
    np.testing.assert_allclose(same.xy, det.xy)
    half = retime(det, 1, 1.0, 0.5)
    mid = 0.5 * (det.xy[10, :, 1] + det.xy[11, :, 1])
    np.testing.assert_allclose(half.xy[10, :, 1], mid)
    t = np.arange(10.0) * 100
    y = 0.002 * t + 1.0
    y[4] += 5.0
    s, b = fit_line(t, y)
    assert abs(s - 0.002) < 1e-9 and abs(b - 1.0) < 1e-9


def test_error_mode_config_and_long_sessions():
    """Error mode names the camera and its file; ``input.rate_check`` runs it in the camera
    check (its report's ``clocks``), false does not; a long session's sample reports it for
    its chunks (tests/test_chunks.py tracks one)."""
    cams = default_rig()
    det = _clocked(cams, 1, np.arange(int(T * 0.99)) / 0.99)
    with pytest.raises(InputError, match=rf"camera '{cams[1].name}' \({cams[1].name}.csv\)"):
        check_clocks(cams, det, "error")
    _, out, rep = check_from_config(cams, det, {})
    assert set(rep["clocks"]["retimed"]) == {cams[1].name} and out.num_frames == T
    assert rep["excluded"] == {} and rep["sync"]["offsets"] == {}
    _, _, off = check_from_config(cams, det, {"rate_check": False})
    assert "clocks" not in off
    _, _, rep = ChunkHooks(None, 0, det.num_frames).check_cameras(cams, det, {})
    assert set(rep["clocks"]["retimed"]) == {cams[1].name}  # the chunks read it so
