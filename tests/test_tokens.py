"""Tokens: Kabsch, canonicalisation, features, masks, loss, linear baseline."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from deformnet.body import default_mouse
from deformnet.data import MaskConfig, WindowBank, gap_masks, make_masks, toy_sequence
from deformnet.so3 import rodrigues_to_matrix, transform_points
from deformnet.tokens import (
    canonicalize,
    heading_rotation,
    kabsch,
    linear_baseline,
    masked_mse,
    token_features,
    uncanonicalize,
)

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def body():
    return default_mouse()


def _window(body, B=3, W=9, seed=0, dtype=torch.float64):
    """Rigid model moved along a random smooth path + smooth per-part offsets."""
    g = torch.Generator().manual_seed(seed)
    K = body.num_parts
    M = torch.tensor(np.array(body.points), dtype=dtype)
    t = torch.arange(W, dtype=dtype)[None, :, None]
    r0 = torch.randn(B, 1, 3, generator=g, dtype=dtype)
    dr = 0.05 * torch.randn(B, 1, 3, generator=g, dtype=dtype)
    tau = 100 * torch.randn(B, 1, 3, generator=g, dtype=dtype) + 2.0 * t * torch.randn(
        B, 1, 3, generator=g, dtype=dtype
    )
    poses = torch.cat((r0 + dr * t, tau), -1)  # (B, W, 6)
    rigid = transform_points(poses, M.expand(B, W, K, 3))
    off = 2.0 * torch.sin(0.4 * t[..., None] + torch.randn(B, 1, K, 3, generator=g, dtype=dtype))
    deformed = rigid + off
    observed = torch.rand(B, W, K, generator=g) > 0.3
    return poses, rigid, deformed, observed


def test_kabsch_recovers_pose(body):
    poses, rigid, _, _ = _window(body)
    R, t = kabsch(rigid, torch.tensor(np.array(body.points)))
    assert torch.allclose(R, rodrigues_to_matrix(poses[..., :3]), atol=1e-9)
    assert torch.allclose(t, poses[..., 3:], atol=1e-8)
    assert torch.allclose(torch.linalg.det(R), torch.ones(()).double())


def test_canonical_window_is_invariant_to_global_motion(body):
    _, rigid, deformed, _ = _window(body)
    M = torch.tensor(np.array(body.points))
    rc, dc, R, t = canonicalize(rigid, deformed, M, mid=4)
    assert torch.allclose(rc[:, 4], M.expand_as(rc[:, 4]), atol=1e-9)
    Q = rodrigues_to_matrix(torch.tensor([0.3, -1.2, 2.0], dtype=torch.float64))
    shift = torch.tensor([500.0, -20.0, 3.0], dtype=torch.float64)
    rc2, dc2, R2, t2 = canonicalize(rigid @ Q.T + shift, deformed @ Q.T + shift, M, mid=4)
    assert torch.allclose(rc, rc2, atol=1e-8) and torch.allclose(dc, dc2, atol=1e-8)
    assert torch.allclose(
        uncanonicalize(dc2[:, 4], R2, t2), deformed[:, 4] @ Q.T + shift, atol=1e-8
    )


UP = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def _about(axis, angle):
    return rodrigues_to_matrix(torch.tensor(axis, dtype=torch.float64) * angle)


def test_heading_rotation_keeps_yaw_and_puts_the_body_up_axis_on_the_world_up():
    g = torch.Generator().manual_seed(1)
    R = rodrigues_to_matrix(torch.randn(5, 4, 3, generator=g, dtype=torch.float64))
    up = torch.tensor([0.2, -0.3, 2.0], dtype=torch.float64)  # any length, any direction
    Rh = heading_rotation(R, up)
    assert Rh.shape == (5, 4, 3, 3)
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(Rh.transpose(-1, -2) @ Rh, eye.expand_as(Rh), atol=1e-12)
    assert torch.allclose(torch.linalg.det(Rh), torch.ones(5, 4, dtype=torch.float64))
    assert torch.allclose(Rh[..., :, 2], (up / up.norm()).expand(5, 4, 3), atol=1e-12)
    # Rh = Q R with Q a pure swing: its rotation axis is horizontal (no turn about up)
    from deformnet.so3 import matrix_to_rodrigues

    swing = matrix_to_rodrigues(Rh @ R.transpose(-1, -2))
    assert torch.allclose(swing @ (up / up.norm()), torch.zeros(5, 4, dtype=torch.float64),
                          atol=1e-10)  # fmt: skip
    # a yaw, then a pitch or a roll (< 90 deg): the heading part is the yaw
    for yaw in (0.0, 0.7, -2.5):
        turns = (([1, 0, 0], 0.0), ([1, 0, 0], 0.9), ([1, 0, 0], -1.4), ([0, 1, 0], 0.6))
        for axis, angle in turns:
            Rb = _about([0, 0, 1], yaw) @ _about(axis, angle)
            assert torch.allclose(heading_rotation(Rb, UP), _about([0, 0, 1], yaw), atol=1e-12)
    # upside down (the one singular pose): still a rotation with Z on up, finite
    Rd = _about([1, 0, 0], math.pi)
    Rhd = heading_rotation(Rd, UP)
    assert torch.isfinite(Rhd).all() and torch.allclose(Rhd[:, 2], UP, atol=1e-12)
    assert torch.allclose(torch.linalg.det(Rhd), torch.ones((), dtype=torch.float64))
    with pytest.raises(ValueError, match="non-zero"):
        heading_rotation(R, torch.zeros(3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"\(3,\)"):
        heading_rotation(R, torch.ones(2, dtype=torch.float64))


def test_heading_rotation_gradcheck():
    r = torch.tensor([[0.3, -0.5, 1.1], [1.2, 0.4, -0.2]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: heading_rotation(rodrigues_to_matrix(v), UP), (r,))


def test_heading_frame_is_invariant_to_yaw_and_place_not_to_pitch(body):
    _, rigid, deformed, _ = _window(body)
    M = torch.tensor(np.array(body.points))
    rc, dc, R, t = canonicalize(rigid, deformed, M, mid=4, up=UP)
    # the mid frame's rigid points: the body model tilted by the mid pose's pitch and roll
    Rb, tb = kabsch(rigid[:, 4], M)
    tilt = R.transpose(-1, -2) @ Rb
    assert torch.allclose(rc[:, 4], M @ tilt.transpose(-1, -2), atol=1e-9)
    assert torch.allclose(t, tb, atol=1e-9) and torch.allclose(R[..., :, 2], UP.expand(3, 3))
    Q = _about([0, 0, 1], 2.2)  # a turn about the world's up, and any shift
    shift = torch.tensor([500.0, -20.0, 30.0], dtype=torch.float64)
    rc2, dc2, R2, t2 = canonicalize(rigid @ Q.T + shift, deformed @ Q.T + shift, M, 4, UP)
    assert torch.allclose(rc, rc2, atol=1e-8) and torch.allclose(dc, dc2, atol=1e-8)
    assert torch.allclose(
        uncanonicalize(dc2[:, 4], R2, t2), deformed[:, 4] @ Q.T + shift, atol=1e-8
    )
    P = _about([1, 0, 0], 0.5)  # a pitch is seen (the body frame would remove it)
    rc3, _, _, _ = canonicalize(rigid @ P.T, deformed @ P.T, M, 4, UP)
    assert (rc3 - rc).abs().max() > 5.0
    rb, _, _, _ = canonicalize(rigid, deformed, M, 4)
    rb3, _, _, _ = canonicalize(rigid @ P.T, deformed @ P.T, M, 4)
    assert torch.allclose(rb, rb3, atol=1e-8)


def test_heading_canonicalize_gradcheck(body):
    _, rigid, deformed, _ = _window(body, B=1, W=3)
    M = torch.tensor(np.array(body.points))
    rigid.requires_grad_(True)
    deformed.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda r, d: canonicalize(r, d, M, 1, UP)[:2], (rigid, deformed)
    )


def test_features_mask_the_mid_frame_and_unobserved(body):
    _, rigid, deformed, observed = _window(body)
    observed[:] = True
    f1, _, obs = token_features(rigid, deformed, observed, mid=4)
    assert not obs[:, 4].any() and obs[:, :4].all()
    d2 = deformed.clone()
    d2[:, 4] += 100.0
    d2[:, 2, 3] += 50.0
    o2 = observed.clone()
    o2[:, 2, 3] = False
    f2, _, _ = token_features(rigid, d2, o2, mid=4)
    assert torch.equal(f1[:, 4], f2[:, 4])
    assert torch.all(f2[:, 2, 3, 3:6] == 0) and torch.all(f2[:, 2, 3, 6] == 0)


def test_masked_mse_ignores_unobserved_targets():
    g = torch.Generator().manual_seed(1)
    pred = torch.randn(4, 8, 3, generator=g, requires_grad=True)
    target = torch.randn(4, 8, 3, generator=g)
    mask = torch.rand(4, 8, generator=g) > 0.5
    loss = masked_mse(pred, target, mask)
    loss.backward()
    assert torch.all(pred.grad[~mask] == 0) and torch.any(pred.grad[mask] != 0)
    t2 = target.clone()
    t2[~mask] = float("nan")  # unobserved targets may be anything, even NaN
    assert torch.allclose(masked_mse(pred, t2, mask), loss)
    expected = ((pred - target) ** 2).sum(-1)[mask].mean()
    assert torch.allclose(loss, expected)


def test_linear_baseline_interpolates_between_nearest_observed():
    W, K, mid = 7, 2, 3
    t = torch.arange(W, dtype=torch.float64)
    deformed = torch.stack((t, 2 * t, -t), -1)[:, None, :].expand(W, K, 3).clone()
    rigid = torch.zeros(W, K, 3, dtype=torch.float64)
    observed = torch.ones(W, K, dtype=torch.bool)
    observed[2:5, 0] = False  # part 0: nearest observed frames 1 and 5 -> exact linear value
    observed[mid + 1 :, 1] = False  # part 1: nothing after mid -> rigid fallback
    deformed[1, 0] += 0.0
    out = linear_baseline(rigid, deformed, observed, mid)
    assert torch.allclose(out[0], torch.tensor([3.0, 6.0, -3.0], dtype=torch.float64))
    assert torch.allclose(out[1], torch.zeros(3, dtype=torch.float64))
    # a non-linear value at the mid frame itself is never used
    deformed[mid] = 1e6
    assert torch.allclose(linear_baseline(rigid, deformed, observed, mid)[0], out[0])


def test_masks_hide_mid_and_gaps():
    gen = torch.Generator().manual_seed(0)
    hide = make_masks(500, 25, 8, MaskConfig(), gen)
    assert hide[:, 12].all()
    rate = hide.float().mean().item()
    assert 0.2 < rate < 0.7
    # some windows have the mid frame's neighbours hidden for all parts (mid-centred gaps)
    assert hide[:, 10:15].all(-1).all(-1).any()
    g = gap_masks(10, 25, 8, gap=5, dropout=0.0, gen=gen)
    assert g[:, 10:15].all() and not g[:, :10].any() and not g[:, 15:].any()
    g = gap_masks(200, 25, 8, gap=15, dropout=0.3, gen=gen)
    assert g[:, 5:20].all()
    assert math.isclose(g[:, :5].float().mean().item(), 0.3, abs_tol=0.05)


def test_window_bank_batches(body):
    seq = toy_sequence(body, num_frames=100, seed=3)
    bank = WindowBank([seq, seq], half_window=4)
    assert len(bank) == 2 * (100 - 8)
    hide = torch.zeros(2, 9, 8, dtype=torch.bool)
    b = bank.batch(torch.tensor([0, len(bank) - 1]), hide)
    assert b["rigid"].shape == (2, 9, 8, 3) and b["target"].shape == (2, 8, 3)
    assert torch.allclose(b["rigid"][0, 0], torch.from_numpy(seq.rigid[0]))
    assert torch.allclose(b["target"][1], torch.from_numpy(seq.deformed[95]))
    assert torch.equal(b["observed"][0], torch.from_numpy(seq.observed[:9]))
    assert torch.equal(b["target_mask"][1], torch.from_numpy(seq.observed[95]))
    hide[:, 4] = True
    b = bank.batch(torch.tensor([0, 1]), hide)
    assert not b["observed"][:, 4].any() and torch.all(b["deformed"][:, 4] == 0)


def test_interpolation_prior_uses_nearest_observed_frames(body):
    W, mid, K = 9, 4, body.num_parts
    M = torch.tensor(np.array(body.points))
    rigid = M.expand(1, W, K, 3).clone()  # a mouse standing still: canonical = model frame
    t = torch.arange(W, dtype=torch.float64)
    deformed = rigid + t[None, :, None, None] * torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    observed = torch.zeros(1, W, K, dtype=torch.bool)
    observed[0, [1, 2, 6, 7], 0] = True  # part 0: nearest 2 and 6, second-nearest 1 and 7
    observed[0, [0, 3], 1] = True  # part 1: nothing after the mid frame
    _, prior, _ = token_features(rigid, deformed, observed, mid, offset_scale=10.0)
    p = prior[0, 0]
    assert prior.shape == (1, K, 26)
    x = lambda v: torch.tensor([v, 0.0, 0.0], dtype=torch.float64)  # noqa: E731
    assert torch.allclose(p[0:3], x(0.4)) and torch.allclose(p[3:6], x(0.4))  # linear at t=4
    assert torch.allclose(p[6:9], x(0.2)) and torch.allclose(p[9:12], x(0.6))
    assert torch.allclose(p[12:15], x(0.1)) and torch.allclose(p[15:18], x(0.7))
    assert torch.allclose(p[18:22], torch.tensor([0.5, 0.5, 0.75, 0.75], dtype=torch.float64))
    assert torch.all(p[22:] == 1)
    q = prior[0, 1]  # one side only: held, second-nearest before is frame 0
    assert torch.allclose(q[0:3], x(0.3)) and torch.allclose(q[12:15], x(0.0))
    assert torch.allclose(q[22:], torch.tensor([1.0, 0.0, 1.0, 0.0], dtype=torch.float64))
    assert torch.all(prior[0, 2:, 22:] == 0)  # nothing observed


def test_check_window_names_the_input_that_is_off():
    from deformnet.tokens import check_window

    r = torch.zeros(2, 5, 4, 3)
    check_window(r, r, torch.zeros(2, 5, 4, dtype=torch.bool), 5, 4)
    check_window(r[None], r[None], torch.zeros(1, 2, 5, 4, dtype=torch.bool), 5, 4, lead="...")
    with pytest.raises(ValueError, match=r"^rigid must have shape \(B, 5, 4, 3\), got"):
        check_window(r[None], r[None], torch.zeros(1, 2, 5, 4), 5, 4)
    with pytest.raises(ValueError, match=r"\(\.\.\., 5, 3, 3\) \(window W = 5, parts a, b, c\)"):
        check_window(r, r, torch.zeros(2, 5, 4), 5, 3, lead="...", parts=("a", "b", "c"))
    with pytest.raises(ValueError, match="deformed shape"):
        check_window(r, r[:1], torch.zeros(2, 5, 4), 5, 4)
    with pytest.raises(ValueError, match=r"observed must have shape \(2, 5, 4\)"):
        check_window(r, r, torch.zeros(2, 5), 5, 4)
