"""Rotations and rigid poses in torch: pure, batched over leading dims, differentiable.

Conventions (stated once for the whole project): angles in radians; a rotation vector
(Rodrigues vector) r has angle |r| and axis r/|r|; a pose p = (r, tau) in R^6 maps model
coordinates to global ones, X_g = R(r) X_m + tau (mm).

Every function is stable (finite value and gradient) near angle 0 and near angle pi.
"""

from __future__ import annotations

import torch
from torch import Tensor

_SMALL2 = 1e-8  # squared angle below which Taylor series replace sin/cos ratios
_SMALL_QUAT = 1e-12  # (|v| / w)^2 below which a series replaces atan2 in the quaternion log


def _check_last(x: Tensor, size: int | tuple[int, ...], name: str) -> None:
    size = (size,) if isinstance(size, int) else size
    if not isinstance(x, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if tuple(x.shape[x.dim() - len(size) :]) != size or x.dim() < len(size):
        raise ValueError(
            f"{name} must have shape (..., {', '.join(map(str, size))}), got {tuple(x.shape)}"
        )


def skew(v: Tensor) -> Tensor:
    """Cross-product matrix [v]_x with [v]_x w = v x w.  v: (..., 3) -> (..., 3, 3)."""
    _check_last(v, 3, "v")
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        (torch.stack((o, -z, y), -1), torch.stack((z, o, -x), -1), torch.stack((-y, x, o), -1)), -2
    )


def rodrigues_to_matrix(r: Tensor) -> Tensor:
    """Rotation matrix from a rotation vector (exponential map).  r: (..., 3) -> (..., 3, 3)."""
    _check_last(r, 3, "r")
    theta2 = (r * r).sum(-1)[..., None, None]
    small = theta2 < _SMALL2
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = t2.sqrt()
    a = torch.where(small, 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0, torch.sin(theta) / theta)
    half = torch.sin(theta / 2.0) / theta
    b = torch.where(small, 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0, 2.0 * half * half)
    k = skew(r)
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand(k.shape)
    return eye + a * k + b * (k @ k)


def matrix_to_quaternion(R: Tensor) -> Tensor:
    """Unit quaternion (w, x, y, z) with w >= 0 from a rotation matrix.  (..., 3, 3) -> (..., 4).

    Shepperd's method: of four algebraically equal formulas it uses the best-conditioned one.
    """
    _check_last(R, (3, 3), "R")
    m = R
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    d = torch.stack(
        (1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22), -1
    )
    cands = torch.stack(
        (
            torch.stack((d[..., 0], m21 - m12, m02 - m20, m10 - m01), -1),
            torch.stack((m21 - m12, d[..., 1], m01 + m10, m02 + m20), -1),
            torch.stack((m02 - m20, m01 + m10, d[..., 2], m12 + m21), -1),
            torch.stack((m10 - m01, m02 + m20, m12 + m21, d[..., 3]), -1),
        ),
        -2,
    )  # (..., 4 candidates, 4)
    best = d.argmax(-1)
    denom = 2.0 * d.clamp_min(1e-12).sqrt()  # (..., 4)
    q = cands / denom[..., None]
    idx = best[..., None, None].expand(*best.shape, 1, 4)
    q = q.gather(-2, idx).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quaternion_to_rodrigues(q: Tensor) -> Tensor:
    """Rotation vector (angle in [0, pi]) from a quaternion (w, x, y, z), unit or not.

    q: (..., 4) -> (..., 3). Scale-invariant: the series replaces 2 atan2(s, w) / s where
    s^2 < 1e-12 w^2 (s = |(x, y, z)|), so any non-zero multiple of a unit quaternion gives the
    same vector (the one implementation; `adjust.lsq.geometry.rotvec_from_quat` is this).
    """
    _check_last(q, 4, "q")
    q = torch.where(q[..., :1] < 0, -q, q)
    w, v = q[..., :1], q[..., 1:]
    s2 = (v * v).sum(-1, keepdim=True)
    small = s2 < _SMALL_QUAT * (w * w)
    s = torch.where(small, torch.ones_like(s2), s2).sqrt()
    # angle / s = 2 atan2(s, w) / s; series for small s / w: 2/w (1 - s^2 / (3 w^2))
    w_safe = torch.where(small, w, torch.ones_like(w))
    factor = torch.where(
        small, 2.0 / w_safe * (1.0 - s2 / (3.0 * w_safe * w_safe)), 2.0 * torch.atan2(s, w) / s
    )
    return factor * v


