"""Classification heads on the deformation nets' encoders: shapes, fast_dev_run, freezing."""

from __future__ import annotations

import hydra
import numpy as np
import pytest
import torch
from helpers import pinned, quiet_trainer

from deformnet.behavior.encoder import WindowEncoder
from deformnet.behavior.heads import BehaviorClassifier, LinearHead, MLPHead, build_head
from deformnet.body import default_mouse
from deformnet.deformation import build_net
from deformnet.paths import CONF_DIR

TINY = {
    "lstm": {"_target_": "deformnet.nets.LSTMPredictor", "hidden": 8, "layers": 1, "embed": 8},
    "transformer": {
        "_target_": "deformnet.nets.TransformerPredictor",
        "d_model": 16,
        "heads": 2,
        "layers": 1,
        "ff": 16,
        "d_part": 4,
    },
}


def _encoder(kind: str, half_window: int = 2, frame_features: bool = True) -> WindowEncoder:
    body = default_mouse()
    cfg = {**TINY[kind], "num_parts": body.num_parts, "half_window": half_window}
    return WindowEncoder(build_net(cfg), np.asarray(body.points), half_window, frame_features)


def _windows(B: int, W: int, K: int = 8, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    body = torch.tensor(np.asarray(default_mouse().points), dtype=torch.float32)
    shift = torch.randn(B, W, 1, 3, generator=g) * 20 + torch.tensor([150.0, 150.0, 10.0])
    rigid = body.expand(B, W, K, 3) + shift
    deformed = rigid + torch.randn(B, W, K, 3, generator=g)
    observed = torch.rand(B, W, K, generator=g) > 0.2
    return rigid, deformed, observed


@pytest.mark.parametrize("kind", ["lstm", "transformer"])
@pytest.mark.parametrize("frame_features", [True, False])
def test_encoder_and_head_shapes(kind, frame_features):
    enc = _encoder(kind, frame_features=frame_features)
    rigid, deformed, observed = _windows(6, enc.window)
    z = enc(rigid, deformed, observed)
    assert z.shape == (6, enc.out_dim) and torch.isfinite(z).all()
    for head in (LinearHead(enc.out_dim, 8), MLPHead(enc.out_dim, 8, hidden=16, layers=2)):
        logits = BehaviorClassifier(enc, head)(rigid, deformed, observed)
        assert logits.shape == (6, 8)
    with pytest.raises(ValueError, match="rigid must have shape"):
        enc(rigid[:, :-1], deformed[:, :-1], observed[:, :-1])
    with pytest.raises(ValueError, match="head.name"):
        build_head({"name": "svm"}, enc.out_dim, 8)


def test_encoder_ignores_unobserved_values():
    enc = _encoder("lstm").eval()
    rigid, deformed, observed = _windows(4, enc.window)
    other = torch.where(observed[..., None], deformed, deformed + 100.0)
    torch.testing.assert_close(enc(rigid, deformed, observed), enc(rigid, other, observed))


@pytest.mark.parametrize("kind", ["lstm", "transformer"])
def test_heading_frame_encoder_sees_pitch_and_keeps_the_body_frame_features(kind):
    """up set: the encoder reads the heading frame (a pitch changes its summary; a turn about up
    does not), while the frame features are the body frame's, as without up."""
    from deformnet.so3 import rodrigues_to_matrix

    torch.manual_seed(0)
    enc = _encoder(kind).eval()
    head = WindowEncoder(enc.net, enc.body_points.numpy(), enc.half_window, True, up=[0, 0, 1])
    rigid, deformed, observed = _windows(5, enc.window)
    rigid, deformed = rigid.double(), deformed.double()
    enc, head = enc.double(), head.double()
    a, b = enc(rigid, deformed, observed), head(rigid, deformed, observed)
    S = 2 * enc.net.encode_dim  # the encoder summary; the frame features after it
    torch.testing.assert_close(a[:, S:], b[:, S:])
    P = rodrigues_to_matrix(torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64))
    Z = rodrigues_to_matrix(torch.tensor([0.0, 0.0, 1.9], dtype=torch.float64))
    c = rigid[:, :, :1].mean(1, keepdim=True)  # tilt about the window's own place
    tilt = [(x - c) @ P.T + c for x in (rigid, deformed)]
    torch.testing.assert_close(enc(*tilt, observed)[:, :S], a[:, :S])
    assert (head(*tilt, observed)[:, :S] - b[:, :S]).abs().max() > 1e-3
    turn = [x @ Z.T for x in (rigid, deformed)]
    torch.testing.assert_close(head(*turn, observed)[:, :S], b[:, :S])


