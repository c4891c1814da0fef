"""Class-balanced pseudo-labels (`deformnet.pseudo`) and the forest head's self-training
(`deformnet-classify pseudo_labels.teacher=linear`)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch
from test_classify import CLASSES, TINY, _compose, _files, _toy_session

from deformnet.behavior.teachers import (
    class_balanced_pseudo_labels,
    co_training_pseudo_labels,
    pseudo_sample_weights,
)
from deformnet.behavior.tracks import POSE_COLUMNS
from deformnet.body import default_mouse


def test_every_class_keeps_its_own_most_confident_share():
    """A teacher sure of class 0 (0.9-0.99) and unsure of class 1 (0.51-0.6): a global threshold
    at 0.7 would keep class 0 only; the class-balanced choice keeps the top 30% of each, the
    labelled frames never, and the labels are the teacher's classes."""
    n0, n1 = 100, 50
    c0 = np.linspace(0.9, 0.99, n0)
    c1 = np.linspace(0.51, 0.6, n1)
    probs = np.concatenate(
        [np.stack([c0, 1 - c0], 1), np.stack([1 - c1, c1], 1)]
    )  # frames 0-99 class 0, 100-149 class 1
    labelled = np.zeros(n0 + n1, bool)
    labelled[[99, 149]] = True  # the most confident frame of each class is labelled
    rows, labels = class_balanced_pseudo_labels(probs, [n0 + n1], labelled, keep=0.3, smooth=1)
    # the share among every frame given the class (labelled ones included), then those dropped
    expect0 = np.arange(n0)[c0 >= np.quantile(c0, 0.7)]
    expect1 = n0 + np.arange(n1)[c1 >= np.quantile(c1, 0.7)]
    expect = np.setdiff1d(np.concatenate([expect0, expect1]), [99, 149])
    np.testing.assert_array_equal(rows, expect)
    np.testing.assert_array_equal(labels, (rows >= n0).astype(int))
    assert (labels == 1).sum() == len(expect1) - 1 == 14  # 30% of 50, less the labelled one
    assert probs[rows[labels == 1]].max() < 0.7  # what a global threshold of 0.7 would drop
    all_rows, _ = class_balanced_pseudo_labels(probs, [n0 + n1], np.zeros(n0 + n1, bool), 1.0, 1)
    np.testing.assert_array_equal(all_rows, np.arange(n0 + n1))  # keep=1: every frame


def test_co_training_pools_the_views_and_drops_their_conflicts():
    """Two views of 40 frames: view A is sure of frames 0-9 (class 0) and 30-34 (class 0), view
    B of frames 10-19 (class 1) and 30-34 (class 1), each unsure elsewhere. Each keeps its own
    most confident share; the pool has A's and B's sure frames, the frames both are sure of with
    different classes are dropped and counted, a labelled frame never appears, and one view
    alone gives `class_balanced_pseudo_labels`' result."""
    n = 40
    a = np.tile([0.55, 0.45], (n, 1))
    a[0:10] = a[30:35] = [0.95, 0.05]
    b = np.tile([0.45, 0.55], (n, 1))
    b[10:20] = [0.05, 0.95]
    b[30:35] = [0.1, 0.9]
    lab = np.zeros(n, bool)
    lab[0] = True
    # A gives class 0 to every frame: its top 30% are its 15 sure ones (ties kept); B gives
    # class 1 to every frame, its top 30% its 15 sure ones
    rows, y, conflicts = co_training_pseudo_labels([a, b], [n], lab, [0.3, 0.3], smooth=1)
    np.testing.assert_array_equal(rows, np.r_[1:20])
    np.testing.assert_array_equal(y, np.r_[np.zeros(9, int), np.ones(10, int)])
    assert conflicts == 5
    one = co_training_pseudo_labels([a], [n], lab, [0.3], smooth=1)
    for got, want in zip(one[:2], class_balanced_pseudo_labels(a, [n], lab, 0.3, smooth=1)):
        np.testing.assert_array_equal(got, want)
    assert one[2] == 0
    # views that agree add nothing twice and drop nothing
    rows2, _, c2 = co_training_pseudo_labels([a, a], [n], lab, [0.3, 0.3], smooth=1)
    np.testing.assert_array_equal(rows2, one[0])
    assert c2 == 0
    with pytest.raises(ValueError, match="one keep share per view: 2 views, 1 shares"):
        co_training_pseudo_labels([a, b], [n], lab, [0.3], smooth=1)
    with pytest.raises(ValueError, match="one shape"):
        co_training_pseudo_labels([a, b[:20]], [n], lab, [0.3, 0.3], smooth=1)


