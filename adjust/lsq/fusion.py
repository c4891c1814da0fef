"""Part-position fusion: each frame's own detections of a part combined with the model.

Per part and frame, minimise over X in R^3
    sum_c w_c |x_c - proj_c(X)|^2 + (X - X_model)^T P^-1 (X - X_model),
with w_c = detection weight / sigma_det^2 (robust weights included) and the prior covariance
P = sigma_def^2 I + J_X Sigma_p J_X^T (unmodelled deformation plus the pose's uncertainty
propagated to the part). A few Gauss-Newton steps from X_model, each a batched 3x3 solve; the
covariance of the result is the inverse of the final 3x3 normal matrix. A part seen well by two
or more cameras gets (at least) its triangulation's accuracy; an occluded part falls back to
the model with the model's uncertainty.
"""

from __future__ import annotations

import torch
from torch import Tensor

from adjust.camera import CameraTensors, project_cameras
from adjust.lsq.geometry import (
    normal_blocks_3d,
    project_components,
    project_with_jacobian,
    rotation_gemm_weights,
)
from adjust.sym3 import sym3_inverse

#: chi-square (2 dof) gate of a detection's innovation: tail probability 0.001
GATE_CHI2 = 13.8


def fuse_points(
    X_model: Tensor,
    prior_cov: Tensor,
    xy: Tensor,
    w: Tensor,
    cams: CameraTensors,
    iterations: int = 2,
    W6: Tensor | None = None,
    Wg: Tensor | None = None,
    tol: float | None = None,
) -> tuple[Tensor, Tensor]:
    """Fuse detections with model points.

    X_model: (T, K, 3) mm; prior_cov: (T, K, 3, 3) mm^2 (positive definite); xy: (T, K, C, 2) px
    (any finite value where w = 0); w: (T, K, C) inverse variances px^-2 (0 = no detection)
    -> X (T, K, 3) mm, cov (T, K, 3, 3) mm^2. W6, Wg: `rotation_gemm_weights(cams.R)` (optional).
    ``iterations`` Gauss-Newton steps, or with ``tol`` (mm) up to that many, until no point
    moves by more than ``tol`` (run to convergence).
    """
    T, K, C, _ = xy.shape
    if X_model.shape != (T, K, 3) or prior_cov.shape != (T, K, 3, 3) or w.shape != (T, K, C):
        raise ValueError(
            f"shapes: X_model {tuple(X_model.shape)}, prior_cov {tuple(prior_cov.shape)}, "
            f"xy {tuple(xy.shape)}, w {tuple(w.shape)}"
        )
    if W6 is None or Wg is None:
        W6, Wg = rotation_gemm_weights(cams.R)
    Pinv = sym3_inverse(prior_cov)
    X = X_model.clone()
    A = Pinv
    for _ in range(max(iterations, 1)):
        u, v, _, Ac = project_components(X, cams, True)
        H, g = normal_blocks_3d(Ac, xy[..., 0] - u, xy[..., 1] - v, w, W6, Wg)
        A = Pinv + H
        b = g - (Pinv @ (X - X_model)[..., None])[..., 0]
        step = (sym3_inverse(A) @ b[..., None])[..., 0]
        X = X + step
        if tol is not None and (
            not bool(torch.isfinite(step).all()) or float(step.abs().max()) < tol
        ):
            break
    if tol is not None:  # the covariance at the converged point
        return X, posterior_cov(X, Pinv, xy, w, cams, W6, Wg)
    return X, sym3_inverse(A)


def posterior_cov(
    X: Tensor,
    prior_inv: Tensor,
    xy: Tensor,
    w: Tensor,
    cams: CameraTensors,
    W6: Tensor,
    Wg: Tensor,
) -> Tensor:
    """The covariance (T, K, 3, 3) mm^2 of fused points X (T, K, 3) mm: the inverse of the
    prior's information ``prior_inv`` (T, K, 3, 3) mm^-2 plus the detections' (xy (T, K, C, 2)
    px, w (T, K, C) px^-2; W6, Wg: `rotation_gemm_weights(cams.R)`) linearised at X."""
    u, v, _, Ac = project_components(X, cams, True)
    H, _ = normal_blocks_3d(Ac, xy[..., 0] - u, xy[..., 1] - v, w, W6, Wg)
    return sym3_inverse(prior_inv + H)


#: candidate inflation factors of a prior covariance (`prior_inflation`)
INFLATIONS = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 13.0, 16.0, 20.0, 25.0)


def prior_inflation(
    X_prior: Tensor,
    prior_cov: Tensor,
    xy: Tensor,
    use: Tensor,
    cams: CameraTensors,
    sigma_px: float,
    min_count: int = 30,
) -> Tensor:
    """Per part, the factor alpha >= 1 on the prior covariance that makes the prior agree with
    the data: the mean over the detections ``use`` (T, K, C) (e.g. the single views, which
    are independent of the prior) of the innovation's squared Mahalanobis distance under
    S = alpha J P J^T + sigma^2 I, each clipped at 30 so that gross mis-detections do not
    count, is at most the chi-square (2 dof) mean, 2 (the smallest candidate alpha that gets
    there). Parts with fewer than ``min_count`` such detections keep 1. Returns (K,)."""
    uv, J, _ = project_with_jacobian(X_prior, cams)
    JPJ = J @ prior_cov[..., None, :, :] @ J.transpose(-1, -2)  # (T, K, C, 2, 2)
    e = torch.where(use[..., None], xy - uv, torch.zeros_like(uv))
    K = use.shape[1]
    out = torch.ones(K, dtype=X_prior.dtype)
    eye = torch.eye(2, dtype=JPJ.dtype)
    for k in range(K):
        m = use[:, k]
        if int(m.sum()) < min_count:
            continue
        Pk, ek = JPJ[:, k][m], e[:, k][m]
        best = None
        for a in INFLATIONS:
            S = a * Pk + sigma_px**2 * eye
            d2 = (ek[..., None, :] @ torch.linalg.solve(S, ek[..., None]))[..., 0, 0]
            stat = float(d2.clamp_max(30.0).mean())
            best = a
            if stat <= 2.0:
                break
        out[k] = best
    return out


