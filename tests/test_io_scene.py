"""Detections loader: files matched to cameras and parts to a body model; the real hand data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from adjust.camera import Camera
from adjust.io import InputError, load_detections, load_scene, match_files, write_dlc_csv
from deformnet.body import BodyModel, default_mouse
from deformnet.paths import real_hand_dir

REAL = real_hand_dir()
HAND_PARTS = ("elbow", "wrist", "thumb1", "thumb2", "thumb3") + tuple(
    f"{f}{i}" for f in ("index", "middle", "ring", "little") for i in range(1, 5)
)
MOUSE_FILE_PARTS = [  # a user's DeepLabCut names, all aliases of the default mouse's parts
    "snout", "leftear", "rightear", "left_forepaw", "right_forepaw", "left_hindpaw",
    "right_hindpaw", "tailbase",
]  # fmt: skip


def _cams(names) -> list[Camera]:
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    return [
        Camera(n, K, np.zeros(5), np.zeros(3), np.array([0, 0, 500.0]), (640, 480)) for n in names
    ]


def _write(folder: Path, name: str, parts, T=5, seed=0, lik=None) -> Path:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(10, 400, (T, len(parts), 2))
    lik = rng.uniform(0.6, 1, (T, len(parts))) if lik is None else lik
    return write_dlc_csv(folder / name, parts, xy, lik, scorer="DLC_test")


def test_real_hand_data_loads():
    cams, det = load_scene(REAL / "calibration.toml", REAL / "trial_000", None)
    names = ("08150951", "08151951", "08152151", "08154551")
    assert tuple(c.name for c in cams) == names == det.cameras
    assert det.parts == HAND_PARTS
    assert det.xy.shape == (513, 21, 4, 2) and det.likelihood.shape == (513, 21, 4)
    assert [f.name for f in det.files] == [f"{n}.csv" for n in names]
    assert cams[0].size == (1280, 1024) and cams[0].dist[0] == pytest.approx(-0.10246784690944921)
    # NaN exactly where the likelihood is below 0.5
    below = det.likelihood < 0.5
    assert np.isnan(det.xy[below]).all() and np.isfinite(det.xy[~below]).all()
    assert 0.5 < det.observed.mean() < 0.8
    # first data cell of 08150951.csv: elbow x in frame 0, likelihood 0.0797 (< 0.5)
    assert det.likelihood[0, 0, 0] == pytest.approx(0.07978874444961548)
    assert np.isnan(det.xy[0, 0, 0]).all()
    assert det.xy[0, 1, 0].tolist() == [269.98651123046875, 771.3764038085938]


def test_body_model_aliases_and_threshold(tmp_path):
    mouse = default_mouse()
    names = ["camA", "camB"]
    lik = np.full((5, 8), 0.9)
    lik[2, 0] = 0.3
    _write(tmp_path, "camA.csv", MOUSE_FILE_PARTS, lik=lik)
    _write(tmp_path, "camB.csv", MOUSE_FILE_PARTS[::-1], seed=1)  # other order
    det = load_detections(tmp_path, _cams(names), mouse, likelihood_threshold=0.5)
    assert det.parts == mouse.parts and det.cameras == tuple(names)
    assert det.xy.shape == (5, 8, 2, 2)
    assert np.isnan(det.xy[2, 0, 0]).all() and det.likelihood[2, 0, 0] == 0.3
    assert det.observed.sum() == 5 * 8 * 2 - 1
    # camB's file lists parts in reverse: its 'snout' column is the last
    b = pd.read_csv(tmp_path / "camB.csv", header=[0, 1, 2], index_col=0)
    assert np.array_equal(det.xy[:, 0, 1, 0], b[("DLC_test", "snout", "x")].to_numpy())


def test_file_name_matching_longest_and_ambiguous(tmp_path):
    for n in ("video_cam1_DLC.csv", "video_cam10_DLC.csv"):
        _write(tmp_path, n, ["a"])
    m = match_files(tmp_path, ["cam1", "cam10"])
    assert m["cam1"].name == "video_cam1_DLC.csv" and m["cam10"].name == "video_cam10_DLC.csv"
    _write(tmp_path, "camX_camY.csv", ["a"])
    with pytest.raises(InputError, match=r"camX_camY\.csv.*several cameras.*camX.*camY"):
        match_files(tmp_path, ["camX", "camY"])


def test_h5_preferred_over_csv_copy(tmp_path):
    _write(tmp_path, "camA.csv", ["a", "b"])
    df = pd.read_csv(tmp_path / "camA.csv", header=[0, 1, 2], index_col=0)
    df.iloc[:, 0] += 1.0
    df.to_hdf(tmp_path / "camA.h5", key="df_with_missing")
    det = load_detections(tmp_path, _cams(["camA"]), None)
    assert det.files[0].name == "camA.h5"
    assert np.array_equal(det.xy[:, 0, 0, 0], df.iloc[:, 0].to_numpy())


def test_camera_without_file(tmp_path):
    _write(tmp_path, "camA.csv", ["a"])
    with pytest.raises(InputError) as exc:
        load_detections(tmp_path, _cams(["camA", "camB"]), None)
    assert "cameras without a file: ['camB']" in str(exc.value) and "camA.csv" in str(exc.value)


def test_file_without_camera(tmp_path):
    _write(tmp_path, "camA.csv", ["a"])
    _write(tmp_path, "stray.csv", ["a"])
    with pytest.raises(InputError) as exc:
        load_detections(tmp_path, _cams(["camA"]), None)
    assert "files without a camera: ['stray.csv']" in str(exc.value)


def test_different_frame_counts_matched_by_frame_number(tmp_path):
    a = _write(tmp_path, "camA.csv", ["a"], T=5)
    _write(tmp_path, "camB.csv", ["a"], T=4)
    det = load_detections(tmp_path, _cams(["camA", "camB"]), None)
    assert det.num_frames == 5 and det.frames.tolist() == [0, 1, 2, 3, 4]
    assert det.observed[:4].all() and not det.observed[4, 0, 1] and det.observed[4, 0, 0]
    # camB's rows numbered 10..13: the union of frame numbers, never paired by position
    xy = np.random.default_rng(1).uniform(10, 400, (4, 1, 2))
    write_dlc_csv(tmp_path / "camB.csv", ["a"], xy, np.ones((4, 1)), frames=[3, 4, 5, 6])
    det = load_detections(tmp_path, _cams(["camA", "camB"]), None)
    assert det.frames.tolist() == [0, 1, 2, 3, 4, 5, 6]
    assert np.array_equal(det.xy[3:, 0, 1], xy[:, 0])
    assert det.observed[:, 0, 0].tolist() == [True] * 5 + [False] * 2
    assert np.isfinite(pd.read_csv(a, header=[0, 1, 2], index_col=0).to_numpy()).all()


def test_duplicate_frame_number_refused(tmp_path):
    _write(tmp_path, "camA.csv", ["a"], T=3)
    xy = np.full((3, 1, 2), 50.0)
    write_dlc_csv(tmp_path / "camB.csv", ["a"], xy, np.ones((3, 1)), frames=[0, 1, 1])
    with pytest.raises(InputError, match=r"camB.csv: frame 1 appears 2 times"):
        load_detections(tmp_path, _cams(["camA", "camB"]), None)


def test_unknown_part(tmp_path):
    _write(tmp_path, "camA.csv", [*MOUSE_FILE_PARTS, "whisker"])
    with pytest.raises(InputError) as exc:
        load_detections(tmp_path, _cams(["camA"]), default_mouse())
    msg = str(exc.value)
    assert "camA.csv" in msg and "camera 'camA'" in msg and "unknown parts ['whisker']" in msg
    det = load_detections(tmp_path, _cams(["camA"]), default_mouse(), ignore_unknown_parts=True)
    assert det.parts == default_mouse().parts


def test_missing_part(tmp_path):
    _write(tmp_path, "camA.csv", MOUSE_FILE_PARTS[:-1])  # no tail base
    with pytest.raises(InputError) as exc:
        load_detections(tmp_path, _cams(["camA"]), default_mouse())
    msg = str(exc.value)
    assert "camA.csv" in msg and "missing parts ['tail_root']" in msg
    det = load_detections(tmp_path, _cams(["camA"]), default_mouse(), allow_missing_parts=True)
    assert np.isnan(det.xy[:, -1]).all() and (det.likelihood[:, -1] == 0).all()


def test_files_disagree_on_parts_without_body(tmp_path):
    _write(tmp_path, "camA.csv", ["a", "b"])
    _write(tmp_path, "camB.csv", ["a", "c"])
    with pytest.raises(InputError, match=r"camB\.csv.*'camB'.*\['c'\]"):
        load_detections(tmp_path, _cams(["camA", "camB"]), None)


def test_two_aliases_of_one_part(tmp_path):
    body = BodyModel(("nose", "tail"), np.eye(2, 3), {"snout": "nose"}, "m")
    _write(tmp_path, "camA.csv", ["nose", "snout", "tail"])
    with pytest.raises(InputError, match="'nose' and 'snout' both map to body part 'nose'"):
        load_detections(tmp_path, _cams(["camA"]), body)


def test_multi_animal_folder(tmp_path):
    cols = pd.MultiIndex.from_product(
        [["DLC_ma"], ["m1", "m2"], ["a", "b"], ["x", "y", "likelihood"]],
        names=["scorer", "individuals", "bodyparts", "coords"],
    )
    data = np.random.default_rng(0).uniform(0.5, 1, (4, len(cols)))
    for n in ("camA", "camB"):
        pd.DataFrame(data, columns=cols).to_csv(tmp_path / f"{n}.csv")
    with pytest.raises(InputError) as exc:
        load_detections(tmp_path, _cams(["camA", "camB"]), None)
    assert "camA.csv" in str(exc.value) and "['m1', 'm2']" in str(exc.value)
    det = load_detections(tmp_path, _cams(["camA", "camB"]), None, individual="m2")
    assert det.parts == ("a", "b")
    assert np.array_equal(det.xy[:, 1, 0, 1], data[:, 6 + 3 + 1])  # m2 / b / y