def test_smoothing_stays_within_each_session():
    """Probabilities are averaged over 9 frames within a session: a lone flipped frame takes
    its neighbours' class, and the last frames of a session keep their (weak) class beside the
    next session's strong other class, which an average across the boundary would give them."""
    a = np.tile([0.6, 0.4], (20, 1))
    a[10] = [0.3, 0.7]  # a lone flip inside session 1
    b = np.tile([0.1, 0.9], (20, 1))
    probs = np.concatenate([a, b])
    none = np.zeros(40, bool)
    rows, labels = class_balanced_pseudo_labels(probs, [20, 20], none, keep=1.0, smooth=9)
    np.testing.assert_array_equal(rows, np.arange(40))
    np.testing.assert_array_equal(labels, np.r_[np.zeros(20, int), np.ones(20, int)])
    _, raw = class_balanced_pseudo_labels(probs, [20, 20], none, keep=1.0, smooth=1)
    assert raw[10] == 1  # unsmoothed, the flip stays
    _, joined = class_balanced_pseudo_labels(probs, [40], none, keep=1.0, smooth=9)
    assert joined[19] == 1 and joined[15] == 0  # one 40-frame session: b reaches into a
    assert probs[19, 0] == 0.6  # the inputs are not changed in place


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"keep": 0.0}, r"keep must be in \(0, 1\]"),
        ({"keep": 1.5}, r"keep must be in \(0, 1\]"),
        ({"smooth": 0}, "smooth must be an integer >= 1"),
        ({"smooth": 2.5}, "smooth must be an integer >= 1"),
        ({"lengths": [3, 3]}, "must be >= 0 and sum to 10 frames"),
        ({"labelled": np.zeros(9, bool)}, r"labelled must be \(10,\)"),
    ],
)
def test_pseudo_label_argument_errors(kwargs, match):
    args = {"probs": np.full((10, 2), 0.5), "lengths": [10], "labelled": np.zeros(10, bool)}
    args |= kwargs
    with pytest.raises(ValueError, match=match):
        class_balanced_pseudo_labels(**args)


def test_sample_weights_balance_classes_and_favour_labels():
    y = np.array([0, 1, 0, 0, 0, 1])  # 2 labelled (0, 1), 4 pseudo-labelled
    w = pseudo_sample_weights(y, 2, 3, labelled_weight=5.0)
    per = np.array([6 / (3 * 4), 6 / (3 * 2)])  # class 0: 4 frames, class 1: 2
    np.testing.assert_allclose(w, per[y] * np.r_[5.0, 5.0, 1, 1, 1, 1])
    # balanced: each present class carries the same total weight among the pseudo-labels
    assert w[2:][y[2:] == 0].sum() == pytest.approx(3 * per[0])
    with pytest.raises(ValueError, match="labelled_weight must be > 0"):
        pseudo_sample_weights(y, 2, 3, 0.0)
    # loss.class_weights=none: every pseudo-label weighs 1 (the teacher's class frequencies)
    w = pseudo_sample_weights(y, 2, 3, labelled_weight=5.0, balanced=False)
    np.testing.assert_allclose(w, [5.0, 5.0, 1, 1, 1, 1])


def few_label_toy(tmp_path) -> tuple[list[str], list]:
    """deformnet-classify overrides for two toy training sessions at 5% labels and a test
    session (`test_classify._toy_session`), and the test sessions."""
    train = [_toy_session(tmp_path, f"train{i}", i) for i in range(2)]
    test = [_toy_session(tmp_path, "test", 8)]
    base = [
        *TINY,
        f"classes=[{','.join(CLASSES)}]",
        "label_fraction=0.05",
        *_files("train", train),
        *_files("test", test),
        "logger=none",
        "smoothing.median=0",
        "smoothing.min_bout=0",
    ]
    return base, test