def _compose(overrides):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose("classify", overrides=pinned(overrides))


def _sim_session(tmp_path, seed: int, T: int = 120) -> tuple[str, str]:
    """A short simulated session as files: points3d CSV (truth, pose columns), per-frame labels."""
    import pandas as pd

    from deformnet.behavior.tracks import POSE_COLUMNS
    from deformnet.sim import simulate

    d = simulate(None, num_frames=T, seed=seed)
    cols = {"fnum": np.arange(T)} | dict(zip(POSE_COLUMNS, d.poses.T))
    for k, part in enumerate(d.parts):
        cols |= {f"{part}_{a}": d.deformed[:, k, i] for i, a in enumerate("xyz")}
    tracks, labels = tmp_path / f"s{seed}.csv", tmp_path / f"s{seed}_labels.csv"
    pd.DataFrame(cols).to_csv(tracks, index=False)
    names = np.asarray(d.behaviors, dtype=object)[d.labels]
    pd.DataFrame({"fnum": np.arange(T), "label": names}).to_csv(labels, index=False)
    return str(tracks), str(labels)


@pytest.mark.parametrize("net", ["lstm", "transformer"])
def test_fast_dev_run_both_encoders(tmp_path, net):
    from deformnet.behavior.predict import run

    tiny = [f"net.{k}={v}" for k, v in TINY[net].items() if k != "_target_"]
    (tt, tl), (vt, vl) = _sim_session(tmp_path, 0), _sim_session(tmp_path, 10000)
    cfg = _compose(
        [
            f"net={net}",
            *tiny,
            "half_window=2",
            f"data.train_tracks=[{tt}]",
            f"data.train_labels=[{tl}]",
            f"data.val_tracks=[{vt}]",
            f"data.val_labels=[{vl}]",
            "logger=none",
            "trainer.fast_dev_run=true",
            f"output.dir={tmp_path}",
        ]
    )
    res = run(cfg)
    assert (tmp_path / "classifier.pt").exists()
    assert (tmp_path / "confusion.png").exists() and (tmp_path / "ethogram.png").exists()
    assert res["report"]["split"] == "val"
    assert 0.0 <= res["report"]["raw"]["macro_f1"] <= 1.0


def _batches(enc, n: int = 4, B: int = 16):
    out = []
    for i in range(n):
        rigid, deformed, observed = _windows(B, enc.window, seed=i)
        label = torch.randint(0, 3, (B,), generator=torch.Generator().manual_seed(i))
        out.append({"rigid": rigid, "deformed": deformed, "observed": observed, "label": label})
    return out


@pytest.mark.parametrize("freeze", [True, False])
def test_frozen_encoder_weights_do_not_change(freeze):
    from deformnet.behavior.lit import ClassifyLit

    torch.manual_seed(0)
    enc = _encoder("lstm")
    model = BehaviorClassifier(enc, MLPHead(enc.out_dim, 3, hidden=8))
    before_enc = {k: v.clone() for k, v in model.encoder.state_dict().items()}
    before_head = {k: v.clone() for k, v in model.head.state_dict().items()}
    lit = ClassifyLit(model, ["a", "b", "c"], freeze=freeze, lr=1e-2, encoder_lr=1e-2)
    trainer = quiet_trainer(4)
    batches = torch.utils.data.DataLoader(_batches(enc), batch_size=None)
    trainer.fit(lit, train_dataloaders=batches)
    enc_changed = [
        k for k, v in model.encoder.state_dict().items() if not torch.equal(v, before_enc[k])
    ]
    head_changed = [
        k for k, v in model.head.state_dict().items() if not torch.equal(v, before_head[k])
    ]
    assert head_changed  # the head trains either way
    if freeze:
        assert enc_changed == []
    else:
        assert any(k.startswith("net.lstm") for k in enc_changed)