def matrix_to_rodrigues(R: Tensor) -> Tensor:
    """Rotation vector (angle in [0, pi]) from a rotation matrix (log map).

    R: (..., 3, 3) -> (..., 3).
    """
    return quaternion_to_rodrigues(matrix_to_quaternion(R))


def pose_to_matrix(p: Tensor) -> Tensor:
    """4x4 homogeneous transform of a pose (r, tau).  p: (..., 6) -> (..., 4, 4)."""
    _check_last(p, 6, "p")
    R = rodrigues_to_matrix(p[..., :3])
    top = torch.cat((R, p[..., 3:, None]), -1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom = bottom + torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=p.dtype, device=p.device)
    return torch.cat((top, bottom), -2)


def matrix_to_pose(H: Tensor) -> Tensor:
    """Pose (r, tau) of a 4x4 (or 3x4) rigid transform.  (..., 4, 4) -> (..., 6)."""
    if H.shape[-2:] not in ((4, 4), (3, 4)):
        raise ValueError(f"H must have shape (..., 4, 4) or (..., 3, 4), got {tuple(H.shape)}")
    return torch.cat((matrix_to_rodrigues(H[..., :3, :3]), H[..., :3, 3]), -1)


def transform_points(p: Tensor, X: Tensor) -> Tensor:
    """Move model points by poses: X_g = R(r) X_m + tau.

    p: (..., 6), X: (..., K, 3) (leading dims broadcast) -> (..., K, 3).
    """
    _check_last(p, 6, "p")
    _check_last(X, 3, "X")
    R = rodrigues_to_matrix(p[..., :3])
    return X @ R.transpose(-1, -2) + p[..., None, 3:]


def inverse_transform_points(p: Tensor, X: Tensor) -> Tensor:
    """Global points into the model frame of poses p: X_m = R(r)^T (X_g - tau).

    p: (..., 6), X: (..., K, 3) -> (..., K, 3).
    """
    _check_last(p, 6, "p")
    _check_last(X, 3, "X")
    R = rodrigues_to_matrix(p[..., :3])
    return (X - p[..., None, 3:]) @ R


def kabsch(
    src: Tensor, dst: Tensor, weights: Tensor | None = None, *, spread: bool = False
) -> tuple[Tensor, Tensor] | tuple[Tensor, Tensor, Tensor]:
    """Least-squares rigid transform mapping `dst` onto `src`: src ≈ dst @ R^T + t (Kabsch).

    src: (..., K, 3) points (e.g. a frame's rigid points in global mm); dst: (..., K, 3) or
    (K, 3) reference points (e.g. the body model), broadcast against src; weights: (..., K)
    >= 0 per point or None (all 1): points of zero weight may hold any value, NaN included.
    Returns R (..., 3, 3) (a proper rotation) and t (..., 3); with ``spread=True`` also the
    singular values (..., 3) (descending) of the weighted cross-covariance, which tell a
    degenerate (collinear, < 3 points) fit. The rotation is the polar factor of the
    cross-covariance (`_rotation_of`: Newton iterations, no SVD, where it is a proper rotation
    away from degeneracy; the SVD elsewhere). Differentiable; the gradient is well defined
    when the reference's principal spreads are distinct (true for a mouse body model). The one
    implementation (the tokens' canonicalisation, the initial poses, occluders following
    parts, the body model's Procrustes fit).
    """
    _check_last(src, 3, "src")
    _check_last(dst, 3, "dst")
    src, dst = torch.broadcast_tensors(src, dst.to(src.dtype))
    if weights is None:
        cs = src.mean(-2, keepdim=True)
        cd = dst.mean(-2, keepdim=True)
        H = (src - cs).transpose(-1, -2) @ (dst - cd)  # (..., 3, 3) = sum (s_i)(d_i)^T
    else:
        if weights.shape != src.shape[:-1]:
            raise ValueError(
                f"weights must have shape {tuple(src.shape[:-1])}, got {tuple(weights.shape)}"
            )
        w = weights.to(src.dtype)[..., None]  # (..., K, 1)
        keep = w > 0
        src = torch.where(keep, src, torch.zeros_like(src))
        dst = torch.where(keep, dst, torch.zeros_like(dst))
        ws = w.sum(-2, keepdim=True)
        ws = torch.where(ws > 0, ws, torch.ones_like(ws))
        cs = (src * w).sum(-2, keepdim=True) / ws
        cd = (dst * w).sum(-2, keepdim=True) / ws
        H = ((src - cs) * w).transpose(-1, -2) @ (dst - cd)
    S = None
    if spread:
        R, S = _rotation_svd(H, spread=True)
    else:
        R = _rotation_of(H)
    t = cs.squeeze(-2) - (cd.squeeze(-2)[..., None, :] @ R.transpose(-1, -2)).squeeze(-2)
    return (R, t, S) if spread else (R, t)


