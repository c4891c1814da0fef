"""``deformation=self``'s fine-tuning (`adjust.adapt`): the device it picks, its step budget and
early stopping, and that it adapts the shipped net (a net that differs from it, better on the
recording's held-out tokens than where it started)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

import adjust.adapt as adapt
from adjust.adapt import AdaptConfig, adapt_net, fine_tune, select_device, starting_model
from deformnet.body import BodyModel, default_mouse
from deformnet.deformation import DeformationModel
from deformnet.pretrained import SIM_CHECKPOINT, load_default
from deformnet.sessions import SessionTokens
from deformnet.windows import Augment, toy_sequence

torch.set_num_threads(1)


def _tokens(body: BodyModel, frames: int = 400, seed: int = 3) -> SessionTokens:
    """A recording's tokens: the toy generator's smoothly deforming body, 2% unmeasured."""
    s = toy_sequence(body, frames, seed)
    deformed = np.where(s.observed[..., None], s.deformed, np.nan).astype(np.float32)
    pts = np.array(body.points, dtype=np.float64)
    return SessionTokens(s.rigid, deformed, s.observed, tuple(body.parts), pts, body.name)


# --- the device ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("accelerator", "cuda", "expected"),
    [("auto", True, "cuda"), ("auto", False, "cpu"), ("cpu", True, "cpu"), ("cuda", True, "cuda"),
     ("gpu", True, "cuda")],
)  # fmt: skip
def test_select_device(monkeypatch, accelerator, cuda, expected):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda)
    assert select_device(accelerator).type == expected


def test_select_device_refuses_cuda_without_one_and_unknown_names(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="no CUDA device"):
        select_device("cuda")
    with pytest.raises(ValueError, match="adapt.accelerator must be one of"):
        select_device("tpu")
    with pytest.raises(ValueError, match="adapt.accelerator must be one of"):
        AdaptConfig.from_any({"accelerator": "tpu"})


def test_adapt_net_trains_on_the_device_auto_selects(monkeypatch, tmp_path):
    """adapt.accelerator=auto: adapt_net hands fine_tune CUDA when torch sees it."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    seen = {}

    def fake(model, train, val, cfg, device, *args, **kwargs):
        seen["device"] = device
        raise RuntimeError("stop here")

    monkeypatch.setattr(adapt, "fine_tune", fake)
    with pytest.raises(RuntimeError, match="stop here"):
        adapt_net(_tokens(default_mouse()), tmp_path, {"accelerator": "auto"}, False)
    assert seen["device"] == torch.device("cuda")


# --- the config ------------------------------------------------------------------------------


def test_config_reads_the_track_yaml_block():
    from deformnet.confutil import compose, to_plain

    cfg = AdaptConfig.from_any(to_plain(compose("track", []).adapt))
    assert cfg.max_time == 180.0 and cfg.max_steps >= 1 and cfg.pretrained == "default"
    assert cfg.augment.steps == (1, 1, 2, 3)
    with pytest.raises(ValueError, match=r"unknown adapt options \['steps_per_epochs'\]"):
        AdaptConfig.from_any({"steps_per_epochs": 3})
    with pytest.raises(ValueError, match="DD:HH:MM:SS"):
        AdaptConfig.from_any({"max_time": "3 minutes"})
    with pytest.raises(ValueError, match="adapt.max_steps must be >= 1"):
        AdaptConfig.from_any({"max_steps": 0})


# --- the step budget and early stopping ------------------------------------------------------


def _data(model: DeformationModel, tokens: SessionTokens, every: int):
    cfg = AdaptConfig(eval_every=every, batch_size=16, val_windows=32, block_frames=100)
    train, val, _ = adapt.window_data(tokens, model, cfg)
    return train, val


def test_fine_tune_stops_at_its_step_budget():
    model, _ = starting_model(load_default(), default_mouse())
    train, val = _data(model, _tokens(model.body), every=3)
    cfg = AdaptConfig(max_steps=7, eval_every=3, patience=100, max_time=None, warmup_steps=1)
    facts = fine_tune(model, train, val, cfg, torch.device("cpu"))
    assert facts["steps"] == 7 and facts["stopped"] == "max_steps"
    assert [h["step"] for h in facts["history"]] == [0, 3, 6, 7]


def test_fine_tune_stops_early_without_improvement_and_keeps_the_best_weights():
    """lr 0: no score ever improves, so it stops after `patience` scores and keeps the
    starting weights."""
    model, _ = starting_model(load_default(), default_mouse())
    start = {k: v.clone() for k, v in model.state_dict().items()}
    train, val = _data(model, _tokens(model.body), every=2)
    cfg = AdaptConfig(max_steps=1000, eval_every=2, patience=3, lr=0.0, max_time=None)
    facts = fine_tune(model, train, val, cfg, torch.device("cpu"))
    assert facts["steps"] == 6 and facts["stopped"] == "no improvement"
    assert facts["best_step"] == 0
    for k, v in model.state_dict().items():
        assert torch.equal(v, start[k]), k


# --- what it produces ------------------------------------------------------------------------


