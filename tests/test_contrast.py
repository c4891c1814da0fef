"""The temporal-contrastive pretraining term (behavior pretraining, `deformnet.lit.DeformLit`
with `contrast`): pairs of windows from the same sequence a few frames apart, the nets' shared
`encode`, the InfoNCE value and gradient, learning on a toy sequence, and the config checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from deformnet.body import default_mouse
from deformnet.data import MaskConfig, RandomWindowBatches, SequenceArrays, WindowBank, toy_sequence
from deformnet.deformation import DeformationModel
from deformnet.lit import DeformLit
from deformnet.nets import LSTMPredictor, TransformerPredictor

torch.set_num_threads(1)


def _coded(T: int, K: int, base: float) -> SequenceArrays:
    """rigid[t, k] = (base + t, k, 0): a window shows its sequence and frames."""
    t = base + np.arange(T, dtype=np.float32)[:, None].repeat(K, 1)
    k = np.arange(K, dtype=np.float32)[None].repeat(T, 0)
    rigid = np.stack([t, k, np.zeros_like(t)], -1)
    return SequenceArrays(rigid, rigid + 1.0, np.ones((T, K), bool))


def test_pairs_are_a_few_frames_away_in_the_same_sequence():
    n, shift = 2, 6
    bank = WindowBank([_coded(40, 3, 0.0), _coded(25, 3, 1000.0)], n)
    it = RandomWindowBatches(bank, 256, 8, MaskConfig(), seed=1, pair_shift=shift)
    seen = set()
    for b in it:
        a = b["rigid"][:, n, 0, 0]  # the mid frames' codes
        p = b["pair"]["rigid"][:, n, 0, 0]
        d = (p - a).abs()
        assert ((d >= 1) & (d <= shift)).all()  # 1..shift frames away, never the same window
        assert ((a >= 1000) == (p >= 1000)).all()  # never across sequences
        assert b["pair"]["observed"].shape == b["observed"].shape
        seen |= set((p - a).tolist())
    assert seen == {float(s) for s in range(-shift, shift + 1) if s}  # both ways, every shift
    # the last valid mid of a sequence pairs backwards; a one-mid sequence pairs with itself
    j = bank.shifted(torch.tensor([len(bank.mids_for(1)) - 1]), torch.tensor([3]))
    assert bank.mids_for(1)[j] == bank.mids_for(1)[-1] - 3
    single = WindowBank([_coded(5, 3, 0.0)], n)
    assert single.shifted(torch.tensor([0]), torch.tensor([2])).item() == 0
    with pytest.raises(ValueError, match="pair_shift"):
        RandomWindowBatches(bank, 4, 1, MaskConfig(), pair_shift=-1)
    plain = next(iter(RandomWindowBatches(bank, 4, 1, MaskConfig())))
    assert "pair" not in plain


@pytest.mark.parametrize(
    "net",
    [
        LSTMPredictor(8, 3, hidden=8, embed=8, layers=1),
        TransformerPredictor(8, 3, d_model=16, heads=2, layers=1, ff=32, d_part=8),
    ],
)
def test_encode_is_what_forward_reads(net):
    g = torch.Generator().manual_seed(0)
    for p in net.parameters():  # the zero-initialised output layer too: a net that deforms
        p.data = 0.3 * torch.randn(p.shape, generator=g)
    B, W, K = 4, net.window, 8
    rigid = 20 * torch.randn(B, W, K, 3, generator=g)
    deformed = rigid + torch.randn(B, W, K, 3, generator=g)
    observed = torch.rand(B, W, K, generator=g) > 0.3
    seq, prior = net.encode(rigid, deformed, observed)
    assert seq.shape == (B, W, net.encode_dim)
    out = net(rigid, deformed, observed)
    assert out.abs().sub(rigid[:, net.half_window].abs()).abs().max() > 1e-3  # it deforms
    torch.testing.assert_close(out, net._finish(net.head(seq[:, net.half_window], prior), rigid))


def _lit(contrast: dict | None, half_window: int = 4) -> DeformLit:
    body = default_mouse()
    net = LSTMPredictor(body.num_parts, half_window, hidden=16, embed=16, layers=1)
    model = DeformationModel(net, body, half_window)
    return DeformLit(model, contrast=contrast)


def test_contrast_loss_value_and_gradient():
    torch.manual_seed(0)
    lit = _lit({"weight": 1.0, "temperature": 0.5, "dim": 8})
    bank = WindowBank([toy_sequence(default_mouse(), 300, seed=0)], 4)
    batch = next(iter(RandomWindowBatches(bank, 6, 1, MaskConfig(), seed=0, pair_shift=5)))
    loss, acc = lit.contrast_loss(batch)
    # by hand: normalised projections, cosine logits / temperature, symmetric cross-entropy
    z1 = torch.nn.functional.normalize(
        lit.contrast_head(lit.summary(batch["rigid"], batch["deformed"], batch["observed"])), dim=-1
    )
    pr = batch["pair"]
    z2 = torch.nn.functional.normalize(
        lit.contrast_head(lit.summary(pr["rigid"], pr["deformed"], pr["observed"])), dim=-1
    )
    logits = (z1 @ z2.T / 0.5).double()
    lsm_r, lsm_c = logits.log_softmax(1), logits.log_softmax(0)
    want = -0.5 * (lsm_r.diagonal().mean() + lsm_c.diagonal().mean())
    assert loss.item() == pytest.approx(want.item(), rel=1e-5)
    assert acc.item() == pytest.approx((logits.argmax(1) == torch.arange(6)).double().mean().item())
    # the summary is the encoder's mid output and window mean, invariant to a rigid motion
    s = lit.summary(batch["rigid"], batch["deformed"], batch["observed"])
    assert s.shape == (6, 2 * lit.model.net.encode_dim)
    from deformnet.so3 import rodrigues_to_matrix

    R = rodrigues_to_matrix(torch.tensor([0.3, -0.2, 1.1], dtype=torch.float64)).float()
    move = lambda x: x @ R.T + torch.tensor([40.0, -25.0, 3.0])  # noqa: E731
    s2 = lit.summary(move(batch["rigid"]), move(batch["deformed"]), batch["observed"])
    torch.testing.assert_close(s2, s, atol=2e-4, rtol=1e-4)
    # the gradient reaches the encoder (LSTM) and the projection, not the per-part output layer
    loss.backward()
    net = lit.model.net
    assert net.lstm.weight_ih_l0.grad.abs().sum() > 0 and net.embed[0].weight.grad.abs().sum() > 0
    assert all(p.grad.abs().sum() > 0 for p in lit.contrast_head.parameters())
    assert all(p.grad is None for p in net.head.parameters())


def test_contrast_pretraining_learns_to_pair_windows():
    """On a toy sequence whose motion changes over time, the encoder learns to tell a window's
    neighbour (a few frames away) from the batch's other windows: far above chance (1/B)."""
    torch.manual_seed(0)
    lit = _lit({"weight": 1.0, "temperature": 0.1, "dim": 16})
    bank = WindowBank([toy_sequence(default_mouse(), 1500, seed=s) for s in range(2)], 4)
    B = 32
    mask = MaskConfig(gap_max=3, occlusion_max=3)  # training's gaps, scaled to a 9-frame window
    it = RandomWindowBatches(bank, B, 150, mask, seed=0, pair_shift=3)
    opt = torch.optim.Adam(lit.parameters(), lr=3e-3)
    losses, accs = [], []
    for batch in it:
        loss, acc = lit.contrast_loss(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        accs.append(acc.item())
    assert np.mean(losses[:5]) > 0.8 * math.log(B)  # chance at the start
    assert np.mean(losses[-20:]) < 0.6 * math.log(B)
    assert np.mean(accs[-20:]) > 6 / B


def test_training_step_adds_the_term_and_config_is_checked():
    lit = _lit({"weight": 0.5, "temperature": 0.1, "dim": 8, "max_shift": 3})
    bank = WindowBank([toy_sequence(default_mouse(), 200, seed=0)], 4)
    batch = next(iter(RandomWindowBatches(bank, 8, 1, MaskConfig(), seed=0, pair_shift=3)))
    torch.manual_seed(0)
    total = lit.training_step(batch, 0)
    deform, _ = lit._canonical_loss(batch)
    c, _ = lit.contrast_loss(batch)
    assert total.item() == pytest.approx(deform.item() + 0.5 * c.item(), rel=1e-5)
    del batch["pair"]
    with pytest.raises(ValueError, match="needs training batches with pairs"):
        lit.training_step(batch, 0)
    off = _lit(None)
    assert off.contrast_head is None
    assert off.training_step(batch, 0).item() == pytest.approx(deform.item(), rel=1e-5)
    with pytest.raises(ValueError, match="unknown keys"):
        _lit({"weight": 1.0, "temprature": 0.1})
    with pytest.raises(ValueError, match="temperature"):
        _lit({"weight": 1.0, "temperature": 0.0})
    from deformnet.confutil import compose
    from deformnet.train import build_datamodule, build_model

    cfg = compose("train", ["contrast.weight=1.0", "contrast.max_shift=0"])
    with pytest.raises(ValueError, match="contrast.max_shift"):
        build_model(cfg)
    cfg = compose("train", ["contrast.weight=1.0", "contrast.max_shift=7", "data.source=toy"])
    lit2, body, _ = build_model(cfg)
    assert lit2.contrast_head is not None
    assert build_datamodule(cfg, body).pair_shift == 7
    assert build_datamodule(compose("train", ["data.source=toy"]), body).pair_shift == 0
