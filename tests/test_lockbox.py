"""deformnet.lockbox: the mechanisms' table, validated, and read from a calibration.toml."""

from __future__ import annotations

import pytest

from deformnet.behavior.lockbox import calibration_mechanisms, mechanism_table


def test_mechanism_table_validates_and_names_the_mechanism():
    t = mechanism_table({"lever": [1, 2, 3], "ball": (4.0, 5.0, 6.5)}, "here")
    assert t == {"lever": [1.0, 2.0, 3.0], "ball": [4.0, 5.0, 6.5]}
    with pytest.raises(ValueError, match=r"here: mechanism 'ball' needs \[x, y, z\]"):
        mechanism_table({"lever": [1, 2, 3], "ball": [1, 2]}, "here")
    with pytest.raises(ValueError, match="mechanism 'lever' needs"):
        mechanism_table({"lever": [1, "a", 3]}, "here")
    with pytest.raises(ValueError, match="mechanism 'lever' needs"):
        mechanism_table({"lever": [1, float("nan"), 3]}, "here")
    with pytest.raises(ValueError, match="here: expected a table"):
        mechanism_table([[1, 2, 3]], "here")


def test_calibration_mechanisms_reads_the_metadata_table(tmp_path):
    ok = tmp_path / "calibration.toml"
    ok.write_text("[cam_0]\nname = 'top'\n\n[metadata.mechanisms]\nlever = [90.0, 245.0, 18]\n")
    assert calibration_mechanisms(ok) == {"lever": [90.0, 245.0, 18.0]}
    none = tmp_path / "none.toml"
    none.write_text("[cam_0]\nname = 'top'\n")
    with pytest.raises(ValueError, match=r"none.toml: no \[metadata.mechanisms\] table"):
        calibration_mechanisms(none)
    bad = tmp_path / "bad.toml"
    bad.write_text("[metadata.mechanisms]\nlever = [1, 2\n")
    with pytest.raises(ValueError, match="bad.toml: not a TOML calibration file"):
        calibration_mechanisms(bad)
    with pytest.raises(ValueError, match="calibration file not found"):
        calibration_mechanisms(tmp_path / "missing.toml")
    wrong = tmp_path / "wrong.toml"
    wrong.write_text("[metadata.mechanisms]\nlever = 'here'\n")
    with pytest.raises(ValueError, match=r"wrong.toml \[metadata.mechanisms\]: mechanism 'lever'"):
        calibration_mechanisms(wrong)


def test_calibration_mechanisms_in_the_files_units(tmp_path):
    """A calibration in cm ([metadata] units) gives its mechanisms in mm; an unknown unit is an
    error naming the file."""
    cm = tmp_path / "cm.toml"
    cm.write_text("[metadata]\nunits = 'cm'\n\n[metadata.mechanisms]\nlever = [9.0, 24.5, 1.8]\n")
    assert calibration_mechanisms(cm)["lever"] == pytest.approx([90.0, 245.0, 18.0])
    bad = tmp_path / "inch.toml"
    bad.write_text("[metadata]\nunits = 'inch'\n\n[metadata.mechanisms]\nlever = [1, 2, 3]\n")
    with pytest.raises(ValueError, match=r"inch.toml: \[metadata\] units = 'inch' is not a length"):
        calibration_mechanisms(bad)