def test_forest_self_training_in_deformnet_classify(tmp_path):
    """pseudo_labels.teacher=linear with head=forest: the teacher labels the unlabelled training
    frames, about `keep` of them (per class) join the labelled ones, the forest is refitted on
    both and is still right on a held-out session; classifier.pt reloads and mode=predict
    round-trips. A teacher for a head that is not a forest, or a bad share, is an error before
    any data is read."""
    from deformnet.behavior.model import load_classifier
    from deformnet.behavior.predict import run

    base, test = few_label_toy(tmp_path)
    forest = ["head=forest", "head.trees=25", "freeze=true"]
    with pytest.raises(ValueError, match="pseudo_labels.teacher=linear self-trains the forest"):
        run(_compose([*base, "pseudo_labels.teacher=linear", f"output.dir={tmp_path / 'x'}"]))
    with pytest.raises(ValueError, match=r"pseudo_labels.keep must be in \(0, 1\]"):
        run(_compose([*base, *forest, "pseudo_labels.teacher=linear", "pseudo_labels.keep=2",
                      f"output.dir={tmp_path / 'x'}"]))  # fmt: skip
    with pytest.raises(ValueError, match="pseudo_labels.smooth must be an integer"):
        run(_compose([*base, *forest, "pseudo_labels.teacher=linear", "pseudo_labels.smooth=2.5",
                      f"output.dir={tmp_path / 'x'}"]))  # fmt: skip
    with pytest.raises(ValueError, match="pseudo_labels.teacher must be one of"):
        run(_compose([*base, *forest, "pseudo_labels.teacher=teacher",
                      f"output.dir={tmp_path / 'x'}"]))  # fmt: skip
    out = tmp_path / "self"
    rep = run(_compose([*base, *forest, "pseudo_labels.teacher=linear", f"output.dir={out}"]))[
        "report"
    ]
    pl = rep["probe"]["pseudo_labels"]
    frames, labelled = 2 * 360, 2 * 18
    assert pl["teacher"] == "linear" and sum(pl["per_class"]) == pl["frames"]
    # every class keeps at least 30% of the frames given it (ties can add more), less labelled
    assert 0.3 * frames - labelled <= pl["frames"] <= 0.5 * frames
    assert min(pl["per_class"]) >= 0.3 * 0.3 * frames  # both behaviors, not the easy one only
    assert pl["forest"]["trees"] == 25
    assert rep["raw"]["macro_f1"] >= 0.95, rep["raw"]
    plain = run(_compose([*base, *forest, f"output.dir={tmp_path / 'plain'}"]))["report"]
    assert "pseudo_labels" not in plain["probe"]  # teacher=none (default): labelled frames only
    model, meta = load_classifier(out / "classifier.pt")
    assert int(model.head.roots.numel()) == 25
    p = run(_compose(["mode=predict", f"checkpoint={out / 'classifier.pt'}",
                      f"tracks={test[0][0]}", f"output.dir={tmp_path / 'pred'}"]))  # fmt: skip
    df = pd.read_csv(p["predictions"])
    assert np.mean(df["label"].to_numpy() == np.asarray(CLASSES)[test[0][2]]) >= 0.95


def test_linear_teacher_in_deformnet_classify(tmp_path):
    """pseudo_labels.teacher=linear: a logistic regression on the binned frame features labels
    the unlabelled training frames (both behaviors), the forest head is refitted on them and is
    right on a held-out session; the teacher is kept in classifier.pt; bins < 2 is an error
    before any data is read."""
    from deformnet.behavior.model import load_classifier
    from deformnet.behavior.predict import run

    base, _ = few_label_toy(tmp_path)
    forest = ["head=forest", "head.trees=25", "freeze=true", "pseudo_labels.teacher=linear"]
    with pytest.raises(ValueError, match="pseudo_labels.bins must be an integer >= 2"):
        run(_compose([*base, *forest, "pseudo_labels.bins=1", f"output.dir={tmp_path / 'x'}"]))
    out = tmp_path / "linear"
    rep = run(_compose([*base, *forest, f"output.dir={out}"]))["report"]
    pl = rep["probe"]["pseudo_labels"]
    frames, labelled = 2 * 360, 2 * 18
    assert pl["teacher"] == "linear" and sum(pl["per_class"]) == pl["frames"]
    assert 0.3 * frames - labelled <= pl["frames"] <= 0.5 * frames
    assert min(pl["per_class"]) >= 0.3 * 0.3 * frames
    assert "pretraining" not in pl and "encoder" not in pl
    assert rep["raw"]["macro_f1"] >= 0.95, rep["raw"]
    _, meta = load_classifier(out / "classifier.pt")
    assert meta["pseudo_labels"]["teacher"] == "linear" and meta["pseudo_labels"]["bins"] == 4
    # a recording nobody labelled: by default (pseudo_labels.unlabelled=true) its frames are
    # pseudo-labelled too, and the forest learns from them
    unl = _toy_session(tmp_path, "unlabelled", 5)
    more = run(_compose([*base, *forest, f"data.unlabelled_tracks=[{unl[0]}]",
                         f"output.dir={tmp_path / 'linear_unl'}"]))["report"]  # fmt: skip
    mpl = more["probe"]["pseudo_labels"]
    assert pl["unlabelled_frames"] == 0 and 0.2 * 360 <= mpl["unlabelled_frames"] <= 360
    assert mpl["frames"] > pl["frames"] and more["raw"]["macro_f1"] >= 0.95, more["raw"]
    off = run(
        _compose(
            [
                *base,
                *forest,
                f"data.unlabelled_tracks=[{unl[0]}]",
                "pseudo_labels.unlabelled=false",
                f"output.dir={tmp_path / 'off'}",
            ]
        )
    )
    assert off["report"]["probe"]["pseudo_labels"]["per_class"] == pl["per_class"]
    with pytest.raises(ValueError, match="pseudo_labels.unlabelled must be true or false"):
        run(_compose([*base, *forest, "pseudo_labels.unlabelled=3",
                      f"output.dir={tmp_path / 'x'}"]))  # fmt: skip


