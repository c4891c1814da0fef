"""Each part's body-frame offset smoothed over the whole recording: a Gauss-Markov model whose
covariance is the session's own (`OffsetCovariance`), every observation in it with its own
information, rank-deficient ones included.

`krige_offsets` interpolates a part-frame from the two nearest observed frames with a scalar
weight per frame; a view that fixes only two of the three coordinates (one camera's ray)
cannot enter it as what it is. Here each part's offset o_t (3, body axes) follows a Matern-3/2
process per body axis (a smooth motion: position and velocity, Sarkka & Solin 2019) with the
part's mean, variance (`OffsetCovariance.sill`) and a length fitted to its semivariogram
(`matern_lengths`), and an observation of part-frame (t, k) is any Gaussian likelihood on o_t
in information form: J (3, 3) and J z for an observed offset z. A part-frame triangulated from
>= 2 cameras has J = diag(1 / nugget); a part-frame one camera saw has J = (I - u u^T) /
sigma_perp^2 with u its ray in body coordinates: it fixes the offset across the ray and says
nothing along it, where the motion model carries what the other frames (and other cameras'
rays as the body turns) say. A Rauch-Tung-Striebel smoother gives every frame's posterior;
each observed frame's own likelihood is then divided out (exact: it is a factor on that
frame's state alone), so the prediction at t never sees t's own observation and stays an
independent prior to fuse with t's detections, as `krige_offsets` (``skip_self``) is.

Shapes: T frames, K parts. Units: mm, frames. numpy float64. Cost: a Python loop over the
frames, two passes (about 0.2 s for 1000 frames and 8 parts); the filter keeps (T, K, 6, 6)
covariances (a 50,000-frame chunk of 34 parts: 0.5 GB).
"""

from __future__ import annotations

import math

import numpy as np

from adjust.lsq.stochastic import OffsetCovariance

#: Matern-3/2 lengths (frames) tried by `matern_lengths`: log-spaced, 0.5 .. 2000 frames
LENGTH_GRID = np.geomspace(0.5, 2000.0, 80)
JITTER = 1e-9  # relative, on the diagonals inverted


def matern32_semivariogram(h: np.ndarray, sill: np.ndarray, length: np.ndarray) -> np.ndarray:
    """gamma(h) = sill (1 - (1 + a h) exp(-a h)), a = sqrt(3) / length; broadcasting."""
    a = math.sqrt(3.0) * np.asarray(h, dtype=np.float64) / np.asarray(length, dtype=np.float64)
    return np.asarray(sill, dtype=np.float64) * (1.0 - (1.0 + a) * np.exp(-a))


def matern_lengths(cov: OffsetCovariance, grid: np.ndarray = LENGTH_GRID) -> np.ndarray:
    """(K, 3) frames: per part and body axis the Matern-3/2 length whose semivariogram is
    nearest the estimated one (`cov.gamma` at `cov.lags`, least squares relative to the sill);
    a part-axis with no temporal information (gamma at the sill at every lag) gets the
    shortest length of the grid (its offset is its mean, as `krige_offsets` predicts)."""
    lags = np.asarray(cov.lags, dtype=np.float64)
    g = cov.gamma / np.maximum(cov.sill, 1e-12)[..., None]  # (K, 3, L) in [0, 1]
    model = 1.0 - (1.0 + (a := math.sqrt(3.0) * lags[None] / grid[:, None])) * np.exp(-a)
    err = ((g[:, :, None, :] - model[None, None]) ** 2).sum(-1)  # (K, 3, G)
    return grid[np.argmin(err, -1)]


