"""DeformationModel: checkpoint round trip, differentiability (float64 vs finite differences),
independence of batched windows, no Lightning import at module import."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from deformnet.body import default_mouse
from deformnet.deformation import DeformationModel, build_net
from deformnet.so3 import transform_points

torch.set_num_threads(1)
N = 2
W = 2 * N + 1

NET_CONFIGS = {
    "lstm": {
        "_target_": "deformnet.nets.LSTMPredictor",
        "num_parts": 8,
        "half_window": N,
        "hidden": 12,
        "layers": 2,
        "embed": 12,
    },
    "transformer": {
        "_target_": "deformnet.nets.TransformerPredictor",
        "num_parts": 8,
        "half_window": N,
        "d_model": 16,
        "heads": 2,
        "layers": 2,
        "ff": 24,
        "d_part": 8,
    },
}


@pytest.fixture(scope="module")
def body():
    return default_mouse()


def _model(body, kind: str) -> DeformationModel:
    torch.manual_seed(0)
    net = build_net(NET_CONFIGS[kind])
    last = net.head.out
    with torch.no_grad():  # not the zero-initialised rigid baseline
        last.weight.normal_(0.0, 0.3)
        last.bias.normal_(0.0, 0.3)
    return DeformationModel(net, body, N, NET_CONFIGS[kind]).eval()


def _poses(B: int, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(W, dtype=dtype)[None, :, None]
    r = torch.randn(B, 1, 3, generator=g, dtype=dtype) + 0.05 * t
    tau = 100 * torch.randn(B, 1, 3, generator=g, dtype=dtype) + 3.0 * t
    return torch.cat((r.expand(B, W, 3), tau), -1)


def _inputs(body, poses, seed=0):
    g = torch.Generator().manual_seed(seed + 1)
    B = poses.shape[0]
    M = torch.tensor(np.array(body.points), dtype=poses.dtype)
    rigid = transform_points(poses, M.expand(B, W, 8, 3))
    deformed = rigid + 3 * torch.randn(rigid.shape, generator=g, dtype=poses.dtype)
    observed = torch.rand(B, W, 8, generator=g) > 0.3
    return rigid, deformed, observed


def test_module_import_does_not_import_lightning():
    code = "import sys, deformnet.deformation; print('lightning' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize("kind", ["lstm", "transformer"])
def test_gradient_matches_finite_differences_float64(body, kind):
    model = _model(body, kind).double()
    poses = _poses(3)
    rigid, deformed, observed = _inputs(body, poses)
    g = torch.Generator().manual_seed(5)
    weights = torch.randn(3, 8, 3, generator=g, dtype=torch.float64)

    def f(r, d):
        return (model(r, d, observed) * weights).sum()

    r = rigid.clone().requires_grad_(True)
    d = deformed.clone().requires_grad_(True)
    f(r, d).backward()
    assert torch.isfinite(r.grad).all() and r.grad.abs().max() > 0
    eps = 1e-6
    for k in range(4):
        v = torch.randn(rigid.shape, generator=g, dtype=torch.float64)
        fd = (f(rigid + eps * v, deformed) - f(rigid - eps * v, deformed)) / (2 * eps)
        an = (r.grad * v).sum()
        assert torch.allclose(an, fd, rtol=1e-5, atol=1e-7), (k, an.item(), fd.item())
        fd = (f(rigid, deformed + eps * v) - f(rigid, deformed - eps * v)) / (2 * eps)
        an = (d.grad * v).sum()
        assert torch.allclose(an, fd, rtol=1e-5, atol=1e-7), (k, an.item(), fd.item())
    # the mid frame's deformed input is ignored: zero gradient
    assert torch.all(d.grad[:, N] == 0)

    # through the poses, as a least-squares solver uses it (rigid = pose applied to the model)
    M = torch.tensor(np.array(body.points))
    p = poses.clone().requires_grad_(True)
    f(transform_points(p, M.expand(3, W, 8, 3)), deformed).backward()
    v = torch.randn(poses.shape, generator=g, dtype=torch.float64)
    v[..., 3:] *= 10.0

    def fp(q):
        return f(transform_points(q, M.expand(3, W, 8, 3)), deformed)

    fd = (fp(poses + eps * v) - fp(poses - eps * v)) / (2 * eps)
    assert torch.allclose((p.grad * v).sum(), fd, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("kind", ["lstm", "transformer"])
def test_batched_windows_are_independent(body, kind):
    model = _model(body, kind).double()
    rigid, deformed, observed = _inputs(body, _poses(4, seed=3))
    r = rigid.clone().requires_grad_(True)
    out = model(r, deformed, observed)
    out[1].sum().backward()
    assert r.grad[1].abs().sum() > 0
    assert torch.all(r.grad[[0, 2, 3]] == 0)
    # leading dims: (2, 2, W, K, 3) gives the same as the flat batch
    out2 = model(
        rigid.reshape(2, 2, W, 8, 3), deformed.reshape(2, 2, W, 8, 3), observed.reshape(2, 2, W, 8)
    )
    assert torch.allclose(out2.reshape(4, 8, 3), out.detach())
    single = model(rigid[1], deformed[1], observed[1])
    assert single.shape == (8, 3) and torch.allclose(single, out[1].detach())


@pytest.mark.parametrize("kind", ["lstm", "transformer"])
def test_save_and_load_round_trip(body, kind, tmp_path):
    model = _model(body, kind)
    path = tmp_path / "m.ckpt"
    model.save(path)
    loaded = DeformationModel.from_checkpoint(path)
    assert loaded.window == W and loaded.half_window == N and loaded.body.parts == body.parts
    rigid, deformed, observed = (
        x.float() if x.is_floating_point() else x for x in _inputs(body, _poses(2))
    )
    assert torch.equal(loaded(rigid, deformed, observed), model(rigid, deformed, observed))


def test_lightning_checkpoint_round_trip(body, tmp_path):
    from helpers import quiet_trainer

    from deformnet.data import DeformDataModule
    from deformnet.lit import DeformLit

    torch.manual_seed(0)
    cfg = NET_CONFIGS["transformer"]
    lit = DeformLit(DeformationModel(build_net(cfg), body, N, cfg), lr=1e-2, warmup_steps=1)
    dm = DeformDataModule(
        body,
        N,
        source="toy",
        num_frames=80,
        train_sequences=1,
        val_sequences=1,
        batch_size=16,
        steps_per_epoch=2,
        val_windows=16,
    )
    trainer = quiet_trainer(2, num_sanity_val_steps=0)
    trainer.fit(lit, datamodule=dm)
    path = tmp_path / "lit.ckpt"
    trainer.save_checkpoint(path)
    loaded = DeformationModel.from_checkpoint(path)
    assert isinstance(loaded.body, type(body)) and loaded.window == W
    rigid, deformed, observed = (
        x.float() if x.is_floating_point() else x for x in _inputs(body, _poses(3))
    )
    lit.eval()
    expected = lit.model(rigid, deformed, observed)
    assert not torch.allclose(expected, rigid[:, N], atol=1e-4)  # trained away from zero-init
    assert torch.allclose(loaded(rigid, deformed, observed), expected, atol=1e-6)


def test_not_a_deformnet_checkpoint(tmp_path):
    path = tmp_path / "x.ckpt"
    torch.save({"state_dict": {}}, path)
    with pytest.raises(ValueError, match="not a deformnet checkpoint"):
        DeformationModel.from_checkpoint(path)


def test_checkpoint_that_does_not_fit_the_net_gives_a_clear_error(tmp_path):
    """A checkpoint whose weights do not fit the current net (an architecture change) is a
    ValueError naming the file, not a state-dict traceback."""
    from helpers import tiny_deformation_model

    from deformnet.deformation import CHECKPOINT_KEY

    path = tmp_path / "old.ckpt"
    tiny_deformation_model().save(path)
    blob = torch.load(path, weights_only=False)
    blob[CHECKPOINT_KEY]["net_config"]["hidden"] = 16  # the net changed since
    torch.save(blob, path)
    with pytest.raises(ValueError, match="old.ckpt.*does not fit"):
        DeformationModel.from_checkpoint(path)
