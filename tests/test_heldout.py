"""The held-out check of a net against interpolation on a recording's own windows
(`deformnet.heldout`, `deformnet.tokens.offset_baseline`) and adjust-track's
``deform.require_better``: a net no better than interpolation on a recording does not predict
its parts (per part, or at all)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from deformnet.body import default_mouse
from deformnet.confutil import compose
from deformnet.deformation import DeformationModel
from deformnet.heldout import (
    MIN_TARGETS,
    evaluating,
    heldout_errors,
    rmse_by_part,
    summed_over,
    window_sums,
)
from deformnet.sessions import SessionTokens
from deformnet.tokens import linear_baseline, offset_baseline

torch.set_num_threads(1)


def test_offset_baseline_interpolates_the_offsets_and_follows_the_rigid_model():
    """Rigid points on a curved path, offsets linear in time: the offset interpolation is
    exact where linear interpolation of the positions is not; no observation on one side:
    the rigid mid point; the mid frame's own value is never used."""
    W, K, mid = 7, 2, 3
    t = torch.arange(W, dtype=torch.float64)
    rigid = torch.stack((t**2, torch.sin(t), 0 * t), -1)[:, None, :].expand(W, K, 3).clone()
    offset = torch.stack((t, -2 * t, 0.5 * t), -1)[:, None, :].expand(W, K, 3)
    deformed = rigid + offset
    observed = torch.ones(W, K, dtype=torch.bool)
    observed[2:5, 0] = False  # part 0: nearest observed frames 1 and 5
    observed[mid + 1 :, 1] = False  # part 1: nothing after mid -> rigid mid point
    out = offset_baseline(rigid, deformed, observed, mid)
    assert torch.allclose(out[0], deformed[mid, 0])
    assert torch.allclose(out[1], rigid[mid, 1])
    # linear interpolation of the positions misses the curved path (t^2: 13 at 1..5, not 9)
    lin = linear_baseline(rigid, deformed, observed, mid)
    assert abs(float(lin[0, 0] - deformed[mid, 0, 0]) - 4.0) < 1e-9
    deformed[mid] = 1e6
    assert torch.allclose(offset_baseline(rigid, deformed, observed, mid)[0], out[0])


def test_offset_baseline_batched_shape_and_gradcheck():
    g = torch.Generator().manual_seed(0)
    rigid = torch.randn(2, 3, 9, 4, 3, generator=g, dtype=torch.float64, requires_grad=True)
    deformed = torch.randn(2, 3, 9, 4, 3, generator=g, dtype=torch.float64, requires_grad=True)
    observed = torch.rand(2, 3, 9, 4, generator=g) > 0.3
    assert offset_baseline(rigid, deformed, observed, 4).shape == (2, 3, 4, 3)
    assert torch.autograd.gradcheck(
        lambda r, d: offset_baseline(r, d, observed, 4), (rigid, deformed)
    )


class _OffsetNet(nn.Module):
    """A net that deforms: the offset interpolation, in the canonical frame (equivariant, so
    its global prediction is `offset_baseline`'s); `scale` != 1 makes it over-shoot."""

    def __init__(self, half_window: int, scale: float = 1.0) -> None:
        super().__init__()
        self.mid, self.scale = half_window, scale

    def forward(self, rigid_c, deformed_c, observed):
        pred = offset_baseline(rigid_c, deformed_c, observed, self.mid)
        return rigid_c[:, self.mid] + self.scale * (pred - rigid_c[:, self.mid])


class _RigidNet(nn.Module):
    """The rigid mid point moved by `shift_mm` along the body's x axis (0: no deformation at
    all; 10: a net far worse than interpolation on every part)."""

    def __init__(self, half_window: int, shift_mm: float = 0.0) -> None:
        super().__init__()
        self.mid, self.shift = half_window, shift_mm

    def forward(self, rigid_c, deformed_c, observed):
        out = rigid_c[:, self.mid].clone()
        out[..., 0] += self.shift
        return out


def _model(net, body, n=4) -> DeformationModel:
    return DeformationModel(net, body, n).eval()