@pytest.mark.parametrize("kind", ["lstm", "transformer"])
def test_temporal_context_pools_the_surrounding_windows(kind):
    """With context (5, 9) and stride 2 the features are the mid window's encoder output plus
    the mean and std of the outputs of the windows at offsets within +-2 and +-4 (step 2), and
    the bank path (`context_features`, one encoder pass per distinct frame) gives the same."""
    from deformnet.behavior.features import SessionBank, context_features
    from deformnet.behavior.heads import context_offsets
    from deformnet.behavior.tracks import Session

    enc = _encoder(kind).eval()
    assert context_offsets((5, 9), 2) == (-4, -2, 0, 2, 4)
    dim = BehaviorClassifier.feature_dim(enc.out_dim, (5, 9))
    model = BehaviorClassifier(enc, LinearHead(dim, 3), (5, 9), 2).eval()
    assert model.span == 4 and model.window == enc.window + 8 and model.out_dim == 5 * enc.out_dim
    rigid, deformed, observed = _windows(3, model.window, seed=1)
    with torch.no_grad():
        f = model.features(rigid, deformed, observed)
        W = enc.window
        per = torch.stack(
            [enc(rigid[:, s : s + W], deformed[:, s : s + W], observed[:, s : s + W])
             for s in (0, 2, 4, 6, 8)], 1)  # fmt: skip
    want = torch.cat(
        [per[:, 2], per[:, 1:4].mean(1), per[:, 1:4].std(1, unbiased=False),
         per.mean(1), per.std(1, unbiased=False)], -1)  # fmt: skip
    assert f.shape == (3, model.out_dim)
    torch.testing.assert_close(f, want)
    assert model(rigid, deformed, observed).shape == (3, 3)
    with pytest.raises(ValueError, match="context span"):
        model.features(rigid[:, 1:], deformed[:, 1:], observed[:, 1:])
    with pytest.raises(ValueError, match="odd"):
        context_offsets((4,))
    # the bank path: one session, every frame
    T = 12
    r, d, o = _windows(1, T, seed=2)
    s = Session("s", r[0].numpy(), d[0].numpy(), o[0].numpy(), np.arange(T), np.zeros(T, int))
    bank = SessionBank([s], model.half_window)
    idx = torch.arange(T)
    b = bank.batch(idx)
    with torch.no_grad():
        direct = model.features(b["rigid"], b["deformed"], b["observed"])
    torch.testing.assert_close(context_features(model, bank, idx, batch_size=5), direct)
    # standardisation: centred and scaled by the training features; constant ones only centred
    feats = torch.randn(50, model.out_dim) * 3 + 1
    feats[:, 0] = 7.0
    model.set_standardization(feats)
    z = (feats - model.feature_mean) / model.feature_std
    assert torch.allclose(z[:, 1:].mean(0), torch.zeros(model.out_dim - 1), atol=1e-5)
    assert torch.allclose(z[:, 1:].std(0), torch.ones(model.out_dim - 1), atol=1e-4)
    assert float(model.feature_std[0]) == 1.0 and torch.all(z[:, 0] == 0)