def _transition(length: np.ndarray, sill: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per part (K): the one-frame transition F (K, 6, 6), its noise Q and the stationary
    covariance P (state: the three axes' offsets, then their velocities)."""
    K = length.shape[0]
    lam = math.sqrt(3.0) / length  # (K, 3)
    e = np.exp(-lam)
    F = np.zeros((K, 6, 6))
    P = np.zeros((K, 6, 6))
    ax = np.arange(3)
    F[:, ax, ax] = e * (1.0 + lam)
    F[:, ax, ax + 3] = e
    F[:, ax + 3, ax] = -(lam**2) * e
    F[:, ax + 3, ax + 3] = e * (1.0 - lam)
    P[:, ax, ax] = sill
    P[:, ax + 3, ax + 3] = lam**2 * sill
    Q = P - F @ P @ F.transpose(0, 2, 1)
    return F, 0.5 * (Q + Q.transpose(0, 2, 1)), P


def _inv(A: np.ndarray) -> np.ndarray:
    """Inverse of symmetric positive definite matrices (..., n, n), symmetrised."""
    n = A.shape[-1]
    scale = np.abs(np.diagonal(A, axis1=-2, axis2=-1)).max(-1)[..., None, None]
    out = np.linalg.inv(A + JITTER * np.maximum(scale, 1e-300) * np.eye(n))
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def smooth_offsets(
    offsets: np.ndarray,
    info: np.ndarray,
    cov: OffsetCovariance,
    lengths: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Every part-frame's offset predicted from all the other frames' observations.

    offsets (T, K, 3) mm: the observed offsets (any finite value where info is 0); info
    (T, K, 3, 3) mm^-2: each part-frame's observation information (0: not observed; see the
    module's docstring); cov: the session's `OffsetCovariance` (mean, sill); lengths (K, 3)
    frames (None: `matern_lengths(cov)`). Returns the prediction (T, K, 3) mm and its
    covariance (T, K, 3, 3) mm^2 in body axes, each frame's own observation left out."""
    o = np.asarray(offsets, dtype=np.float64)
    J = np.asarray(info, dtype=np.float64)
    T, K, _ = o.shape
    if J.shape != (T, K, 3, 3):
        raise ValueError(f"info must be {(T, K, 3, 3)} for offsets {o.shape}, got {J.shape}")
    L = matern_lengths(cov) if lengths is None else np.asarray(lengths, dtype=np.float64)
    F, Q, P0 = _transition(L, np.asarray(cov.sill, dtype=np.float64))
    z = np.where(np.isfinite(o), o, 0.0) - cov.mean[None]  # about the part's mean
    h = np.einsum("tkij,tkj->tki", J, z)  # information vectors (T, K, 3)
    seen = (np.abs(J) > 0).any((-1, -2))  # (T, K)
    mf = np.zeros((T, K, 6))  # filtered (t's observation in)
    Pf = np.zeros((T, K, 6, 6))
    m = np.zeros((K, 6))
    P = P0.copy()
    Ft = F.transpose(0, 2, 1)
    for t in range(T):
        if t:
            m = np.einsum("kij,kj->ki", F, m)
            P = F @ P @ Ft + Q
        if seen[t].any():
            Lam = _inv(P)
            eta = np.einsum("kij,kj->ki", Lam, m)
            Lam[:, :3, :3] += J[t]
            eta[:, :3] += h[t]
            P = _inv(Lam)
            m = np.einsum("kij,kj->ki", P, eta)
        mf[t], Pf[t] = m, P
    # Rauch-Tung-Striebel, backwards; each smoothed marginal with its own observation divided out
    pred = np.empty((T, K, 3))
    var = np.empty((T, K, 3, 3))
    ms, Ps = mf[-1], Pf[-1]
    for t in range(T - 1, -1, -1):
        if t < T - 1:
            Pp = F @ Pf[t] @ Ft + Q
            G = Pf[t] @ Ft @ _inv(Pp)
            ms = mf[t] + np.einsum("kij,kj->ki", G, ms - np.einsum("kij,kj->ki", F, mf[t]))
            Ps = Pf[t] + G @ (Ps - Pp) @ G.transpose(0, 2, 1)
            Ps = 0.5 * (Ps + Ps.transpose(0, 2, 1))
        if seen[t].any():
            Lam = _inv(Ps)
            eta = np.einsum("kij,kj->ki", Lam, ms)
            Lam[:, :3, :3] -= J[t]
            eta[:, :3] -= h[t]
            C = _inv(Lam)
            pred[t] = np.einsum("kij,kj->ki", C, eta)[:, :3]
            var[t] = C[:, :3, :3]
        else:
            pred[t] = ms[:, :3]
            var[t] = Ps[:, :3, :3]
    return pred + cov.mean[None], var


def ray_information(rays: np.ndarray, perp_var: np.ndarray) -> np.ndarray:
    """(I - u u^T) / perp_var (..., 3, 3): what one camera's view says of a point, u (..., 3)
    the unit ray (in the frame the information is wanted in), perp_var (...) mm^2 the view's
    variance across the ray."""
    u = np.asarray(rays, dtype=np.float64)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    proj = np.eye(3) - u[..., :, None] * u[..., None, :]
    return proj / np.asarray(perp_var, dtype=np.float64)[..., None, None]


def view_rays(
    points: np.ndarray,
    weights: np.ndarray,
    centers: np.ndarray,
    focal: np.ndarray,
    sigma_px: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    sd_factor: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The camera ray of each part-frame that one view was accepted for.

    points (T, K, 3) mm its fused point, weights (T, K, C) the views' final weights (> 0:
    accepted), centers (C, 3) mm, focal (C,) px, sigma_px (C,) the detector noise, R (C, 3, 3)
    and t (C, 3) world -> camera. Returns one (T, K) bool (exactly one view), rays (T, K, 3) unit
    vectors from that camera's centre through the point (0 elsewhere) and perp_var (T, K) mm^2
    the view's variance across its ray, (sd_factor sigma_px depth / focal)^2 (1 elsewhere).
    sd_factor > 1 stands for what the detector's noise leaves out: in body coordinates a ray
    also carries the pose's error, smooth in time and shared by neighbouring frames, which
    nearly parallel rays would otherwise triangulate far along themselves."""
    w = np.asarray(weights) > 0
    one = (w.sum(-1) == 1) & np.isfinite(points).all(-1)
    cam = np.argmax(w, -1)  # (T, K)
    X = np.where(one[..., None], points, 0.0)
    d = X - centers[cam]
    rays = np.where(
        one[..., None], d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9), 0.0
    )
    depth = np.einsum("tkj,tkj->tk", R[cam][..., 2, :], X) + t[cam][..., 2]
    sd = sd_factor * sigma_px[cam] * np.maximum(depth, 1.0) / focal[cam]
    return one, rays, np.where(one, sd * sd, 1.0)


def across_ray_rms(resid: np.ndarray, rays: np.ndarray, mask: np.ndarray, min_count: int = 20):
    """(K,) per part, the rms across its ray of resid (T, K, 3) over the part-frames of mask
    (T, K) (rays (T, K, 3), any length): how far a prediction left a view's ray where that
    view was left out of it (NaN with fewer than min_count part-frames)."""
    u = rays / np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-12)
    d = resid - (resid * u).sum(-1, keepdims=True) * u
    d2 = np.where(mask, (d * d).sum(-1), 0.0)
    n = mask.sum(0)
    return np.where(n >= min_count, np.sqrt(d2.sum(0) / np.maximum(n, 1)), np.nan)