def _tokens(body, T=400, seed=0) -> SessionTokens:
    """Tokens of a mouse walking a curve whose parts deform smoothly (sine offsets)."""
    from deformnet.windows import toy_sequence

    s = toy_sequence(body, T, seed)
    return SessionTokens(
        s.rigid, s.deformed, s.observed, tuple(body.parts), np.array(body.points), body.name,
        30.0, "toy",
    )  # fmt: skip


def test_heldout_errors_measure_the_net_and_the_baselines():
    body = default_mouse()
    tok = _tokens(body)
    h = heldout_errors(_model(_OffsetNet(4), body), tok, windows=300, batch_size=64)
    assert h["parts"] == list(body.parts) and h["windows"] == 300
    assert min(h["targets"]) > 50
    # the equivariant net is the offset interpolation, to float32 rounding
    np.testing.assert_allclose(h["net_mm"], h["interp_mm"], rtol=1e-3)
    # on a smooth deformation the interpolation beats the rigid model (measured: 0.67-0.82x
    # per part; the toy's 0.5-2.5 Hz offsets change across the longer masked gaps)
    assert all(i < 0.9 * r for i, r in zip(h["interp_mm"], h["rigid_mm"]))
    rig = heldout_errors(_model(_RigidNet(4), body), tok, windows=300, batch_size=64)
    np.testing.assert_allclose(rig["net_mm"], rig["rigid_mm"], rtol=1e-3)
    with pytest.raises(ValueError, match="parts"):
        heldout_errors(_model(_OffsetNet(4), body), tok.__class__(
            tok.rigid[:, :3], tok.deformed[:, :3], tok.observed[:, :3], tok.parts[:3],
            tok.body_points[:3], "x", 30.0, "toy",
        ))  # fmt: skip


def test_window_sums_are_the_per_part_squared_errors():
    body = default_mouse()
    from deformnet.windows import FixedWindowBatches, MaskConfig, WindowBank

    bank = WindowBank([_tokens(body, 200).to_sequence()], 4)
    batch = FixedWindowBatches.build(bank, 32, 32, 0, MaskConfig()).batches[0]
    model = _model(_OffsetNet(4, scale=1.5), body)
    s = window_sums(model, batch, 4)
    m = batch["target_mask"].double()
    with torch.no_grad():
        pred = model(batch["rigid"], batch["deformed"], batch["observed"]).double()
    expect = (((pred - batch["target"].double()) ** 2).sum(-1) * m).sum(0)
    torch.testing.assert_close(s["net"], expect, rtol=1e-4, atol=1e-3)
    torch.testing.assert_close(s["count"], m.sum(0))
    assert set(s) == {"net", "rigid", "linear", "offset", "count"}
    with pytest.raises(ValueError, match="rigid"):
        window_sums(model, {**batch, "target": batch["target"][:, :3]}, 4)


def test_rmse_by_part_per_part_nan_without_targets_and_over_all():
    """Per part sqrt(sum / count), NaN where a part has no target; over all parts
    sqrt(total sum / total count) (not the mean of the parts' RMSEs); no target at all: NaN."""
    sums = {"a": torch.tensor([8.0, 0.0, 27.0], dtype=torch.float64)}
    count = torch.tensor([2.0, 0.0, 3.0], dtype=torch.float64)
    part, overall = rmse_by_part(sums, count)["a"]
    assert part[0] == 2.0 and part[2] == 3.0 and np.isnan(part[1])
    assert overall == pytest.approx(np.sqrt(35.0 / 5.0), rel=1e-15)
    part, overall = rmse_by_part(sums, torch.zeros(3, dtype=torch.float64))["a"]
    assert np.isnan(overall) and all(np.isnan(part))


