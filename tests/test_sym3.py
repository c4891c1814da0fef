"""adjust.sym3: the one symmetric 3x3 solver (cofactors), and the initialiser's triangulated
parts (adjust.lsq.init.triangulated_parts, on adjust.triangulate's one triangulator)."""

from __future__ import annotations

import pytest
import torch

from adjust.sym3 import sym3_cofactors, sym3_inverse, sym3_solve

D = torch.float64


def _spd(*lead: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(*lead, 3, 3, generator=g, dtype=D)
    return A @ A.transpose(-1, -2) + 0.5 * torch.eye(3, dtype=D)


def _entries(M: torch.Tensor) -> tuple[torch.Tensor, ...]:
    return tuple(M[..., i, j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))


def test_inverse_and_solve_match_linalg_in_any_batch_shape():
    M = _spd(4, 5)
    assert sym3_inverse(M).shape == (4, 5, 3, 3)
    torch.testing.assert_close(sym3_inverse(M), torch.linalg.inv(M), rtol=1e-10, atol=1e-12)
    v = torch.randn(4, 5, 3, dtype=D, generator=torch.Generator().manual_seed(1))
    X, ok = sym3_solve(_entries(M), v, 1e-12)
    assert X.shape == (4, 5, 3) and ok.shape == (4, 5) and bool(ok.all())
    torch.testing.assert_close(X, torch.linalg.solve(M, v[..., None])[..., 0], rtol=1e-10,
                               atol=1e-12)  # fmt: skip
    _, det = sym3_cofactors(_entries(M))
    torch.testing.assert_close(det, torch.linalg.det(M), rtol=1e-10, atol=1e-12)


def test_solve_flags_singular_systems_and_stays_finite():
    M = _spd(3)
    M[1] = torch.outer(
        torch.tensor([1.0, 2.0, 3.0], dtype=D), torch.tensor([1.0, 2.0, 3.0], dtype=D)
    )
    M[2] = 0.0
    X, ok = sym3_solve(_entries(M), torch.ones(3, 3, dtype=D), 1e-12)
    assert ok.tolist() == [True, False, False] and bool(torch.isfinite(X).all())


def test_shapes_are_checked():
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        sym3_inverse(torch.zeros(4, 3, dtype=D))
    with pytest.raises(ValueError, match="six entries"):
        sym3_cofactors(tuple(torch.zeros(2, dtype=D) for _ in range(5)))
    with pytest.raises(ValueError, match="one shape"):
        sym3_cofactors((torch.zeros(2, dtype=D),) * 5 + (torch.zeros(3, dtype=D),))
    with pytest.raises(ValueError, match="v must be"):
        sym3_solve(_entries(_spd(2)), torch.zeros(2, 2, dtype=D), 1e-12)


def test_gradcheck_float64():
    M = _spd(2).requires_grad_(True)
    v = torch.randn(2, 3, dtype=D, generator=torch.Generator().manual_seed(2), requires_grad=True)

    def inv(A):
        return sym3_inverse(0.5 * (A + A.transpose(-1, -2)))

    def solve(A, b):
        S = 0.5 * (A + A.transpose(-1, -2))
        return sym3_solve(_entries(S), b, 1e-12)[0]

    assert torch.autograd.gradcheck(inv, (M,))
    assert torch.autograd.gradcheck(solve, (M, v))


def test_initial_triangulated_parts_drop_outliers_and_points_behind_a_camera():
    from adjust.camera import CameraTensors, project_cameras
    from adjust.lsq import synthetic
    from adjust.lsq.init import triangulated_parts
    from adjust.triangulate import triangulate

    cams = CameraTensors.from_cameras(synthetic.ring_cameras(4, distortion=0.05))
    g = torch.Generator().manual_seed(0)
    X = (torch.rand(20, 5, 3, generator=g, dtype=D) - 0.5) * 100.0
    centre = -cams.R[0].T @ cams.t[0]
    X[2, 0] = centre - 200.0 * cams.R[0, 2]  # behind camera 0
    xy = project_cameras(X, cams)
    valid = torch.ones(xy.shape[:-1], dtype=torch.bool)
    valid[0, 0, 1:] = False  # one view: not triangulated
    xy[1, 0, 2] += 200.0  # an outlier view: dropped
    Xt, ok = triangulated_parts(xy, valid, cams)
    assert Xt.shape == (20, 5, 3) and ok.shape == (20, 5)
    assert not ok[0, 0] and bool((Xt[0, 0] == 0).all())
    assert not ok[2, 0] and triangulate(xy, valid.to(D), cams).ncams[2, 0] == 4
    others = ok.clone()
    others[0, 0] = others[2, 0] = True
    assert bool(others.all())
    torch.testing.assert_close(Xt[ok], X[ok], rtol=0, atol=1e-6)
    plain = triangulate(xy, valid.to(D), cams)
    assert (plain.points[1, 0] - X[1, 0]).norm() > 1.0  # the outlier pulls the plain fit off
    with pytest.raises(ValueError, match=r"xy \(T, K, C, 2\)"):
        triangulated_parts(xy[0], valid[0], cams)
