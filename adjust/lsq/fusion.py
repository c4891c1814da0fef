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

from torch import Tensor

from adjust.camera import CameraTensors
from adjust.lsq.geometry import (
    normal_blocks_3d,
    project_components,
    rotation_gemm_weights,
    sym3_inverse,
)


def fuse_points(
    X_model: Tensor,
    prior_cov: Tensor,
    xy: Tensor,
    w: Tensor,
    cams: CameraTensors,
    iterations: int = 2,
    W6: Tensor | None = None,
    Wg: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Fuse detections with model points.

    X_model: (T, K, 3) mm; prior_cov: (T, K, 3, 3) mm^2 (positive definite); xy: (T, K, C, 2) px
    (any finite value where w = 0); w: (T, K, C) inverse variances px^-2 (0 = no detection)
    -> X (T, K, 3) mm, cov (T, K, 3, 3) mm^2. W6, Wg: `rotation_gemm_weights(cams.R)` (optional).
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
        X = X + (sym3_inverse(A) @ b[..., None])[..., 0]
    return X, sym3_inverse(A)
