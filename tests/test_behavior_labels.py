"""Labels as labs export them (deformnet.behavior.labels.read_labels): per frame, bouts, BORIS's
aggregated events, SimBA's behavior columns; small files."""

from __future__ import annotations

import numpy as np
import pytest

from deformnet.behavior.labels import read_labels

CLASSES = ["walk", "rear", "groom"]
FNUM = np.arange(100, 120)  # a track's frames 100..119


def _labels(tmp_path, text, **kw):
    p = tmp_path / "labels.csv"
    p.write_text(text)
    return read_labels(p, FNUM, CLASSES, **kw)


def test_plain_bouts_and_frames(tmp_path):
    y = _labels(tmp_path, "start,stop,label\n100,104,walk\n110,111,groom\n")
    assert y[:5].tolist() == [0] * 5 and y[5:10].tolist() == [-1] * 5
    assert y[10:12].tolist() == [2, 2] and np.all(y[12:] == -1)
    y = _labels(tmp_path, "fnum,label\n101,rear\n119,walk\n")
    assert y[1] == 1 and y[19] == 0 and (y >= 0).sum() == 2


def test_boris_aggregated_events(tmp_path):
    head = "Observation id,Subject,Behavior,Behavior type,Start (s),Stop (s),Duration (s),FPS\n"
    y = _labels(
        tmp_path,
        head + "s1,mouse,walk,STATE,0.0,0.2,0.2,10\n"
        "s1,mouse,groom,STATE,0.5,0.8,0.3,10\ns1,mouse,rear,POINT,1.5,1.5,0,10\n",
    )
    # 10 fps: walk [0, 0.2) s = frames 100-101, groom 105-107, the point event frame 115
    assert np.flatnonzero(y == 0).tolist() == [0, 1]
    assert np.flatnonzero(y == 2).tolist() == [5, 6, 7]
    assert np.flatnonzero(y == 1).tolist() == [15]
    # without an FPS column the track's frame rate is needed
    head2 = "Behavior,Start (s),Stop (s)\nwalk,0.0,0.2\n"
    with pytest.raises(ValueError, match="give the frame rate"):
        _labels(tmp_path, head2)
    assert np.flatnonzero(_labels(tmp_path, head2, fps=20.0) == 0).tolist() == [0, 1, 2, 3]
    # image indices, when BORIS wrote them, are frames
    y = _labels(tmp_path, "Behavior,Start (s),Stop (s),Image index start,Image index stop\n"
                "rear,9.9,9.9,3,4\n")  # fmt: skip
    assert np.flatnonzero(y == 1).tolist() == [3, 4]


def test_simba_behavior_columns(tmp_path):
    rows = "\n".join(["nose_x,walk,rear,groom"] + [f"1.0,{int(i < 3)},{int(i == 5)},0"
                                                    for i in range(20)])  # fmt: skip
    y = _labels(tmp_path, rows + "\n")
    assert y[:3].tolist() == [0, 0, 0] and y[5] == 1 and (y >= 0).sum() == 4
    bad = "walk,rear\n1,1\n" + "0,0\n" * 19
    with pytest.raises(ValueError, match="row 1: several behaviors"):
        _labels(tmp_path, bad)


def test_unknown_format_names_the_formats(tmp_path):
    with pytest.raises(ValueError, match="BORIS"):
        _labels(tmp_path, "a,b\n1,2\n")
