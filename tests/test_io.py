"""File formats: anipose calibration TOML, DeepLabCut CSV/H5 tables, points3d CSV."""

from __future__ import annotations

import logging
import re

import numpy as np
import pandas as pd
import pytest

from adjust.camera import Camera
from adjust.io import (
    InputError,
    calibration_units,
    load_calibration,
    load_calibration_metadata,
    read_dlc,
    read_points3d,
    save_calibration,
    write_dlc_csv,
    write_points3d,
)

CAM_TOML = """
[cam_0]
name = "left"
size = [640, 480]
matrix = [[500.0, 0.0, 319.5], [0.0, 501.0, 239.5], [0.0, 0.0, 1.0]]
distortions = [-0.1]
rotation = [0.1, 0.2, 0.3]
translation = [1.0, 2.0, 300.0]
"""


def _cameras(rng: np.random.Generator) -> list[Camera]:
    cams = []
    for i in range(3):
        K = np.array([[rng.uniform(400, 1500), 0.0, 1 / 3 + 320], [0.0, 1e4 / 7, 240.1], [0, 0, 1]])
        cams.append(
            Camera(
                f"cam{i}",
                K,
                rng.normal(0, 0.1, 5),
                rng.normal(0, 1, 3),
                rng.normal(0, 300, 3),
                (640 + i, 480),
                {"serial": f"SN{i}", "gain": 1.5} if i == 1 else {},
            )
        )
    return cams


def test_calibration_round_trip_is_exact(tmp_path):
    cams = _cameras(np.random.default_rng(0))
    path = save_calibration(tmp_path / "calibration.toml", cams, {"adjusted": True, "error": 0.25})
    back = load_calibration(path)
    assert [c.name for c in back] == ["cam0", "cam1", "cam2"]
    for a, b in zip(cams, back):
        for key in ("K", "dist", "rvec", "tvec"):
            assert np.array_equal(getattr(a, key), getattr(b, key)), key  # bit-exact
        assert a.size == b.size and a.extra == b.extra
    assert load_calibration_metadata(path) == {"adjusted": True, "error": 0.25}
    # writing again gives the same text
    again = save_calibration(tmp_path / "again.toml", back, {"adjusted": True, "error": 0.25})
    assert again.read_text() == path.read_text()


def test_calibration_pads_distortions_and_orders_sections(tmp_path):
    text = CAM_TOML.replace("cam_0", "cam_10").replace('"left"', '"ten"') + CAM_TOML.replace(
        "cam_0", "cam_2"
    ).replace("[-0.1]", "[-0.1, 0.01, 0.001, 0.002]").replace("[1.0, 2.0", "[90.0, 2.0")
    (tmp_path / "c.toml").write_text(text)
    cams = load_calibration(tmp_path / "c.toml")
    assert [c.name for c in cams] == ["left", "ten"]  # cam_2 before cam_10
    assert cams[0].dist.tolist() == [-0.1, 0.01, 0.001, 0.002, 0.0]
    assert cams[1].dist.tolist() == [-0.1, 0.0, 0.0, 0.0, 0.0]
    assert cams[0].size == (640, 480)


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (("translation = [1.0, 2.0, 300.0]", "translation = [1.0, nan, 300.0]"), ["translation"]),
        (("rotation = [0.1, 0.2, 0.3]", "rotation = [0.1, inf, 0.3]"), ["rotation", "non-finite"]),
        (("rotation = [0.1, 0.2, 0.3]\n", ""), ["missing", "rotation"]),
        (("[0.0, 0.0, 1.0]]", "[0.0, 0.0]]"), ["matrix"]),
        (("rotation = [0.1, 0.2, 0.3]", "rotation = [0.1, 0.2]"), ["rotation", "(3,)"]),
        (("distortions = [-0.1]", 'distortions = [-0.1]\nfisheye = "yes"'), ["fisheye"]),
        (
            ("distortions = [-0.1]", "distortions = [-0.1, 0, 0, 0, 0.1]\nfisheye = true"),
            ["at most 4"],
        ),
        (("distortions = [-0.1]", "distortions = [1, 2, 3, 4, 5, 6, 7, 8]"), ["distortions"]),
    ],
)
def test_bad_calibration_names_file_and_camera(tmp_path, edit, words):
    old, new = edit
    assert old in CAM_TOML
    path = tmp_path / "calib.toml"
    path.write_text(CAM_TOML.replace(old, new))
    with pytest.raises(InputError) as exc:
        load_calibration(path)
    msg = str(exc.value)
    assert str(path) in msg and "[cam_0]" in msg and "'left'" in msg
    for w in words:
        assert w in msg


