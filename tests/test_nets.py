"""Nets: shapes, residual zero-init, no mid-frame leak, invariance, positional encoding."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deformnet.body import default_mouse
from deformnet.deformation import DeformationModel
from deformnet.nets import LSTMPredictor, TransformerPredictor
from deformnet.so3 import rodrigues_to_matrix, transform_points
from deformnet.tokens import canonicalize

torch.set_num_threads(1)
N = 3  # half window in these tests
W = 2 * N + 1


@pytest.fixture(scope="module")
def body():
    return default_mouse()


def _randomise_head(net: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Give the zero-initialised output layer weights, so the net is not the rigid baseline."""
    g = torch.Generator().manual_seed(seed)
    last = net.head.out
    with torch.no_grad():
        last.weight.copy_(0.3 * torch.randn(last.weight.shape, generator=g))
        last.bias.copy_(0.3 * torch.randn(last.bias.shape, generator=g))
    return net.eval()


def _make(kind: str, K: int, **kw) -> torch.nn.Module:
    torch.manual_seed(0)
    if kind == "lstm":
        return LSTMPredictor(K, N, hidden=16, layers=2, embed=16, **kw)
    return TransformerPredictor(K, N, d_model=16, heads=2, layers=2, ff=32, d_part=8, **kw)


def _window(body, B=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    K = body.num_parts
    M = torch.tensor(np.array(body.points), dtype=torch.float32)
    t = torch.arange(W, dtype=torch.float32)[None, :, None]
    poses = torch.cat(
        (
            torch.randn(B, 1, 3, generator=g) + 0.05 * t * torch.randn(B, 1, 3, generator=g),
            50 * torch.randn(B, 1, 3, generator=g) + 2 * t,
        ),
        -1,
    )
    rigid = transform_points(poses, M.expand(B, W, K, 3))
    deformed = rigid + 2 * torch.randn(B, W, K, 3, generator=g)
    observed = torch.rand(B, W, K, generator=g) > 0.3
    return rigid, deformed, observed


@pytest.mark.parametrize("kind", ["lstm", "transformer"])
def test_untrained_net_is_the_rigid_baseline(body, kind):
    net = _make(kind, body.num_parts)
    rigid, deformed, observed = _window(body)
    out = net(rigid, deformed, observed)
    assert out.shape == (4, body.num_parts, 3)
    assert torch.allclose(out, rigid[:, N])


@pytest.mark.parametrize("kind", ["lstm", "transformer"])
def test_masked_mid_frame_does_not_leak(body, kind):
    model = DeformationModel(_randomise_head(_make(kind, body.num_parts)), body, N).eval()
    rigid, deformed, observed = _window(body)
    observed[:, N] = True  # even if the caller claims the mid frame is observed
    out = model(rigid, deformed, observed)
    d2 = deformed.clone()
    d2[:, N] += torch.randn_like(d2[:, N]) * 10.0
    o2 = observed.clone()
    o2[:, N] = False
    assert torch.equal(model(rigid, d2, observed), out)
    assert torch.equal(model(rigid, d2, o2), out)
    # ... whereas the neighbours' deformed values do matter
    d3 = deformed.clone()
    d3[:, N - 1] += 5.0
    o3 = observed.clone()
    o3[:, N - 1] = True
    assert not torch.allclose(model(rigid, d3, o3), model(rigid, deformed, o3))


@pytest.mark.parametrize("kind", ["lstm", "transformer"])
def test_rigid_motion_of_window_is_equivariant(body, kind):
    model = DeformationModel(_randomise_head(_make(kind, body.num_parts)), body, N).eval()
    model = model.double()
    rigid, deformed, observed = (x.double() if x.is_floating_point() else x for x in _window(body))
    Q = rodrigues_to_matrix(torch.tensor([0.7, -2.1, 1.3], dtype=torch.float64))
    shift = torch.tensor([300.0, -150.0, 40.0], dtype=torch.float64)
    out = model(rigid, deformed, observed)
    out2 = model(rigid @ Q.T + shift, deformed @ Q.T + shift, observed)
    assert torch.allclose(out2, out @ Q.T + shift, atol=1e-8)
    # canonical predictions agree
    M = model.body_points
    _, _, R, t = canonicalize(rigid, deformed, M, N)
    _, _, R2, t2 = canonicalize(rigid @ Q.T + shift, deformed @ Q.T + shift, M, N)
    c1 = (out - t[:, None]) @ R
    c2 = (out2 - t2[:, None]) @ R2
    assert torch.allclose(c1, c2, atol=1e-8)
    assert not torch.allclose(out, rigid[:, N], atol=1e-3)  # the test has teeth


@pytest.mark.parametrize("kind", ["lstm", "transformer"])
def test_heading_frame_model_is_equivariant_to_yaw_not_to_tilt_and_round_trips(
    body, kind, tmp_path
):
    """up = world z: turning the window about z (and shifting it) turns the prediction with it;
    tilting it does not (the net sees pitch and roll); the checkpoint keeps up."""
    net = _randomise_head(_make(kind, body.num_parts))
    cfg = {"_target_": f"deformnet.nets.{type(net).__name__}", "num_parts": body.num_parts,
           "half_window": N, **({"hidden": 16, "layers": 2, "embed": 16} if kind == "lstm" else
           {"d_model": 16, "heads": 2, "layers": 2, "ff": 32, "d_part": 8})}  # fmt: skip
    model = DeformationModel(net, body, N, cfg, up=(0.0, 0.0, 2.0)).eval()
    model.save(tmp_path / "m.ckpt")
    back = DeformationModel.from_checkpoint(tmp_path / "m.ckpt")
    assert back.up == (0.0, 0.0, 1.0)
    model, back = model.double(), back.double()
    assert model.up == (0.0, 0.0, 1.0)
    rigid, deformed, observed = (x.double() if x.is_floating_point() else x for x in _window(body))
    shift = torch.tensor([300.0, -150.0, 40.0], dtype=torch.float64)
    out = model(rigid, deformed, observed)
    assert torch.allclose(back(rigid, deformed, observed), out, atol=1e-10)
    Q = rodrigues_to_matrix(torch.tensor([0.0, 0.0, 2.3], dtype=torch.float64))
    out2 = model(rigid @ Q.T + shift, deformed @ Q.T + shift, observed)
    assert torch.allclose(out2, out @ Q.T + shift, atol=1e-8)
    P = rodrigues_to_matrix(torch.tensor([0.6, 0.0, 0.0], dtype=torch.float64))
    out3 = model(rigid @ P.T, deformed @ P.T, observed)
    assert (out3 - out @ P.T).abs().max() > 1e-3
    body_frame = DeformationModel(net, body, N, cfg).eval().double()  # same weights, body frame
    b1 = body_frame(rigid, deformed, observed)
    assert torch.allclose(body_frame(rigid @ P.T, deformed @ P.T, observed), b1 @ P.T, atol=1e-8)
    assert "up" not in body_frame.export() and model.export()["up"] == [0.0, 0.0, 1.0]


def test_check_up_errors():
    from deformnet.deformation import check_up

    assert check_up(None) is None and check_up([0, 0, 3]) == (0.0, 0.0, 1.0)
    for bad in ([0, 0, 0], [0, 1], [0, "a", 1], [float("nan"), 0, 1], 5):
        with pytest.raises(ValueError, match="up must be"):
            check_up(bad)


def test_positional_encoding_changes_transformer_output(body):
    K = body.num_parts
    net = _randomise_head(_make("transformer", K))
    rigid, deformed, observed = _window(body)
    out = net(rigid, deformed, observed)
    # same weights without the encoding: a different function
    net.use_pos_enc = False
    out_nope = net(rigid, deformed, observed)
    assert not torch.allclose(out, out_nope, atol=1e-4)
    # without the encoding, the encoder cannot tell the order of the other frames ... (nothing
    # observed, so the order-dependent interpolation prior is constant; rigid tokens still differ)
    none = torch.zeros_like(observed)
    perm = torch.tensor([2, 0, 1, N, 6, 4, 5])
    base = net(rigid, deformed, none)
    shuffled = net(rigid[:, perm], deformed[:, perm], none)
    assert torch.allclose(shuffled, base, atol=1e-5)
    # ... with it, it can
    net.use_pos_enc = True
    base = net(rigid, deformed, none)
    shuffled = net(rigid[:, perm], deformed[:, perm], none)
    assert not torch.allclose(shuffled, base, atol=1e-4)


def test_bad_shapes_raise(body):
    net = _make("lstm", body.num_parts)
    rigid, deformed, observed = _window(body)
    with pytest.raises(ValueError, match="rigid must have shape"):
        net(rigid[:, :-1], deformed[:, :-1], observed[:, :-1])
    model = DeformationModel(net, body, N)
    with pytest.raises(ValueError, match="observed must have shape"):
        model(rigid, deformed, observed[..., :-1])