def test_self_adapts_the_shipped_net(tmp_path):
    """On a recording the shipped net did not see: a net that differs from the shipped one,
    saved as deformation.ckpt, better on the held-out blocks than the shipped net was."""
    shipped = load_default()
    tokens = _tokens(default_mouse(), frames=600)
    cfg = {"max_steps": 40, "eval_every": 10, "batch_size": 32, "val_windows": 128,
           "block_frames": 100, "tensorboard": False}  # fmt: skip
    model, facts = adapt_net(tokens, tmp_path, cfg, False)
    assert facts["start"] == "fine-tune" and facts["pretrained"] == "default"
    assert facts["device"] == "cpu" and 10 <= facts["steps"] <= 40
    assert facts["data"]["val_blocks"]
    saved = DeformationModel.from_checkpoint(tmp_path / "deformation.ckpt")
    differ = [
        not torch.equal(a, b)
        for a, b in zip(saved.net.state_dict().values(), shipped.net.state_dict().values())
    ]
    assert any(differ)
    history = __import__("json").loads((tmp_path / "adapt" / "metrics.json").read_text())
    first = history["history"][0]["net"]  # the shipped net, before any step
    assert facts["val_rmse_mm"] < 0.9 * first, (facts["val_rmse_mm"], first)
    assert tuple(saved.body.parts) == tuple(tokens.parts)
    np.testing.assert_allclose(np.array(saved.body.points), tokens.body_points, atol=1e-5)


class _AgnosticNet(nn.Module):
    """Stands for a part-agnostic net: runs on any number of parts (predicts the rigid mid
    point plus a learned shift)."""

    part_agnostic = True

    def __init__(self, half_window: int = 2):
        super().__init__()
        self.half_window = half_window
        self.shift = nn.Parameter(torch.zeros(3))

    def forward(self, rigid, deformed, observed):
        return rigid[:, self.half_window] + self.shift


def test_starting_model_for_another_skeleton():
    """A skeleton the net does not know: a part-agnostic net is fine-tuned as it is (its
    weights copied, not shared), a net that knows parts by index gets its architecture built
    for the new parts."""
    body = BodyModel.from_mapping(
        {"a": [0.0, 0.0, 0.0], "b": [0.0, 30.0, 0.0], "c": [10.0, 10.0, 5.0]}, name="three"
    )
    agnostic = DeformationModel(_AgnosticNet(), default_mouse(), 2, {"_target_": "x"})
    model, how = starting_model(agnostic, body)
    assert how == "fine-tune" and model.body.parts == body.parts
    assert model.net is not agnostic.net and torch.equal(model.net.shift, agnostic.net.shift)
    by_index = DeformationModel.from_checkpoint(SIM_CHECKPOINT)  # an LSTM: parts by index
    model, how = starting_model(by_index, body)
    assert how == "scratch" and model.num_parts == 3
    assert model.net_config["prior_residual"] is True
    out = model(*(torch.zeros(2, model.window, 3, 3), torch.zeros(2, model.window, 3, 3),
                  torch.ones(2, model.window, 3, dtype=torch.bool)))  # fmt: skip
    assert out.shape == (2, 3, 3)


def test_mirror_rule_is_deformnet_trains():
    """adapt mirrors windows exactly where deformnet-train data=sessions would: a symmetric
    body (the default mouse), not a lopsided one, not without left/right pairs."""
    from deformnet.data import DeformDataModule

    aug = Augment(mirror=0.5)
    mouse = default_mouse()
    pts = np.array(mouse.points, dtype=np.float64)
    i = mouse.parts.index("left_ear")
    lop = pts.copy()
    lop[i] += [40.0, 30.0, 0.0]
    lopsided = BodyModel.from_mapping(dict(zip(mouse.parts, lop.tolist())), name="lopsided")
    plain = BodyModel.from_mapping({"a": [0.0, 0, 0], "b": [0.0, 20, 0], "c": [0.0, 40, 5]})
    for body in (mouse, lopsided, plain):
        dm = DeformDataModule(body=body, source="toy", augment=aug)
        assert adapt.mirror_perm(body, aug) == dm.mirror_perm, body.name
    assert adapt.mirror_perm(mouse, aug) is not None
    assert adapt.mirror_perm(mouse, Augment(mirror=0.0)) is None


def test_adamw_is_torchs():
    """adapt's AdamW (no torch.optim import) takes torch.optim.AdamW's steps, learning rate
    changing from step to step, one group with weight decay and one without."""
    torch.manual_seed(0)
    a = [torch.randn(4, 3, requires_grad=True), torch.randn(3, requires_grad=True)]
    b = [x.detach().clone().requires_grad_(True) for x in a]
    start = [x.detach().clone() for x in a]
    ours = adapt.AdamW([(a[:1], 0.1), (a[1:], 0.0)])
    ref = torch.optim.AdamW(
        [{"params": b[:1], "weight_decay": 0.1}, {"params": b[1:], "weight_decay": 0.0}], lr=1.0
    )
    target = torch.randn(4, 3)
    for i in range(20):
        lr = 0.01 * (1 + i % 3)
        for params, opt in ((a, ours), (b, ref)):
            loss = ((params[0] + params[1] - target) ** 2).sum()
            opt.zero_grad()
            loss.backward()
            if opt is ref:
                for g in ref.param_groups:
                    g["lr"] = lr
                ref.step()
            else:
                ours.step(lr)
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6)
    assert all((x - s).abs().max() > 0.05 for x, s in zip(a, start))  # they moved
