"""adjust.triangulate: exact recovery, weights, robust view dropping, missing views, gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from adjust.camera import Camera, CameraTensors, look_at_pose, project_cameras
from adjust.triangulate import TriangulationResult, reprojection_errors, triangulate
from deformnet.so3 import matrix_to_rodrigues

D = torch.float64
DIST = np.array([-0.21, 0.08, 1.2e-3, -7e-4, -0.015])


def look_at(name: str, center, target=(0.0, 0.0, 0.0), dist=DIST, f=1200.0) -> Camera:
    """A camera at `center` (mm) looking at `target`, OpenCV axes (x right, y down, z forward)."""
    c, tgt = np.asarray(center, float), np.asarray(target, float)
    z = (tgt - c) / np.linalg.norm(tgt - c)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    R, t = look_at_pose(c, tgt, up, name)
    K = np.array([[f, 0.0, 640.0], [0.0, f * 0.99, 512.0], [0.0, 0.0, 1.0]])
    rvec = matrix_to_rodrigues(torch.as_tensor(R)).numpy()
    return Camera(name, K, dist, rvec, t, (1280, 1024))


def rig(n: int = 3) -> CameraTensors:
    """Front, top and side cameras ~1 m from the origin (like the lock-box rig), plus extras."""
    centers = [(0, -1000, 150), (30, 20, 1100), (1000, 40, 200), (-700, -700, 400)]
    return CameraTensors.from_cameras([look_at(f"c{i}", centers[i]) for i in range(n)])


def scene(T: int = 50, K: int = 8, C: int = 3, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    cams = rig(C)
    X = (torch.rand(T, K, 3, generator=g, dtype=D) - 0.5) * torch.tensor([300.0, 200.0, 150.0])
    uv = project_cameras(X, cams)
    w = torch.rand(T, K, C, generator=g, dtype=D) * 0.8 + 0.2
    return cams, X, uv, w, g


def test_noiseless_exact_with_distortion_and_dropout():
    cams, X, uv, w, g = scene()
    drop = torch.rand(w.shape, generator=g) < 0.3
    uv[drop] = float("nan")
    w[drop] = 0.0
    res = triangulate(uv, w, cams)
    assert isinstance(res, TriangulationResult)
    assert res.points.shape == (50, 8, 3) and res.error.shape == (50, 8)
    assert res.ncams.shape == (50, 8) and res.used.shape == (50, 8, 3)
    assert res.ncams.dtype == torch.int64 and res.used.dtype == torch.bool
    seen = (~drop).sum(-1) >= 2
    assert 0 < seen.sum() < seen.numel()  # both cases present
    assert (res.points[seen] - X[seen]).abs().max() < 1e-6
    assert res.error[seen].max() < 1e-6
    assert torch.isnan(res.points[~seen]).all() and torch.isnan(res.error[~seen]).all()
    assert torch.equal(res.ncams, torch.where(seen, (~drop).sum(-1), 0))
    assert torch.equal(res.used, ~drop & seen[..., None])
    assert torch.equal(res.nviews, (~drop).sum(-1))


def test_zero_and_one_view_give_nan_without_error():
    cams, X, uv, w, _ = scene(T=2, K=3)
    uv[0, 0] = float("nan")  # zero views
    w[0, 0] = 0.0
    uv[0, 1, 1:] = float("nan")  # one view
    w[0, 1, 1:] = 0.0
    w[0, 2, :2] = 0.0  # one view: finite xy but zero weight counts as missing
    for robust in (False, True):
        res = triangulate(uv, w, cams, robust=robust)
        assert torch.isnan(res.points[0]).all() and torch.isnan(res.error[0]).all()
        assert (res.ncams[0] == 0).all() and not res.used[0].any()
        assert res.nviews[0].tolist() == [0, 1, 1]
        assert torch.isfinite(res.points[1]).all()
    # all missing, and no frames at all
    res = triangulate(torch.full((4, 2, 3, 2), float("nan"), dtype=D), torch.zeros(4, 2, 3), cams)
    assert torch.isnan(res.points).all()
    res = triangulate(torch.zeros(0, 8, 3, 2, dtype=D), torch.zeros(0, 8, 3, dtype=D), cams)
    assert res.points.shape == (0, 8, 3)


def test_min_views_and_errors():
    cams, X, uv, w, _ = scene(T=4, K=2)
    w[0, 0, 2] = 0.0
    res = triangulate(uv, w, cams, min_views=3)
    assert torch.isnan(res.points[0, 0]).all() and torch.isfinite(res.points[1:]).all()
    with pytest.raises(ValueError, match="min_views"):
        triangulate(uv, w, cams, min_views=1)
    with pytest.raises(ValueError, match="xy must have shape"):
        triangulate(uv[..., :2, :], w, cams)
    with pytest.raises(ValueError, match="weight must have shape"):
        triangulate(uv, w[..., :2], cams)
    with pytest.raises(ValueError, match=">= 0"):
        triangulate(uv, -w, cams)


def test_numpy_inputs_and_float32():
    cams, X, uv, w, _ = scene(T=5, K=2)
    res = triangulate(uv.numpy(), w.numpy(), cams)
    assert (res.points - X).abs().max() < 1e-6
    cam_list = [
        Camera.from_matrices(
            f"c{i}", cams.K[i].numpy(), cams.R[i].numpy(), cams.t[i].numpy(), cams.dist[i].numpy()
        )
        for i in range(3)
    ]
    assert (triangulate(uv, w, cam_list).points - X).abs().max() < 1e-6
    with pytest.raises(TypeError):
        triangulate(uv, w, [1, 2, 3])
    res32 = triangulate(uv.float(), w.float(), cams.to(torch.float32))
    assert res32.points.dtype == torch.float32
    assert (res32.points.double() - X).abs().max() < 0.05  # mm


def test_weights_matter():
    """A view with a large error and a tiny weight barely moves the point."""
    cams, X, uv, w, _ = scene(T=1, K=4)
    uv = uv.clone()
    uv[..., 0, :] += 15.0
    w = torch.ones_like(w)
    e_equal = (triangulate(uv, w, cams).points - X).norm(dim=-1)
    w[..., 0] = 1e-4
    e_low = (triangulate(uv, w, cams).points - X).norm(dim=-1)
    assert (e_low < 0.02 * e_equal).all()


def test_noise_accuracy():
    cams, X, uv, w, g = scene(T=200, K=8)
    uv = uv + torch.randn(uv.shape, generator=g, dtype=D) * 0.5
    res = triangulate(uv, torch.ones_like(w), cams)
    err = (res.points - X).norm(dim=-1)
    assert err.median() < 0.6  # ~0.5 px at f = 1200 px, 1 m -> ~0.4 mm per axis
    assert 0.2 < res.error.median() < 0.8


def test_robust_rejects_far_outlier_view():
    cams, X, uv, w, g = scene(T=20, K=8, C=4)
    uv = uv + torch.randn(uv.shape, generator=g, dtype=D) * 0.5
    bad = torch.randint(0, 4, (20, 8), generator=g)
    uv.scatter_add_(
        2, bad[..., None, None].expand(20, 8, 1, 2), torch.full((20, 8, 1, 2), 150.0, dtype=D)
    )
    plain = triangulate(uv, w, cams)
    res = triangulate(uv, w, cams, robust=True, max_error_px=10.0)
    assert (plain.points - X).norm(dim=-1).min() > 5.0  # the outlier spoils every plain point
    assert (res.points - X).norm(dim=-1).max() < 3.0
    expected = torch.ones(20, 8, 4, dtype=torch.bool)
    expected.scatter_(2, bad[..., None], False)
    assert torch.equal(res.used, expected)
    assert (res.ncams == 3).all() and (res.error < 2.0).all()
    assert (res.view_error.gather(2, bad[..., None]) > 50).all()
    # with only two views nothing can be dropped; with a loose threshold nothing is
    two = triangulate(
        uv[..., :2, :],
        w[..., :2],
        CameraTensors(*(getattr(cams, k)[:2] for k in ("K", "R", "t", "dist"))),
        robust=True,
    )
    assert (two.ncams == 2).all()
    loose = triangulate(uv, w, cams, robust=True, max_error_px=1e4)
    assert torch.allclose(loose.points, plain.points)


def test_leading_dims_and_reprojection_errors():
    cams, X, uv, w, _ = scene(T=6, K=2)
    res = triangulate(uv.reshape(3, 2, 2, 3, 2), w.reshape(3, 2, 2, 3), cams)
    assert res.points.shape == (3, 2, 2, 3)
    e = reprojection_errors(X, uv, cams)
    assert e.shape == (6, 2, 3) and e.max() < 1e-9
    with pytest.raises(ValueError):
        reprojection_errors(X, uv[..., :2, :], cams)


def test_gradcheck_triangulation():
    cams, X, uv, w, _ = scene(T=1, K=2)
    uv = uv.clone().requires_grad_(True)
    w = w.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: triangulate(a, b, cams).points, (uv, w))
    t = cams.t.clone().requires_grad_(True)
    dist = cams.dist.clone().requires_grad_(True)

    def f(t, dist):
        return triangulate(uv.detach(), w.detach(), CameraTensors(cams.K, cams.R, t, dist)).points

    assert torch.autograd.gradcheck(f, (t, dist))
    # gradients are finite despite missing views, and zero for them
    uv2 = uv.detach().clone()
    uv2[0, 0, 2] = float("nan")
    uv2.requires_grad_(True)
    triangulate(uv2, w.detach(), cams, robust=True).points.sum().backward()
    assert torch.isfinite(uv2.grad).all() and (uv2.grad[0, 0, 2] == 0).all()


def test_gradcheck_reprojection_errors():
    cams, X, uv, w, _ = scene(T=2, K=2)
    X = (X + 1.0).requires_grad_(True)  # non-zero residuals (the norm is not smooth at 0)
    assert torch.autograd.gradcheck(lambda X: reprojection_errors(X, uv, cams), (X,))