def innovation_gate(
    X_prior: Tensor,
    prior_cov: Tensor,
    xy: Tensor,
    valid: Tensor,
    cams: CameraTensors,
    sigma_px: float | Tensor,
    chi2: float = GATE_CHI2,
    agree: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Which detections agree with the part's predicted position (its own track and model).

    X_prior (T, K, 3) mm with covariance prior_cov (T, K, 3, 3); xy (T, K, C, 2) px; valid
    (T, K, C) bool; sigma_px: detector noise (scalar or (C,)). The innovation of a detection,
    e = xy - proj(X_prior), has covariance S = J P J^T + sigma^2 I (J = d proj / dX); it passes
    when e^T S^-1 e <= chi2. Cameras that agree with each other outvote the prediction: a
    part-frame whose detections all fail although >= 2 of them agree keeps those. agree
    (T, K, C) bool, optional: the views known to agree (e.g. a consensus triangulation's,
    `adjust.estimate.consensus`); without it any >= 2 failing detections count as agreeing,
    a correct view and a far outlier, or two unrelated far outliers, included (fused, such a
    part-frame is tens of mm off: `benchmarks/real_motion.py --split val`, 3 cameras, 4
    detector seeds, RMSE all 4.57 mm with every pair outvoting, 4.33 with the consensus').
    Returns (accepted (T, K, C) bool, d2 (T, K, C) the squared Mahalanobis distances).
    """
    uv, J, _ = project_with_jacobian(X_prior, cams)  # (T, K, C, 2), (T, K, C, 2, 3)
    S = J @ prior_cov[..., None, :, :] @ J.transpose(-1, -2)
    s2 = torch.as_tensor(sigma_px, dtype=S.dtype, device=S.device) ** 2
    s2 = s2.expand(S.shape[-3]) if s2.dim() == 1 else s2
    S = S + (s2[..., None, None] if s2.dim() else s2) * torch.eye(2, dtype=S.dtype, device=S.device)
    e = torch.where(valid[..., None], xy - uv, torch.zeros_like(uv))
    a, b, d = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
    det = (a * d - b * b).clamp_min(1e-300)
    d2 = (d * e[..., 0] ** 2 - 2 * b * e[..., 0] * e[..., 1] + a * e[..., 1] ** 2) / det
    ok = valid & (d2 <= chi2)
    voters = valid if agree is None else valid & agree.to(torch.bool)
    outvoted = (voters.sum(-1, keepdim=True) >= 2) & ~ok.any(-1, keepdim=True)
    return ok | (voters & outvoted), torch.where(valid, d2, torch.full_like(d2, float("nan")))


def held_out_view_errors(
    X_prior: Tensor,
    prior_cov: Tensor,
    xy: Tensor,
    accepted: Tensor,
    cams: CameraTensors,
    sigma_px: float,
    min_others: int = 1,
    prior_without=None,
) -> Tensor:
    """How well a prior predicts views it did not use: per camera c, every part-frame with an
    accepted view in c and >= ``min_others`` accepted views in the other cameras is fused
    (`fuse_points`, to convergence) from the prior and those other views alone, projected into
    c, and compared with c's detection.

    X_prior (T, K, 3) mm, prior_cov (T, K, 3, 3) mm^2, xy (T, K, C, 2) px (any finite value
    where not accepted), accepted (T, K, C) bool, sigma_px the detector noise ->
    (T, K, C) px, NaN where not evaluated. ``prior_without(c) -> (X_prior, prior_cov)``
    (optional): a prior built without camera c's detections, so that c is truly held out.
    """
    T, K, C, _ = xy.shape
    if accepted.shape != (T, K, C) or X_prior.shape != (T, K, 3):
        raise ValueError(
            f"shapes: X_prior {tuple(X_prior.shape)}, accepted {tuple(accepted.shape)}, "
            f"xy {tuple(xy.shape)}"
        )
    out = torch.full((T, K, C), float("nan"), dtype=X_prior.dtype)
    for c in range(C):
        others = accepted.clone()
        others[..., c] = False
        ask = accepted[..., c] & (others.sum(-1) >= min_others)
        if not bool(ask.any()):
            continue
        Xp, Pp = (X_prior, prior_cov) if prior_without is None else prior_without(c)
        w = others.to(X_prior.dtype) / sigma_px**2
        X, _ = fuse_points(Xp, Pp, xy, w, cams, 50, tol=1e-4)
        uv = project_cameras(X, cams)[:, :, c]
        e = (uv - xy[:, :, c]).norm(dim=-1)
        out[..., c] = torch.where(ask, e, out[..., c])
    return out
