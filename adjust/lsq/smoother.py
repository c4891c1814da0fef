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

Shapes: T frames, K parts. Units: mm, frames. numpy float64. Cost: the filter and the smoother
are associative scans (`_prefix`), vectorised over the frames: about 0.7 s for 10,000 frames of 8
parts on one core (a Python loop over the frames took 2-4 s); memory is bounded by smoothing
GROUP_PART_FRAMES part-frames at a time (about 30 arrays of 288 bytes each per part-frame).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from adjust.lsq.stochastic import OffsetCovariance
from adjust.sym3 import sym3_inverse

#: Matern-3/2 lengths (frames) tried by `matern_lengths`: log-spaced, 0.5 .. 2000 frames
LENGTH_GRID = np.geomspace(0.5, 2000.0, 80)
JITTER = 1e-9  # relative, on the diagonals inverted
GROUP_PART_FRAMES = 50_000  # part-frames smoothed at a time (bounds the memory)


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
    """Inverse of symmetric positive definite matrices (..., n, n), symmetrised (a relative
    jitter on the diagonal; torch's batched inverse, about twice numpy's speed here)."""
    n = A.shape[-1]
    scale = np.abs(np.diagonal(A, axis1=-2, axis2=-1)).max(-1)[..., None, None]
    A = np.ascontiguousarray(A + JITTER * np.maximum(scale, 1e-300) * np.eye(n))
    out = torch.linalg.inv(torch.from_numpy(A)).numpy()
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def _inv3(A: np.ndarray) -> np.ndarray:
    """Inverse of symmetric positive definite 3 x 3 matrices (..., 3, 3), with `_inv`'s jitter,
    by cofactors (`adjust.sym3.sym3_inverse`: elementwise over the batch)."""
    scale = np.abs(np.diagonal(A, axis1=-2, axis2=-1)).max(-1)[..., None, None]
    A = np.ascontiguousarray(A + JITTER * np.maximum(scale, 1e-300) * np.eye(3))
    return sym3_inverse(torch.from_numpy(A)).numpy()


