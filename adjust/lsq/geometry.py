"""Batched geometry with analytic Jacobians for the adjustment (torch, float64 by default).

Pose increments are *left* (global-frame) perturbations: a step (delta_r, delta_tau) maps a pose
(R, tau) to (exp(delta_r) R, tau + delta_tau), so rotations never pass through the Rodrigues
singularity at |r| = pi. Under it a moved model point X = R X_m + tau changes by
dX = -[R X_m]_x delta_r + delta_tau.
"""

from __future__ import annotations

import torch
from torch import Tensor

from adjust.camera import CameraTensors, camera_to_pixels
from deformnet.so3 import matrix_to_rodrigues, rodrigues_to_matrix, skew
from deformnet.so3 import quaternion_to_rodrigues as rotvec_from_quat  # the one quaternion log

_SMALL2 = 1e-6


def _check(x: Tensor, tail: tuple[int, ...], name: str) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.dim() < len(tail) or tuple(x.shape[x.dim() - len(tail) :]) != tail:
        raise ValueError(
            f"{name} must have shape (..., {', '.join(map(str, tail))}), got {tuple(x.shape)}"
        )


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
    # [phi]^2 = phi phi^T - theta^2 I
    out = coef * (phi[..., :, None] * phi[..., None, :]) - 0.5 * skew(phi)
    d = (1.0 - coef * th2)[..., 0]  # (..., 1)
    out = out + torch.diag_embed(d.expand(*d.shape[:-1], 3))
    return out


def quat_from_rotvec(r: Tensor) -> Tensor:
    """Unit quaternion (w, x, y, z) of rotation vectors.  (..., 3) -> (..., 4)."""
    th2 = (r * r).sum(-1, keepdim=True)
    small = th2 < _SMALL2
    th = torch.where(small, torch.ones_like(th2), th2).sqrt()
    s = torch.where(small, 0.5 - th2 / 48.0, torch.sin(0.5 * th) / th)
    c = torch.where(small, 1.0 - th2 / 8.0, torch.cos(0.5 * th))
    return torch.cat((c, s * r), -1)


def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a b (rotation b first, then a).  (..., 4), (..., 4) -> (..., 4)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        -1,
    )


def quat_conj(q: Tensor) -> Tensor:
    return torch.cat((q[..., :1], -q[..., 1:]), -1)


def retract(poses: Tensor, delta: Tensor) -> Tensor:
    """Apply left increments.  poses (..., 6), delta (..., 6) -> (..., 6): R <- exp(d_r) R."""
    _check(poses, (6,), "poses")
    _check(delta, (6,), "delta")
    q = quat_mul(quat_from_rotvec(delta[..., :3]), quat_from_rotvec(poses[..., :3]))
    return torch.cat((rotvec_from_quat(q), poses[..., 3:] + delta[..., 3:]), -1)


def pose_difference(a: Tensor, b: Tensor) -> Tensor:
    """Left difference a (-) b = (log(R_a R_b^T), tau_a - tau_b).

    (..., 6), (..., 6) -> (..., 6).
    """
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
    `project_components` stacked, its camera-frame derivative chained through x_cam = R X + t.
    """
    _check(X, (3,), "X")
    u, v, z, A = project_components(X, cams, True)
    Ac = torch.stack((torch.stack(A[:3], -1), torch.stack(A[3:], -1)), -2)  # (..., C, 2, 3)
    return torch.stack((u, v), -1), Ac @ cams.R, z


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


def project_components(
    X: Tensor, cams: CameraTensors, jacobian: bool = True
) -> tuple[Tensor, Tensor, Tensor, tuple[Tensor, ...] | None]:
    """Fast projection for the solver: components instead of stacked tensors.

    X: (..., 3) -> u, v, z (..., C) and, if `jacobian`, the six entries (A00, A01, A02, A10, A11,
    A12) of d(u, v)/d(X_cam) (..., C) each, the derivative w.r.t. *camera* coordinates (chain
    with the camera rotation: d(u, v)/dX = A R_c). Skips the distortion terms when no camera
    has distortion (nor is a fisheye) and the skew terms when none has skew. The model is
    `adjust.camera.camera_to_pixels`, the one projection.
    """
    Xc = torch.einsum("...j,cij->...ci", X, cams.R) + cams.t  # (..., C, 3)
    fisheye = cams.fisheye
    dist = cams.dist if fisheye is not None or bool((cams.dist != 0).any()) else None
    skewed = bool((cams.K[:, 0, 1] != 0).any())
    u, v, A = camera_to_pixels(Xc, cams.K, dist, jacobian, skew=skewed, fisheye=fisheye)
    return u, v, Xc[..., 2], A


def normal_blocks_3d(
    A: tuple[Tensor, ...], eu: Tensor, ev: Tensor, w: Tensor, W6: Tensor, Wg: Tensor
) -> tuple[Tensor, Tensor]:
    """Per point: sum over cameras of w J^T J (3x3) and w J^T e (3), J = d(u,v)/dX = A R_c.

    A: six (..., C) entries of d(u, v)/dX_cam (`project_components`); eu, ev, w: (..., C);
    W6 (C 6, 9), Wg (C 3, 3): camera -> world rotation weights. -> (..., 3, 3), (..., 3).
    """
    a0, a1 = A[:3], A[3:]
    wa0 = [w * x for x in a0]
    wa1 = [w * x for x in a1]
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    h = torch.stack([wa0[j] * a0[m] + wa1[j] * a1[m] for j, m in pairs], -1)  # (..., C, 6)
    gc = torch.stack([wa0[j] * eu + wa1[j] * ev for j in range(3)], -1)  # (..., C, 3)
    lead = w.shape[:-1]
    C = w.shape[-1]
    H = (h.reshape(-1, C * 6) @ W6).reshape(*lead, 3, 3)
    g = (gc.reshape(-1, C * 3) @ Wg).reshape(*lead, 3)
    return H, g


def rotation_gemm_weights(R: Tensor) -> tuple[Tensor, Tensor]:
    """Constant matrices turning per-camera camera-frame normal blocks into world ones.

    sum_c R_c^T H_c R_c = H6 (.., C 6) @ W6 (C 6, 9) for symmetric H_c given by its 6 unique
    entries (00, 01, 02, 11, 12, 22); sum_c R_c^T g_c = g (.., C 3) @ Wg (C 3, 3). R: (C, 3, 3).
    """
    C = R.shape[0]
    W6 = R.new_zeros((C, 6, 3, 3))
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    for p, (j, m) in enumerate(pairs):
        W6[:, p] = R[:, j, :, None] * R[:, m, None, :]
        if j != m:
            W6[:, p] += R[:, m, :, None] * R[:, j, None, :]
    return W6.reshape(C * 6, 9), R.reshape(C * 3, 3)
