"""Cameras a fraction of a frame out of step (`adjust.subframe`): the offset is found from the
epipolar geometry, the camera named, and its detections interpolated in time to the others'
frames; cameras in step, and the real recordings, are left alone."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest
import torch
from helpers import projected_detections

from adjust.camera_check import check_from_config
from adjust.chunks import ChunkHooks, SessionModel
from adjust.io import Detections, InputError
from adjust.scene import default_rig
from adjust.subframe import check_subframe, resample

torch.set_num_threads(1)


def _path(t: np.ndarray, K: int = 8, seed: int = 0) -> np.ndarray:
    """(len(t), K, 3) mm at times t (frames, fractional): K parts about a centre that wanders
    smoothly round the arena, each turning slowly about it."""
    rng = np.random.default_rng(seed)
    w = 2 * np.pi / 400
    centre = np.stack(
        [150 + 80 * np.cos(w * t), 150 + 70 * np.sin(2 * w * t), 30 + 15 * np.sin(3 * w * t)], -1
    )
    body = rng.normal(0, 20, (K, 3))
    a = 0.5 * np.sin(w * t / 2)
    c, s = np.cos(a), np.sin(a)
    x = c[:, None] * body[None, :, 0] - s[:, None] * body[None, :, 1]
    y = s[:, None] * body[None, :, 0] + c[:, None] * body[None, :, 1]
    return centre[:, None] + np.stack([x, y, np.broadcast_to(body[:, 2], x.shape)], -1)


def _late(cams, c: int, late: float, T: int = 1500, noise: float = 0.5, seed: int = 1):
    """Detections of `_path` with camera c exposed `late` frames after the others (its row f
    shows the scene at time f + late), and the in-step detections (the truth to compare)."""
    t = np.arange(T, dtype=np.float64)
    det = projected_detections(cams, _path(t), noise, np.random.default_rng(seed))
    shifted = projected_detections(cams, _path(t + late), noise, np.random.default_rng(seed))
    xy = det.xy.copy()
    xy[:, :, c] = shifted.xy[:, :, c]
    truth = projected_detections(cams, _path(t), 0.0, np.random.default_rng(0))
    return dataclasses.replace(det, xy=xy), truth


def _err(det, truth, c: int) -> float:
    return float(np.nanmedian(np.linalg.norm(det.xy[5:-5, :, c] - truth.xy[5:-5, :, c], axis=-1)))


def _line(T: int, late: float = 0.0) -> np.ndarray:
    """(T, 2, 1, 2) px: two parts moving at 3.6 and 2.2 px per frame, at times f + late."""
    t = np.arange(T, dtype=np.float64)[:, None] + late
    a = np.concatenate([100 + 3 * t, 50 + 2 * t], -1)
    b = np.concatenate([200 - 2 * t, 80 + t], -1)
    return np.stack([a, b], 1)[:, :, None]


def _one_camera(xy: np.ndarray) -> Detections:
    T, K = xy.shape[:2]
    parts = tuple(f"p{k}" for k in range(K))
    return Detections(("cam",), parts, xy, np.ones((T, K, 1)), ("cam.csv",), 0.5, np.arange(T))


def test_resample_reads_the_camera_at_its_fractional_row():
    """Offset -0.3 (the camera 0.3 of a frame late): frame f is read at its row f - 0.3, on the
    line between its rows f - 1 and f: exact on straight motion, the likelihood kept; the
    first frame has no row before it and keeps the nearer one."""
    det = _one_camera(_line(40))
    out = resample(det, {"cam": -0.3})
    np.testing.assert_allclose(out.xy[1:], _line(40, -0.3)[1:], atol=1e-9)
    np.testing.assert_allclose(out.xy[0], _line(40)[0])
    assert (out.likelihood == 1).all()
    assert resample(det, {}) is det and resample(det, {"cam": 0.0}) is det


def test_resample_keeps_an_outlier_out_of_its_neighbours():
    """A spike (an outlier or a swap in one frame) is not spread by the line: the frames it
    brackets take their other row; a frame whose nearer row has no detection has none (the
    farther row is not used), the next frame keeps its own."""
    xy = _line(40)
    xy[20, 0, 0] += 60.0  # an outlier in frame 20
    xy[30, 1, 0] = np.nan  # a missing detection in frame 30
    out = resample(_one_camera(xy), {"cam": -0.3})
    clean = resample(_one_camera(_line(40)), {"cam": -0.3})
    d = np.linalg.norm(out.xy - clean.xy, axis=-1)[:, :, 0]
    off = {tuple(b) for b in np.argwhere(~(d < 1e-9))}
    assert off == {(20, 0), (21, 0), (30, 1), (31, 1)}, off
    assert d[20, 0] < 0.71 * 3.61 and d[21, 0] < 0.31 * 3.61  # a row 0.7 / 0.3 frame off
    assert np.isnan(out.xy[30, 1]).all() and out.likelihood[30, 1, 0] == 0
    assert d[31, 1] < 0.31 * 2.24  # its own row, 0.3 frame off


@pytest.mark.parametrize(("ncams", "c", "late"), [(3, 2, 0.4), (3, 0, -0.35), (2, 1, 0.5)])
def test_a_camera_out_of_step_by_a_fraction_is_found_and_interpolated(ncams, c, late, caplog):
    """The camera exposed `late` frames after the others is named with its offset (-late:
    its frame f - late matches theirs), within 0.06 frame, and its detections interpolated:
    closer to the in-step projections than as filmed. With two cameras the first keeps the
    session's time."""
    cams = default_rig()[:ncams]
    det, truth = _late(cams, c, late)
    with caplog.at_level(logging.WARNING, logger="adjust.subframe"):
        out, rep = check_subframe(cams, det)
    name = cams[c].name
    if ncams == 2 and c == 0:
        name, late = cams[1].name, -late
    assert set(rep["offsets"]) == {name}, rep
    assert abs(rep["offsets"][name] + late) < 0.06, rep
    assert name in caplog.text and "INTERPOLATED" in caplog.text
    assert _err(out, truth, c) < 0.6 * _err(det, truth, c)