def test_ensemble_head_averages_its_members_probabilities_and_each_member_is_fitted_alone():
    import copy

    from deformnet.behavior.fit import fit_head_lbfgs
    from deformnet.behavior.heads import EnsembleHead

    torch.manual_seed(0)
    ens = build_head({"name": "mlp", "hidden": 8, "ensemble": 3, "dropout": 0.0}, 5, 4)
    assert isinstance(ens, EnsembleHead) and len(ens.members) == 3
    assert isinstance(build_head({"name": "mlp", "hidden": 8}, 5, 4), MLPHead)
    x = torch.randn(7, 5)
    out = ens(x)
    assert out.shape == (7, 4)
    mean_p = torch.stack([m(x).softmax(-1) for m in ens.members]).mean(0)
    torch.testing.assert_close(out.softmax(-1), mean_p)
    torch.testing.assert_close(out.exp().sum(-1), torch.ones(7))  # log of the mean probabilities
    with pytest.raises(ValueError, match="head.ensemble"):
        build_head({"name": "linear", "ensemble": 0}, 5, 4)

    class Probe(torch.nn.Module):  # what fit_head_lbfgs reads of a classifier
        def __init__(self, head):
            super().__init__()
            self.head = head
            self.register_buffer("feature_mean", torch.zeros(5))
            self.register_buffer("feature_std", torch.ones(5))

    g = torch.Generator().manual_seed(1)
    X = torch.randn(60, 5, generator=g)
    y = (X[:, 0] > 0).long() + 2 * (X[:, 1] > 0).long()
    alone = [copy.deepcopy(m) for m in ens.members]
    facts = fit_head_lbfgs(Probe(ens), X, y, l2=0.5, max_iter=50)
    for m, a in zip(ens.members, alone):
        fit_head_lbfgs(Probe(a), X, y, l2=0.5, max_iter=50)
        for p, q in zip(m.parameters(), a.parameters()):
            torch.testing.assert_close(p, q)
    assert facts["iterations"] > 3
    # the members start apart and end apart (independent fits), and the ensemble fits the data
    assert (ens.members[0].net[1].weight - ens.members[1].net[1].weight).abs().max() > 1e-2
    assert (ens(X).argmax(-1) == y).float().mean() > 0.9


def test_forest_head_is_scikit_learns_forest_and_reads_only_the_frame_features():
    """fit_head_forest: the torch evaluation equals RandomForestClassifier.predict_proba on the
    columns it read (the frame features); a stored forest reloads into a fresh head; changing
    the encoder's outputs does not move the forest."""
    from sklearn.ensemble import RandomForestClassifier

    from deformnet.behavior.fit import fit_head_forest

    enc = _encoder("lstm")
    model = BehaviorClassifier(enc, build_head({"name": "forest", "trees": 15}, enc.out_dim, 3))
    cols = model.frame_columns()
    E = 2 * enc.net.encode_dim
    assert cols.tolist() == list(range(E, enc.out_dim))  # no context: one block
    g = np.random.default_rng(0)
    N = 240
    X = torch.tensor(g.normal(size=(N, enc.out_dim)), dtype=torch.float32)
    y = (X[:, E + 2] > 0.0).long() + (X[:, E + 5] > 1.0).long()  # from frame features alone
    X[:, :E] += y[:, None] * 3.0  # the encoder outputs separate the classes too (not read)
    w = [1.0, 2.0, 3.0]
    model.set_standardization(X)
    facts = fit_head_forest(model, X, y, w)
    assert facts["trees"] == 15 and facts["columns"] == cols.numel() and facts["depth"] >= 2
    x = (X - model.feature_mean) / model.feature_std
    ref = RandomForestClassifier(
        15, min_samples_leaf=2, class_weight={0: 1.0, 1: 2.0, 2: 3.0}, random_state=0
    ).fit(x[:, cols].numpy(), y.numpy())
    Xt = torch.tensor(g.normal(size=(500, enc.out_dim)), dtype=torch.float32)
    p = model.classify(Xt).softmax(-1)
    xt = ((Xt - model.feature_mean) / model.feature_std)[:, cols].numpy()
    np.testing.assert_allclose(p.numpy(), ref.predict_proba(xt), atol=1e-6)
    moved = Xt.clone()
    moved[:, :E] += 100.0
    torch.testing.assert_close(model.classify(moved), model.classify(Xt))
    # a forest head's state (its size known only once fitted) reloads into a fresh one
    fresh = build_head({"name": "forest", "trees": 15}, enc.out_dim, 3)
    with pytest.raises(RuntimeError, match="not fitted"):
        fresh(Xt)
    fresh.load_state_dict(model.head.state_dict())
    torch.testing.assert_close(fresh(x), model.head(x))
    with pytest.raises(ValueError, match="ensemble must be 1"):
        build_head({"name": "forest", "ensemble": 3}, enc.out_dim, 3)
    with pytest.raises(ValueError, match="cannot build the forest head"):
        build_head({"name": "forest", "inputs": "all"}, enc.out_dim, 3)  # deleted (no gain)
    no_frame = BehaviorClassifier(_encoder("lstm", frame_features=False), fresh)
    with pytest.raises(ValueError, match="no frame features"):
        no_frame.frame_columns()


