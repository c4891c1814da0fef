"""The forecasting pretraining term (behavior pretraining, `deformnet.lit.DeformLit` with
`forecast`): targets a given number of token steps beyond the window in the same sequence
(mirror, reversal and token steps respected), the loss's value and gradient, learning on a toy
sequence, and the config checks."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deformnet.body import default_mouse
from deformnet.data import (
    Augment,
    MaskConfig,
    RandomWindowBatches,
    SequenceArrays,
    WindowBank,
    toy_sequence,
)
from deformnet.deformation import DeformationModel
from deformnet.lit import DeformLit
from deformnet.nets import LSTMPredictor

torch.set_num_threads(1)


def _coded(T: int, K: int, base: float) -> SequenceArrays:
    """deformed[t, k] = (base + t + 1, k + 1, 1): a target shows its sequence, frame, part."""
    t = base + np.arange(T, dtype=np.float32)[:, None].repeat(K, 1)
    k = np.arange(K, dtype=np.float32)[None].repeat(T, 0)
    rigid = np.stack([t, k, np.zeros_like(t)], -1)
    return SequenceArrays(rigid, rigid + np.float32(1.0), np.ones((T, K), bool))


def test_ahead_targets_are_the_frames_shift_steps_away_in_the_same_sequence():
    n, lo, hi = 2, 3, 9
    bank = WindowBank([_coded(60, 3, 0.0), _coded(30, 3, 1000.0)], n)
    it = RandomWindowBatches(bank, 256, 6, MaskConfig(), seed=1, ahead_shift=(lo, hi))
    seen = set()
    for b in it:
        a = b["target"][:, 0, 0]  # the mid frames' codes
        far, shift, mask = b["ahead"]["points"], b["ahead"]["shift"], b["ahead"]["mask"]
        torch.testing.assert_close(far[:, 0, 0] - a, shift)  # exactly `shift` frames away
        assert ((far[:, 0, 0] >= 1000) == (a >= 1000)).all()  # never across sequences
        assert (far[:, :, 1] == torch.arange(1.0, 4.0)).all() and (far[:, :, 2] == 1).all()
        assert mask.all() and ((shift.abs() >= lo) & (shift.abs() <= hi)).all()
        seen |= set(shift.tolist())
    assert seen == {float(s) for s in range(-hi, hi + 1) if abs(s) >= lo}  # both ways, all
    # a sequence too short for the shift either way: no target (mask false), not a wrong one
    short = WindowBank([_coded(8, 3, 0.0)], n)
    b = next(iter(RandomWindowBatches(short, 16, 1, MaskConfig(), ahead_shift=(5, 5))))
    assert (b["ahead"]["shift"] == 0).all() and not b["ahead"]["mask"].any()
    # token steps: the shift counts token steps (here 2 frames each)
    b = next(iter(RandomWindowBatches(bank, 64, 1, MaskConfig(), ahead_shift=(lo, hi),
                                      augment=Augment(steps=(2,)))))  # fmt: skip
    torch.testing.assert_close(b["ahead"]["points"][:, 0, 0] - b["target"][:, 0, 0],
                               2 * b["ahead"]["shift"])  # fmt: skip
    # a window played backwards: later in the recording is earlier in the window
    b = next(iter(RandomWindowBatches(bank, 64, 1, MaskConfig(), ahead_shift=(lo, hi),
                                      augment=Augment(reverse=1.0))))  # fmt: skip
    torch.testing.assert_close(b["ahead"]["points"][:, 0, 0] - b["target"][:, 0, 0],
                               -b["ahead"]["shift"])  # fmt: skip
    plain = next(iter(RandomWindowBatches(bank, 4, 1, MaskConfig())))
    assert "ahead" not in plain
    for bad in ((0, 3), (4, 3), (-1, 2)):
        with pytest.raises(ValueError, match="ahead_shift"):
            RandomWindowBatches(bank, 4, 1, MaskConfig(), ahead_shift=bad)


def test_ahead_targets_are_mirrored_with_their_window():
    from deformnet.data import mirror_permutation

    perm = mirror_permutation(default_mouse().parts)
    K = len(perm)
    bank = WindowBank([_coded(60, K, 0.0)], 2)
    it = RandomWindowBatches(bank, 64, 1, MaskConfig(), seed=4, augment=Augment(mirror=0.5),
                             mirror_perm=perm, ahead_shift=(3, 9))  # fmt: skip
    b = next(iter(it))
    flip = b["target"][:, 0, 0] < 0  # mirrored: x -> -x and left / right parts swapped
    assert 0 < int(flip.sum()) < 64
    far, mid = b["ahead"]["points"], b["target"]
    want_parts = 1 + torch.where(flip[:, None], torch.tensor(perm, dtype=torch.float32),
                                 torch.arange(K, dtype=torch.float32))  # fmt: skip
    assert (far[..., 1] == want_parts).all() and (mid[..., 1] == want_parts).all()
    torch.testing.assert_close(far[:, 0, 0].abs() - mid[:, 0, 0].abs(), b["ahead"]["shift"])


def _lit(forecast: dict | None, half_window: int = 4, up=None) -> DeformLit:
    body = default_mouse()
    net = LSTMPredictor(body.num_parts, half_window, hidden=16, embed=16, layers=1)
    model = DeformationModel(net, body, half_window, up=up)
    return DeformLit(model, forecast=forecast)


@pytest.mark.parametrize("up", [None, (0.0, 0.0, 1.0)])
def test_forecast_loss_value_invariance_and_gradient(up):
    torch.manual_seed(0)
    lit = _lit({"weight": 1.0, "hidden": 16, "scale_mm": 50.0}, up=up)
    bank = WindowBank([toy_sequence(default_mouse(), 300, seed=0)], 4)
    batch = next(iter(RandomWindowBatches(bank, 6, 1, MaskConfig(), seed=0, ahead_shift=(5, 9))))
    loss, rmse = lit.forecast_loss(batch)
    # by hand: the head on [summary, shift / n], targets in the mid frame's canonical frame
    from deformnet.windows import window_summary

    m = lit.model
    s, (_, _, R, t) = window_summary(
        m.net, m.body_points, batch["rigid"], batch["deformed"], batch["observed"],
        m.up_tensor(batch["rigid"]),
    )  # fmt: skip
    a = batch["ahead"]
    pred = lit.forecast_head(torch.cat((s, a["shift"][:, None] / 4), -1)).reshape(6, -1, 3)
    sq = ((pred * 50.0 - (a["points"] - t[:, None]) @ R) ** 2).sum(-1)
    assert 0 < int(a["mask"].sum()) < a["mask"].numel()  # some parts unseen there: left out
    want = sq[a["mask"]].mean() / 50.0**2
    assert loss.item() == pytest.approx(want.item(), rel=1e-5)
    assert rmse.item() == pytest.approx(50.0 * want.sqrt().item(), rel=1e-5)
    # the targets move with the window: a rigid motion of the world (about the up axis for a
    # heading-frame net) leaves the loss unchanged
    from deformnet.so3 import rodrigues_to_matrix

    axis = torch.tensor([0.0, 0.0, 1.1] if up else [0.3, -0.2, 1.1], dtype=torch.float64)
    Rw = rodrigues_to_matrix(axis).float()
    move = lambda x: x @ Rw.T + torch.tensor([40.0, -25.0, 3.0])  # noqa: E731
    moved = {**batch, "rigid": move(batch["rigid"]), "deformed": move(batch["deformed"]),
             "ahead": {**a, "points": move(a["points"])}}  # fmt: skip
    assert lit.forecast_loss(moved)[0].item() == pytest.approx(loss.item(), rel=1e-3)
    # the gradient reaches the encoder and the forecasting head, not the per-part output layer
    loss.backward()
    net = lit.model.net
    assert net.lstm.weight_ih_l0.grad.abs().sum() > 0 and net.embed[0].weight.grad.abs().sum() > 0
    assert all(p.grad.abs().sum() > 0 for p in lit.forecast_head.parameters())
    assert all(p.grad is None for p in net.head.parameters())


def test_forecast_pretraining_learns_to_forecast():
    """On toy sequences that move, the encoder learns where the body will be 6-10 frames after
    (or was before) the window: far better than "it stays where it is" (the mid frame's
    positions), which a net without motion state would be stuck near."""
    torch.manual_seed(0)
    lit = _lit({"weight": 1.0, "hidden": 32, "scale_mm": 20.0})
    bank = WindowBank([toy_sequence(default_mouse(), 1500, seed=s) for s in range(2)], 4)
    mask = MaskConfig(gap_max=3, occlusion_max=3)
    it = RandomWindowBatches(bank, 32, 250, mask, seed=0, ahead_shift=(6, 10))
    opt = torch.optim.Adam(lit.parameters(), lr=3e-3)
    losses, stay = [], []
    for batch in it:
        loss, _ = lit.forecast_loss(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        R, t = lit.model.canonical(batch["rigid"], batch["deformed"], batch["observed"])[1:]
        a = batch["ahead"]
        far = (a["points"] - t[:, None]) @ R
        here = (batch["target"] - t[:, None]) @ R
        stay.append((((far - here) ** 2).sum(-1).mean() / 20.0**2).item())
    assert np.mean(losses[-30:]) < 0.3 * np.mean(stay[-30:])


def test_training_step_adds_the_term_and_config_is_checked():
    lit = _lit({"weight": 0.5, "hidden": 8, "min_shift": 2, "max_shift": 5})
    bank = WindowBank([toy_sequence(default_mouse(), 200, seed=0)], 4)
    batch = next(iter(RandomWindowBatches(bank, 8, 1, MaskConfig(), seed=0, ahead_shift=(2, 5))))
    total = lit.training_step(batch, 0)
    deform, _ = lit._canonical_loss(batch)
    f, _ = lit.forecast_loss(batch)
    assert total.item() == pytest.approx(deform.item() + 0.5 * f.item(), rel=1e-5)
    del batch["ahead"]
    with pytest.raises(ValueError, match="forecasting targets"):
        lit.training_step(batch, 0)
    off = _lit(None)
    assert off.forecast_head is None
    assert off.training_step(batch, 0).item() == pytest.approx(deform.item(), rel=1e-5)
    with pytest.raises(ValueError, match="unknown keys"):
        _lit({"weight": 1.0, "hiden": 8})
    with pytest.raises(ValueError, match="scale_mm"):
        _lit({"weight": 1.0, "scale_mm": 0.0})
    from deformnet.confutil import compose
    from deformnet.train import build_datamodule, build_model

    for bad in (["forecast.min_shift=0"], ["forecast.min_shift=9", "forecast.max_shift=4"]):
        cfg = compose("train", ["forecast.weight=1.0", *bad])
        with pytest.raises(ValueError, match="forecast.min_shift"):
            build_model(cfg)
    cfg = compose("train", ["forecast.weight=1.0", "forecast.min_shift=3", "data.source=toy"])
    lit2, body, _ = build_model(cfg)
    assert lit2.forecast_head is not None
    assert build_datamodule(cfg, body).ahead_shift == (3, 45)
    assert build_datamodule(compose("train", ["data.source=toy"]), body).ahead_shift is None
