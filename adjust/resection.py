"""Spatial resection (paper eq. 1): a camera from known 3D points and their image points.

``x_i ~ P G_i``: with unknown intrinsics, P comes from >= 6 non-coplanar points by the
normalized direct linear transform (DLT), is split into K, R, t (eq. 2,
`adjust.camera.decompose_projection_matrix`) and refined by Levenberg-Marquardt on the pixel
reprojection error over fx, fy, cx, cy (skew optional), the rotation vector, t and optional
distortion coefficients. With known intrinsics (and distortion) >= 4 points suffice:
``cv2.solvePnP`` gives the start, the same LM refines r, t.

Shapes: N points; `dlt` is batched over leading dims. Units: mm, px, radians.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from adjust.camera import Camera, decompose_projection_matrix, project_points, undistort_points
from adjust.lsq import lm
from deformnet.so3 import matrix_to_rodrigues, rodrigues_to_matrix

log = logging.getLogger(__name__)

DIST_NAMES = ("k1", "k2", "p1", "p2", "k3")


def _normalizer(pts: Tensor) -> Tensor:
    """Hartley similarity T (..., d+1, d+1): centroid to 0, mean distance sqrt(d)."""
    d = pts.shape[-1]
    c = pts.mean(-2)
    s = (pts - c[..., None, :]).norm(dim=-1).mean(-1).clamp_min(1e-300)
    scale = (d**0.5) / s
    T = torch.zeros(*pts.shape[:-2], d + 1, d + 1, dtype=pts.dtype, device=pts.device)
    idx = torch.arange(d)
    T[..., idx, idx] = scale[..., None]
    T[..., :d, d] = -scale[..., None] * c
    T[..., d, d] = 1.0
    return T


def _as_points(X, x) -> tuple[Tensor, Tensor]:
    X = torch.as_tensor(X, dtype=torch.float64)
    x = torch.as_tensor(x, dtype=torch.float64)
    if X.dim() < 2 or X.shape[-1] != 3 or x.shape != (*X.shape[:-1], 2):
        raise ValueError(
            f"need object points (..., N, 3) and image points (..., N, 2) with the same N, got "
            f"{tuple(X.shape)} and {tuple(x.shape)}"
        )
    if not (torch.isfinite(X).all() and torch.isfinite(x).all()):
        raise ValueError("object and image points must be finite (drop missing points first)")
    return X, x


def _check_not_coplanar(X: Tensor, rel_tol: float = 1e-3) -> None:
    """ValueError if the points (..., N, 3) are (nearly) coplanar or collinear."""
    Xc = X - X.mean(-2, keepdim=True)
    s = torch.linalg.svdvals(Xc)  # (..., 3)
    ratio = s[..., 2] / s[..., 0].clamp_min(1e-300)
    if bool((ratio < rel_tol).any()):
        raise ValueError(
            f"object points are (nearly) coplanar (smallest/largest spread {ratio.min():.2e} < "
            f"{rel_tol:g}): the DLT needs a 3D configuration; give K to resect by PnP instead"
        )


def dlt(object_points: Tensor | np.ndarray, image_points: Tensor | np.ndarray) -> Tensor:
    """Normalized DLT: the projection matrix P with x ~ P X, up to scale.

    object_points: (..., N, 3) mm; image_points: (..., N, 2) px; N >= 6, not coplanar
    -> P (..., 3, 4) float64, scaled to unit Frobenius norm with det(P[:, :3]) > 0.
    Raises ValueError for too few, non-finite or coplanar points. Differentiable (SVD) where
    the null space is simple.
    """
    X, x = _as_points(object_points, image_points)
    N = X.shape[-2]
    if N < 6:
        raise ValueError(f"the DLT needs >= 6 points (11 unknowns, 2 equations each), got {N}")
    _check_not_coplanar(X)
    T3, T2 = _normalizer(X), _normalizer(x)
    Xn = X @ T3[..., :3, :3].transpose(-1, -2) + T3[..., None, :3, 3]
    xn = x @ T2[..., :2, :2].transpose(-1, -2) + T2[..., None, :2, 2]
    Xh = torch.cat((Xn, torch.ones_like(Xn[..., :1])), -1)  # (..., N, 4)
    zero = torch.zeros_like(Xh)
    u, v = xn[..., 0:1], xn[..., 1:2]
    rows1 = torch.cat((Xh, zero, -u * Xh), -1)  # (..., N, 12)
    rows2 = torch.cat((zero, Xh, -v * Xh), -1)
    A = torch.cat((rows1, rows2), -2)  # (..., 2N, 12)
    _, S, Vh = torch.linalg.svd(A, full_matrices=False)
    if bool((S[..., -2] < 1e-9 * S[..., 0]).any()):
        raise ValueError("degenerate point configuration: the DLT solution is not unique")
    Pn = Vh[..., -1, :].reshape(*A.shape[:-2], 3, 4)
    P = torch.linalg.solve(T2, Pn) @ T3  # denormalize: T2^-1 Pn T3
    P = P / P.norm(dim=(-2, -1), keepdim=True)
    sign = torch.sign(torch.linalg.det(P[..., :3]))
    return P * sign[..., None, None]


def levenberg_marquardt(
    fun: Callable[[Tensor], Tensor],
    theta0: Tensor,
    max_iter: int = 200,
    tol: float = 1e-12,
) -> tuple[Tensor, float, int]:
    """Minimise ||fun(theta)||^2 for small dense problems with the project's one
    Levenberg-Marquardt loop (`adjust.lsq.lm.levenberg_marquardt`, Marquardt-scaled damping;
    the dense normal matrix is its band with one frame and no off-diagonal blocks).

    fun: (P,) -> (M,) residuals (torch); theta0: (P,) float64. Returns (theta (P,), final
    cost sum r^2, iterations). Stops when a step gains less than `tol` (relative) or moves
    less than about `tol` |theta0|. Jacobians by central differences.
    """

    def jac(p: Tensor) -> Tensor:
        # central differences: 2P (<= 32) evaluations, however many residuals (reverse-mode
        # autodiff needs one pass per residual: minutes for a few thousand points)
        with torch.no_grad():
            h = 1e-6 * p.abs().clamp_min(1.0)
            cols = []
            for i in range(p.numel()):
                d = torch.zeros_like(p)
                d[i] = h[i]
                cols.append((fun(p + d) - fun(p - d)) / (2 * h[i]))
            return torch.stack(cols, -1)

    def cost(theta: Tensor, ctx=None) -> float:
        r = fun(theta)
        return float(r @ r)

    def linearise(theta: Tensor) -> tuple[np.ndarray, np.ndarray, float, None]:
        r, J = fun(theta), jac(theta)
        N = (J.T @ J).detach().cpu().numpy()[None, None]  # blocks (b + 1 = 1, T = 1, P, P)
        g = (-(J.T @ r)).detach().cpu().numpy()[None]  # (T = 1, P)
        return N, g, float(r @ r), None

    def retract(theta: Tensor, delta: np.ndarray) -> Tensor:
        return theta + torch.as_tensor(delta[0], dtype=theta.dtype, device=theta.device)

    theta0 = theta0.detach().clone()
    out = lm.levenberg_marquardt(
        theta0,
        linearise,
        cost,
        retract,
        max_iterations=max_iter,
        ftol=tol,
        xtol=tol * (float(theta0.norm()) + tol),
        lam=1e-3,
        lam_up=10.0,
        lam_down=0.1,
        max_tries=30,
    )
    return out.x, cost(out.x), out.iterations


def _dist_mask(fit_dist: Sequence[str]) -> list[int]:
    unknown = [k for k in fit_dist if k not in DIST_NAMES]
    if unknown:
        raise ValueError(f"fit_dist entries must be among {DIST_NAMES}, got {unknown}")
    return [DIST_NAMES.index(k) for k in DIST_NAMES if k in fit_dist]


def _refine(
    X: Tensor,
    x: Tensor,
    K0: Tensor,
    R0: Tensor,
    t0: Tensor,
    dist0: Tensor,
    fit_intrinsics: bool,
    fit_skew: bool,
    fit_dist: Sequence[str],
    max_iter: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, float]:
    """LM over (fx, fy, cx, cy[, skew]), r, t[, dist subset]; returns K, R, t, dist, rms px."""
    di = _dist_mask(fit_dist)
    r0 = matrix_to_rodrigues(R0)
    parts = [r0, t0]
    if fit_intrinsics:
        parts.append(torch.stack((K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2])))
        if fit_skew:
            parts.append(K0[0, 1:2])
    if di:
        parts.append(dist0[di])
    theta0 = torch.cat(parts)

    def unpack(theta: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        r, t = theta[0:3], theta[3:6]
        k = 6
        K = K0
        if fit_intrinsics:
            fx, fy, cx, cy = theta[6:10].unbind()
            k = 10
            s = K0[0, 1]
            if fit_skew:
                s, k = theta[10], 11
            zero, one = torch.zeros_like(fx), torch.ones_like(fx)
            K = torch.stack(
                (
                    torch.stack((fx, s, cx)),
                    torch.stack((zero, fy, cy)),
                    torch.stack((zero, zero, one)),
                )
            )
        dist = dist0
        if di:
            dist = dist0.clone()
            dist = dist.index_put((torch.tensor(di),), theta[k : k + len(di)])
        return K, rodrigues_to_matrix(r), t, dist

    def residuals(theta: Tensor) -> Tensor:
        K, R, t, dist = unpack(theta)
        return (project_points(X, K, R, t, dist) - x).reshape(-1)

    theta, cost, _ = levenberg_marquardt(residuals, theta0, max_iter=max_iter)
    K, R, t, dist = unpack(theta)
    return K, R, t, dist, (cost / X.shape[0]) ** 0.5


def resect(
    object_points: Tensor | np.ndarray,
    image_points: Tensor | np.ndarray,
    K: Tensor | np.ndarray | None = None,
    dist: Tensor | np.ndarray | None = None,
    *,
    name: str = "camera",
    size: tuple[int, int] = (0, 0),
    fit_skew: bool = False,
    fit_dist: Sequence[str] = (),
    max_iter: int = 200,
    fisheye: bool = False,
) -> Camera:
    """Resect one camera from N known 3D points and their (distorted) pixel positions.

    object_points: (N, 3) mm (e.g. lock-box corners); image_points: (N, 2) px.
    K None: N >= 6 non-coplanar points; normalized DLT -> RQ -> LM over fx, fy, cx, cy
    (+ skew if ``fit_skew``), r, t (+ the distortion coefficients named in ``fit_dist``,
    e.g. ("k1", "k2"), starting from ``dist`` or 0). K (3, 3) given: N >= 4 points (may be
    coplanar); cv2.solvePnP start, LM over r, t (+ ``fit_dist``). ``dist`` (5,) is the known
    (or starting) distortion, default none. Returns a `Camera`; ``extra`` holds ``rms_px``
    (final RMS reprojection error per point) and ``n_points``. Raises ValueError for too few,
    non-finite or (DLT) coplanar points. ``fisheye``: the camera is OpenCV's fisheye model with
    K and ``dist`` (k1 k2 k3 k4) known; its pose is resected from the ideal (undistorted)
    pixels, the RMS measured in the image's.
    """
    X, x = _as_points(object_points, image_points)
    if X.dim() != 2:
        raise ValueError(f"resect takes one camera: points (N, 3), got {tuple(X.shape)}")
    N = X.shape[0]
    dist0 = torch.zeros(5, dtype=torch.float64)
    if dist is not None:
        dist0 = torch.as_tensor(dist, dtype=torch.float64).reshape(-1)
        if dist0.numel() > 5 or not torch.isfinite(dist0).all():
            raise ValueError(f"dist must be <= 5 finite coefficients, got {dist0.tolist()}")
        dist0 = torch.cat((dist0, torch.zeros(5 - dist0.numel(), dtype=torch.float64)))
    n_free = len(_dist_mask(fit_dist))
    if fisheye:
        if K is None or n_free:
            raise ValueError(
                "a fisheye camera is resected with its intrinsics known (K and dist given, "
                "fit_dist empty)"
            )
        K1 = torch.as_tensor(K, dtype=torch.float64)
        flag = torch.tensor(True)
        ideal = undistort_points(x, K1, dist0, pixels=True, fisheye=flag)
        cam = resect(X, ideal, K1, name=name, size=size, max_iter=max_iter)
        cam = Camera.from_matrices(name, cam.K, cam.R, cam.tvec, dist0.numpy(), size, True)
        seen = project_points(X, K1, torch.as_tensor(cam.R), torch.as_tensor(cam.tvec), dist0, flag)
        rms = float(((seen - x) ** 2).sum(-1).mean().sqrt())
        cam.extra.update(rms_px=rms, n_points=int(N))
        return cam
    if K is None:
        n_unknown = 10 + int(fit_skew) + n_free
        if N < 6 or 2 * N < n_unknown:
            raise ValueError(
                f"resection with unknown intrinsics needs >= 6 points (and 2N >= {n_unknown} "
                f"unknowns), got {N}"
            )
        K0, R0, t0 = decompose_projection_matrix(dlt(X, x))
        if not fit_skew:
            K0 = K0.clone()
            K0[0, 1] = 0.0
        fit_intrinsics = True
    else:
        K0 = torch.as_tensor(K, dtype=torch.float64)
        if K0.shape != (3, 3) or not torch.isfinite(K0).all():
            raise ValueError(f"K must be a finite (3, 3) matrix, got {K0.shape}")
        if N < 4 or 2 * N < 6 + n_free:
            raise ValueError(f"resection with known K (PnP) needs >= 4 points, got {N}")
        try:
            ok, rvec, tvec = cv2.solvePnP(
                X.numpy(), x.numpy(), K0.numpy(), dist0.numpy(),
                flags=cv2.SOLVEPNP_SQPNP,  # global, any N >= 3, planar or not
            )  # fmt: skip
        except cv2.error:  # SQPnP asserts on points that fix no pose (all nearly at one place)
            ok = False
        if not ok:
            raise ValueError("cv2.solvePnP failed: degenerate configuration (collinear points?)")
        R0 = rodrigues_to_matrix(torch.as_tensor(rvec.reshape(3), dtype=torch.float64))
        t0 = torch.as_tensor(tvec.reshape(3), dtype=torch.float64)
        fit_intrinsics = False
    Kf, Rf, tf, distf, rms = _refine(
        X, x, K0, R0, t0, dist0, fit_intrinsics, fit_skew, fit_dist, max_iter
    )
    depths = X @ Rf[2] + tf[2]
    if bool((depths <= 0).any()):
        log.warning(
            "resection of %s: %d points lie behind the camera", name, int((depths <= 0).sum())
        )
    if rms > 5.0:
        log.warning("resection of %s: RMS reprojection error %.2f px is large", name, rms)
    cam = Camera.from_matrices(
        name, Kf.detach().numpy(), Rf.detach().numpy(), tf.detach().numpy(),
        distf.detach().numpy(), size,
    )  # fmt: skip
    cam.extra.update(rms_px=float(rms), n_points=int(N))
    return cam
