"""The animal's size against the body model (`body_scale`) and the classifier dividing it out
(`normalize_size`, `WindowEncoder(..., scale)`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deformnet.behavior.encoder import (
    MechanismFeatures,
    WindowEncoder,
    normalize_size,
    pose_measurements,
)
from deformnet.behavior.heads import BehaviorClassifier, LinearHead
from deformnet.behavior.tracks import body_scale
from deformnet.body import default_mouse
from deformnet.deformation import build_net
from deformnet.so3 import transform_points

LSTM = {"_target_": "deformnet.nets.LSTMPredictor", "hidden": 8, "layers": 1, "embed": 8}


def _posed(T: int, seed: int = 0) -> np.ndarray:
    """The default mouse (T, K, 3) under random poses (mm)."""
    g = np.random.default_rng(seed)
    poses = np.concatenate([g.normal(0, 0.5, (T, 3)), g.uniform(0, 300, (T, 3))], 1)
    body = torch.tensor(np.asarray(default_mouse().points))
    return transform_points(torch.tensor(poses), body.expand(T, -1, -1)).numpy()


def _grown(rigid: np.ndarray, s: float) -> np.ndarray:
    c = rigid.mean(1, keepdims=True)
    return c + (rigid - c) * s


def test_body_scale_measures_the_animal_size():
    """A mouse 1.2x the model's size with 1 mm noise: 1.2 (per frame least squares about the
    centroid, the median over the frames: the noise moves it by about 1 mm / 100 mm); offsets
    that average out: 1, where the pose-free rms-radius estimate (the tracker's) is inflated
    by them; unobserved parts do not count."""
    body = default_mouse()
    rigid = _posed(60)
    g = np.random.default_rng(1)
    T, K = rigid.shape[:2]
    obs = np.ones((T, K), bool)
    big = _grown(rigid, 1.2) + g.normal(0, 1.0, rigid.shape)
    assert body_scale(body, rigid, big, obs) == pytest.approx(1.2, abs=0.005)
    wobble = rigid + g.normal(0, 5.0, rigid.shape)  # 5 mm deformations, no size change
    assert body_scale(body, rigid, wobble, obs) == pytest.approx(1.0, abs=0.01)
    assert body.estimate_scale(wobble)[0] > 1.01  # rms radius: sqrt(1 + 3 * 25 / |r - c|^2)
    hidden = obs.copy()
    hidden[:, :3] = False  # three parts unseen, their values far off: not counted
    far = big.copy()
    far[:, :3] += 1000.0
    assert body_scale(body, rigid, far, hidden) == pytest.approx(1.2, abs=0.01)
    far[:, :3] = np.nan
    assert body_scale(body, rigid, far, hidden) == pytest.approx(1.2, abs=0.01)
    s, n = body.estimate_scale(np.where(hidden[..., None], big, np.nan), 3, rigid)
    assert n == T and s == body_scale(body, rigid, big, hidden)
    with pytest.raises(ValueError, match="rigid must be"):
        body.estimate_scale(big, rigid=rigid[:, :3])


def test_body_scale_errors_name_the_track():
    body = default_mouse()
    rigid = _posed(10)
    T, K = rigid.shape[:2]
    obs = np.ones((T, K), bool)
    few = np.zeros((T, K), bool)
    few[:, :2] = True
    with pytest.raises(ValueError, match="a.csv: no frame with 3 or more observed parts"):
        body_scale(body, rigid, rigid, few, "a.csv")
    with pytest.raises(ValueError, match=r"m.csv: the tracked parts are 0.001 times .* in mm"):
        body_scale(body, rigid, _grown(rigid, 1e-3), obs, "m.csv")
    with pytest.raises(ValueError, match="3 times"):
        body_scale(body, rigid, _grown(rigid, 3.0), obs)
    with pytest.raises(ValueError, match=r"\(T, K, 3\)"):
        body_scale(body, rigid[0], rigid[0], obs[0])
    with pytest.raises(ValueError, match="observed must be"):
        body_scale(body, rigid, rigid, obs[:, :3])


def test_normalize_size_shape_value_gradient():
    """(..., K, 3) points about the rigid model's centroid divided by (...,) scales: the grown
    model comes back to the model; the centroid stays; float64 gradcheck in points and scale."""
    rigid = torch.tensor(_posed(6)).reshape(2, 3, -1, 3)
    scale = torch.tensor([[1.2, 0.8, 1.0], [1.5, 1.1, 0.9]], dtype=torch.float64)
    c = rigid.mean(-2, keepdim=True)
    big = c + (rigid - c) * scale[..., None, None]
    out = normalize_size(rigid, big, scale)
    assert out.shape == rigid.shape
    torch.testing.assert_close(out, rigid)
    p = big + torch.randn(big.shape, dtype=torch.float64)
    want = c[..., 0, :] + (p.mean(-2) - c[..., 0, :]) / scale[..., None]
    torch.testing.assert_close(normalize_size(rigid, p, scale).mean(-2), want)
    x, s = p.clone().requires_grad_(), scale.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: normalize_size(rigid, a, b), (x, s), eps=1e-6)
    with pytest.raises(ValueError, match="scale must be"):
        normalize_size(rigid, p, scale[0])
    with pytest.raises(ValueError, match="alike"):
        normalize_size(rigid, p[..., :2], scale)


def test_encoder_divides_the_body_scale_out_but_not_the_mechanism_distances():
    """A window of a mouse 1.3x the size, given scale 1.3, gives the encoder outputs, frame
    features and measurements of the model-size mouse; its mechanism distances stay its real
    points'. Without the scale its offsets and measurements differ. The classifier's temporal
    context passes the scale to every sub-window."""
    body = default_mouse()
    K = body.num_parts
    cfg = {**LSTM, "num_parts": K, "half_window": 2}
    mech = MechanismFeatures([[150.0, 250.0, 10.0], [200.0, 250.0, 10.0]], [0, 1])
    torch.manual_seed(0)
    enc = WindowEncoder(build_net(cfg), np.asarray(body.points), 2, True, None, mech, True,
                        heights_up=[0, 0, 1]).eval()  # fmt: skip
    B, W = 4, enc.window + 4
    rigid = torch.tensor(_posed(B * W, 3), dtype=torch.float32).reshape(B, W, K, 3)
    g = torch.Generator().manual_seed(0)
    deformed = rigid + torch.randn(rigid.shape, generator=g)
    observed = torch.rand(B, W, K, generator=g) > 0.2
    s = torch.full((B,), 1.3)
    c = rigid.mean(-2, keepdim=True)
    big = c + (deformed - c) * 1.3
    win = slice(2, 2 + enc.window)
    with torch.no_grad():
        small = enc(rigid[:, win], deformed[:, win], observed[:, win])
        scaled = enc(rigid[:, win], big[:, win], observed[:, win], s)
        plain = enc(rigid[:, win], big[:, win], observed[:, win])
        ones = enc(rigid[:, win], deformed[:, win], observed[:, win], torch.ones(B))
    torch.testing.assert_close(ones, small)
    m0 = enc.out_dim - (K * (K - 1) // 2 + 2 * K) - mech.out_dim  # the mechanism columns
    mcols = torch.zeros(enc.out_dim, dtype=torch.bool)
    mcols[m0 : m0 + mech.out_dim] = True
    torch.testing.assert_close(scaled[:, ~mcols], small[:, ~mcols], atol=1e-4, rtol=1e-4)
    mid = enc.half_window + 2
    seen_big = torch.where(observed[:, mid, :, None], big[:, mid], rigid[:, mid])
    torch.testing.assert_close(scaled[:, mcols], mech(seen_big))
    assert (scaled[:, mcols] - small[:, mcols]).abs().max() > 0.01
    meas = slice(enc.out_dim - (K * (K - 1) // 2 + 2 * K), enc.out_dim)
    assert (plain[:, meas] - small[:, meas]).abs().max() > 0.05
    seen_small = torch.where(observed[:, mid, :, None], deformed[:, mid], rigid[:, mid])
    before = torch.where(observed[:, mid - 1, :, None], deformed[:, mid - 1], rigid[:, mid - 1])
    up = torch.tensor([0.0, 0.0, 1.0])
    torch.testing.assert_close(scaled[:, meas], pose_measurements(seen_small, before, up=up),
                               atol=1e-4, rtol=1e-4)  # fmt: skip
    with pytest.raises(ValueError, match=r"scale must be \(4,\)"):
        enc(rigid[:, win], big[:, win], observed[:, win], s[:2])
    model = BehaviorClassifier(enc, LinearHead(enc.out_dim * 3, 2), context_frames=(5,)).eval()
    assert model.window == W
    with torch.no_grad():
        f_small = model.features(rigid, deformed, observed)
        f_big = model.features(rigid, big, observed, s)
    keep = ~mcols.repeat(3)
    torch.testing.assert_close(f_big[:, keep], f_small[:, keep], atol=1e-4, rtol=1e-4)
    with pytest.raises(ValueError, match=r"scale must be \(4,\)"):
        model.features(rigid, big, observed, s[:1])
