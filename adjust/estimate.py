"""What `adjust-track` learns from a session before it adjusts: the cameras' consensus, the
detector noise, the animal's size and how far each of its parts strays from the rigid body.

- `consensus`: robust triangulation of every part-frame; views the other cameras outvote are
  marked as mis-detections (dropped from the adjustment); the triangulated points whose views
  agree (reprojection error within a gate of the estimated detector noise) become the
  session's 3D observations of its parts, with their triangulation covariance.
- `deformation_moments`: per part and body axis, the second moment of the observed parts about
  their rigid model points at given poses (mean^2 + variance): the rigid model's prior.

Shapes: T frames, K parts, C cameras; mm, px.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from adjust.camera import CameraTensors
from adjust.lsq.geometry import (
    normal_blocks_3d,
    project_components,
    project_with_jacobian,
    rotation_gemm_weights,
    so3_exp,
)
from adjust.lsq.robust import kernel_weight
from adjust.lsq.stochastic import body_offsets, detector_sigma
from adjust.sym3 import sym3_inverse
from adjust.triangulate import triangulate
from deformnet.so3 import rodrigues_to_matrix

log = logging.getLogger(__name__)

MAX_ERROR_PX = 20.0  # robust triangulation: drop the worst view while it reprojects worse (px)
GATE_SIGMAS = 4.0  # a triangulated point is a 3D observation within this x the detector noise
RAYS_MIN_VIEWS = 10  # `place_from_rays` places a part from at least this many detections


@dataclass
class Consensus:
    """points (T, K, 3) mm robustly triangulated (NaN: < 2 agreeing views); observed (T, K)
    bool: gated 3D observations (>= 2 views, reprojection error within the gate); used
    (T, K, C) the views they rest on; dropped (T, K, C): detections outvoted by the other
    cameras; sigma_det_px (pooled) and sigma_det_per_camera (C,); noise_var (T, K) float32 mm^2
    the triangulation variance per axis (trace / 3 of its covariance; 1e6 where not observed);
    gate_px."""

    points: np.ndarray
    observed: np.ndarray
    used: np.ndarray
    dropped: np.ndarray
    sigma_det_px: float
    sigma_det_per_camera: np.ndarray
    noise_var: np.ndarray
    gate_px: float

    def facts(self, cameras) -> dict:
        return {
            "sigma_det_px": self.sigma_det_px,
            "sigma_det_px_per_camera": {
                c: (None if not math.isfinite(v) else float(v))
                for c, v in zip(cameras, self.sigma_det_per_camera)
            },
            "observed_3d_fraction": float(self.observed.mean()) if self.observed.size else 0.0,
            "outvoted_detections": int(self.dropped.sum()),
            "gate_px": self.gate_px,
        }


def consensus(
    xy: np.ndarray,
    weight: np.ndarray,
    cams: CameraTensors,
    max_error_px: float = MAX_ERROR_PX,
    gate_sigmas: float = GATE_SIGMAS,
    sigma_det_px: float | None = None,
) -> Consensus:
    """Robust triangulation, detector noise and gated 3D observations.

    xy (T, K, C, 2) px, NaN missing; weight (T, K, C) (0 = missing). A view is outvoted when
    >= 3 cameras saw the part and robust triangulation (drop the worst view while the point
    reprojects worse than ``max_error_px``) left it out. The detector noise is estimated from
    the residuals (`detector_sigma`) unless given; the gate is ``gate_sigmas`` x that noise
    (+ 1 px): the robust triangulation is repeated dropping views while one is off by more than
    the gate, and a triangulated point is an observation when every view it rests on is within
    the gate.
    """

    observed_views = np.isfinite(xy).all(-1) & (weight > 0)

    def robust(threshold: float):
        with torch.no_grad():
            tri = triangulate(
                torch.as_tensor(xy),
                torch.as_tensor(weight),
                cams,
                robust=True,
                max_error_px=threshold,
            )
        X = tri.points.numpy().astype(np.float64)
        used = tri.used.numpy()
        fin = np.isfinite(X).all(-1)
        dropped = observed_views & ~used & (tri.nviews.numpy() >= 3)[..., None] & fin[..., None]
        return tri, X, used, tri.view_error.numpy(), fin, dropped

    tri, X, used, ve, fin, dropped = robust(max_error_px)
    est, per = detector_sigma(ve, used)
    sig = float(sigma_det_px) if sigma_det_px else (est if math.isfinite(est) else 2.0)
    gate = gate_sigmas * sig + 1.0
    if gate < max_error_px:  # again, dropping views while any disagrees by more than the gate
        tri, X, used, ve, fin, dropped = robust(gate)
    worst = np.where(used, np.nan_to_num(ve, nan=np.inf), 0.0).max(-1)
    obs = fin & (tri.ncams.numpy() >= 2) & (worst <= gate)
    # triangulation variance: trace / 3 of (sum_c J^T J / sigma^2)^-1 over the used views,
    # in blocks of frames (bounded memory on long sessions), stored as float32 (T, K)
    W6, Wg = rotation_gemm_weights(cams.R)
    eye = torch.eye(3, dtype=torch.float64)
    T = X.shape[0]
    noise_var = np.full(obs.shape, 1e6, dtype=np.float32)
    for s0 in range(0, T, 20000):
        sl = slice(s0, min(T, s0 + 20000))
        Xt = torch.as_tensor(np.nan_to_num(X[sl]))
        u, v, _, A = project_components(Xt, cams, True)
        w = torch.as_tensor(used[sl] & obs[sl][..., None], dtype=Xt.dtype) / sig**2
        H, _ = normal_blocks_3d(A, torch.zeros_like(u), torch.zeros_like(v), w, W6, Wg)
        ob = torch.as_tensor(obs[sl])
        H = torch.where(ob[..., None, None], H, eye * 1e-6)
        cov = sym3_inverse(H + 1e-9 * eye)
        var = torch.diagonal(cov, dim1=-2, dim2=-1).sum(-1) / 3.0
        noise_var[sl] = np.where(obs[sl], var.numpy(), 1e6).astype(np.float32)
    log.info(
        "consensus: detector noise %.2f px (estimated %.2f), %.1f%% of part-frames observed in "
        "3D, %d detections outvoted by the other cameras",
        sig,
        est,
        100 * obs.mean() if obs.size else 0.0,
        int(dropped.sum()),
    )
    return Consensus(
        np.where(obs[..., None], X, np.nan), obs, used, dropped, sig, per, noise_var, gate
    )


def deformation_moments(
    poses: np.ndarray, X: np.ndarray, observed: np.ndarray, body: np.ndarray, floor_mm: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """Second moments (K, 3) mm^2 per body axis of the observed parts about the rigid model
    points at ``poses`` (T, 6) (mean^2 + variance of the body-frame offsets), and the offsets'
    means (K, 3). A part never observed gets the largest moment of the others."""

    R = rodrigues_to_matrix(torch.as_tensor(poses[:, :3], dtype=torch.float64)).numpy()
    o = body_offsets(R, poses[:, 3:], np.where(observed[..., None], X, np.nan), body)
    m = observed & np.isfinite(o).all(-1)
    n = m.sum(0)
    z = np.where(m[..., None], o, 0.0)
    mean = z.sum(0) / np.maximum(n, 1)[:, None]
    mom = (z**2).sum(0) / np.maximum(n, 1)[:, None]
    if (n > 0).any():  # never observed in 3D: much less certain than any observed part
        mom[n == 0] = 4.0 * mom[n > 0].max(0)
    else:
        mom[:] = 100.0  # nothing observed in 3D: 10 mm per axis, and say so elsewhere
    return np.maximum(mom, floor_mm**2), mean


@dataclass
class RayPlacement:
    """Parts placed on the body from their single views (`place_from_rays`).

    points (K, 3) mm: the body model with the placed parts moved; var (K, 3) mm^2 per body axis:
    a placed part's spread about its model point (deformation beyond the detector noise, plus
    the placement's own uncertainty; the input ``var`` elsewhere); placed (K,) bool; views (K,)
    the detections each placement rests on; rms_px (K,) their robust rms residual (NaN where
    not placed)."""

    points: np.ndarray
    var: np.ndarray
    placed: np.ndarray
    views: np.ndarray
    rms_px: np.ndarray


def place_from_rays(
    poses: np.ndarray,
    xy: np.ndarray,
    weight: np.ndarray,
    cams: CameraTensors,
    body_points: np.ndarray,
    var: np.ndarray,
    which: np.ndarray,
    sigma_px: float,
    prior_sd_mm: float,
    min_views: int = RAYS_MIN_VIEWS,
    iterations: int = 20,
    kernel_scale: float = 3.0,
) -> RayPlacement:
    """Locate parts in the body frame from their detections across frames at known poses.

    A part that no two cameras see together has no 3D observation, so a body model built from
    triangulated parts (`BodyModel.from_observations`) cannot place it. Its detections still
    constrain it: in the body frame the part is (nearly) fixed while the body moves in front of
    the cameras, so each detection is a ray through the body frame and the rays of many
    frames meet near the part. Per part k with ``which[k]`` and >= ``min_views`` detections,
    this minimises over the body-frame point B_k

        sum_{t,c} rho(|x_tkc - proj_c(R_t B_k + tau_t)|^2 / sigma^2) + |B_k - B0_k|^2 / s^2

    (Gauss-Newton, Cauchy kernel at ``kernel_scale`` sigma against mis-detections), the weak
    prior (B0 = ``body_points``, s = ``prior_sd_mm``) holding the directions the rays leave open
    (a body that stands still in front of one camera sees a part along one ray). The part's
    spread about its point, per body axis: the robust residual variance beyond the detector noise
    (median |e|^2 / (2 ln 2) - sigma^2, in mm at each view's depth), plus the placement's own
    variance (the inverse normal matrix).

    poses (T, 6) model -> global (Rodrigues rad, mm); xy (T, K, C, 2) px, NaN missing; weight
    (T, K, C) (0 = missing); body_points (K, 3) mm; var (K, 3) mm^2 (kept where not placed);
    which (K,) bool -> `RayPlacement`.
    """

    xy = np.asarray(xy, dtype=np.float64)
    T, K, C, _ = xy.shape
    if np.shape(poses) != (T, 6) or np.shape(body_points) != (K, 3) or np.shape(var) != (K, 3):
        raise ValueError(
            f"poses {np.shape(poses)} must be ({T}, 6), body_points {np.shape(body_points)} and "
            f"var {np.shape(var)} ({K}, 3) for xy {xy.shape}"
        )
    if np.shape(weight) != (T, K, C) or np.shape(which) != (K,):
        raise ValueError(f"weight must be ({T}, {K}, {C}) and which ({K},)")
    valid = np.isfinite(xy).all(-1) & (np.nan_to_num(np.asarray(weight, np.float64)) > 0)
    views = valid.sum((0, 2))
    todo = np.flatnonzero(np.asarray(which, bool) & (views >= min_views))
    points = np.array(body_points, dtype=np.float64)
    out_var = np.array(var, dtype=np.float64)
    placed = np.zeros(K, dtype=bool)
    rms = np.full(K, np.nan)
    if todo.size == 0:
        return RayPlacement(points, out_var, placed, views, rms)
    dt = torch.float64
    R = so3_exp(torch.as_tensor(poses[:, :3], dtype=dt))  # (T, 3, 3)
    tau = torch.as_tensor(poses[:, 3:], dtype=dt)
    x = torch.as_tensor(np.nan_to_num(xy[:, todo]), dtype=dt)  # (T, P, C, 2)
    ok = torch.as_tensor(valid[:, todo])
    B0 = torch.as_tensor(points[todo], dtype=dt)  # (P, 3)
    B = B0.clone()
    s2 = float(prior_sd_mm) ** 2
    eye = torch.eye(3, dtype=dt)

    def normal_equations(B: Tensor):
        """Residuals e (T, P, C, 2) px, depths z, the views used, and the robust normal
        equations H (P, 3, 3), g (P, 3) of the placement at B (P, 3)."""
        X = torch.einsum("tij,pj->tpi", R, B) + tau[:, None]
        uv, J, z = project_with_jacobian(X, cams)  # (T, P, C, 2), (T, P, C, 2, 3), (T, P, C)
        JB = J @ R[:, None, None]  # d uv / d B
        e = x - uv
        use = ok & (z > 0) & torch.isfinite(e).all(-1)
        e = torch.where(use[..., None], e, torch.zeros_like(e))
        u = e.norm(dim=-1) / sigma_px
        w = use.to(dt) * kernel_weight(u, "cauchy", kernel_scale) / sigma_px**2
        H = torch.einsum("tpc,tpcai,tpcaj->pij", w, JB, JB) + eye / s2
        g = torch.einsum("tpc,tpcai,tpca->pi", w, JB, e) - (B - B0) / s2
        return e, z, use, H, g

    for _ in range(iterations):
        _, _, _, H, g = normal_equations(B)
        step = torch.linalg.solve(H, g[..., None])[..., 0]
        B = B + step
        if float(step.abs().max()) < 1e-4:
            break
    e, z, use, H, _ = normal_equations(B)
    cov_B = torch.linalg.inv(H)  # (P, 3, 3) in body axes
    focal = cams.focal.to(dt)  # (C,)
    mm_per_px2 = (z / focal) ** 2  # (T, P, C)
    e2 = (e**2).sum(-1)
    for i, k in enumerate(todo):
        m = use[:, i]
        if int(m.sum()) < min_views:
            continue
        s2_px = float(e2[:, i][m].median()) / (2.0 * math.log(2.0))  # per image axis
        scale = float(mm_per_px2[:, i][m].median())
        def_var = max(s2_px - sigma_px**2, 0.0) * scale
        points[k] = B[i].numpy()
        out_var[k] = np.maximum(def_var + np.diag(cov_B[i].numpy()), 0.25)
        placed[k] = True
        rms[k] = math.sqrt(2.0 * s2_px)
    return RayPlacement(points, out_var, placed, views, rms)
