"""A camera at another frame rate (`adjust.rates`): a camera whose file spans a whole multiple
(or fraction) of the others' frames, and agrees with them once renumbered, has its frames
renumbered to theirs; cameras at one rate, a truncated file and a camera that does not agree
either way are left alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import own_clock_detections, projected_detections, wandering_path

from adjust.camera_check import check_from_config
from adjust.chunks import ChunkHooks
from adjust.io import Detections, InputError
from adjust.rates import check_rates, ratio_of
from adjust.scene import default_rig

torch.set_num_threads(1)
T = 600


def _mixed(cams, c: int, k: int, phase: int = 0, noise: float = 0.5) -> Detections:
    """Detections (`helpers.own_clock_detections`) with camera c at k x the others' rate (k <
    0: 1 / |k|), its rows numbered in its own frames: k = 2, its frame g shows time g / 2;
    k = -2, its frame g shows time 2 g + phase."""
    times = (np.arange(k * T) / k) if k > 0 else (np.arange(T // -k) * -k + phase)
    return own_clock_detections(cams, T, c, times, noise)


def test_ratio_of_whole_multiples_only():
    assert ratio_of(2000, 1000) == 2 and ratio_of(1000, 3000) == -3
    assert ratio_of(1990, 1000) == 2  # within 2%
    assert ratio_of(1500, 1000) is None and ratio_of(1000, 1000) is None


@pytest.mark.parametrize(("c", "k", "phase"), [(2, 2, 0), (1, -2, 1), (0, 3, 0)])
def test_a_camera_at_another_rate_is_renumbered(c, k, phase, caplog):
    """Camera c at k x the others' rate: named with the ratio and phase, its frames renumbered
    so that its detections are the others' frames' (the session's frames are theirs)."""
    cams = default_rig()
    det = _mixed(cams, c, k, phase)
    out, rep = check_rates(cams, det)
    name = cams[c].name
    assert set(rep["renumbered"]) == {name}, rep
    got = rep["renumbered"][name]
    assert got["ratio"] == (k if k > 0 else 0.5) and got["phase"] == phase
    assert got["epipolar_px"][1] < 2.0 < 10 * got["epipolar_px"][1] < got["epipolar_px"][0]
    assert out.num_frames == T and out.frames.tolist() == list(range(T))
    truth = projected_detections(
        cams, wandering_path(np.arange(T, dtype=np.float64)), 0.0, np.random.default_rng(0)
    )
    seen = np.isfinite(out.xy[:, :, c]).all(-1)
    assert seen.sum() >= (T if k > 0 else T // 2) * det.num_parts - 1
    err = np.linalg.norm(out.xy[:, :, c][seen] - truth.xy[:, :, c][seen], axis=-1)
    assert np.median(err) < 1.5
    assert name in caplog.text and "RENUMBERED" in caplog.text


def test_one_rate_truncated_and_disagreeing_files_are_left_alone():
    cams = default_rig()
    det = _mixed(cams, 2, 2)
    # one rate (the camera's first T rows only: its file as long as the others')
    same = Detections(det.cameras, det.parts, det.xy[:T], det.likelihood[:T], det.files, 0.5,
                      det.frames[:T])  # fmt: skip
    assert check_rates(cams, same)[1]["renumbered"] == {}
    # truncated: 1.5 x the others' frames
    cut = Detections(det.cameras, det.parts, det.xy[: T * 3 // 2], det.likelihood[: T * 3 // 2],
                     det.files, 0.5, det.frames[: T * 3 // 2])  # fmt: skip
    assert check_rates(cams, cut)[1]["renumbered"] == {}
    # the camera's file twice as long, but its detections belong to no renumbering
    noise = det.xy.copy()
    rng = np.random.default_rng(5)
    noise[:, :, 2] = rng.uniform(0, 1000, noise[:, :, 2].shape)
    bad = Detections(det.cameras, det.parts, noise, det.likelihood, det.files, 0.5, det.frames)
    out, rep = check_rates(cams, bad)
    assert rep["renumbered"] == {} and out is bad


def test_error_mode_config_and_long_sessions():
    """Error mode names the camera and its file; ``input.rate_check`` (default true) runs it in
    the camera check, false does not; a long session's sample refuses it (its chunks are cut by
    frame number)."""
    cams = default_rig()
    det = _mixed(cams, 1, 2)
    with pytest.raises(InputError, match=rf"camera '{cams[1].name}' \({cams[1].name}.csv\)"):
        check_rates(cams, det, "error")
    _, out, rep = check_from_config(cams, det, {})
    assert set(rep["rates"]["renumbered"]) == {cams[1].name} and out.num_frames == T
    assert rep["excluded"] == {}
    _, _, off = check_from_config(cams, det, {"rate_check": False})
    assert "rates" not in off
    with pytest.raises(InputError, match="chunk_frames=0"):
        ChunkHooks(None, 0, det.num_frames).check_cameras(cams, det, {})
