"""adjust.distortion (and the one projection, adjust.camera.camera_to_pixels): shape, value
(against OpenCV and autograd) and float64 gradcheck of every public function."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from adjust.camera import CameraTensors, camera_to_pixels, project_points
from adjust.distortion import (
    check_shape,
    distort_components,
    distort_jacobian,
    distort_normalized,
    distort_points,
    normalized_to_pixels,
    pixels_to_normalized,
    undistort_normalized,
    undistort_points,
)
from adjust.lsq.geometry import project_components, project_with_jacobian

D = torch.float64
DIST = torch.tensor(
    [[-0.21, 0.08, 1.2e-3, -7e-4, -0.015], [0.05, -0.02, -4e-4, 9e-4, 0.003]], dtype=D
)
K = torch.tensor(
    [
        [[1210.0, 1.5, 641.0], [0.0, 1180.0, 512.0], [0.0, 0.0, 1.0]],
        [[1090.0, 0.0, 630.0], [0.0, 1062.0, 500.0], [0.0, 0.0, 1.0]],
    ],
    dtype=D,
)


def _xy(*shape: int, seed: int = 0, half: float = 0.35) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(*shape, 2, generator=g, dtype=D) * 2 - 1) * half


def test_check_shape():
    check_shape(torch.zeros(4, 3, 3), (3, 3), "M")
    for bad in (torch.zeros(3), torch.zeros(4, 3, 2), np.zeros((3, 3))):
        with pytest.raises(ValueError, match=r"M must be a tensor of shape \(\.\.\., 3, 3\)"):
            check_shape(bad, (3, 3), "M")


def test_distort_matches_cv2_and_components():
    xy = _xy(300, seed=1)  # up to the image corners
    for c in range(2):
        pts = torch.cat((xy, torch.ones(300, 1, dtype=D)), -1).numpy()
        ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), DIST[c].numpy())
        out = distort_normalized(xy, DIST[c])
        assert out.shape == (300, 2)
        np.testing.assert_allclose(out.numpy(), ref[:, 0], rtol=0, atol=1e-14)
        xd, yd, J = distort_components(xy[:, 0], xy[:, 1], DIST[c])
        assert J is None
        torch.testing.assert_close(torch.stack((xd, yd), -1), out, rtol=0, atol=0)
    # broadcast: points (T, C, 2) with one distortion per camera (C, 5)
    xy3 = _xy(5, 2, seed=2)
    out = distort_normalized(xy3, DIST)
    assert out.shape == (5, 2, 2)
    torch.testing.assert_close(out[:, 1], distort_normalized(xy3[:, 1], DIST[1]))
    with pytest.raises(ValueError):
        distort_normalized(xy3[..., :1], DIST)
    with pytest.raises(ValueError):
        distort_normalized(xy3, DIST[:, :4])


def test_distort_jacobian_value_and_gradients():
    xy = _xy(4, 2, seed=3).requires_grad_(True)
    dist = DIST.clone().requires_grad_(True)
    J = distort_jacobian(xy, dist)
    assert J.shape == (4, 2, 2, 2)
    torch.testing.assert_close(J, J.transpose(-1, -2), rtol=0, atol=0)  # symmetric
    for i in range(4):
        for c in range(2):
            ref = torch.autograd.functional.jacobian(
                lambda p, c=c: distort_normalized(p, DIST[c]), xy[i, c].detach()
            )
            torch.testing.assert_close(J[i, c], ref, rtol=1e-13, atol=1e-14)
    _, _, (a, b, d) = distort_components(xy[..., 0], xy[..., 1], dist, jacobian=True)
    torch.testing.assert_close(torch.stack((a, b, d), -1), J[..., [0, 0, 1], [0, 1, 1]])
    assert torch.autograd.gradcheck(distort_normalized, (xy, dist))
    assert torch.autograd.gradcheck(distort_jacobian, (xy, dist))
    with pytest.raises(ValueError):
        distort_jacobian(xy[..., :1], dist)


def test_undistort_inverts_distort_with_implicit_gradients():
    xyd = _xy(6, 2, seed=4, half=0.3)
    xy = undistort_normalized(xyd, DIST)
    assert xy.shape == (6, 2, 2)
    torch.testing.assert_close(distort_normalized(xy, DIST), xyd, rtol=0, atol=1e-14)
    # no distortion: the identity, exactly
    assert torch.equal(undistort_normalized(xyd, torch.zeros(5, dtype=D)), xyd)
    # the derivative is the inverse of distort_jacobian at the solution
    g = torch.autograd.functional.jacobian(lambda p: undistort_normalized(p, DIST[0]), xyd[0, 0])
    torch.testing.assert_close(g, torch.linalg.inv(distort_jacobian(xy[0, 0], DIST[0])))
    a = xyd.clone().requires_grad_(True)
    dist = DIST.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(undistort_normalized, (a, dist))
    nan = xyd.clone()
    nan[0, 0] = float("nan")
    out = undistort_normalized(nan, DIST)
    assert torch.isnan(out[0, 0]).all() and torch.isfinite(out[1:]).all()
    with pytest.raises(ValueError):
        undistort_normalized(xyd, DIST, iters=-1)
    with pytest.raises(ValueError):
        undistort_normalized(xyd[..., :1], DIST)


def test_intrinsics_and_pixel_functions():
    uv = (torch.rand(5, 2, 2, generator=torch.Generator().manual_seed(5), dtype=D) * 900) + 100
    xy = pixels_to_normalized(uv, K)
    assert xy.shape == (5, 2, 2)
    torch.testing.assert_close(normalized_to_pixels(xy, K), uv, rtol=0, atol=1e-10)
    ideal = undistort_points(uv, K, DIST, pixels=True)
    assert ideal.shape == (5, 2, 2)
    torch.testing.assert_close(distort_points(ideal, K, DIST), uv, rtol=0, atol=1e-10)
    # against OpenCV (no skew there): camera 0 with its skew removed
    K0 = K[0].clone()
    K0[0, 1] = 0.0
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    pts = uv[:, 0].numpy()[:, None]
    if hasattr(cv2, "undistortPointsIter"):
        ref = cv2.undistortPointsIter(pts, K0.numpy(), DIST[0].numpy(), None, None, crit)
    else:  # OpenCV >= 5
        ref = cv2.undistortPoints(pts, K0.numpy(), DIST[0].numpy(), None, None, None, crit)
    np.testing.assert_allclose(
        undistort_points(uv[:, 0], K0, DIST[0]).numpy(), ref[:, 0], rtol=0, atol=1e-9
    )
    args = (uv.clone().requires_grad_(True), K.clone().requires_grad_(True))
    assert torch.autograd.gradcheck(pixels_to_normalized, args)
    assert torch.autograd.gradcheck(normalized_to_pixels, (xy.detach().requires_grad_(True), K))
    dist = DIST.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(distort_points, (ideal.detach().requires_grad_(True), K, dist))
    assert torch.autograd.gradcheck(undistort_points, (*args, dist))
    with pytest.raises(ValueError):
        distort_points(uv, K[..., :2], DIST)


def _cams() -> CameraTensors:
    from deformnet.so3 import rodrigues_to_matrix

    R = rodrigues_to_matrix(torch.tensor([[0.3, -0.2, 0.1], [-0.1, 0.4, 0.2]], dtype=D))
    t = torch.tensor([[10.0, -20.0, 900.0], [-30.0, 5.0, 1000.0]], dtype=D)
    return CameraTensors(K, R, t, DIST, ("a", "b"))


def test_camera_to_pixels_is_the_one_projection():
    cams = _cams()
    g = torch.Generator().manual_seed(6)
    X = (torch.rand(4, 3, 3, generator=g, dtype=D) - 0.5) * 200
    Xc = torch.einsum("cij,...j->...ci", cams.R, X) + cams.t  # (4, 3, C, 3)
    u, v, A = camera_to_pixels(Xc, cams.K, cams.dist, jacobian=True)
    assert u.shape == v.shape == (4, 3, 2) and len(A) == 6
    uv = torch.stack((u, v), -1)
    # value: pinhole of the distorted normalized point
    xd = distort_normalized(Xc[..., :2] / Xc[..., 2:], cams.dist)
    torch.testing.assert_close(uv, normalized_to_pixels(xd, cams.K), rtol=0, atol=1e-10)
    torch.testing.assert_close(
        uv, project_points(X[..., None, :], cams.K, cams.R, cams.t, cams.dist)
    )
    # the solver's fast path and the stacked Jacobian call the same projection
    pu, pv, z, PA = project_components(X, cams, True)
    torch.testing.assert_close(torch.stack((pu, pv), -1), uv, rtol=0, atol=0)
    torch.testing.assert_close(z, Xc[..., 2])
    for a, b in zip(A, PA, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    uv2, J, _ = project_with_jacobian(X, cams)
    torch.testing.assert_close(uv2, uv, rtol=0, atol=0)
    # derivative: against autograd, through camera coordinates
    Am = torch.stack((torch.stack(A[:3], -1), torch.stack(A[3:], -1)), -2)  # (4, 3, C, 2, 3)
    for c in range(2):
        ref = torch.autograd.functional.jacobian(
            lambda p, c=c: torch.stack(camera_to_pixels(p, cams.K[c], cams.dist[c])[:2], -1),
            Xc[1, 2, c],
        )
        torch.testing.assert_close(Am[1, 2, c], ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(J, Am @ cams.R)
    # no distortion and no skew: the skipped terms are exact
    K0 = cams.K.clone()
    K0[:, 0, 1] = 0.0
    full = camera_to_pixels(Xc, K0, torch.zeros_like(cams.dist), jacobian=True)
    fast = camera_to_pixels(Xc, K0, None, jacobian=True, skew=False)
    for a, b in zip((*full[:2], *full[2]), (*fast[:2], *fast[2]), strict=True):
        torch.testing.assert_close(a, b.expand_as(a), rtol=0, atol=0)
    # gradients (float64)
    args = (Xc[0].clone().requires_grad_(True), cams.K.clone().requires_grad_(True))
    dist = cams.dist.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda *a: camera_to_pixels(*a, jacobian=True)[2], (*args, dist)
    )
    assert torch.autograd.gradcheck(lambda *a: camera_to_pixels(*a)[:2], (*args, dist))
    with pytest.raises(ValueError):
        camera_to_pixels(Xc[..., :2], cams.K)
    with pytest.raises(ValueError):
        camera_to_pixels(Xc, cams.K[..., :2])