def test_class_weights_reach_the_self_trained_forest(tmp_path, monkeypatch):
    """loss.class_weights is the student forest's too: balanced, its pseudo-labels weigh
    inversely to their class's count; none, each weighs 1 (the teacher's class frequencies, an
    estimate of the recordings', are kept; the labelled frames are a person's pick per class);
    pseudo_labels.balanced=false (the default) does that for the student alone."""
    import deformnet.behavior.fit as fit
    from deformnet.behavior.predict import run

    seen, real = [], fit.pseudo_sample_weights

    def spy(*args, **kwargs):
        w = real(*args, **kwargs)
        seen.append(bool(np.ptp(w[args[1] :]) > 0))  # pseudo-labels weighed unequally
        return w

    monkeypatch.setattr(fit, "pseudo_sample_weights", spy)
    base, _ = few_label_toy(tmp_path)
    forest = ["head=forest", "head.trees=10", "freeze=true", "pseudo_labels.teacher=linear"]
    runs = [["pseudo_labels.balanced=true"], ["pseudo_labels.balanced=true",
            "loss.class_weights=none"], []]  # fmt: skip
    for i, ov in enumerate(runs):
        run(_compose([*base, *forest, *ov, f"output.dir={tmp_path / str(i)}"]))
    assert seen == [True, False, False]
    with pytest.raises(ValueError, match="pseudo_labels.balanced must be true or false"):
        run(_compose([*base, *forest, "pseudo_labels.balanced=2", f"output.dir={tmp_path}"]))


def _subtle_session(tmp_path, name: str, seed: int, T: int = 600, shift: float = 0.55):
    """Two behaviors told apart only by a small shift of every part (0.55 mm along a fixed
    direction per part, under 1 mm of noise per coordinate and frame): no one feature
    separates them, their sum does. Bouts of 40 frames; points3d CSV and per-frame labels."""
    from deformnet.so3 import transform_points

    rng = np.random.default_rng(seed)
    body = default_mouse()
    lab = (np.arange(T) // 40 + seed) % 2
    yaw = np.cumsum(rng.normal(0, 0.05, T))
    poses = np.zeros((T, 6))
    poses[:, 2] = yaw
    poses[:, 3] = 150 + np.cumsum(-np.sin(yaw)) % 100
    poses[:, 4] = 150 + np.cumsum(np.cos(yaw)) % 100
    poses[:, 5] = 10.0
    u = np.random.default_rng(123).normal(size=(body.num_parts, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    off = (2 * lab - 1)[:, None, None] * shift * u + rng.normal(0, 1.0, (T, body.num_parts, 3))
    local = torch.tensor(np.asarray(body.points))[None] + torch.tensor(off)
    pts = transform_points(torch.tensor(poses), local).numpy()
    cols = {"fnum": np.arange(T)} | dict(zip(POSE_COLUMNS, poses.T))
    for k, p in enumerate(body.parts):
        cols |= {f"{p}_{a}": pts[:, k, i] for i, a in enumerate("xyz")}
    tracks, labels = tmp_path / f"{name}.csv", tmp_path / f"{name}_labels.csv"
    pd.DataFrame(cols).to_csv(tracks, index=False)
    pd.DataFrame({"fnum": np.arange(T), "label": np.asarray(CLASSES)[lab]}).to_csv(
        labels, index=False
    )
    return tracks, labels, lab


def test_the_teacher_matters_where_the_forest_alone_falls_short(tmp_path):
    """With 3% of the frames labelled (36) and behaviors that no single feature separates, the
    forest head alone scores at most 0.85 on a held-out session; taught by the linear teacher
    (a logistic regression on the binned frame features, which adds the weak features up) it
    scores at least 0.04 more."""
    from deformnet.behavior.predict import run

    train = [_subtle_session(tmp_path, f"train{i}", i) for i in range(2)]
    test = [_subtle_session(tmp_path, "test", 8)]
    base = [*TINY, f"classes=[{','.join(CLASSES)}]", "label_fraction=0.03",
            *_files("train", train), *_files("test", test), "logger=none",
            "smoothing.median=0", "smoothing.min_bout=0", "head=forest", "head.trees=25",
            "freeze=true", "context.frames=[]"]  # fmt: skip
    score = {}
    for teacher in ("none", "linear"):
        rep = run(_compose([*base, f"pseudo_labels.teacher={teacher}",
                            f"output.dir={tmp_path / teacher}"]))["report"]  # fmt: skip
        assert rep["labelled_training_frames"] == 36
        score[teacher] = rep["raw"]["macro_f1"]
    assert score["none"] <= 0.85, score
    assert score["linear"] >= score["none"] + 0.04, score
