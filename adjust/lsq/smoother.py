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
run in blocks of frames, vectorised over the blocks, the blocks' totals composed by associative
scans (`_prefix`): about 0.26 s for 10,000 frames of 8 parts on one core (the scans over every
frame took 0.45 s, a Python loop over the frames 2-4 s); memory is bounded by smoothing
GROUP_PART_FRAMES part-frames at a time (a peak of about 2.7 kB per part-frame, 9 arrays of
288 bytes; the scans over every frame took 4.7 kB).
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


def _jittered(A: np.ndarray) -> np.ndarray:
    """A (..., n, n) plus JITTER times its largest absolute diagonal entry on the diagonal."""
    scale = np.abs(np.diagonal(A, axis1=-2, axis2=-1)).max(-1)[..., None, None]
    return A + JITTER * np.maximum(scale, 1e-300) * np.eye(A.shape[-1])


def _inv3(A: np.ndarray) -> np.ndarray:
    """Inverse of symmetric positive definite 3 x 3 matrices (..., 3, 3), with a relative jitter
    on the diagonal, by cofactors (`adjust.sym3.sym3_inverse`: elementwise over the batch)."""
    return sym3_inverse(torch.from_numpy(np.ascontiguousarray(_jittered(A)))).numpy()


def _inv3_general(A: np.ndarray) -> np.ndarray:
    """Inverse of general (non-singular) 3 x 3 matrices (..., 3, 3) by cofactors, elementwise
    over the batch (about 1.6 ms for 50,000 on one core; torch.linalg.inv takes 4 ms)."""
    a00, a01, a02 = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    a10, a11, a12 = A[..., 1, 0], A[..., 1, 1], A[..., 1, 2]
    a20, a21, a22 = A[..., 2, 0], A[..., 2, 1], A[..., 2, 2]
    out = np.empty(A.shape)
    c00, c10, c20 = a11 * a22 - a12 * a21, a12 * a20 - a10 * a22, a10 * a21 - a11 * a20
    d = 1.0 / (a00 * c00 + a01 * c10 + a02 * c20)
    out[..., 0, 0], out[..., 1, 0], out[..., 2, 0] = c00 * d, c10 * d, c20 * d
    out[..., 0, 1] = (a02 * a21 - a01 * a22) * d
    out[..., 0, 2] = (a01 * a12 - a02 * a11) * d
    out[..., 1, 1] = (a00 * a22 - a02 * a20) * d
    out[..., 1, 2] = (a02 * a10 - a00 * a12) * d
    out[..., 2, 1] = (a01 * a20 - a00 * a21) * d
    out[..., 2, 2] = (a00 * a11 - a01 * a10) * d
    return out


