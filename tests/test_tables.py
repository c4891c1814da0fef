"""deformnet.tables: the one CSV reader with one-line errors and the points3d part columns,
shared by adjust.io.points3d, adjust.export and deformnet.behavior.tracks."""

from __future__ import annotations

import pytest

from adjust.io import InputError, read_points3d
from deformnet.tables import read_csv, xyz_parts


def test_read_csv_names_the_file_and_raises_the_callers_error(tmp_path):
    with pytest.raises(ValueError, match="^tracks file not found: "):
        read_csv(tmp_path / "none.csv", "tracks file")
    with pytest.raises(InputError, match="^intervals file not found: "):
        read_csv(tmp_path / "none.csv", "intervals file", InputError)
    bad = tmp_path / "bad.csv"
    bad.write_bytes(b"")
    with pytest.raises(InputError, match=r"bad\.csv: cannot read CSV"):
        read_csv(bad, "points3d file", InputError)
    good = tmp_path / "good.csv"
    good.write_text("a_x,a_y,a_z,label\n1,2,3,x\n")
    assert read_csv(good, "labels file", dtype={"label": str})["label"].tolist() == ["x"]


def test_xyz_parts_and_a_points3d_without_them(tmp_path):
    cols = ["fnum", "nose_x", "nose_y", "nose_z", "ear_x", "ear_y", "tail_x", "tail_y", "tail_z"]
    assert xyz_parts(cols) == ["nose", "tail"]
    f = tmp_path / "points3d.csv"
    f.write_text("fnum,a,b\n0,1,2\n")
    with pytest.raises(InputError, match=r"no part columns \(\{part\}_x, _y, _z\)"):
        read_points3d(f)
