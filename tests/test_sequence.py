"""The behavior-scale sequence encoder (`deformnet.sequence`) and its teacher
(`deformnet-classify pseudo_labels.teacher=cotrain`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_classify import _compose, _toy_session
from test_pseudo import few_label_toy

from deformnet.behavior.sequence import (
    SequenceEncoder,
    embeddings,
    export_sequence_encoder,
    load_sequence_encoder,
    pooled,
    pretrain_sequences,
    span_mask,
)
from deformnet.behavior.teachers import (
    binned,
    embedding_teacher_probs,
    linear_teacher_probs,
    standardised,
)


def test_encoder_shapes_and_guards():
    torch.manual_seed(0)
    m = SequenceEncoder(6, channels=8, dilations=(1, 2), target=[1, 4])
    x = torch.randn(3, 40, 6)
    assert m.embed(x).shape == (3, 40, 8)
    assert m(x, torch.zeros(3, 40)).shape == (3, 40, 2)
    assert m.receptive_field == 7
    with pytest.raises(ValueError, match=r"x must be \(B, T, 6\)"):
        m.embed(torch.randn(3, 40, 5))
    with pytest.raises(ValueError, match=r"mask must be \(3, 40\)"):
        m(x, torch.zeros(3, 41))
    with pytest.raises(ValueError, match="target columns must index the 6 features"):
        SequenceEncoder(6, target=[6])
    with pytest.raises(ValueError, match="dilations"):
        SequenceEncoder(6, dilations=())


def test_hidden_frames_are_not_read():
    """A hidden frame's features are zeroed before the net: changing them changes nothing."""
    torch.manual_seed(0)
    m = SequenceEncoder(4, channels=8, dilations=(1, 2)).eval()
    m.set_standardization(torch.randn(100, 4))
    x = torch.randn(1, 30, 4)
    mask = torch.zeros(1, 30)
    mask[0, 10:15] = 1
    y = x.clone()
    y[0, 10:15] += 5.0
    torch.testing.assert_close(m(x, mask), m(y, mask))
    assert not torch.allclose(m(x, torch.zeros(1, 30)), m(y, torch.zeros(1, 30)))


def test_span_mask_covers_the_ratio_in_spans():
    gen = torch.Generator().manual_seed(0)
    m = span_mask(16, 200, 0.5, gen, longest=20)
    share = m.mean(1)
    assert (share >= 0.5).all() and (share < 0.5 + 20 / 200 + 1e-9).all()
    for row in m:  # every run of hidden frames is at least 4 long (spans may touch)
        d = np.diff(np.r_[0, row.numpy(), 0])
        assert ((np.flatnonzero(d == -1) - np.flatnonzero(d == 1)) >= 4).all()
    with pytest.raises(ValueError, match=r"ratio must be in \(0, 1\)"):
        span_mask(1, 100, 1.0, gen)


def test_pooled_is_the_centred_mean_and_std():
    z = torch.randn(2, 3, 20, dtype=torch.float64)
    p = pooled(z, [5])
    assert p.shape == (2, 20, 9)
    for t in (0, 1, 10, 19):  # the edges: over the frames there are
        win = z[:, :, max(0, t - 2) : t + 3]
        torch.testing.assert_close(p[:, t, :3], z[:, :, t])
        torch.testing.assert_close(p[:, t, 3:6], win.mean(-1))
        torch.testing.assert_close(p[:, t, 6:], win.std(-1, unbiased=False))
    with pytest.raises(ValueError, match="odd"):
        pooled(z, [4])


def _smooth_sessions(n: int, T: int, seed: int) -> list[torch.Tensor]:
    """Slow sines of random phases, frequencies and mixing, plus a little noise: a hidden frame
    follows from its neighbours."""
    rng = np.random.default_rng(seed)
    out = []
    t = np.arange(T)[:, None]
    for _ in range(n):
        f = rng.uniform(0.01, 0.05, 3)
        base = np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi, 3))
        x = base @ rng.normal(size=(3, 5)) + 0.05 * rng.normal(size=(T, 5))
        out.append(torch.as_tensor(x, dtype=torch.float32))
    return out


