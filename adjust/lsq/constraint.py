"""Motion-track constraint (paper eq. 10) in two forms, with analytic Jacobians.

For every interior frame t (2 <= t <= T-3) the pose p_t = (R_t, tau_t) is compared with the
cubic through its neighbours t-2, t-1, t+1, t+2 evaluated at t, i.e. the weighted sum with
weights w = (-1/6, 2/3, 2/3, -1/6) (a residual proportional to the fourth difference).
Rotations are interpolated relative to R_t, never as raw Rodrigues vectors: with
phi_s = log(R_s R_t^T) (small for neighbouring frames), phi_S = sum_s w_s phi_s is the
interpolated rotation relative to R_t, so R_S = exp(phi_S) R_t and tau_S = sum_s w_s tau_s
form the interpolated transform S_t. This is exact (zero residual) for translations cubic in t
and for rotations at a constant rate about a fixed axis, whatever the angle (through pi and
beyond), as long as the rotation between neighbouring frames stays below pi/2.

- ``spline``: residual (rho (0 - phi_S), tau_t - tau_S), 6 per frame; rho (mm/rad) puts the
  rotation part into mm at the body's scale.
- ``grid``: the paper's better option: a g^3 grid of points G around the body's centre (model
  frame, covering the body) moved by H_t and by S_t; the residual is the root-mean-square of
  H_t G - S_t G over the grid (= moving the grid S_t G by H_t S_t^-1 and comparing with itself).
  With A = (I - exp(phi_S)) R_t, b = tau_t - tau_S, grid centre c and M = sum_g o_g o_g^T =
  diag(m) of the offsets, mean_g |A G_g + b|^2 = |A c + b|^2 + sum_j (m_j / N) |A e_j|^2 exactly,
  so 12 residuals (A c + b, sqrt(m_j / N) A e_j) carry the whole grid's sum of squares.

Frame boundaries: frames t < 2 and t > T-3 get no residual of their own (a one-sided cubic
extrapolation residual is a multiple of the first/last interior one, so it would only double
its weight); they are still constrained through their neighbours' residuals, which is exactly
the one-sided cubic extrapolation. With T < 5 there is no track constraint.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from adjust.lsq.geometry import (
    left_jacobian,
    left_jacobian_inverse,
    quat_conj,
    quat_from_rotvec,
    quat_mul,
    rotvec_from_quat,
    so3_exp,
)
from deformnet.so3 import skew

SPLINE_WEIGHTS = (-1.0 / 6.0, 2.0 / 3.0, 2.0 / 3.0, -1.0 / 6.0)
OFFSETS = (-2, -1, 1, 2)
SPAN = 5  # frames per residual group (t-2..t+2)


def make_grid(body: Tensor, size: int = 3, margin: float = 0.0) -> Tensor:
    """A size^3 axis-aligned grid (model frame) centred at the body's centroid, spanning the
    body's bounding box (plus `margin` mm each side).  body (K, 3) -> (size^3, 3)."""
    if body.dim() != 2 or body.shape[-1] != 3:
        raise ValueError(f"body must have shape (K, 3), got {tuple(body.shape)}")
    c = body.mean(0)
    half = (body.max(0).values - body.min(0).values) / 2 + margin
    half = torch.where(half > 1e-6, half, torch.full_like(half, 1.0))
    lin = torch.linspace(-1.0, 1.0, size, dtype=body.dtype, device=body.device)
    g = torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij"), -1).reshape(-1, 3)
    return c + g * half


def grid_moments(grid: Tensor) -> tuple[Tensor, Tensor]:
    """Centre c (3,) and sqrt(m_j / N) (3,) of a grid symmetric about its centre.  (N, 3)."""
    c = grid.mean(0)
    o = grid - c
    M = o.T @ o
    if (M - torch.diag(torch.diagonal(M))).abs().max() > 1e-9 * (1 + M.abs().max()):
        raise ValueError("grid offsets must be axis-aligned (diagonal second moment)")
    return c, (torch.diagonal(M) / grid.shape[0]).sqrt()