def _inv(A: np.ndarray) -> np.ndarray:
    """Inverse of symmetric positive definite matrices (..., n, n), with a relative jitter on the
    diagonal, symmetrised (torch's batched inverse: about twice numpy's speed here, and as fast
    as a 6 x 6 inverse by 3 x 3 blocks of cofactors)."""
    out = torch.linalg.inv(torch.from_numpy(np.ascontiguousarray(_jittered(A)))).numpy()
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def _sym(A: np.ndarray) -> np.ndarray:
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def _mv(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A (..., n, m) times v (..., m), batched."""
    return (A @ v[..., None])[..., 0]


def _t(A: np.ndarray) -> np.ndarray:
    return np.swapaxes(A, -1, -2)


# The smoother as blocked scans (after Sarkka & Garcia-Fernandez 2021, "Temporal parallelization
# of Bayesian smoothers"): the frames in blocks of SCAN_BLOCK, the Python loops run over a
# block's frames, each step vectorised over all the blocks (and parts) at once.
# Filtering: each block's total element (A, b, C, eta, J) stands for p(x_t | x_s, y_{s+1:t}) =
# N(A x_s + b, C) and p(y_{s+1:t} | x_s) as the information (J, eta) on x_s, x_s the state
# before the block; it is built by Kalman steps conditional on x_s (`_kalman_step`), the blocks'
# totals are composed by the general associative scan (`_prefix`, `_filter_op`: 1 / SCAN_BLOCK
# of the elements), and a plain Kalman filter then runs through every block from the filtered
# state before it. Smoothing: a Rauch-Tung-Striebel element (E, g, L) stands for
# p(x_t | x_{t+1}, y_{1:t}) = N(E x_{t+1} + g, L); each frame's composition with its block's later
# frames (a loop backwards), the blocks' totals by `_prefix` (`_smooth_op`), then every frame
# from the smoothed state after its block. Identities: (I, 0, 0, 0, 0) and (I, 0, 0).
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


def _blocks(a: np.ndarray, L: int, pad) -> np.ndarray:
    """(T, ...) -> (L, B, ...): the frames in blocks of L (B = ceil(T / L)), a frame's place in
    its block first (so a loop's slices over it are contiguous), padded to whole blocks with
    ``pad`` (broadcast to a frame's shape)."""
    T = a.shape[0]
    B = -(-T // L)
    if B * L > T:
        a = np.concatenate([a, np.broadcast_to(pad, (B * L - T, *a.shape[1:]))])
    return np.ascontiguousarray(np.swapaxes(a.reshape(B, L, *a.shape[1:]), 0, 1))


def _unblocked(x: np.ndarray, T: int) -> np.ndarray:
    """`_blocks`' inverse: (L, B, ...) -> (T, ...), the padding dropped."""
    L, B = x.shape[:2]
    return np.swapaxes(x, 0, 1).reshape(B * L, *x.shape[2:])[:T]


def _prefix(elems: tuple, op, identity: tuple, from_start=None, keep=None) -> tuple:
    """Inclusive prefix scan of elements (arrays with the time axis first, T) under the
    associative op: the frames in blocks of SCAN_BLOCK, a loop within every block at once, the
    blocks' totals scanned the same way (recursively), then every frame composed with the total
    of the blocks before its own (vectorised; by from_start(total, element) where given: op for
    a left operand that starts at the first frame). identity pads T to whole blocks. keep: the
    indices of the elements' parts returned (None: all), the others are not copied out."""
    T = elems[0].shape[0]
    L = min(SCAN_BLOCK, T)
    x = [_blocks(a, L, e) for a, e in zip(elems, identity)]  # (L, B, ...)
    for i in range(1, L):
        for a, n in zip(x, op(tuple(a[i - 1] for a in x), tuple(a[i] for a in x))):
            a[i] = n
    if x[0].shape[1] > 1:
        totals = _prefix(tuple(a[-1, :-1] for a in x), op, identity, from_start)
        before = tuple(np.broadcast_to(p, a[:, 1:].shape) for p, a in zip(totals, x))
        for a, n in zip(x, (from_start or op)(before, tuple(a[:, 1:] for a in x))):
            a[:, 1:] = n
    keep = range(len(x)) if keep is None else keep
    return tuple(_unblocked(x[i], T) for i in keep)


def _kalman_step(m, C, Jo, h, F, Ft, Q, cond=None):
    """One frame of the Kalman filter, vectorised: the previous frame's state N(m, C) (..., 6),
    (..., 6, 6) predicted through F, Ft = F^T, Q (..., 6, 6) and updated with the observation's
    information Jo (..., 3, 3), h (..., 3) on the offsets. Returns the new (m, C), F C (the
    product the prediction used) and cond: where given, (A, eta, J) of a state conditional on
    an earlier one x_s (m = A x_s + b, `_filter_op`'s element) carried along the same step.
    The update's only inverse is the 3 x 3 (I + Jo Cp_oo)^-1 (Cp the predicted covariance, oo
    its offsets' block; its eigenvalues are >= 1: Jo, Cp are positive semi-definite)."""
    FC = F @ C
    Cp = FC @ Ft + Q
    mp = _mv(F, m)
    Y = _inv3_general(np.eye(3) + Jo @ Cp[..., :3, :3])
    W = Y @ Jo  # (Jo^-1 + Cp_oo)^-1: the observation's information on the predicted offsets
    r = _mv(Y, h - _mv(Jo, mp[..., :3]))
    K = Cp[..., :3] @ W  # the gain, times Jo^-1
    out = (mp + _mv(Cp[..., :3], r), _sym(Cp - K @ Cp[..., :3, :]), FC)
    if cond is None:
        return out
    A, eta, J = cond
    Ap = F @ A
    Ho = Ap[..., :3, :]  # the predicted offsets' dependence on x_s
    HoT = _t(Ho)
    return (*out, (Ap - K @ Ho, eta + _mv(HoT, r), J + HoT @ W @ Ho))


def _smoothed_states(F, Q, P0, J, h) -> tuple[np.ndarray, np.ndarray]:
    """The smoothed offsets (T, G, 3) and their covariance (T, G, 3, 3) of G parts: F, Q, P0
    (G, 6, 6) from `_transition`, J (T, G, 3, 3) and h (T, G, 3) the observations' information.

    The frames in blocks (L = SCAN_BLOCK), arrays (L, B, G, ...): a frame's place in its block
    first. Cost per part-frame about 30 batched 6 x 6 products, two elementwise 3 x 3 inverses
    (`_kalman_step` twice) and a 6 x 6 one (`_inv`), plus the blocks' scans (1 / L of the
    frames)."""
    T, G = J.shape[:2]
    L = min(SCAN_BLOCK, T)
    B = -(-T // L)
    I6, Ft = np.eye(6), np.ascontiguousarray(_t(F))
    Jb, hb = _blocks(J, L, 0.0), _blocks(h, L, 0.0)  # no information after the last frame
    # each block's total, conditional on the state before it; the first block's is the
    # stationary prior's (A = 0): its "state before" is N(0, P0), and F P0 F^T + Q = P0
    A = np.broadcast_to(I6, (B, G, 6, 6)).copy()
    A[0] = 0.0
    C = np.zeros((B, G, 6, 6))
    C[0] = P0
    m, eta, Jx = np.zeros((B, G, 6)), np.zeros((B, G, 6)), np.zeros((B, G, 6, 6))
    for i in range(L):
        m, C, _, (A, eta, Jx) = _kalman_step(m, C, Jb[i], hb[i], F, Ft, Q, (A, eta, Jx))
    ident = (I6, np.zeros(6), np.zeros((6, 6)), np.zeros(6), np.zeros((6, 6)))
    mt, Ct = _prefix((A, m, C, eta, Jx), _filter_op, ident, _filter_from_start, (1, 2))
    # the Kalman filter through every block from the filtered state before it; FPf: F Pf, Pn:
    # the next frame's prediction F Pf F^T + Q from the frame's own filtered covariance
    m = np.concatenate([np.zeros((1, G, 6)), mt[:-1]])
    C = np.concatenate([P0[None], _sym(Ct[:-1])])
    mf, Pf = np.empty((L, B, G, 6)), np.empty((L, B, G, 6, 6))
    FPf, Pn = np.empty((L, B, G, 6, 6)), np.empty((L, B, G, 6, 6))
    for i in range(L):
        m, C, FC = _kalman_step(m, C, Jb[i], hb[i], F, Ft, Q)
        if i > 0:
            FPf[i - 1], Pn[i - 1] = FC, FC @ Ft + Q
        mf[i], Pf[i] = m, C
    FPf[-1] = F @ C
    Pn[-1] = FPf[-1] @ Ft + Q
    # Rauch-Tung-Striebel elements: E = Pf F^T Pn^-1 (Et its transpose), g = mf - E F mf,
    # Ls = Pf - E F Pf; the last frame's is (0, mf, Pf) and the padding's (0, 0, 0)
    Et = _inv(Pn) @ FPf
    E = np.ascontiguousarray(_t(Et))
    g = mf - _mv(E, _mv(F, mf))
    Ls = _sym(Pf - E @ FPf)
    last, lb = (T - 1) % L, (T - 1) // L
    for a in (E, Et, g, Ls):
        a[last + 1 :, lb] = 0.0
    E[last, lb], Et[last, lb], g[last, lb], Ls[last, lb] = 0.0, 0.0, mf[last, lb], Pf[last, lb]
    # each frame composed with its block's later frames, backwards
    for i in range(L - 2, -1, -1):
        g[i] += _mv(E[i], g[i + 1])
        Ls[i] += E[i] @ Ls[i + 1] @ Et[i]
        E[i] = E[i] @ E[i + 1]
    # the smoothed state at every block's first frame (a reversed scan of the blocks' totals);
    # every frame's from the next block's (none after the last: its E is 0)
    ident = (I6, np.zeros(6), np.zeros((6, 6)))
    ms0, Ps0 = _prefix((E[0, ::-1], g[0, ::-1], Ls[0, ::-1]), _smooth_op, ident, keep=(1, 2))
    mn = np.concatenate([ms0[::-1][1:], np.zeros((1, G, 6))])  # (B, G, 6)
    Psn = np.concatenate([Ps0[::-1][1:], np.zeros((1, G, 6, 6))])
    Eo = E[..., :3, :]
    ms = _mv(Eo, mn) + g[..., :3]
    Ps = _sym(Eo @ Psn @ _t(Eo) + Ls[..., :3, :3])
    return _unblocked(ms, T), _unblocked(Ps, T)


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
        Lam = _inv3(Ps)
        C = _inv3(Lam - J[:, ks])
        p = _mv(C, _mv(Lam, ms) - h[:, ks])
        s = seen[:, ks]
        pred[:, ks] = np.where(s[..., None], p, ms)
        var[:, ks] = np.where(s[..., None, None], C, Ps)
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