def test_pretraining_learns_to_fill_hidden_spans_and_is_deterministic():
    """On smooth sequences the masked-span loss (standardised features: about 1 for a net
    that knows nothing) falls well below it; the same seed gives the same weights."""
    sessions = _smooth_sessions(4, 300, 0)
    torch.manual_seed(0)
    m = SequenceEncoder(5, channels=32, dilations=(1, 2, 4, 8))
    kw = {"steps": 300, "ratio": 0.5, "longest": 12, "crop": 128, "batch": 8, "lr": 3e-3}
    facts = pretrain_sequences(m, sessions, **kw)
    assert facts["steps"] == 300 and facts["sessions"] == 4 and facts["frames"] == 1200
    assert facts["loss"] < 0.35, facts  # the last 100 steps' mean
    # a net with random weights: about the features' variance (1)
    torch.manual_seed(0)
    r = SequenceEncoder(5, channels=32, dilations=(1, 2, 4, 8))
    r.set_standardization(torch.cat(sessions))
    gen = torch.Generator().manual_seed(1)
    x = torch.stack([s[:128] for s in sessions])
    mask = span_mask(4, 128, 0.5, gen, 12)
    with torch.no_grad():
        err = lambda net: float(  # noqa: E731
            (((net(x, mask) - net.normalize(x)) ** 2).mean(-1) * mask).sum() / mask.sum()
        )
        assert err(r) > 0.8 and err(m) < 0.25, (err(r), err(m))
    torch.manual_seed(0)
    again = SequenceEncoder(5, channels=32, dilations=(1, 2, 4, 8))
    pretrain_sequences(again, sessions, **kw)
    for a, b in zip(m.state_dict().values(), again.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    emb = embeddings(m, sessions[:2], [15])
    assert emb.shape == (600, 3 * 32) and torch.isfinite(emb).all()
    with pytest.raises(ValueError, match=r"\(T_i, 5\)"):
        pretrain_sequences(m, [torch.zeros(100, 4)], steps=1)
    with pytest.raises(ValueError, match="too short"):
        pretrain_sequences(m, [torch.randn(10, 5)], steps=1)


def test_binned_and_standardised():
    rng = np.random.default_rng(0)
    x = np.c_[rng.normal(size=200), np.full(200, 3.0), 1e-9 * rng.normal(size=200)]
    s = standardised(x)
    np.testing.assert_allclose(s[:, 0].mean(), 0, atol=1e-12)
    np.testing.assert_allclose(s[:, 0].std(), 1, rtol=1e-12)
    assert (s[:, 1:] == 0).all()  # (nearly) constant columns: zero
    b = binned(s, 4)
    assert b.shape == (200, 4 + 3)  # only the varying column is binned
    np.testing.assert_array_equal(b[:, :4].sum(1), 1)  # one-hot
    np.testing.assert_array_equal(b[:, 4:], s)
    assert abs(b[:, :4].mean(0) - 0.25).max() < 0.01  # quantile bins
    np.testing.assert_array_equal(binned(np.zeros((5, 2))), np.zeros((5, 2)))


def test_teacher_probabilities():
    """Two classes that differ in one frame feature: the teacher fitted on 10 labelled frames
    labels the rest right; a class no labelled frame has gets probability 0; the embedding's
    teacher (cotrain's second view) reads the embedding alone."""
    rng = np.random.default_rng(0)
    y = np.repeat([0, 1], 100)
    frame = np.c_[y + 0.2 * rng.normal(size=200), rng.normal(size=(200, 3))]
    idx = np.r_[0:5, 100:105]
    P = linear_teacher_probs(frame, idx, y[idx], 3, [1.0, 1.0, 1.0])
    assert P.shape == (200, 3)
    np.testing.assert_allclose(P.sum(1), 1)
    assert (P[:, 2] == 0).all()
    assert (P.argmax(1) == y).mean() >= 0.97
    noise = rng.normal(size=(200, 4))
    assert (linear_teacher_probs(noise, idx, y[idx], 2).argmax(1) == y).mean() < 0.7  # chance
    # the embedding's own teacher (cotrain's second view) reads the embedding alone
    P = embedding_teacher_probs(frame[:, :1], idx, y[idx], 3, [1.0, 1.0, 1.0])
    assert P.shape == (200, 3) and (P[:, 2] == 0).all() and (P.argmax(1) == y).mean() >= 0.95
    assert (embedding_teacher_probs(noise, idx, y[idx], 2).argmax(1) == y).mean() < 0.7
    with pytest.raises(ValueError, match=r"embedding must be \(N, E\)"):
        embedding_teacher_probs(frame[:, 0], idx, y[idx], 2)
    one = linear_teacher_probs(frame, idx[:5], y[:5], 3)
    assert (one[:, 0] == 1).all()
    with pytest.raises(ValueError, match=r"idx and labels"):
        linear_teacher_probs(frame, idx, y[:3], 3)


def test_saved_encoder_round_trip_and_signature(tmp_path):
    torch.manual_seed(0)
    m = SequenceEncoder(5, channels=8, dilations=(1, 2), target=[0, 2])
    m.set_standardization(torch.randn(50, 5) * 3 + 1)
    sig = {"encoder_sha1": "abc", "measurements": True}
    path = tmp_path / "sequence_encoder.pt"
    torch.save(export_sequence_encoder(m, sig, {"steps": 3}), path)
    back = load_sequence_encoder(str(path), sig)
    x = torch.randn(2, 30, 5)
    torch.testing.assert_close(back.embed(x), m.eval().embed(x))
    assert back.target.tolist() == [0, 2]
    with pytest.raises(ValueError, match="differ in measurements"):
        load_sequence_encoder(str(path), {**sig, "measurements": False})
    (tmp_path / "other.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="other.pt is not a PyTorch checkpoint"):
        load_sequence_encoder(str(tmp_path / "other.pt"))
    torch.save({"kind": "something else"}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="other.pt: not a sequence encoder"):
        load_sequence_encoder(str(tmp_path / "other.pt"))
    with pytest.raises(ValueError, match="sequence encoder not found: .*missing.pt"):
        load_sequence_encoder(str(tmp_path / "missing.pt"))


def _teacher_toy(tmp_path, teacher: str) -> tuple[list, list]:
    """The few-label toy's overrides for a forest head taught by ``teacher`` with a small,
    briefly pretrained sequence encoder, and one unlabelled session's files."""
    base, _ = few_label_toy(tmp_path)
    unl = _toy_session(tmp_path, "unlabelled", 5)
    return [*base, "head=forest", "head.trees=25", "freeze=true",
            f"pseudo_labels.teacher={teacher}", "pseudo_labels.sequence.steps=30",
            "pseudo_labels.sequence.channels=16",
            "pseudo_labels.sequence.dilations=[1,2,4]"], unl  # fmt: skip


def test_sequence_encoder_in_deformnet_classify(tmp_path):
    """pseudo_labels.teacher=cotrain: the sequence encoder pretrains on the training and the
    unlabelled sessions (data.unlabelled_tracks), is saved, teaches the forest head (the
    unlabelled session's frames pseudo-labelled too), and the classifier is right on a held-out
    session; a run that reuses the saved encoder pseudo-labels
    the same frames; one whose per-frame features differ is told so; bad settings are errors
    before any data is read."""
    from deformnet.behavior.model import load_classifier
    from deformnet.behavior.predict import run

    base, unl = _teacher_toy(tmp_path, "cotrain")
    for bad, match in (
        ("pseudo_labels.sequence.mask_ratio=1", r"mask_ratio must be in \(0, 1\)"),
        ("pseudo_labels.sequence.context=[4]", "context must be odd"),
        ("pseudo_labels.sequence.steps=2.5", "steps must be an integer"),
        ("+pseudo_labels.sequence.epochs=3", "unknown pseudo_labels.sequence settings"),
        ("+pseudo_labels.sequence.bins=3", r"sequence.bins: unknown \(it is pseudo_labels.bins\)"),
    ):
        with pytest.raises(ValueError, match=match):
            run(_compose([*base, bad, f"output.dir={tmp_path / 'x'}"]))
    out = tmp_path / "seq"
    unl_on = [f"data.unlabelled_tracks=[{unl[0]}]", "pseudo_labels.unlabelled=true"]
    rep = run(_compose([*base, *unl_on, f"output.dir={out}"]))
    pl = rep["report"]["probe"]["pseudo_labels"]
    assert pl["teacher"] == "cotrain" and pl["encoder"] == str(out / "sequence_encoder.pt")
    assert pl["pretraining"]["sessions"] == 3 and pl["pretraining"]["frames"] == 3 * 360
    assert pl["pretraining"]["steps"] == 30
    assert min(pl["per_class"]) >= 0.3 * 0.3 * 720  # both behaviors pseudo-labelled
    assert rep["report"]["raw"]["macro_f1"] >= 0.95, rep["report"]["raw"]
    model, meta = load_classifier(out / "classifier.pt")  # how the head was taught is kept
    assert meta["pseudo_labels"]["teacher"] == "cotrain"
    # the unlabelled session's frames are pseudo-labelled too (the forest learns from them)
    assert 0 < pl["unlabelled_frames"] <= 360 and pl["frames"] == sum(pl["per_class"])
    assert meta["pseudo_labels"]["sequence"]["steps"] == 30
    reused = run(_compose([*base, f"pseudo_labels.sequence.encoder={out / 'sequence_encoder.pt'}",
                           *unl_on, f"output.dir={tmp_path / 'reuse'}"]))["report"]  # fmt: skip
    rpl = reused["probe"]["pseudo_labels"]
    assert "pretraining" not in rpl and rpl["per_class"] == pl["per_class"]
    assert not (tmp_path / "reuse" / "sequence_encoder.pt").exists()
    with pytest.raises(ValueError, match="other per-frame features .* measurements"):
        run(_compose([*base, f"pseudo_labels.sequence.encoder={out / 'sequence_encoder.pt'}",
                      "measurements=true", "heights_up=[0,0,1]",
                      f"output.dir={tmp_path / 'mismatch'}"]))  # fmt: skip


def test_cotrain_teacher_in_deformnet_classify(tmp_path):
    """pseudo_labels.teacher=cotrain: the sequence encoder pretrains as above;
    the binned frame features' teacher and the embedding's own teacher each pseudo-label their
    most confident frames (keep, embedding_keep), pooled, conflicts dropped; the classifier is
    right on a held-out session, and the pool holds more frames than one view's share alone.
    A bad embedding_keep is an error before any data is read."""
    from deformnet.behavior.model import load_classifier
    from deformnet.behavior.predict import run

    base, unl = _teacher_toy(tmp_path, "cotrain")
    base = [*base, f"data.unlabelled_tracks=[{unl[0]}]"]
    with pytest.raises(ValueError, match=r"embedding_keep must be in \(0, 1\]"):
        run(_compose([*base, "pseudo_labels.embedding_keep=0", f"output.dir={tmp_path / 'x'}"]))
    out = tmp_path / "co"
    rep = run(_compose([*base, f"output.dir={out}"]))
    pl = rep["report"]["probe"]["pseudo_labels"]
    assert pl["teacher"] == "cotrain" and pl["encoder"] == str(out / "sequence_encoder.pt")
    assert pl["pretraining"]["sessions"] == 3 and pl["pretraining"]["steps"] == 30
    assert pl["frames"] == sum(pl["per_class"]) and pl["conflicts"] >= 0
    assert 0 < pl["unlabelled_frames"] <= 360
    # 720 training and 360 unlabelled frames: the embedding's teacher alone keeps about half
    assert pl["frames"] + pl["conflicts"] >= 0.45 * 1080, pl
    assert min(pl["per_class"]) >= 0.3 * 0.3 * 720  # both behaviors pseudo-labelled
    assert rep["report"]["raw"]["macro_f1"] >= 0.95, rep["report"]["raw"]
    _, meta = load_classifier(out / "classifier.pt")
    assert meta["pseudo_labels"]["teacher"] == "cotrain"
    assert meta["pseudo_labels"]["embedding_keep"] == 0.5