def test_summed_over_adds_each_key_in_eval_mode_and_restores_training():
    """The batches' sums added key by key, each batch summed with the model in eval mode and
    no gradients; the model's training flag restored after, also when a batch raises."""
    net = nn.Linear(1, 1).train()
    seen = []

    def sums(batch):
        seen.append((net.training, torch.is_grad_enabled()))
        if batch.get("bad"):
            raise RuntimeError("bad batch")
        return {"x": batch["x"], "count": torch.ones(2, dtype=torch.float64)}

    batches = [{"x": torch.tensor([1.0, 2.0])}, {"x": torch.tensor([3.0, 5.0])}]
    total = summed_over(net, batches, sums)
    torch.testing.assert_close(total["x"], torch.tensor([4.0, 7.0]))
    torch.testing.assert_close(total["count"], torch.full((2,), 2.0, dtype=torch.float64))
    assert seen == [(False, False)] * 2 and net.training
    with pytest.raises(RuntimeError, match="bad batch"):
        summed_over(net, [{"bad": True}], sums)
    assert net.training
    with evaluating(net.eval()):
        assert not net.training
    assert not net.training


def test_net_parts_keep_the_other_parts_on_interp():
    """NetObservation(net_parts=...): the excluded parts take interp's model points."""
    from adjust.lsq.net_observation import NetObservation

    body = default_mouse()
    s = _tokens(body, 120, seed=3)
    B = torch.tensor(np.array(body.points), dtype=torch.float64)
    model = _model(_OffsetNet(4, scale=1.5), body).float()
    K = body.num_parts
    keep = torch.zeros(K, dtype=torch.bool)
    keep[:3] = True
    T = s.rigid.shape[0]
    obs = torch.as_tensor(s.observed)
    data = torch.as_tensor(s.deformed, dtype=torch.float64)
    poses = torch.zeros(T, 6, dtype=torch.float64)  # any poses: both read the same data
    full = NetObservation(model, B, 9, data, obs, 0.0, 256, "frozen")
    part = NetObservation(model, B, 9, data, obs, 0.0, 256, "frozen", net_parts=keep)
    Xf, _ = full.points(poses, False)
    Xp, _ = part.points(poses, False)
    Xi, _ = part.interp.points(poses, False)
    assert part.use_net[:, 3:].sum() == 0 and full.use_net[:, 3:].any()
    torch.testing.assert_close(Xp[:, 3:], Xi[:, 3:])
    torch.testing.assert_close(Xp[:, :3], Xf[:, :3])
    assert not torch.allclose(Xf[:, 3:], Xi[:, 3:])  # the net there would have deformed them
    with pytest.raises(ValueError, match="net_parts"):
        NetObservation(model, B, 9, data, obs, 0.0, 256, "frozen", net_parts=keep[:3])


#: a simulator seed the shipped net never saw: deformnet.pretrained.build trains on seeds 0-15
#: (data.train_sequences=16) and validates on 10000 (conf/data/sim.yaml)
HELDOUT_SEED = 100


def _scene(tmp_path_factory, frames: int) -> Path:
    """A default-mouse scene (the shipped net's own kind of mouse) of the held-out seed."""
    from adjust.apps.simulate import run

    out = tmp_path_factory.mktemp("heldout") / "scene"
    run(compose("scene", [f"output.dir={out}", f"num_frames={frames}", f"seed={HELDOUT_SEED}"]))
    return out


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """300 frames (the tests whose net is a stand-in)."""
    return _scene(tmp_path_factory, 300)


@pytest.fixture(scope="module")
def long_scene(tmp_path_factory) -> Path:
    """1800 frames: on 600-frame held-out scenes the net's margin over interpolation varies
    from scene to scene (measured over seeds 100-107 and 200-202: net/interp 0.88-1.04, median
    0.93, 3 of 11 above 0.95); on 1800 frames 0.87-0.93 (seeds 100, 101, 103, 200)."""
    return _scene(tmp_path_factory, 1800)


def _track(scene: Path, out: Path, overrides: list[str]) -> dict:
    from helpers import track_session

    return track_session(scene, out, overrides)


