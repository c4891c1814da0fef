"""Left and right named the other way round in one camera (`adjust.sides`): found from the
epipolar geometry and swapped back; with two cameras the body model's handedness tells which
camera; cameras labelled alike, and the real recordings, are left alone."""

from __future__ import annotations

import dataclasses
import itertools
import logging

import numpy as np
import pytest
import torch
from helpers import projected_detections
from omegaconf import OmegaConf

from adjust.camera_check import check_from_config, drop_cameras
from adjust.chunks import ChunkHooks, SessionModel
from adjust.io import InputError, load_scene
from adjust.scene import default_rig
from adjust.sides import check_sides, combine, handedness, labelling, swap, swap_all
from deformnet.body import BodyModel
from deformnet.paths import CONF_DIR, shared_dir
from deformnet.windows import mirror_permutation

torch.set_num_threads(1)
DATA = shared_dir() / "data"
MOUSE = BodyModel.from_config(OmegaConf.load(CONF_DIR / "body" / "mouse.yaml"))


def _det(cams, T: int = 400, seed: int = 0):
    """Detections (0.5 px noise) of the default mouse (Table 1, its own part names) walking
    round the arena, turning as it goes and pitching a little."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 4 * np.pi, T)
    yaw, pitch = t + 0.3 * np.sin(3 * t), 0.2 * np.sin(2 * t)
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    Rz = np.stack([np.stack([cy, -sy, 0 * t], -1), np.stack([sy, cy, 0 * t], -1),
                   np.stack([0 * t, 0 * t, 1 + 0 * t], -1)], -2)  # fmt: skip
    Rx = np.stack([np.stack([1 + 0 * t, 0 * t, 0 * t], -1), np.stack([0 * t, cp, -sp], -1),
                   np.stack([0 * t, sp, cp], -1)], -2)  # fmt: skip
    Y = np.asarray(MOUSE.points) * 1.2
    centre = np.stack([150 + 60 * np.cos(t), 150 + 60 * np.sin(2 * t), 12 + 0 * t], -1)
    X = np.einsum("tij,kj->tki", Rz @ Rx, Y) + centre[:, None] + rng.normal(0, 1.0, (T, 8, 3))
    det = projected_detections(cams, X, 0.5, np.random.default_rng(seed + 1))
    return dataclasses.replace(det, parts=tuple(MOUSE.parts))


def test_left_and_right_pairs_by_name():
    assert mirror_permutation(["L1A", "L1B", "R1A", "R1B", "Lx"]) == [2, 3, 0, 1, 4]
    assert mirror_permutation(["Nose", "Ear_R", "Ear_L", "Shoulder_left", "Shoulder_right"]) == [
        0, 2, 1, 4, 3]  # fmt: skip
    assert mirror_permutation(["nose", "L", "R", "l1"]) is None  # no twin for l1; L alone no side


def test_combine_two_passes():
    """A pair swapped in both passes is swapped in neither; a camera left with none is dropped."""
    a = {"swapped": {"top": {"pairs": [["l", "r"], ["la", "ra"]], "decided_by": ["x"]},
                     "side": {"pairs": [["l", "r"]], "decided_by": ["x"]}}}  # fmt: skip
    b = {"swapped": {"top": {"pairs": [["la", "ra"]], "decided_by": ["y"]},
                     "side": {"pairs": [["l", "r"]], "decided_by": ["y"]},
                     "front": {"pairs": [["l", "r"]], "decided_by": ["y"]}}}  # fmt: skip
    got = combine(a, b)["swapped"]
    assert got["top"]["pairs"] == [["l", "r"]] and got["top"]["decided_by"] == ["x", "y"]
    assert "side" not in got and got["front"]["pairs"] == [["l", "r"]]


def test_labelling_explains_every_telling_pair_with_fewest_swapped():
    assert labelling(3, {(0, 1): True, (0, 2): True, (1, 2): False}) == [(1, 0, 0)]
    assert labelling(2, {(0, 1): True}) == [(0, 1), (1, 0)]  # a tie: the geometry cannot tell
    assert labelling(4, {(0, 1): True, (0, 2): False, (1, 2): False}) == []  # no swap explains it
    assert labelling(3, {(0, 1): False, (1, 2): False}) == [(0, 0, 0)]


@pytest.mark.parametrize("c", [0, 1, 2])
def test_a_camera_labelled_the_other_way_round_is_swapped_back(c, caplog):
    cams = default_rig()[:3]
    det = _det(cams)
    name = cams[c].name
    with caplog.at_level(logging.WARNING, logger="adjust.sides"):
        out, rep = check_sides(cams, swap_all(det, [name]))
    assert set(rep["swapped"]) == {name}, rep
    s = rep["swapped"][name]
    assert s["decided_by"] == ["the other cameras"] and s["swapped_px"] < 2 < 10 < s["labelled_px"]
    assert len(s["pairs"]) == 3
    np.testing.assert_array_equal(out.xy, det.xy)
    assert f"camera '{name}' ({name}.csv)" in caplog.text and "SWAPPED" in caplog.text


@pytest.mark.parametrize("c", [0, 1])
def test_two_cameras_the_body_tells_which(c):
    """Either camera of two swapped: the geometry ties; the mouse's handedness picks the
    swapped camera. Without a body the first camera keeps its labels: right where the second
    was swapped, the whole output's left and right exchanged where the first was."""
    cams = default_rig()[:2]
    det = _det(cams)
    name = cams[c].name
    out, rep = check_sides(cams, swap_all(det, [name]), reference=MOUSE)
    assert set(rep["swapped"]) == {name} and rep["swapped"][name]["decided_by"] == [
        "the body model 'mouse'"], rep  # fmt: skip
    np.testing.assert_array_equal(out.xy, det.xy)
    hand, votes = handedness(cams, det, MOUSE)
    assert hand > 0.9 and votes > 100, (hand, votes)
    out, rep = check_sides(cams, swap_all(det, [name]))
    assert set(rep["swapped"]) == {cams[1].name}, rep
    assert rep["swapped"][cams[1].name]["decided_by"] == ["the first camera"]
    want = det if c == 1 else swap_all(det, [n.name for n in cams])
    np.testing.assert_array_equal(out.xy, want.xy)


