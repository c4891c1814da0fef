"""Frame rates in `deformnet-classify`: a track at another rate than the classifier's is
labelled resampled to the classifier's (`resample_session`, `to_track_frames`,
`predict_session(rates=...)`), and the rates are checked and reported."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch
from helpers import pinned, write_bout_labels

from adjust.io import write_points3d
from deformnet.behavior.rates import resample_session, to_track_frames
from deformnet.behavior.tracks import Session
from deformnet.body import default_mouse
from deformnet.confutil import check_fps, compose
from deformnet.so3 import transform_points

CLASSES = ["walk", "scan"]


def _motion(t: np.ndarray) -> np.ndarray:
    """A smooth (T, K, 3) point motion at times t (s): each coordinate a sum of sines."""
    k = np.arange(8)[None, :, None]
    a = np.arange(3)[None, None, :]
    return 20 * np.sin(2 * np.pi * (0.3 + 0.1 * k + 0.05 * a) * t[:, None, None] + k + a)


def _session(fps: float, seconds: float = 4.0, fnum=None) -> Session:
    fnum = np.arange(int(round(seconds * fps)) + 1) if fnum is None else np.asarray(fnum)
    t = fnum / fps
    P = _motion(t).astype(np.float32)
    labels = (t // 0.5).astype(np.int64) % 2
    obs = np.ones(P.shape[:2], bool)
    return Session("s", P + 1.0, P, obs, fnum, labels, scale=1.1, pose="columns")


def test_check_fps():
    assert check_fps(None, "fps") is None and check_fps("100", "fps") == 100.0
    for bad in (0, -30, "fast", float("nan"), float("inf")):
        with pytest.raises(ValueError, match="fps must be a frame rate in Hz"):
            check_fps(bad, "fps")


def test_resample_session_value_shape_and_gaps():
    """90 -> 30 Hz: without antialiasing every third frame exactly (the same times), with it
    the motion within the low-pass's attenuation (a Gaussian of sd 1/60 s passes 1.1 Hz at
    exp(-2 pi^2 sd^2 f^2) = 0.9934: 20 mm x 0.0066 = 0.13 mm, and the edges' truncation);
    30 -> 90 Hz: the motion within linear interpolation's error (h^2 / 8 max |x''|: 20 mm, up
    to 1.1 Hz, h = 1/30 s: 0.13 mm); labels the nearest frame's; the scale and pose carried;
    frame numbers 0, 1, ..."""
    fast, slow = _session(90.0), _session(30.0)
    plain = resample_session(fast, 90.0, 30.0, antialias=False)
    np.testing.assert_allclose(plain.deformed, slow.deformed, atol=1e-4)
    down = resample_session(fast, 90.0, 30.0)
    assert down.rigid.shape == slow.rigid.shape and down.observed.shape == slow.observed.shape
    inner = slice(3, -3)  # the Gaussian's edges: normalised over the frames there are
    err = np.abs(down.deformed[inner] - slow.deformed[inner]).max()
    assert 0.02 < err <= 20 * (1 - np.exp(-2 * np.pi**2 * (1 / 60) ** 2 * 1.1**2)) * 1.05
    assert np.abs(down.deformed - slow.deformed).max() < 0.3  # the ends: a local line
    np.testing.assert_array_equal(down.labels, slow.labels)
    np.testing.assert_array_equal(down.fnum, np.arange(len(slow.fnum)))
    assert down.scale == 1.1 and down.pose == "columns"
    up = resample_session(slow, 30.0, 90.0)
    assert up.deformed.shape == fast.deformed.shape
    err = np.abs(up.deformed - fast.deformed).max()
    bound = (1 / 30) ** 2 / 8 * 20 * (2 * np.pi * 1.1) ** 2
    assert 0.01 < err <= bound * 1.05
    # nearest labels: the 90 Hz frames of each 30 Hz frame's +-1 neighbourhood take its label
    assert np.mean(up.labels == fast.labels) > 0.97
    # gaps in the frame numbers are gaps in time: frames 0..59 and 90..120 at 30 Hz
    gap = _session(30.0, fnum=np.r_[0:60, 90:121])
    g = resample_session(gap, 30.0, 60.0)
    assert len(g.fnum) == 241  # 4 s at 60 Hz
    t = np.arange(241) / 60.0
    inside = (t <= 59 / 30) | (t >= 3.0)
    np.testing.assert_allclose(g.deformed[inside], _motion(t[inside]), atol=0.2)
    # across the gap: the straight line between its ends
    mid = np.flatnonzero(np.isclose(t, 2.5))[0]
    w = (2.5 - 59 / 30) / (3.0 - 59 / 30)
    want = (1 - w) * _motion(np.array([59 / 30])) + w * _motion(np.array([3.0]))
    np.testing.assert_allclose(g.deformed[mid], want[0], atol=1e-3)


def test_antialiasing_removes_what_the_lower_rate_cannot_carry():
    """Jitter at 40 Hz on a 90 Hz track, resampled to 30 Hz: plain sampling (every third
    frame) folds it into a 10 Hz wobble of 0.87 its amplitude; low-passed first it is all but
    gone (the Gaussian of sd 1/60 s passes 40 Hz at exp(-2 pi^2 (40/60)^2) = 1.6e-4), the slow
    motion kept (0.993 at 1.1 Hz). Unobserved part-frames do not leak into the observed ones;
    near a gap or an end the fit is a local line (not pulled back); gaps stay gaps."""
    s = _session(90.0)
    t = s.fnum / 90.0
    jitter = (3.0 * np.sin(2 * np.pi * 40 * t))[:, None, None].astype(np.float32)
    noisy = Session("n", s.rigid, s.deformed + jitter, s.observed.copy(), s.fnum, s.labels)
    slow = _motion(np.arange(121) / 30.0)
    plain = resample_session(noisy, 90.0, 30.0, antialias=False)
    down = resample_session(noisy, 90.0, 30.0)
    inner = slice(5, -5)
    assert np.abs(plain.deformed[inner] - slow[inner]).max() > 2.5
    assert np.abs(down.deformed[inner] - slow[inner]).max() < 0.2
    # a part unobserved (its deformed point a far-off value) for a stretch: its observed
    # neighbours are smoothed over observed frames only
    noisy.observed[100:150, 4] = False
    noisy.deformed[100:150, 4] = 1e4
    d2 = resample_session(noisy, 90.0, 30.0)
    err = np.abs(d2.deformed - slow).max(-1)[:, 4]
    assert err[d2.observed[:, 4]].max() < 2.0  # nothing of the far-off unobserved values
    away = np.r_[5:32, 52:116]  # two or more 30 Hz frames from the gap (34..49) and the ends
    assert err[away].max() < 0.2
    assert not d2.observed[34:50, 4].any() and d2.observed[:34, 4].all()
    from deformnet.behavior.rates import lowpass_in_time

    P = lowpass_in_time(np.ones((5, 1, 3)), np.ones((5, 1), bool), np.array([0, 1, 2, 40, 41]), 3)
    np.testing.assert_allclose(P, 1.0)  # a constant stays constant, across the gap too
    line = np.arange(10.0)[:, None, None] * np.ones((1, 2, 3))
    obs = np.ones((10, 2), bool)
    obs[4:7, 1] = False
    np.testing.assert_allclose(lowpass_in_time(line, obs, np.arange(10), 2.0), line, atol=1e-9)


def test_resample_session_observed_and_errors():
    s = _session(30.0)
    s.observed[10, 2] = False
    s.deformed[10, 2] = s.rigid[10, 2]
    up = resample_session(s, 30.0, 90.0)
    # the 90 Hz frames between 30 Hz frames 9..11 that lean on frame 10: unobserved, rigid
    bad = np.flatnonzero(~up.observed[:, 2])
    np.testing.assert_array_equal(bad, np.arange(28, 33))
    np.testing.assert_array_equal(up.deformed[bad, 2], up.rigid[bad, 2])
    assert up.observed[:, [0, 1, 3]].all()
    back = Session("b", s.rigid, s.deformed, s.observed, s.fnum[::-1].copy(), s.labels)
    with pytest.raises(ValueError, match="b: frame numbers must increase"):
        resample_session(back, 30.0, 90.0)
    with pytest.raises(ValueError, match="rate must be a frame rate"):
        resample_session(s, 30.0, 0)


def test_to_track_frames():
    """Back to the track's frames: nearest for labels, linear for probabilities (exact for a
    linear function of time); the resampled length is checked."""
    fnum = np.arange(0, 301)  # 100 Hz, 3 s
    t = fnum / 100.0
    tn = np.arange(91) / 30.0
    lab = (tn // 0.5).astype(int) % 2
    got = to_track_frames(lab, fnum, 100.0, 30.0)
    assert np.mean(got == (t // 0.5).astype(int) % 2) > 0.97
    probs = np.stack([tn / 3.0, 1 - tn / 3.0], -1)
    np.testing.assert_allclose(to_track_frames(probs, fnum, 100.0, 30.0, "linear")[:, 0], t / 3)
    with pytest.raises(ValueError, match="must have the resampled session's 91 frames"):
        to_track_frames(lab[:-1], fnum, 100.0, 30.0)


# --------------------------------------------------------------------------------------------
# end to end: a classifier trained at 30 Hz labels a 90 Hz recording of the same behavior
# --------------------------------------------------------------------------------------------
def _speed_track(tmp_path, name: str, seed: int, fps: float, seconds: float = 16.0):
    """'walk' (forward at 90 mm/s) and 'scan' (standing, turning its heading slowly) in 1.5 s
    bouts: told apart by the speed, which per frame depends on the frame rate. The same motion
    at any `fps`; 0.2 mm noise per coordinate."""
    rng = np.random.default_rng(seed)
    body = default_mouse()
    T = int(round(seconds * fps))
    t = np.arange(T) / fps
    lab = ((t // 1.5).astype(int) + seed) % 2
    yaw = 0.6 * np.sin(0.7 * t + seed) + np.where(lab == 1, 0.4 * np.sin(3 * t), 0.0)
    v = np.where(lab == 0, 90.0, 0.0) / fps  # mm per frame
    x = 150 + np.cumsum(v * np.cos(yaw + np.pi / 2))
    y = 150 + np.cumsum(v * np.sin(yaw + np.pi / 2))
    poses = np.stack([np.zeros(T), np.zeros(T), yaw, x, y, np.full(T, 10.0)], -1)
    model = torch.tensor(np.asarray(body.points)).expand(T, -1, -1)
    pts = transform_points(torch.tensor(poses), model).numpy()
    pts = pts + rng.normal(0, 0.2, pts.shape)
    K = body.num_parts
    names = ("pose_rx", "pose_ry", "pose_rz", "pose_tx", "pose_ty", "pose_tz")
    tracks = write_points3d(
        tmp_path / f"{name}.csv", body.parts, pts, np.zeros((T, K)), np.full((T, K), 2),
        np.ones((T, K)), extra={c: poses[:, i] for i, c in enumerate(names)},
    )  # fmt: skip
    labels = write_bout_labels(tmp_path / f"{name}_labels.csv", lab, CLASSES)
    return tracks, labels, lab


def _compose(overrides):
    return compose("classify", pinned(overrides))


def test_a_classifier_labels_a_recording_at_another_frame_rate(tmp_path, caplog):
    """Trained at 30 Hz (fps=30, stored in classifier.pt), the classifier labels a 90 Hz
    recording given fps=90 resampled to 30 Hz: as right as a 30 Hz recording. Without fps=
    the track is taken to be at 30 Hz: its walking looks three times slower and is mislabelled.
    summary.json and report.json say the rates; a bad fps is an error."""
    from deformnet.behavior.model import load_classifier
    from deformnet.behavior.predict import run

    tiny = ["net.hidden=8", "net.layers=1", "net.embed=8", "half_window=2"]
    train = [_speed_track(tmp_path, f"train{i}", i, 30.0) for i in range(2)]
    test = _speed_track(tmp_path, "test30", 7, 30.0)
    t = ",".join(str(s[0]) for s in train)
    lab = ",".join(str(s[1]) for s in train)
    out = tmp_path / "cls"
    ov = [*tiny, "freeze=true", "head=forest", "measurements=true", "fps=30",
          f"classes=[{','.join(CLASSES)}]", f"data.train_tracks=[{t}]",
          f"data.train_labels=[{lab}]", f"data.test_tracks=[{test[0]}]",
          f"data.test_labels=[{test[1]}]", "logger=none", f"output.dir={out}"]  # fmt: skip
    rep = run(_compose(ov))["report"]
    assert rep["fps"] == 30.0 and rep["raw"]["macro_f1"] > 0.95
    assert load_classifier(out / "classifier.pt")[1]["fps"] == 30.0
    fast_tracks, _, truth = _speed_track(tmp_path, "fast", 7, 90.0)
    pred = ["mode=predict", f"checkpoint={out / 'classifier.pt'}", f"tracks={fast_tracks}"]
    got = {}
    for name, rate in (("given", ["fps=90"]), ("assumed", [])):
        with caplog.at_level("INFO", logger="deformnet.behavior"):
            res = run(_compose([*pred, *rate, f"output.dir={tmp_path / name}"]))
        summary = json.loads((tmp_path / name / "summary.json").read_text())
        df = pd.read_csv(res["predictions"])
        assert len(df) == len(truth) and (df["fnum"] == np.arange(len(truth))).all()
        got[name] = (np.mean(df["label_raw"] == np.asarray(CLASSES)[truth]), summary)
    acc, summary = got["given"]
    assert acc > 0.95
    assert summary["fps"] == 90.0 and summary["classifier_fps"] == 30.0 and summary["resampled"]
    assert "labelled resampled to the classifier's 30 Hz" in caplog.text
    acc0, summary0 = got["assumed"]
    assert summary0["resampled"] is False and summary0["fps"] is None
    assert acc0 < 0.8  # walking at a third of the speed per frame: taken for scanning
    assert "no fps= given" in caplog.text
    with pytest.raises(ValueError, match="fps must be a frame rate in Hz"):
        run(_compose([*pred, "fps=0", f"output.dir={tmp_path / 'bad'}"]))


def test_training_sessions_at_several_frame_rates(tmp_path):
    """data.train_fps: labelled sessions recorded at 30 and at 90 fps, each read resampled to
    fps=30, train one classifier that labels a 30 fps test session right. A list of the wrong
    length, or per-session rates without fps=, are errors naming the setting."""
    from deformnet.behavior.predict import run

    tiny = ["net.hidden=8", "net.layers=1", "net.embed=8", "half_window=2"]
    train = [_speed_track(tmp_path, "a30", 0, 30.0), _speed_track(tmp_path, "b90", 1, 90.0)]
    test = _speed_track(tmp_path, "test30", 7, 30.0)
    t = ",".join(str(s[0]) for s in train)
    lab = ",".join(str(s[1]) for s in train)
    ov = [*tiny, "freeze=true", "head=forest", "measurements=true",
          f"classes=[{','.join(CLASSES)}]", f"data.train_tracks=[{t}]",
          f"data.train_labels=[{lab}]", f"data.test_tracks=[{test[0]}]",
          f"data.test_labels=[{test[1]}]", "logger=none"]  # fmt: skip
    rep = run(_compose([*ov, "fps=30", "data.train_fps=[30,90]", f"output.dir={tmp_path / 'ok'}"]))
    # both sessions' 16 s at 30 fps: 480 + 480 frames, all labelled
    assert rep["report"]["labelled_training_frames"] == 960
    assert rep["report"]["raw"]["macro_f1"] > 0.95
    with pytest.raises(ValueError, match=r"data.train_fps must list one frame rate per session"):
        run(_compose([*ov, "fps=30", "data.train_fps=[30]", f"output.dir={tmp_path / 'b1'}"]))
    with pytest.raises(ValueError, match=r"data.train_fps gives each session's frame rate: set"):
        run(_compose([*ov, "data.train_fps=[30,90]", f"output.dir={tmp_path / 'b2'}"]))