def test_calibration_not_found_and_not_toml(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_calibration(tmp_path / "nope.toml")
    (tmp_path / "bad.toml").write_text("[cam_0\nname=")
    with pytest.raises(InputError, match="bad.toml.*TOML"):
        load_calibration(tmp_path / "bad.toml")


# --- DeepLabCut -----------------------------------------------------------------------------


def _table(rng, T=6, parts=("nose", "left_ear", "tailbase")):
    xy = rng.uniform(0, 600, (T, len(parts), 2))
    lik = rng.uniform(0, 1, (T, len(parts)))
    xy[1, 0] = np.nan
    lik[1, 0] = np.nan
    return list(parts), xy, lik


def test_dlc_csv_round_trip_and_layout(tmp_path):
    parts, xy, lik = _table(np.random.default_rng(1))
    path = write_dlc_csv(tmp_path / "cam.csv", parts, xy, lik, scorer="DLC_net")
    lines = path.read_text().splitlines()
    assert lines[0].startswith("scorer,DLC_net,DLC_net,DLC_net,")
    assert lines[1] == "bodyparts," + ",".join(p for p in parts for _ in range(3))
    assert lines[2] == "coords," + ",".join(["x", "y", "likelihood"] * 3)
    assert lines[3].startswith("0,") and lines[4].startswith("1,,,,")  # NaN -> empty
    t = read_dlc(path)
    assert t.parts == tuple(parts) and t.scorer == "DLC_net"
    assert np.array_equal(t.xy, xy, equal_nan=True)
    assert np.array_equal(t.likelihood, lik, equal_nan=True)
    assert t.frames.tolist() == list(range(6))


def test_dlc_h5_read(tmp_path):
    parts, xy, lik = _table(np.random.default_rng(2))
    cols = pd.MultiIndex.from_product(
        [["DLC_net"], parts, ["x", "y", "likelihood"]], names=["scorer", "bodyparts", "coords"]
    )
    data = np.concatenate([xy, lik[..., None]], -1).reshape(len(xy), -1)
    pd.DataFrame(data, columns=cols).to_hdf(tmp_path / "cam.h5", key="df_with_missing")
    t = read_dlc(tmp_path / "cam.h5")
    assert t.parts == tuple(parts) and t.scorer == "DLC_net"
    assert np.array_equal(t.xy, xy, equal_nan=True)
    assert np.array_equal(t.likelihood, lik, equal_nan=True)


def _multi_animal_csv(path, rng, individuals=("mouse1", "mouse2")):
    parts = ["snout", "tailbase"]
    cols = pd.MultiIndex.from_product(
        [["DLC_ma"], list(individuals), parts, ["x", "y", "likelihood"]],
        names=["scorer", "individuals", "bodyparts", "coords"],
    )
    data = rng.uniform(0, 1, (5, len(cols)))
    pd.DataFrame(data, columns=cols).to_csv(path)
    return parts, data.reshape(5, len(individuals), len(parts), 3)


def test_dlc_multi_animal_selects_individual(tmp_path):
    parts, data = _multi_animal_csv(tmp_path / "ma.csv", np.random.default_rng(3))
    t = read_dlc(tmp_path / "ma.csv", individual="mouse2")
    assert t.individual == "mouse2" and t.parts == tuple(parts)
    assert np.array_equal(t.xy, data[:, 1, :, :2])
    assert np.array_equal(t.likelihood, data[:, 1, :, 2])
    with pytest.raises(InputError) as exc:
        read_dlc(tmp_path / "ma.csv")
    assert "ma.csv" in str(exc.value) and "mouse1" in str(exc.value) and "mouse2" in str(exc.value)
    with pytest.raises(InputError, match="'rat'.*mouse1"):
        read_dlc(tmp_path / "ma.csv", individual="rat")


def test_dlc_non_numeric_cell_names_file_line_frame_column(tmp_path):
    parts, xy, lik = _table(np.random.default_rng(4))
    path = write_dlc_csv(tmp_path / "camA.csv", parts, xy, lik)
    lines = path.read_text().splitlines()
    cells = lines[5].split(",")  # frame 2
    cells[5] = "oops"  # left_ear / y
    lines[5] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as exc:
        read_dlc(path)
    msg = str(exc.value)
    assert "camA.csv" in msg and "'oops'" in msg and "line 6" in msg and "frame 2" in msg
    assert "left_ear/y" in msg


def test_dlc_truncated_row_and_not_dlc(tmp_path):
    parts, xy, lik = _table(np.random.default_rng(5))
    path = write_dlc_csv(tmp_path / "c.csv", parts, xy, lik)
    path.write_text(path.read_text() + "6,1.0,2.0\n")
    with pytest.raises(InputError, match=r"c\.csv: line 10 has 3 cells"):
        read_dlc(path)
    (tmp_path / "d.csv").write_text("a,b\n1,2\n")
    with pytest.raises(InputError, match=r"d\.csv: not a DeepLabCut table"):
        read_dlc(tmp_path / "d.csv")


# --- points3d -------------------------------------------------------------------------------


def test_points3d_round_trip_with_nan(tmp_path):
    rng = np.random.default_rng(6)
    T, parts = 7, ["a", "b"]
    pts = rng.normal(0, 100, (T, 2, 3))
    err = rng.uniform(0, 5, (T, 2))
    ncams = rng.integers(0, 4, (T, 2))
    score = rng.uniform(0, 1, (T, 2))
    pts[ncams < 2] = np.nan
    err[ncams < 2] = np.nan
    score[ncams < 2] = np.nan
    pose = rng.normal(size=T)
    sigma = rng.uniform(size=(T, 2))
    path = write_points3d(
        tmp_path / "points3d.csv",
        parts,
        pts,
        err,
        ncams,
        score,
        extra={"pose_rx": pose, "{part}_sigma": sigma},
    )
    header = path.read_text().splitlines()[0].split(",")
    assert header == [
        "a_x", "a_y", "a_z", "a_error", "a_ncams", "a_score",
        "b_x", "b_y", "b_z", "b_error", "b_ncams", "b_score",
        "M_00", "M_01", "M_02", "M_10", "M_11", "M_12", "M_20", "M_21", "M_22",
        "center_0", "center_1", "center_2", "fnum",
    ]  # fmt: skip
    # anipose's columns only above; ours in the sidecar
    side = (tmp_path / "points3d.extra.csv").read_text().splitlines()
    assert side[0].startswith("# extra columns of points3d.csv sha256=")
    assert side[1].split(",") == ["fnum", "pose_rx", "a_sigma", "b_sigma"]
    d = read_points3d(path)
    assert d["parts"] == ("a", "b")
    assert np.array_equal(d["points"], pts, equal_nan=True)
    assert np.array_equal(d["error"], err, equal_nan=True)
    assert np.array_equal(d["score"], score, equal_nan=True)
    assert np.array_equal(d["ncams"], ncams)
    assert np.array_equal(d["extra"]["pose_rx"], pose)
    assert np.array_equal(d["extra"]["b_sigma"], sigma[:, 1])
    assert d["fnum"].tolist() == list(range(T))
    assert np.array_equal(d["M"], np.eye(3)) and np.array_equal(d["center"], np.zeros(3))
    assert set(d["extra"]) == {"pose_rx", "a_sigma", "b_sigma"}  # the axes columns are M, center
    with pytest.raises(ValueError, match="clashes"):
        write_points3d(tmp_path / "p.csv", parts, pts, err, ncams, score, {"a_x": pose})
    with pytest.raises(ValueError, match="clashes"):
        write_points3d(tmp_path / "p.csv", parts, pts, err, ncams, score, {"M_00": pose})


# --- length units ---------------------------------------------------------------------------


def _in_units(text: str, factor: float, unit: str | None) -> str:
    """CAM_TOML-like text with every translation times `factor` and ``[metadata] units``."""
    out = re.sub(
        r"translation = \[([^\]]*)\]",
        lambda m: f"translation = {[float(v) * factor for v in m.group(1).split(',')]}",
        text,
    )
    return out + (f'\n[metadata]\nunits = "{unit}"\n' if unit else "")


@pytest.mark.parametrize(("unit", "factor"), [("cm", 0.1), ("m", 0.001), ("M", 0.001)])
def test_calibration_in_cm_or_m_is_read_in_mm(tmp_path, unit, factor):
    """[metadata] units: the translations (and mechanisms) come back in mm, so the cameras
    (centres, projection matrices) are the mm file's; saved again, the file says mm."""
    two = CAM_TOML + CAM_TOML.replace("cam_0", "cam_1").replace('"left"', '"right"').replace(
        "[1.0, 2.0, 300.0]", "[-250.0, 2.0, 310.0]"
    )
    (tmp_path / "mm.toml").write_text(two)
    path = tmp_path / f"{unit}.toml"
    path.write_text(
        _in_units(two, factor, unit) + f"\n[metadata.mechanisms]\nlever = [{90 * factor}, 0, 0]\n"
    )
    mm, conv = load_calibration(tmp_path / "mm.toml"), load_calibration(path)
    for a, b in zip(mm, conv):
        np.testing.assert_allclose(b.tvec, a.tvec, rtol=1e-12)
        np.testing.assert_allclose(b.center, a.center, rtol=1e-12)
        np.testing.assert_allclose(b.P, a.P, rtol=1e-12)
    meta = load_calibration_metadata(path)
    assert meta["units"] == "mm" and meta["mechanisms"]["lever"] == pytest.approx([90, 0, 0])
    assert calibration_units(path) == unit.lower()
    back = load_calibration(save_calibration(tmp_path / "again.toml", conv, meta))
    np.testing.assert_allclose([c.tvec for c in back], [c.tvec for c in mm], rtol=1e-12)
    with pytest.raises(ValueError, match="cameras are written in mm"):
        save_calibration(tmp_path / "no.toml", conv, {"units": unit})


def test_rig_in_metres_without_units_is_refused(tmp_path, caplog):
    """A lab rig in metres read as mm (every mm setting 1000x off, a 4-7x larger error on real
    motion) is an error that says how to declare the unit; declared, it is read."""
    two = CAM_TOML + CAM_TOML.replace("cam_0", "cam_1").replace('"left"', '"right"').replace(
        "[1.0, 2.0, 300.0]", "[-250.0, 2.0, 310.0]"
    )
    path = tmp_path / "calibration.toml"
    path.write_text(_in_units(two, 0.001, None))
    with pytest.raises(InputError, match=r'toml: its cameras lie within .* units = "m"'):
        load_calibration(path)
    path.write_text(_in_units(two, 0.001, "mm"))  # a tiny rig, said to be one: kept as it is
    assert load_calibration(path)[1].tvec[0] == pytest.approx(-0.25)
    path.write_text(_in_units(two, 0.1, None))  # in cm: read as mm, warned about
    with caplog.at_level(logging.WARNING):
        load_calibration(path)
    assert 'add units = "cm"' in caplog.text
    caplog.clear()
    path.write_text(_in_units(two, 1.0, None))  # in mm: no word
    with caplog.at_level(logging.WARNING):
        load_calibration(path)
    assert "units" not in caplog.text
    path.write_text(_in_units(two, 0.001, "inch"))
    with pytest.raises(InputError, match=r"\[metadata\] units = 'inch' is not a length unit"):
        load_calibration(path)