def test_mechanism_features_shape_value_gradient():
    """MechanismFeatures: each chosen part's distance to each mechanism, then the nearest part
    per mechanism, / scale; float64 gradcheck; bad input named."""
    from deformnet.behavior.encoder import MechanismFeatures

    pos = [[0.0, 0.0, 0.0], [100.0, 0.0, 0.0]]
    mech = MechanismFeatures(pos, [0, 2], ["lever", "ball"], scale=10.0)
    assert mech.out_dim == 6
    pts = torch.zeros(2, 3, 3)
    pts[0, 0] = torch.tensor([3.0, 4.0, 0.0])  # part 0: 5 mm from lever, ~97 from ball
    pts[0, 2] = torch.tensor([100.0, 0.0, 2.0])  # part 2: at the ball (2 mm)
    f = mech(pts)
    assert f.shape == (2, 6)
    d_ball0 = float(np.hypot(97.0, 4.0))
    # [part 0 to lever, part 0 to ball, part 2 to lever, part 2 to ball, nearest to each]
    want = [0.5, d_ball0 / 10, float(np.hypot(100.0, 2.0)) / 10, 0.2, 0.5, 0.2]
    torch.testing.assert_close(f[0], torch.tensor(want))
    x = pts[:1].double().requires_grad_()
    mech64 = MechanismFeatures(pos, [0, 2], scale=10.0).double()
    assert torch.autograd.gradcheck(mech64, (x + 0.1,), eps=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="points must be"):
        mech(pts[0])
    with pytest.raises(ValueError, match="positions must be"):
        MechanismFeatures([[0.0, 0.0]], [0])
    with pytest.raises(ValueError, match="names"):
        MechanismFeatures(pos, [0], ["lever"])


@pytest.mark.parametrize("kind", ["lstm", "transformer"])
def test_encoder_appends_mechanism_distances_as_frame_features(kind):
    """The lock-box context comes after the frame features (from the mid frame's points:
    observed where seen, rigid elsewhere), counts among the frame columns, and moves with the
    mouse while the canonical encoder outputs do not."""
    from deformnet.behavior.encoder import MechanismFeatures

    body = default_mouse()
    cfg = {**TINY[kind], "num_parts": body.num_parts, "half_window": 2}
    mech = MechanismFeatures([[150.0, 250.0, 10.0], [200.0, 250.0, 10.0]], [0, 1])
    enc = WindowEncoder(build_net(cfg), np.asarray(body.points), 2, True, None, mech).eval()
    plain = _encoder(kind)
    assert enc.out_dim == plain.out_dim + 6
    rigid, deformed, observed = _windows(3, enc.window)
    z = enc(rigid, deformed, observed)
    mid = enc.half_window
    pts = torch.where(observed[:, mid, :, None], deformed[:, mid], rigid[:, mid])
    torch.testing.assert_close(z[:, -6:], mech(pts))
    model = BehaviorClassifier(enc, LinearHead(enc.out_dim * 3, 2), context_frames=(3,))
    cols = model.frame_columns()
    E = 2 * enc.net.encode_dim
    assert all(int(c) % enc.out_dim >= E for c in cols) and cols.numel() == 3 * (enc.out_dim - E)
    shift = torch.tensor([40.0, 0.0, 0.0])
    z2 = enc(rigid + shift, deformed + shift, observed)
    torch.testing.assert_close(z2[:, :E], z[:, :E], atol=1e-4, rtol=1e-4)
    assert (z2[:, -6:] - z[:, -6:]).abs().max() > 0.1
    with pytest.raises(ValueError, match="part index"):
        WindowEncoder(build_net(cfg), np.asarray(body.points), 2, True, None,
                      MechanismFeatures([[0.0, 0.0, 0.0]], [8]))  # fmt: skip