def _sym(A: np.ndarray) -> np.ndarray:
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def _mv(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A (..., n, n) times v (..., n), batched."""
    return (A @ v[..., None])[..., 0]


def _t(A: np.ndarray) -> np.ndarray:
    return np.swapaxes(A, -1, -2)


# The smoother as two associative scans (Sarkka & Garcia-Fernandez 2021, "Temporal
# parallelization of Bayesian smoothers"): each frame an element, composed by `_prefix`, whose
# Python loops run over about 7 log8(T) steps, each vectorised over T / 8^level elements.
# A filtering element (A, b, C, eta, J) stands for p(x_t | x_{t-1}, y_t) = N(A x_{t-1} + b, C) and
# p(y_t | x_{t-1}) as the information (J, eta) on x_{t-1}; a smoothing element (E, g, L) for
# p(x_t | x_{t+1}, y_{1:t}) = N(E x_{t+1} + g, L). Identities: (I, 0, 0, 0, 0) and (I, 0, 0).
SCAN_BLOCK = 8


def _filter_op(ei: tuple, ej: tuple) -> tuple:
    """The filtering element of ei's frames followed by ej's."""
    Ai, bi, Ci, etai, Ji = ei
    Aj, bj, Cj, etaj, Jj = ej
    Minv = torch.linalg.inv(torch.from_numpy(np.eye(Ci.shape[-1]) + Ci @ Jj)).numpy()
    AjM = Aj @ Minv
    AiM = _t(Ai) @ _t(Minv)  # A_i^T (I + J_j C_i)^-1
    return (
        AjM @ Ai,
        _mv(AjM, bi + _mv(Ci, etaj)) + bj,
        AjM @ Ci @ _t(Aj) + Cj,
        _mv(AiM, etaj - _mv(Jj, bi)) + etai,
        AiM @ Jj @ Ai + Ji,
    )


def _filter_from_start(ei: tuple, ej: tuple) -> tuple:
    """`_filter_op` where ei covers the frames from the first (its A, eta and J are 0: the
    first frame's element has A = 0): the filtered mean and covariance after ej's frames."""
    _, bi, Ci, _, _ = ei
    Aj, bj, Cj, etaj, Jj = ej
    Minv = torch.linalg.inv(torch.from_numpy(np.eye(Ci.shape[-1]) + Ci @ Jj)).numpy()
    AjM = Aj @ Minv
    zero = np.zeros(())
    return (zero, _mv(AjM, bi + _mv(Ci, etaj)) + bj, AjM @ Ci @ _t(Aj) + Cj, zero, zero)


def _smooth_op(later: tuple, earlier: tuple) -> tuple:
    """The smoothing element of ``earlier``'s frame conditioned through ``later``'s (a reversed
    scan's operator: its running total is the later frames')."""
    Ej, gj, Lj = later
    Ei, gi, Li = earlier
    return Ei @ Ej, _mv(Ei, gj) + gi, Ei @ Lj @ _t(Ei) + Li


def _prefix(elems: tuple, op, identity: tuple, from_start=None, keep=None) -> tuple:
    """Inclusive prefix scan of elements (arrays with the time axis first, T) under the
    associative op: the frames in blocks of SCAN_BLOCK, a loop within every block at once, the
    blocks' totals scanned the same way (recursively), then every frame composed with the total
    of the blocks before its own (vectorised; by from_start(total, element) where given: op for
    a left operand that starts at the first frame). identity pads T to whole blocks. keep: the
    indices of the elements' parts returned (None: all), the others are not copied out."""
    T = elems[0].shape[0]
    L = min(SCAN_BLOCK, T)
    B = -(-T // L)
    x = []  # (L, B, ...): a frame's place in its block first, so the loop's slices are contiguous
    for a, e in zip(elems, identity):
        if B * L > T:
            a = np.concatenate([a, np.broadcast_to(e, (B * L - T, *a.shape[1:]))])
        x.append(np.ascontiguousarray(np.swapaxes(a.reshape(B, L, *a.shape[1:]), 0, 1)))
    for i in range(1, L):
        for a, n in zip(x, op(tuple(a[i - 1] for a in x), tuple(a[i] for a in x))):
            a[i] = n
    if B > 1:
        totals = _prefix(tuple(a[-1, :-1] for a in x), op, identity, from_start)
        before = tuple(np.broadcast_to(p, a[:, 1:].shape) for p, a in zip(totals, x))
        for a, n in zip(x, (from_start or op)(before, tuple(a[:, 1:] for a in x))):
            a[:, 1:] = n
    keep = range(len(x)) if keep is None else keep
    return tuple(np.swapaxes(x[i], 0, 1).reshape(B * L, *x[i].shape[2:])[:T] for i in keep)


def _smoothed_states(F, Q, P0, J, h) -> tuple[np.ndarray, np.ndarray]:
    """The smoothed state (T, G, 6) and covariance (T, G, 6, 6) of G parts: F, Q, P0 (G, 6, 6)
    from `_transition`, J (T, G, 3, 3) and h (T, G, 3) the observations' information."""
    T, G = J.shape[:2]
    I6, Ft = np.eye(6), _t(F)
    # the frame's own element: prior P (P0 at the first frame, Q after) times its observation;
    # (I + P Jo)^-1 with Jo on the offsets alone is [[X, 0], [-P21 J X, I]], X = (I + P11 J)^-1
    P = np.concatenate([P0[None], np.broadcast_to(Q, (T - 1, G, 6, 6))])
    X = torch.linalg.inv(torch.from_numpy(np.eye(3) + P[..., :3, :3] @ J)).numpy()
    S = np.zeros((T, G, 6, 6))
    S[..., :3, :3] = X
    S[..., 3:, :3] = -P[..., 3:, :3] @ J @ X
    S[..., 3:, 3:] = I6[3:, 3:]
    SP = S @ P
    A = S @ F
    A[0] = 0.0
    eta = _mv(Ft @ _t(S[..., :3, :]), h)  # F^T (I + Jo P)^-1 ho, ho = (h, 0)
    Je = _sym(Ft[..., :3] @ J @ A[..., :3, :])  # F^T Jo (I + P Jo)^-1 F, Jo on the offsets
    eta[0], Je[0] = 0.0, 0.0
    b = _mv(SP[..., :3], h)
    ident = (I6, np.zeros(6), np.zeros((6, 6)), np.zeros(6), np.zeros((6, 6)))
    mf, Pf = _prefix((A, b, _sym(SP), eta, Je), _filter_op, ident, _filter_from_start, (1, 2))
    Pf = _sym(Pf)
    # Rauch-Tung-Striebel elements, then the reversed scan
    Pp = F @ Pf[:-1] @ Ft + Q
    E = Pf[:-1] @ Ft @ _inv(Pp)
    E = np.concatenate([E, np.zeros((1, G, 6, 6))])
    g = np.concatenate([mf[:-1] - _mv(E[:-1] @ F, mf[:-1]), mf[-1:]])
    Ls = np.concatenate([_sym(Pf[:-1] - E[:-1] @ F @ Pf[:-1]), Pf[-1:]])
    ident = (I6, np.zeros(6), np.zeros((6, 6)))
    ms, Ps = _prefix((E[::-1], g[::-1], Ls[::-1]), _smooth_op, ident, keep=(1, 2))
    return ms[::-1], _sym(Ps[::-1])


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
    pred = np.empty((T, K, 3))
    var = np.empty((T, K, 3, 3))
    group = max(1, GROUP_PART_FRAMES // max(T, 1))  # parts at a time: bounded memory
    for k0 in range(0, K, group):
        ks = slice(k0, k0 + group)
        ms, Ps = _smoothed_states(F[ks], Q[ks], P0[ks], J[:, ks], h[:, ks])
        # each frame's own observation divided out of its offsets' marginal (exact: the
        # observation is a factor on that frame's offsets alone)
        Lam = _inv3(Ps[..., :3, :3])
        C = _inv3(Lam - J[:, ks])
        p = _mv(C, _mv(Lam, ms[..., :3]) - h[:, ks])
        s = seen[:, ks]
        pred[:, ks] = np.where(s[..., None], p, ms[..., :3])
        var[:, ks] = np.where(s[..., None, None], C, Ps[..., :3, :3])
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