def test_cameras_in_step_are_left_alone():
    cams = default_rig()
    det, _ = _late(cams, 0, 0.0)
    out, rep = check_subframe(cams, det)
    assert rep["offsets"] == {} and out is det


def test_error_mode_names_the_camera_and_its_file():
    cams = default_rig()
    det, _ = _late(cams, 1, 0.5)
    with pytest.raises(InputError, match=rf"camera '{cams[1].name}' \({cams[1].name}.csv\)"):
        check_subframe(cams, det, "error")


def test_camera_check_interpolates_unless_turned_off():
    """`input.subframe_sync` (default true) runs it in the camera check, whose report (the
    summary's ``camera_check``) holds it; false leaves the detections as filmed."""
    cams = default_rig()
    det, truth = _late(cams, 1, 0.5)
    _, out, rep = check_from_config(cams, det, {})
    assert set(rep["subframe"]["offsets"]) == {cams[1].name}
    _, off, rep_off = check_from_config(cams, det, {"subframe_sync": False})
    assert "subframe" not in rep_off
    assert _err(out, truth, 1) < 0.6 * _err(off, truth, 1)
    with pytest.raises(ValueError, match="input.subframe_sync"):
        check_from_config(cams, det, {"subframe_sync": "maybe"})


def test_every_chunk_of_a_long_session_is_interpolated_as_the_sample_found():
    """A long session's chunks read the camera at the sample's offset (by frame number: a
    chunk's rows are a slice of the session)."""
    cams = default_rig()
    det, _ = _late(cams, 1, 0.5, T=600)
    found = {"subframe": {"offsets": {cams[1].name: -0.5}}}
    model = SessionModel(None, None, None, None, (), found, {})
    part = dataclasses.replace(
        det, xy=det.xy[200:400], likelihood=det.likelihood[200:400], frames=det.frames[200:400]
    )
    _, got, rep = ChunkHooks(None, 200, 400, model=model, keep=(0, 200)).check_cameras(
        cams, part, {}
    )
    want = resample(det, {cams[1].name: -0.5})
    np.testing.assert_array_equal(got.xy[1:], want.xy[201:400])
    assert rep is found