def test_pose_measurements_shape_value_gradient_and_encoder():
    """pose_measurements: pairwise part distances (upper triangle) then part speeds, / scale;
    invariant to a rigid motion of both frames; float64 gradcheck; WindowEncoder appends them
    after the frame features (measurements=True) from the mid frame and the one before."""
    from deformnet.behavior.encoder import pose_measurements
    from deformnet.so3 import rodrigues_to_matrix

    g = torch.Generator().manual_seed(3)
    pts = torch.randn(2, 4, 3, generator=g, dtype=torch.float64) * 10
    before = pts + torch.randn(2, 4, 3, generator=g, dtype=torch.float64)
    m = pose_measurements(pts, before, scale=10.0)
    assert m.shape == (2, 6 + 4)
    torch.testing.assert_close(m[0, 0], (pts[0, 0] - pts[0, 1]).norm() / 10)
    torch.testing.assert_close(m[1, 5], (pts[1, 2] - pts[1, 3]).norm() / 10)
    torch.testing.assert_close(m[1, 6 + 2], (pts[1, 2] - before[1, 2]).norm() / 10)
    R = rodrigues_to_matrix(torch.tensor([0.3, -0.2, 1.1], dtype=torch.float64))
    t = torch.tensor([5.0, -7.0, 2.0], dtype=torch.float64)
    torch.testing.assert_close(pose_measurements(pts @ R.T + t, before @ R.T + t, 10.0), m)
    x = pts.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda p: pose_measurements(p, before), (x,), eps=1e-6)
    with pytest.raises(ValueError, match="points and before"):
        pose_measurements(pts, before[:, :3])
    up = torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64)
    h = pose_measurements(pts, before, 10.0, up)
    assert h.shape == (2, 6 + 4 + 4)
    torch.testing.assert_close(h[:, :10], m)
    torch.testing.assert_close(h[:, 10:], (pts @ up) / 10)

    body = default_mouse()
    cfg = {**TINY["lstm"], "num_parts": body.num_parts, "half_window": 2}
    enc = WindowEncoder(build_net(cfg), np.asarray(body.points), 2, True, None, None, True)
    K = body.num_parts
    assert enc.out_dim == _encoder("lstm").out_dim + K * (K - 1) // 2 + K
    rigid, deformed, observed = _windows(3, enc.window)
    z = enc(rigid, deformed, observed)
    seen = torch.where(observed[..., None], deformed, rigid)
    torch.testing.assert_close(
        z[:, -(K * (K - 1) // 2 + K) :], pose_measurements(seen[:, 2], seen[:, 1])
    )
    cols = BehaviorClassifier(enc, LinearHead(enc.out_dim, 2)).frame_columns()
    assert int(cols[-1]) == enc.out_dim - 1
    # a heading-frame encoder (it has the world's up) also appends the parts' heights
    up_enc = WindowEncoder(build_net(cfg), np.asarray(body.points), 2, True, [0, 0, 1], None, True)
    assert up_enc.out_dim == enc.out_dim + K
    zu = up_enc(rigid, deformed, observed)
    torch.testing.assert_close(zu[:, -K:], seen[:, 2, :, 2] / 50.0)
    # a body-frame encoder given the world's up for the heights: the same heights
    h_enc = WindowEncoder(build_net(cfg), np.asarray(body.points), 2, True, None, None, True,
                          heights_up=[0, 0, 3])  # fmt: skip
    assert h_enc.out_dim == up_enc.out_dim and h_enc.up is None
    torch.testing.assert_close(h_enc(rigid, deformed, observed)[:, -K:], zu[:, -K:])
    with pytest.raises(ValueError, match="heights_up .* differs from the encoder's up"):
        WindowEncoder(build_net(cfg), np.asarray(body.points), 2, True, [0, 0, 1], None, True,
                      heights_up=[0, 1, 0])  # fmt: skip


def test_the_deformation_training_imports_no_behavior_code():
    """deformnet.lit (the deformation nets' training) reads a window's summary from
    deformnet.windows, not from the behavior heads (a layer below them)."""
    from test_layering import BEHAVIOR, ROOT, _imported_modules

    for name in ("lit.py", "windows.py", "train.py", "deformation.py"):
        mods = [m for _, m in _imported_modules(ROOT / "deformnet" / name)]
        assert not [m for m in mods if m.startswith(BEHAVIOR)], (name, mods)