def test_the_shipped_net_is_checked_part_by_part_against_anchored_kriging(long_scene, tmp_path):
    """The check compares the net with what the tracks would otherwise get: interp's kriging
    from the 3D observations and the single-view anchors. Measured (stop 48) with the shipped
    net of issue 48 (trained on filmed real motion; the simulator's mouse is a body it never
    trained on): 4.42 vs 3.39 mm over all parts (against offset interpolation without the
    anchors, the earlier check, 4.42 vs 4.40); the check keeps right_ear only."""
    s = _track(long_scene, tmp_path / "d", ["deformation=default"])
    h = s["deformation"]["heldout"]
    assert h["checked"] and h["require_better"] == "parts"
    assert h["baseline"] == "interp's kriging with single-view anchors"
    net, interp = h["net_mm"], h["interp_mm"]
    targets = dict(zip(net, h["targets"]))
    kept = set(h["net_parts"])
    assert all(net[p] < interp[p] for p in kept)  # the parts kept are the better ones
    judged = [p for p in net if targets[p] >= MIN_TARGETS]
    assert all(net[p] >= interp[p] for p in judged if p not in kept)
    assert "nose_tip" not in kept and len(kept) < len(net)
    assert s["deformation"]["mode"] == "default" and s["completeness"] == 1.0
    assert s["deformation"]["net_passes"] >= 1


def test_a_net_worse_than_interpolation_is_not_used(scene, tmp_path, monkeypatch, caplog):
    """A net 10 mm off on a deforming mouse: no part passes, the tracks are
    interpolated (deformation=interp's model) and the log says so; require_better=false uses
    it."""
    import deformnet.pretrained as pretrained

    def bad():
        return _model(_RigidNet(4, shift_mm=10.0), default_mouse())

    monkeypatch.setattr(pretrained, "load_default", bad)
    with caplog.at_level(logging.WARNING, logger="adjust.track"):
        s = _track(scene, tmp_path / "bad", ["deformation=default"])
    assert "the net is not used, the tracks are interpolated" in caplog.text
    h = s["deformation"]["heldout"]
    assert h["net_parts"] == [] and h["net_all_mm"] > h["interp_all_mm"]
    assert "net_passes" not in s["deformation"]
    # deformation=interp's own tracks (the net modes' interp stage is interp's adjustment)
    i = _track(scene, tmp_path / "interp", ["deformation=interp"])
    from adjust.io import read_points3d

    a = read_points3d(tmp_path / "bad" / "points3d.csv")["points"]
    b = read_points3d(tmp_path / "interp" / "points3d.csv")["points"]
    np.testing.assert_allclose(a, b, atol=1e-9)
    assert i["deformation"]["mode"] == "interp"
    u = _track(scene, tmp_path / "forced", ["deformation=default", "deform.require_better=false"])
    assert u["deformation"]["heldout"] == {"require_better": "false", "checked": False}
    assert u["deformation"]["net_used_fraction"] > 0
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="adjust.track"):
        r = _track(
            scene, tmp_path / "report", ["deformation=default", "deform.require_better=report"]
        )
    assert "it is used for every part as given" in caplog.text
    h = r["deformation"]["heldout"]
    assert h["checked"] and h["net_all_mm"] > h["interp_all_mm"] and len(h["net_parts"]) == 8
    np.testing.assert_allclose(
        read_points3d(tmp_path / "report" / "points3d.csv")["points"],
        read_points3d(tmp_path / "forced" / "points3d.csv")["points"],
        atol=1e-9,
    )


def test_require_better_is_checked(scene, tmp_path):
    from adjust.io import InputError

    with pytest.raises(InputError, match="deform.require_better must be one of auto, parts, all"):
        _track(scene, tmp_path / "x", ["deformation=default", "deform.require_better=some"])


def test_batch_summary_says_how_many_parts_the_net_predicted():
    from adjust.apps.batch import _row_from_summary

    row = {}
    held = {"checked": True, "net_parts": ["nose_tip"], "net_mm": dict.fromkeys("abcdefgh", 1.0)}
    _row_from_summary(row, {"num_frames": 9, "deformation": {"heldout": held}})
    assert row["net_parts"] == "1/8" and row["frames"] == 9
    row = {}
    _row_from_summary(row, {"deformation": {"mode": "interp"}})
    assert "net_parts" not in row
