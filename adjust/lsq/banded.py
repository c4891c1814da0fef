"""Block-banded symmetric positive definite matrices: assembly, O(T) solve, selected inverse.

A symmetric matrix of T x T blocks of size n x n whose block (i, j) vanishes for |i - j| > b is
stored by its lower blocks, offset-major: ``blocks (b + 1, T, n, n)`` with
``blocks[d, s] = N[s + d, s]`` (entries with s + d >= T are ignored and kept zero).
For the pose-track adjustment n = 6 (pose
parameters) and b = 4 (the track residual at t couples frames t-2..t+2), i.e. a scalar
half-bandwidth of n (b + 1) - 1 = 29.

Everything here is numpy/scipy float64 (LAPACK's banded Cholesky); callers convert.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.linalg import cho_solve_banded, cholesky_banded
from torch import Tensor


def _check_blocks(blocks: np.ndarray) -> tuple[int, int, int]:
    if blocks.ndim != 4 or blocks.shape[-1] != blocks.shape[-2]:
        raise ValueError(f"blocks must have shape (b+1, T, n, n), got {blocks.shape}")
    b1, T, n, _ = blocks.shape
    return T, b1 - 1, n


def zeros(T: int, n: int = 6, b: int = 4) -> np.ndarray:
    """An all-zero block band (b+1, T, n, n)."""
    return np.zeros((b + 1, T, n, n))


def add_diagonal(blocks: np.ndarray, D: np.ndarray | Tensor) -> np.ndarray:
    """blocks[0] += D, D: (T, n, n) per-frame blocks (e.g. observation normal matrices)."""
    blocks[0] += np.asarray(D.detach().cpu() if isinstance(D, Tensor) else D, dtype=np.float64)
    return blocks


def add_block_products(
    blocks: np.ndarray, J: np.ndarray | Tensor, w: np.ndarray | Tensor | None, first: int
) -> np.ndarray:
    """Accumulate sum_r J_r^T diag(w_r) J_r for residual groups that each span <= b+1 frames.

    blocks: (b+1, T, n, n) updated in place and returned. J: (R, span, m, n): residual group r
    (m residuals) has Jacobian blocks J[r, a] for frame first + r + a. w: (R, m) weights or None.
    """
    b1, T, n, _ = blocks.shape
    _check_blocks(blocks)
    J = torch.as_tensor(J, dtype=torch.float64)
    R, span, m, n2 = J.shape
    if span > b1 or n2 != n:
        raise ValueError(f"J must have shape (R, <= {b1}, m, {n}), got {tuple(J.shape)}")
    if R == 0:
        return blocks
    if first < 0 or first + R - 1 + span - 1 >= T:
        raise ValueError(
            f"residual groups {first}..{first + R - 1} spanning {span} frames exceed T={T}"
        )
    Jw = J if w is None else J * torch.as_tensor(w, dtype=torch.float64)[:, None, :, None]
    Jw = Jw.transpose(2, 3).contiguous()  # (R, span, n, m)
    bt = torch.from_numpy(blocks)  # shares memory
    for a in range(span):
        for c in range(a + 1):  # frame first+r+a (row) >= frame first+r+c (col): offset a - c
            bt[a - c, first + c : first + c + R] += torch.bmm(Jw[:, a], J[:, c])
    return blocks


def to_lapack_lower(blocks: np.ndarray) -> np.ndarray:
    """LAPACK lower band storage ab (n (b+1), T n) with ab[i - j, j] = N[i, j] for i >= j."""
    T, b, n = _check_blocks(blocks)
    u = n * (b + 1) - 1
    ab = np.zeros((u + 1, T * n))
    abv = ab.reshape(u + 1, T, n)
    for d in range(b + 1):
        rows = T - d
        if rows <= 0:
            break
        for alpha in range(n):
            for beta in range(n):
                off = n * d + alpha - beta
                if off < 0:
                    continue
                abv[off, :rows, beta] = blocks[d, :rows, alpha, beta]
    return ab


def to_dense(blocks: np.ndarray) -> np.ndarray:
    """The full symmetric (T n, T n) matrix (for tests and small problems only)."""
    T, b, n = _check_blocks(blocks)
    N = np.zeros((T * n, T * n))
    for s in range(T):
        for d in range(b + 1):
            if s + d >= T:
                break
            blk = blocks[d, s]
            N[(s + d) * n : (s + d + 1) * n, s * n : (s + 1) * n] = blk
            if d:
                N[s * n : (s + 1) * n, (s + d) * n : (s + d + 1) * n] = blk.T
    return N


def cholesky(blocks: np.ndarray) -> np.ndarray:
    """Banded lower Cholesky factor in LAPACK lower band storage (raises LinAlgError if not PD)."""
    return cholesky_banded(to_lapack_lower(blocks), lower=True, check_finite=False)


def solve(blocks: np.ndarray, rhs: np.ndarray, factor: np.ndarray | None = None) -> np.ndarray:
    """Solve N x = rhs.  blocks: (b+1, T, n, n); rhs: (T, n) or (T, n, k) -> same shape as rhs."""
    T, b, n = _check_blocks(blocks)
    if rhs.shape[:2] != (T, n):
        raise ValueError(f"rhs must have shape ({T}, {n}[, k]), got {rhs.shape}")
    if T == 0:
        return np.zeros_like(rhs)
    cb = cholesky(blocks) if factor is None else factor
    x = cho_solve_banded((cb, True), rhs.reshape(T * n, -1), check_finite=False)
    return x.reshape(rhs.shape)


def diagonal_blocks_of_inverse(blocks: np.ndarray, factor: np.ndarray | None = None) -> np.ndarray:
    """The (n x n) diagonal blocks of N^-1, in O(T).  (b+1, T, n, n) -> (T, n, n).

    Selected inversion (Takahashi recursion, block form): frames are grouped into super-blocks
    of b frames, which makes N block-tridiagonal with (b n)^2 blocks. With the banded Cholesky
    factor N = L L^T (super-blocks L_ii, L_{i+1,i}), M_i = L_{i+1,i} L_ii^-1 and
    P_i = L_ii^-T L_ii^-1, the diagonal super-blocks of S = N^-1 obey
    S_last = P_last and S_i = P_i + M_i^T S_{i+1} M_i (a backward sweep of small matmuls).
    """
    T, b, n = _check_blocks(blocks)
    if T == 0:
        return np.zeros((0, n, n))
    g = max(b, 1)  # frames per super-block
    Tp = -(-T // g) * g
    if Tp != T:  # pad with decoupled identity frames
        pad = np.zeros((b + 1, Tp - T, n, n))
        pad[0] = np.eye(n)
        blocks = np.concatenate([blocks, pad], 1)
        factor = None
    cb = cholesky(blocks) if factor is None else factor
    m = g * n  # super-block size
    nb = Tp // g
    u = cb.shape[0] - 1
    # gather the lower-triangular diagonal super-blocks and the sub-diagonal ones from the band
    a = np.arange(m)[:, None]
    c = np.arange(m)[None, :]
    base = (np.arange(nb) * m)[:, None, None]
    off_d = a - c  # (m, m)
    ok_d = (off_d >= 0) & (off_d <= u)
    Ld = np.where(ok_d, cb[np.clip(off_d, 0, u), base + c], 0.0)  # (nb, m, m)
    off_s = m + a - c
    ok_s = off_s <= u
    Ls = np.where(ok_s, cb[np.clip(off_s, 0, u), base[:-1] + c], 0.0)  # (nb-1, m, m)
    Linv = _batched_lower_inverse(Ld)
    P = np.matmul(Linv.transpose(0, 2, 1), Linv)
    M = Ls @ Linv[:-1]  # (nb-1, m, m)
    S = np.empty_like(P)
    S[-1] = P[-1]
    for i in range(nb - 2, -1, -1):
        Mi = M[i]
        S[i] = P[i] + Mi.T @ S[i + 1] @ Mi
    # diagonal n x n blocks of each super-block
    S = S.reshape(nb, g, n, g, n)
    diag = S[:, np.arange(g), :, np.arange(g), :]  # (g, nb, n, n)
    diag = diag.transpose(1, 0, 2, 3).reshape(Tp, n, n)
    return np.ascontiguousarray(diag[:T])


def _batched_lower_inverse(L: np.ndarray) -> np.ndarray:
    """Inverse of a batch of lower-triangular matrices (B, m, m) (torch's batched solve)."""
    Lt = torch.from_numpy(np.ascontiguousarray(L))
    eye = torch.eye(L.shape[-1], dtype=Lt.dtype).expand_as(Lt)
    return torch.linalg.solve_triangular(Lt, eye, upper=False).numpy()
