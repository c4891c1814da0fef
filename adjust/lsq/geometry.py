"""Batched geometry with analytic Jacobians for the adjustment (torch, float64 by default).

Pose increments are *left* (global-frame) perturbations: a step (delta_r, delta_tau) maps a pose
(R, tau) to (exp(delta_r) R, tau + delta_tau), so rotations never pass through the Rodrigues
singularity at |r| = pi. Under it a moved model point X = R X_m + tau changes by
dX = -[R X_m]_x delta_r + delta_tau.
"""

from __future__ import annotations

import torch
from torch import Tensor

from adjust.camera import CameraTensors
from deformnet.so3 import matrix_to_rodrigues, rodrigues_to_matrix, skew

_SMALL2 = 1e-6


def _check(x: Tensor, tail: tuple[int, ...], name: str) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.dim() < len(tail) or tuple(x.shape[x.dim() - len(tail) :]) != tail:
        raise ValueError(f"{name} must have shape (..., {', '.join(map(str, tail))}), got {tuple(x.shape)}")


def so3_log(R: Tensor) -> Tensor:
    """Rotation vector (angle in [0, pi]) of rotation matrices.  (..., 3, 3) -> (..., 3)."""
    return matrix_to_rodrigues(R)


def so3_exp(r: Tensor) -> Tensor:
    """Rotation matrices of rotation vectors.  (..., 3) -> (..., 3, 3)."""
    return rodrigues_to_matrix(r)


def left_jacobian_inverse(phi: Tensor) -> Tensor:
    """J_l^-1(phi): d log(exp(eps) exp(phi)) / d eps at eps = 0.  (..., 3) -> (..., 3, 3).

    J_l^-1 = I - [phi]/2 + (1/theta^2 - (1 + cos theta) / (2 theta sin theta)) [phi]^2; the right
    inverse is J_r^-1(phi) = J_l^-1(-phi). Accurate for theta < pi - 1e-3 (caller keeps |phi|
    well below pi: neighbours' relative rotations are small).
    """
    _check(phi, (3,), "phi")
    th2 = (phi * phi).sum(-1)[..., None, None]
    small = th2 < _SMALL2
    t2 = torch.where(small, torch.ones_like(th2), th2)
    th = t2.sqrt()
    coef = torch.where(
        small,
        1.0 / 12.0 + th2 / 720.0,
        1.0 / t2 - (1.0 + torch.cos(th)) / (2.0 * th * torch.sin(th)),
    )
    K = skew(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(K.shape)
    return eye - 0.5 * K + coef * (K @ K)


def retract(poses: Tensor, delta: Tensor) -> Tensor:
    """Apply left increments.  poses (..., 6), delta (..., 6) -> (..., 6): R <- exp(d_r) R."""
    _check(poses, (6,), "poses")
    _check(delta, (6,), "delta")
    R = so3_exp(delta[..., :3]) @ so3_exp(poses[..., :3])
    return torch.cat((so3_log(R), poses[..., 3:] + delta[..., 3:]), -1)


def pose_difference(a: Tensor, b: Tensor) -> Tensor:
    """Left difference a (-) b = (log(R_a R_b^T), tau_a - tau_b).  (..., 6), (..., 6) -> (..., 6)."""
    Ra, Rb = so3_exp(a[..., :3]), so3_exp(b[..., :3])
    return torch.cat((so3_log(Ra @ Rb.transpose(-1, -2)), a[..., 3:] - b[..., 3:]), -1)


def rigid_points(poses: Tensor, body: Tensor) -> tuple[Tensor, Tensor]:
    """Model points moved by the poses and their Jacobian.

    poses: (T, 6); body: (K, 3) -> X (T, K, 3) global mm, dX/d(delta) (T, K, 3, 6) for the left
    increment of the frame's own pose.
    """
    _check(poses, (6,), "poses")
    _check(body, (3,), "body")
    R = so3_exp(poses[..., :3])  # (T, 3, 3)
    a = torch.einsum("tij,kj->tki", R, body)  # rotated model points (T, K, 3)
    X = a + poses[:, None, 3:]
    eye = torch.eye(3, dtype=poses.dtype, device=poses.device).expand(*a.shape[:-1], 3, 3)
    J = torch.cat((-skew(a), eye), -1)
    return X, J


def project_with_jacobian(X: Tensor, cams: CameraTensors) -> tuple[Tensor, Tensor, Tensor]:
    """Project points into every camera with the analytic Jacobian d(pixel)/dX.

    X: (..., 3) mm -> uv (..., C, 2) px, J (..., C, 2, 3) px/mm, depth z (..., C) mm.
    Matches `adjust.camera.project_points` (OpenCV pinhole + k1 k2 p1 p2 k3 distortion, skew).
    """
    _check(X, (3,), "X")
    Rc, tc, Kc, dist = cams.R, cams.t, cams.K, cams.dist
    Xc = torch.einsum("cij,...j->...ci", Rc, X) + tc  # (..., C, 3)
    z = Xc[..., 2]
    z = torch.where(z.abs() < 1e-9, torch.full_like(z, 1e-9), z)
    iz = 1.0 / z
    x, y = Xc[..., 0] * iz, Xc[..., 1] * iz
    k1, k2, p1, p2, k3 = dist.unbind(-1)  # (C,)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    dxd_dx = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
    dxd_dy = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    dyd_dx = dxd_dy
    dyd_dy = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
    fx, s, cx = Kc[:, 0, 0], Kc[:, 0, 1], Kc[:, 0, 2]
    fy, cy = Kc[:, 1, 1], Kc[:, 1, 2]
    u = fx * xd + s * yd + cx
    v = fy * yd + cy
    # d(u, v)/d(x, y)
    du_dx = fx * dxd_dx + s * dyd_dx
    du_dy = fx * dxd_dy + s * dyd_dy
    dv_dx = fy * dyd_dx
    dv_dy = fy * dyd_dy
    # d(x, y)/dXc = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
    A = torch.stack(
        (
            torch.stack((du_dx * iz, du_dy * iz, -(du_dx * x + du_dy * y) * iz), -1),
            torch.stack((dv_dx * iz, dv_dy * iz, -(dv_dx * x + dv_dy * y) * iz), -1),
        ),
        -2,
    )  # (..., C, 2, 3) w.r.t. camera coordinates
    J = A @ Rc  # chain through Xc = R X + t
    return torch.stack((u, v), -1), J, Xc[..., 2]


def left_jacobian(phi: Tensor) -> Tensor:
    """J_l(phi) = I + (1 - cos t)/t^2 [phi] + (t - sin t)/t^3 [phi]^2.  (..., 3) -> (..., 3, 3)."""
    _check(phi, (3,), "phi")
    th2 = (phi * phi).sum(-1)[..., None, None]
    small = th2 < _SMALL2
    t2 = torch.where(small, torch.ones_like(th2), th2)
    th = t2.sqrt()
    a = torch.where(small, 0.5 - th2 / 24.0, (1.0 - torch.cos(th)) / t2)
    b = torch.where(small, 1.0 / 6.0 - th2 / 120.0, (th - torch.sin(th)) / (t2 * th))
    K = skew(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(K.shape)
    return eye + a * K + b * (K @ K)
