"""deformnet.so3: Rodrigues <-> matrix against OpenCV, round trips, and stability near 0 and pi."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from deformnet.so3 import (
    kabsch,
    matrix_to_pose,
    matrix_to_quaternion,
    matrix_to_rodrigues,
    pose_to_matrix,
    quaternion_to_rodrigues,
    rodrigues_to_matrix,
    skew,
    transform_points,
)

D = torch.float64


def _axis(seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(3, generator=g, dtype=D)
    return a / a.norm()


def _random_rvecs(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    axes = torch.randn(n, 3, generator=g, dtype=D)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    angles = torch.rand(n, 1, generator=g, dtype=D) * (math.pi - 1e-3)
    return axes * angles


def test_shapes_and_errors():
    r = _random_rvecs(6).reshape(2, 3, 3)
    assert rodrigues_to_matrix(r).shape == (2, 3, 3, 3)
    assert matrix_to_rodrigues(rodrigues_to_matrix(r)).shape == (2, 3, 3)
    assert skew(r).shape == (2, 3, 3, 3)
    with pytest.raises(ValueError):
        rodrigues_to_matrix(torch.zeros(4, dtype=D))
    with pytest.raises(ValueError):
        matrix_to_rodrigues(torch.zeros(3, 4, dtype=D))


def test_values_match_cv2():
    r = _random_rvecs(50, seed=1)
    R = rodrigues_to_matrix(r).numpy()
    for i in range(len(r)):
        R_cv, _ = cv2.Rodrigues(r[i].numpy())
        np.testing.assert_allclose(R[i], R_cv, atol=1e-12)
        r_cv, _ = cv2.Rodrigues(R_cv)
        np.testing.assert_allclose(
            matrix_to_rodrigues(torch.as_tensor(R_cv)).numpy(), r_cv[:, 0], atol=1e-9
        )


def test_proper_rotation():
    R = rodrigues_to_matrix(_random_rvecs(100, seed=2))
    eye = torch.eye(3, dtype=D).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, atol=1e-13, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(100, dtype=D), atol=1e-13, rtol=0)


def test_round_trip_random():
    r = _random_rvecs(1000, seed=3)
    torch.testing.assert_close(matrix_to_rodrigues(rodrigues_to_matrix(r)), r, atol=1e-10, rtol=0)
    g = torch.Generator().manual_seed(4)
    R = rodrigues_to_matrix(torch.randn(1000, 3, generator=g, dtype=D) * 3)
    torch.testing.assert_close(rodrigues_to_matrix(matrix_to_rodrigues(R)), R, atol=1e-12, rtol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-9, 1e-6, 1e-4, 0.3])
def test_round_trip_near_zero(angle):
    r = _axis(5) * angle
    R = rodrigues_to_matrix(r)
    R_cv, _ = cv2.Rodrigues(r.numpy())
    np.testing.assert_allclose(R.numpy(), R_cv, atol=1e-15)
    back = matrix_to_rodrigues(R)
    assert torch.isfinite(back).all()
    torch.testing.assert_close(back, r, atol=1e-15, rtol=1e-9)


@pytest.mark.parametrize("delta", [1e-3, 1e-6, 1e-8, 0.0])
def test_round_trip_near_pi(delta):
    axis = _axis(6)
    r = axis * (math.pi - delta)
    R = rodrigues_to_matrix(r)
    R_cv, _ = cv2.Rodrigues(r.numpy())
    np.testing.assert_allclose(R.numpy(), R_cv, atol=1e-14)
    back = matrix_to_rodrigues(R)
    assert torch.isfinite(back).all()
    if delta == 0.0:  # at pi the sign of the axis is arbitrary
        torch.testing.assert_close(rodrigues_to_matrix(back), R, atol=1e-12, rtol=0)
        assert abs(back.norm().item() - math.pi) < 1e-12
    else:
        torch.testing.assert_close(back, r, atol=1e-9, rtol=0)


def _assert_finite_grad(fn, x):
    x = x.clone().requires_grad_(True)
    fn(x).sum().backward()
    assert torch.isfinite(x.grad).all()


def test_gradients_finite_at_zero_and_pi():
    _assert_finite_grad(rodrigues_to_matrix, torch.zeros(3, dtype=D))
    _assert_finite_grad(lambda R: matrix_to_rodrigues(R), torch.eye(3, dtype=D))
    _assert_finite_grad(rodrigues_to_matrix, _axis(7) * math.pi)
    _assert_finite_grad(matrix_to_rodrigues, rodrigues_to_matrix(_axis(7) * math.pi))
    # gradient of exp at 0 is the skew generator: d R / d r_i = [e_i]_x
    r = torch.zeros(3, dtype=D)
    J = torch.autograd.functional.jacobian(rodrigues_to_matrix, r)
    for i in range(3):
        torch.testing.assert_close(J[..., i], skew(torch.eye(3, dtype=D)[i]), atol=1e-15, rtol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 1.0, math.pi - 1e-3, math.pi - 1e-6])
def test_gradcheck_rodrigues_to_matrix(angle):
    r = (_axis(8) * angle).requires_grad_(True)
    assert torch.autograd.gradcheck(rodrigues_to_matrix, (r,), eps=1e-7, atol=1e-6)


@pytest.mark.parametrize("angle", [1e-9, 1e-5, 1.0, math.pi - 1e-3, math.pi - 1e-6])
def test_gradcheck_matrix_to_rodrigues(angle):
    # perturb along the manifold: f(w) = log(R0 exp(w)), checked at w = 0
    R0 = rodrigues_to_matrix(_axis(9) * angle)
    w = torch.zeros(3, dtype=D, requires_grad=True)

    def f(w):
        return matrix_to_rodrigues(R0 @ rodrigues_to_matrix(w))

    assert torch.autograd.gradcheck(f, (w,), eps=1e-8, atol=1e-5)
    # and in the ambient 3x3 space (the log map extends off SO(3) through the quaternion)
    R = R0.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(matrix_to_rodrigues, (R,), eps=1e-8, atol=1e-5)


def test_pose_helpers():
    g = torch.Generator().manual_seed(10)
    p = torch.cat((_random_rvecs(4, seed=11), torch.randn(4, 3, generator=g, dtype=D) * 100), -1)
    H = pose_to_matrix(p)
    torch.testing.assert_close(matrix_to_pose(H), p, atol=1e-10, rtol=0)
    X = torch.randn(4, 5, 3, generator=g, dtype=D)
    Xh = torch.cat((X, torch.ones(4, 5, 1, dtype=D)), -1)
    torch.testing.assert_close(transform_points(p, X), (Xh @ H.transpose(-1, -2))[..., :3])


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 0.7, math.pi - 1e-6])
def test_quaternion_to_rodrigues_any_scale(angle):
    r = _axis(12) * angle
    q = matrix_to_quaternion(rodrigues_to_matrix(r))
    assert q.shape == (4,)
    for scale in (1.0, 1e-3, 7.0, -2.0):  # any non-zero multiple of a unit quaternion
        torch.testing.assert_close(quaternion_to_rodrigues(scale * q), r, atol=1e-12, rtol=1e-9)
    q = q.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(quaternion_to_rodrigues, (q,), eps=1e-8, atol=1e-6)
    with pytest.raises(ValueError):
        quaternion_to_rodrigues(torch.zeros(3, dtype=D))


def _fit_problem(seed: int = 13):
    g = torch.Generator().manual_seed(seed)
    ref = torch.randn(7, 3, generator=g, dtype=D) * torch.tensor([30.0, 10.0, 5.0], dtype=D)
    R = rodrigues_to_matrix(_random_rvecs(4, seed=seed))  # (4, 3, 3)
    t = torch.randn(4, 3, generator=g, dtype=D) * 100
    return ref, R, t, ref @ R.transpose(-1, -2) + t[:, None, :]  # src (4, 7, 3)


def test_kabsch_shapes_values_weights():
    ref, R, t, src = _fit_problem()
    Rk, tk = kabsch(src, ref)
    assert Rk.shape == (4, 3, 3) and tk.shape == (4, 3)
    torch.testing.assert_close(Rk, R, atol=1e-12, rtol=0)
    torch.testing.assert_close(tk, t, atol=1e-10, rtol=0)
    torch.testing.assert_close(torch.linalg.det(Rk), torch.ones(4, dtype=D))
    # a mirror image still gives a proper rotation
    Rm, _ = kabsch(src * torch.tensor([-1.0, 1.0, 1.0], dtype=D), ref)
    torch.testing.assert_close(torch.linalg.det(Rm), torch.ones(4, dtype=D))
    # weights: zero-weight points may be anything (NaN), and do not move the fit
    w = torch.ones(4, 7, dtype=D)
    w[:, :2] = 0.0
    bad = src.clone()
    bad[:, :2] = float("nan")
    Rw, tw, S = kabsch(bad, ref, w, spread=True)
    torch.testing.assert_close(Rw, R, atol=1e-12, rtol=0)
    torch.testing.assert_close(tw, t, atol=1e-10, rtol=0)
    assert S.shape == (4, 3) and bool((S[:, :-1] >= S[:, 1:]).all())
    # bool weights = a mask; equal to dropping the points; weights rescale-invariant
    R2, t2 = kabsch(src[:, 2:], ref[2:])
    R3, t3 = kabsch(src, ref, w > 0)
    torch.testing.assert_close(R3, R2, atol=1e-13, rtol=0)
    torch.testing.assert_close(t3, t2, atol=1e-11, rtol=0)
    R4, t4 = kabsch(src, ref, 5.0 * w)
    torch.testing.assert_close(R4, R3, atol=1e-13, rtol=0)
    # collinear points: the second singular value vanishes
    line = torch.arange(5, dtype=D)[:, None] * torch.tensor([1.0, 2.0, 3.0], dtype=D)
    _, _, Sl = kabsch(line + 1.0, line, spread=True)
    assert float(Sl[1]) < 1e-10 * float(Sl[0])
    with pytest.raises(ValueError):
        kabsch(src[..., :2], ref)
    with pytest.raises(ValueError):
        kabsch(src, ref, w[:, :3])


def test_gradcheck_kabsch():
    ref, _, _, src = _fit_problem(14)
    g = torch.Generator().manual_seed(15)
    src = (src + torch.randn(src.shape, generator=g, dtype=D))[:2].requires_grad_(True)
    w = (torch.rand(2, 7, generator=g, dtype=D) + 0.5).requires_grad_(True)
    assert torch.autograd.gradcheck(kabsch, (src, ref.requires_grad_(True)))
    assert torch.autograd.gradcheck(kabsch, (src, ref, w))


def test_kabsch_polar_rotation_equals_the_svd_one():
    """The Newton polar factor (no SVD) is Kabsch's U diag(1, 1, det) V^T: same rotation to
    float precision on proper, noisy fits; reflections and degenerate cross-covariances fall
    back to the SVD; differentiable (float64 gradcheck)."""
    from deformnet.so3 import _rotation_of, _rotation_svd

    gen = torch.Generator().manual_seed(0)
    body = torch.tensor(
        [[40.0, 0, 0], [20, 5, 2], [20, -5, 2], [0, 8, -3], [-10, -6, -4], [-30, 0, 0]],
        dtype=torch.float64,
    )
    R = rodrigues_to_matrix(2 * torch.randn(500, 3, generator=gen, dtype=torch.float64))
    src = body @ R.transpose(-1, -2) + torch.randn(500, 6, 3, generator=gen, dtype=torch.float64)
    H = (src - src.mean(-2, keepdim=True)).transpose(-1, -2) @ (body - body.mean(0))
    torch.testing.assert_close(_rotation_of(H), _rotation_svd(H), atol=1e-12, rtol=0)
    torch.testing.assert_close(_rotation_of(H.float()), _rotation_svd(H.float()), atol=5e-6, rtol=0)
    odd = torch.randn(6, 3, 3, generator=gen, dtype=torch.float64)
    odd[0] = -torch.eye(3, dtype=torch.float64)  # a reflection
    odd[1, :, 2] = 0.0  # rank 2 (collinear-like)
    odd[2] = 0.0  # all points at one place
    torch.testing.assert_close(_rotation_of(odd), _rotation_svd(odd), atol=1e-12, rtol=0)
    Hp = H[:4].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(_rotation_of, (Hp,))
