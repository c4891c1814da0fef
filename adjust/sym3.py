"""Symmetric 3x3 systems, batched and elementwise (cofactors): the one 3x3 symmetric solver.

A symmetric 3x3 matrix is given by its six upper-triangle entries (m00, m01, m02, m11, m12,
m22), each a tensor of the same shape ``(...)``, or as ``(..., 3, 3)``. Elementwise cofactor
formulas beat ``torch.linalg`` by far on millions of tiny systems (triangulation, per-point
fusion, covariances) and are differentiable; float64 recommended.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def sym3_cofactors(m: Sequence[Tensor]) -> tuple[tuple[Tensor, ...], Tensor]:
    """Cofactors and determinant of symmetric 3x3 matrices.

    m: the six entries (m00, m01, m02, m11, m12, m22), each (...) -> ((c00, c01, c02, c11, c12,
    c22), det), each (...); the inverse is the cofactor matrix over det.
    """
    if len(m) != 6:
        raise ValueError(f"need the six entries (m00, m01, m02, m11, m12, m22), got {len(m)}")
    m00, m01, m02, m11, m12, m22 = m
    if not all(x.shape == m00.shape for x in m):
        raise ValueError(f"the six entries need one shape, got {[tuple(x.shape) for x in m]}")
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    c11 = m00 * m22 - m02 * m02
    c12 = m01 * m02 - m00 * m12
    c22 = m00 * m11 - m01 * m01
    det = m00 * c00 + m01 * c01 + m02 * c02
    return (c00, c01, c02, c11, c12, c22), det


def sym3_inverse(M: Tensor) -> Tensor:
    """Inverse of symmetric 3x3 matrices by cofactors. M: (..., 3, 3) -> (..., 3, 3).

    No singularity guard (a singular matrix gives inf/NaN); `sym3_solve` has one.
    """
    if M.dim() < 2 or M.shape[-2:] != (3, 3):
        raise ValueError(f"M must be (..., 3, 3), got {tuple(M.shape)}")
    (A, B, Cc, D, E, F), det = sym3_cofactors(
        (M[..., 0, 0], M[..., 0, 1], M[..., 0, 2], M[..., 1, 1], M[..., 1, 2], M[..., 2, 2])
    )
    inv = 1.0 / det
    return (
        torch.stack(
            (torch.stack((A, B, Cc), -1), torch.stack((B, D, E), -1), torch.stack((Cc, E, F), -1)),
            -2,
        )
        * inv[..., None, None]
    )


def sym3_solve(m: Sequence[Tensor], v: Tensor, rel_eps: float) -> tuple[Tensor, Tensor]:
    """Solve M X = v for symmetric 3x3 M by the adjugate; never raises on singular systems.

    m: the six entries of M, each (...); v: (..., 3) -> X (..., 3), ok (...) bool: False where M is
    singular relative to its scale (det <= rel_eps (trace / 3)^3, or not finite; X is then
    meaningless but finite).
    """
    (c00, c01, c02, c11, c12, c22), det = sym3_cofactors(m)
    if v.shape != (*det.shape, 3):
        raise ValueError(
            f"v must be {(*det.shape, 3)} for entries {tuple(det.shape)}, got {tuple(v.shape)}"
        )
    m00, _, _, m11, _, m22 = m
    scale = ((m00 + m11 + m22) / 3.0) ** 3
    ok = (det > rel_eps * scale) & (scale > 0) & torch.isfinite(det)
    det = torch.where(ok, det, torch.ones_like(det))
    v0, v1, v2 = v.unbind(-1)
    X = (
        torch.stack(
            (
                c00 * v0 + c01 * v1 + c02 * v2,
                c01 * v0 + c11 * v1 + c12 * v2,
                c02 * v0 + c12 * v1 + c22 * v2,
            ),
            -1,
        )
        / det[..., None]
    )
    return X, ok