@pytest.mark.parametrize("ncams", [2, 3, 4])
def test_some_pairs_of_a_camera_the_other_way_round(ncams):
    """The paws of the second camera named the other way round, its ears as they should be
    (a labeller's slip on some parts): those pairs alone are swapped back (two cameras: the
    body tells which camera)."""
    cams = default_rig()[:ncams]
    det = _det(cams)
    name = cams[1].name
    for paws in (["front"], ["front", "hind"]):
        pairs = [(f"left_{p}_paw", f"right_{p}_paw") for p in paws]
        out, rep = check_sides(cams, swap(det, {name: pairs}), reference=MOUSE)
        assert set(rep["swapped"]) == {name}, rep
        assert sorted(map(tuple, rep["swapped"][name]["pairs"])) == sorted(pairs), rep
        np.testing.assert_array_equal(out.xy, det.xy)


def test_cameras_labelled_alike_and_real_recordings_are_left_alone():
    cams = default_rig()
    det = _det(cams)
    out, rep = check_sides(cams, det, reference=MOUSE)
    assert rep["swapped"] == {} and out is det
    out, rep = check_sides(cams, swap_all(det, [c.name for c in cams]))
    assert rep["swapped"] == {}  # every camera alike: not ours to say
    for folder, pattern in (("real-fly-3cam", None), ("real-mouse-sleap-4cam", "*.analysis.h5")):
        root = DATA / folder
        rc, rd = load_scene(root / "calibration.toml", root, None, pattern=pattern)
        assert mirror_permutation(rd.parts) is not None
        names = [c.name for c in rc]
        for k in range(2, len(names) + 1):  # the SLEAP mouse's wrong `side` pose too
            for keep in itertools.combinations(names, k):
                sc, sd = drop_cameras(rc, rd, [n for n in names if n not in keep])
                assert check_sides(sc, sd)[1]["swapped"] == {}, keep
        # ... and a camera of theirs swapped is found (the fly's legs L1A..R3B)
        if folder == "real-fly-3cam":
            _, rep = check_sides(rc, swap_all(rd, [names[1]]))
            assert set(rep["swapped"]) == {names[1]}, rep


def test_error_mode_config_and_chunks():
    """Error mode names the camera and its file; ``input.side_check`` (default true) runs it in
    the camera check (the camera is no longer excluded), false does not; a long session's
    chunks swap their rows as the sample found."""
    cams = default_rig()[:3]
    det = _det(cams)
    bad = swap_all(det, [cams[1].name])
    with pytest.raises(InputError, match=rf"camera '{cams[1].name}' \({cams[1].name}.csv\)"):
        check_sides(cams, bad, "error")
    _, got, rep = check_from_config(cams, bad, {})
    assert set(rep["sides"]["swapped"]) == {cams[1].name} and rep["excluded"] == {}
    np.testing.assert_array_equal(got.xy, det.xy)
    _, _, off = check_from_config(cams, bad, {"side_check": False})
    assert "sides" not in off
    model = SessionModel(None, None, None, None, (), rep, {})
    _, got, _ = ChunkHooks(None, 0, det.num_frames, model=model, keep=(0, det.num_frames)
                           ).check_cameras(cams, bad, {})  # fmt: skip
    np.testing.assert_array_equal(got.xy, det.xy)


def test_a_camera_out_of_step_and_the_other_way_round():
    """The last camera 3 frames out of step and its left and right the other way round: the
    camera check shifts it back and swaps its pairs (the side check runs before the sync check
    and again after it)."""
    cams = default_rig()[:3]
    det = _det(cams, T=600)
    k = 2
    xy, lk = det.xy.copy(), det.likelihood.copy()
    xy[:-3, :, k], xy[-3:, :, k] = det.xy[3:, :, k], np.nan
    lk[:-3, :, k], lk[-3:, :, k] = det.likelihood[3:, :, k], 0.0
    bad = swap_all(dataclasses.replace(det, xy=xy, likelihood=lk), [cams[k].name])
    _, got, rep = check_from_config(cams, bad, {}, MOUSE)
    assert rep["sync"]["offsets"] == {cams[k].name: -3}, rep["sync"]
    assert set(rep["sides"]["swapped"]) == {cams[k].name} and rep["excluded"] == {}, rep
    np.testing.assert_allclose(got.xy[5:-5], det.xy[5:-5])