def _relative(poses: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per interior frame: R_t (R, 3, 3), phi_s (4, R, 3), tau_t (R, 3), tau_S (R, 3)."""
    T = poses.shape[0]
    n = T - 4
    q = quat_from_rotvec(poses[:, :3])
    qt_inv = quat_conj(q[2 : 2 + n])
    Rt = so3_exp(poses[2 : 2 + n, :3])
    phi = torch.stack([rotvec_from_quat(quat_mul(q[2 + o : 2 + o + n], qt_inv)) for o in OFFSETS])
    w = torch.tensor(SPLINE_WEIGHTS, dtype=poses.dtype, device=poses.device)
    tau_s = torch.stack([poses[2 + o : 2 + o + n, 3:] for o in OFFSETS])
    tau_S = (w[:, None, None] * tau_s).sum(0)
    return Rt, phi, poses[2 : 2 + n, 3:], tau_S


def track_residuals(
    poses: Tensor,
    kind: str,
    *,
    rho: float = 1.0,
    grid: Tensor | None = None,
    jacobian: bool = True,
) -> tuple[Tensor, Tensor | None]:
    """Track-constraint residuals (mm) of the interior frames and their Jacobian blocks.

    poses: (T, 6). kind: 'spline' (rho: mm per rad) or 'grid' (grid: (N, 3) model-frame points,
    symmetric and axis-aligned about its centre, e.g. `make_grid`).
    Returns r (R, m) with R = max(T - 4, 0) groups for frames t = 2..T-3 (m = 6 spline, 12 grid)
    and, if `jacobian`, J (R, 5, m, 6): J[i, a] = d r[i] / d delta_{i + a} (left increments of
    the poses of frames i..i+4).
    """
    if poses.dim() != 2 or poses.shape[-1] != 6:
        raise ValueError(f"poses must have shape (T, 6), got {tuple(poses.shape)}")
    if kind not in ("spline", "grid"):
        raise ValueError(f"kind must be 'spline' or 'grid', got {kind!r}")
    T = poses.shape[0]
    m = 6 if kind == "spline" else 12
    dt, dev = poses.dtype, poses.device
    if T < SPAN:
        return poses.new_zeros((0, m)), (poses.new_zeros((0, SPAN, m, 6)) if jacobian else None)
    n = T - 4
    w = torch.tensor(SPLINE_WEIGHTS, dtype=dt, device=dev)
    Rt, phi, tau_t, tau_S = _relative(poses)
    phi_S = (w[:, None, None] * phi).sum(0)  # (R, 3)
    eye = torch.eye(3, dtype=dt, device=dev)
    if kind == "spline":
        r = torch.cat((-rho * phi_S, tau_t - tau_S), -1)
        if not jacobian:
            return r, None
        J = poses.new_zeros((n, SPAN, 6, 6))
        Jl_inv = left_jacobian_inverse(phi)  # (4, R, 3, 3) d phi_s / d delta_s
        Jr_inv = Jl_inv.transpose(-1, -2)  # J_r^-1 = J_l^-1(-phi) = J_l^-1^T: -d phi_s / d delta_t
        for j, o in enumerate(OFFSETS):
            J[:, 2 + o, :3, :3] = -rho * w[j] * Jl_inv[j]
            J[:, 2 + o, 3:, 3:] = -w[j] * eye
        J[:, 2, :3, :3] = rho * (w[:, None, None, None] * Jr_inv).sum(0)
        J[:, 2, 3:, 3:] = eye
        return r, J
    if grid is None:
        raise ValueError("kind='grid' needs the grid points")
    c, sq = grid_moments(grid.to(dt))
    E = so3_exp(phi_S)  # (R, 3, 3)
    V = torch.cat((c[None], torch.diag(sq)), 0)  # (4, 3): model vectors c, sqrt(m_j/N) e_j
    a = torch.einsum("rij,vj->vri", Rt, V)  # (4, R, 3) R_t v
    Ea = torch.einsum("rij,vrj->vri", E, a)
    Av = a - Ea  # (4, R, 3)
    Av[0] = Av[0] + (tau_t - tau_S)
    r = Av.permute(1, 0, 2).reshape(n, 12)
    if not jacobian:
        return r, None
    Jl_inv = left_jacobian_inverse(phi)  # (4, R, 3, 3): d phi_s / d delta_s
    Jr_inv = Jl_inv.transpose(-1, -2)  # J_r^-1 = J_l^-1(-phi) = J_l^-1^T: -d phi_s / d delta_t
    # d phi_S / d delta for the five frames (rotation columns), premultiplied by J_l(phi_S)
    Dphi = poses.new_zeros((n, SPAN, 3, 3))
    Dphi[:, 2] = -(w[:, None, None, None] * Jr_inv).sum(0)
    for j, o in enumerate(OFFSETS):
        Dphi[:, 2 + o] = w[j] * Jl_inv[j]
    GD = left_jacobian(phi_S)[:, None] @ Dphi  # (R, 5, 3, 3)
    # d(A v) = [E a]_x J_l(phi_S) d phi_S + (E - I) [a]_x delta_t, for the 4 model vectors v
    Ea_b = Ea.permute(1, 0, 2)[:, None, :, :, None].expand(n, SPAN, 4, 3, 3)
    GD_b = GD[:, :, None].expand(n, SPAN, 4, 3, 3)
    Jrot = torch.linalg.cross(Ea_b, GD_b, dim=-2)  # (R, 5, 4, 3, 3)
    Sa = skew(a)  # (4, R, 3, 3)
    Jrot[:, 2] += (E @ Sa - Sa).permute(1, 0, 2, 3)
    J = poses.new_zeros((n, SPAN, 4, 3, 6))
    J[..., :3] = Jrot
    for j, o in enumerate(OFFSETS):
        J[:, 2 + o, 0, :, 3:] = -w[j] * eye
    J[:, 2, 0, :, 3:] = eye
    return r, J.reshape(n, SPAN, 12, 6)


def default_rho(body: Tensor) -> float:
    """mm per radian for the spline form's rotation residuals: the body's rms radius."""
    c = body.mean(0)
    return float(math.sqrt(((body - c) ** 2).sum(-1).mean()))


def _skew_cols(u: Tensor, M: Tensor) -> Tensor:
    """[u]_x M without building [u]_x.  u (..., 3), M (..., 3, n) -> (..., 3, n)."""
    u0, u1, u2 = (u[..., i, None] for i in range(3))
    m0, m1, m2 = M[..., 0, :], M[..., 1, :], M[..., 2, :]
    return torch.stack((u1 * m2 - u2 * m1, u2 * m0 - u0 * m2, u0 * m1 - u1 * m0), -2)


def add_track_normal(
    blocks: np.ndarray,
    g: np.ndarray,
    poses: Tensor,
    kind: str,
    weight: float,
    *,
    rho: float = 1.0,
    grid: Tensor | None = None,
) -> Tensor:
    """Add the track constraint's weighted normal matrix and gradient, exploiting its structure.

    Same result as assembling J^T (weight I) J and -weight J^T r from `track_residuals`, but the
    rotation columns are handled through the 3-row rotation Jacobian d phi_S / d delta and the
    translation columns through their constant coefficients, so nothing of size (R, 30, 30) is
    ever formed. blocks: (5, T, 6, 6) band (in place); g: (T, 6) right-hand side (in place);
    poses (T, 6). Returns the residuals r (R, m).
    """
    T = poses.shape[0]
    if T < SPAN or weight == 0:
        r, _ = track_residuals(poses, kind, rho=rho, grid=grid, jacobian=False)
        return r
    dt, dev = poses.dtype, poses.device
    n = T - 4
    w = torch.tensor(SPLINE_WEIGHTS, dtype=dt, device=dev)
    ct = (1.0 / 6.0, -2.0 / 3.0, 1.0, -2.0 / 3.0, 1.0 / 6.0)  # d tau-residual / d tau_b
    Rt, phi, tau_t, tau_S = _relative(poses)
    phi_S = (w[:, None, None] * phi).sum(0)
    Jl_inv = left_jacobian_inverse(phi)
    Jr_inv = Jl_inv.transpose(-1, -2)  # J_r^-1(phi) = J_l^-1(-phi) = J_l^-1(phi)^T
    D = torch.stack(
        (
            w[0] * Jl_inv[0],
            w[1] * Jl_inv[1],
            -(w[:, None, None, None] * Jr_inv).sum(0),
            w[2] * Jl_inv[2],
            w[3] * Jl_inv[3],
        ),
        1,
    )  # (R, 5, 3, 3): d phi_S / d delta_b
    eye = torch.eye(3, dtype=dt, device=dev)
    N = Cc = Jc = None
    if kind == "spline":
        r_rot = -rho * phi_S
        r_tr = tau_t - tau_S
        r = torch.cat((r_rot, r_tr), -1)
        P = D
        S = (rho * rho) * eye.expand(n, 3, 3)
        grad_rot = P.transpose(-1, -2) @ (-rho * r_rot)[:, None, :, None]  # J_rot^T r, (R,5,3,1)
        r_c = r_tr
    elif kind == "grid":
        if grid is None:
            raise ValueError("kind='grid' needs the grid points")
        c, sq = grid_moments(grid.to(dt))
        E = so3_exp(phi_S)
        V = torch.cat((c[None], torch.diag(sq)), 0)  # (4, 3)
        a = torch.einsum("rij,vj->rvi", Rt, V)  # (R, 4, 3)
        Ea = torch.einsum("rij,rvj->rvi", E, a)
        Av = a - Ea
        Av[:, 0] = Av[:, 0] + (tau_t - tau_S)
        r = Av.reshape(n, 12)
        P = left_jacobian(phi_S)[:, None] @ D  # (R, 5, 3, 3)
        # B_v = [E a_v]_x; corr_v = (E - I)[a_v]_x (frame-t extra term)
        u = Ea  # (R, 4, 3)
        uu = (u * u).sum(-1)  # (R, 4)
        S = torch.diag_embed(uu.sum(1)[:, None].expand(n, 3)) - torch.einsum("rvi,rvj->rij", u, u)
        Sa = skew(a.reshape(-1, 3)).reshape(n, 4, 3, 3)
        corr = E[:, None] @ Sa - Sa  # (R, 4, 3, 3)
        BtC = -_skew_cols(u, corr)  # B_v^T corr_v = -[u_v]_x corr_v
        N = BtC.sum(1)
        Cc = (corr.transpose(-1, -2) @ corr).sum(1)
        Btr = torch.linalg.cross(Av, u, dim=-1).sum(1)[..., None]  # sum_v B_v^T r_v, (R, 3, 1)
        grad_rot = P.transpose(-1, -2) @ Btr[:, None]  # (R, 5, 3, 1)
        grad_rot[:, 2] += (corr.transpose(-1, -2) @ Av[..., None]).sum(1)
        Jc = _skew_cols(u[:, None, 0], P)  # (R, 5, 3, 3): rotation Jacobian of rows 0..2
        Jc[:, 2] += corr[:, 0]
        r_c = Av[:, 0]
    else:
        raise ValueError(f"kind must be 'spline' or 'grid', got {kind!r}")
    wt = float(weight)
    Sw = wt * S
    P5 = P.permute(1, 0, 2, 3).contiguous()  # (5, R, 3, 3)
    Pt5 = P5.transpose(-1, -2)
    ctt = torch.tensor(ct, dtype=dt, device=dev)
    bt = torch.from_numpy(blocks)
    if Jc is not None:
        Jc5 = (wt * Jc).permute(1, 0, 2, 3).contiguous()  # (5, R, 3 row, 3 rot)
        Nw_t = wt * N.transpose(-1, -2)
        Nw = wt * N
    tt = (wt * ctt[:, None] * ctt[None, :])[..., None, None] * torch.eye(3, dtype=dt, device=dev)
    tmp = poses.new_empty((SPAN, n, 6, 6))
    for ic in range(SPAN):  # column frame ic, row frames ia = ic..4 -> offsets 0..4-ic
        m = SPAN - ic
        blk = tmp[:m]
        # rotation-rotation: P_a^T S P_ic (+ frame-t corrections), a = ic..4
        torch.matmul(Pt5[ic:], (Sw @ P5[ic])[None], out=blk[..., :3, :3])
        if N is not None:
            if ic <= 2:  # row frame t: N^T P_ic
                blk[2 - ic, :, :3, :3] += Nw_t @ P5[ic]
            if ic == 2:  # column frame t: P_a^T N, and the (t, t) block's C
                blk[..., :3, :3] += Pt5[2:] @ Nw[None]
                blk[0, :, :3, :3] += wt * Cc
        if Jc is not None:  # rot(ia) x trans(ic): ct_ic Jc_ia^T; trans(ia) x rot(ic): ct_ia Jc_ic
            torch.mul(Jc5[ic:].transpose(-1, -2), ct[ic], out=blk[..., :3, 3:])
            torch.mul(Jc5[ic][None], ctt[ic:, None, None, None], out=blk[..., 3:, :3])
        else:
            blk[..., :3, 3:] = 0.0
            blk[..., 3:, :3] = 0.0
        blk[..., 3:, 3:] = tt[ic:, ic, None]
        bt[:m, ic : ic + n] += blk
    gt = torch.from_numpy(g)
    for ia in range(SPAN):
        gt[ia : ia + n, :3] -= wt * grad_rot[:, ia, :, 0]
        gt[ia : ia + n, 3:] -= (wt * ct[ia]) * r_c
    return r