def _rotation_svd(H: Tensor, spread: bool = False):
    """The proper rotation nearest H (..., 3, 3) (U diag(1, 1, det) V^T of its SVD)."""
    U, S, Vh = torch.linalg.svd(H)
    with torch.no_grad():
        d = torch.sign(torch.linalg.det(U @ Vh))
        d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.ones(H.shape[:-1], dtype=H.dtype, device=H.device)
    D = torch.cat((D[..., :2], d[..., None]), -1)
    R = (U * D[..., None, :]) @ Vh
    return (R, S) if spread else R


def _cofactor_det(X: Tensor) -> tuple[Tensor, Tensor]:
    """Cofactor matrix C (..., 3, 3) (rows: cross products of the other rows; X^{-T} = C / det)
    and det (...,) of 3x3 matrices, elementwise (no LAPACK call)."""
    a, b, c = X[..., 0, :], X[..., 1, :], X[..., 2, :]
    C = torch.stack(
        (torch.cross(b, c, dim=-1), torch.cross(c, a, dim=-1), torch.cross(a, b, dim=-1)), -2
    )
    return C, (a * C[..., 0, :]).sum(-1)


#: Newton steps of the polar decomposition (determinant-scaled; quadratic convergence: enough
#: for condition numbers up to ~1e6 in float64)
_POLAR_STEPS = 10


def _rotation_of(H: Tensor) -> Tensor:
    """The proper rotation nearest H (..., 3, 3): Kabsch's U diag(1, 1, sign det) V^T.

    Where det H > 0 and H is well conditioned, this is H's orthogonal polar factor, computed
    by the determinant-scaled Newton iteration X <- (g X + X^{-T} / g) / 2, g = |det X|^(-1/3)
    with closed-form 3x3 cofactors: elementwise tensor arithmetic, several times faster than a
    batched LAPACK SVD of many small matrices, and differentiable. Matrices with det H <= 0
    (a reflection to correct) or nearly singular (collinear points) take the SVD."""
    shape = H.shape
    Hf = H.reshape(-1, 3, 3)
    scale = Hf.flatten(1).norm(dim=-1).clamp_min(torch.finfo(H.dtype).tiny)
    X = Hf / scale[:, None, None]
    _, det0 = _cofactor_det(X)
    eps = 1e-4 if H.dtype == torch.float32 else 1e-9
    ok = det0 > eps
    X = torch.where(ok[:, None, None], X, torch.eye(3, dtype=H.dtype, device=H.device))
    for _ in range(_POLAR_STEPS):
        C, det = _cofactor_det(X)
        g = det.abs().clamp_min(torch.finfo(H.dtype).tiny) ** (-1.0 / 3.0)
        X = 0.5 * (g[:, None, None] * X + C / (g * det)[:, None, None])
    if not bool(ok.all()):
        bad = (~ok).nonzero().squeeze(-1)
        X = X.index_put((bad,), _rotation_svd(Hf[bad]))
    return X.reshape(shape)
