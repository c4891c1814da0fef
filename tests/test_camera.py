"""adjust.camera: projection and undistortion vs OpenCV, P = K[R|t] and its decomposition."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from adjust.camera import (
    Camera,
    CameraTensors,
    decompose_projection_matrix,
    depth,
    project_cameras,
    project_points,
    projection_matrix,
    undistort_points,
)
from adjust.distortion import (
    distort_normalized,
    normalized_to_pixels,
    pixels_to_normalized,
    undistort_normalized,
)
from deformnet.so3 import rodrigues_to_matrix

D = torch.float64
DIST = np.array([-0.21, 0.08, 1.2e-3, -7e-4, -0.015])


def make_camera(seed: int = 0, dist: np.ndarray | None = DIST, skew: float = 0.0) -> Camera:
    rng = np.random.default_rng(seed)
    K = np.array(
        [[1200 + 100 * rng.random(), skew, 640 + rng.normal() * 5], [0, 1180, 512], [0, 0, 1]]
    )
    rvec = rng.normal(size=3) * 0.6
    tvec = np.array([20.0, -30.0, 900.0]) + rng.normal(size=3) * 10
    return Camera(f"cam{seed}", K, np.zeros(5) if dist is None else dist, rvec, tvec, (1280, 1024))


def points_in_front(cam: Camera, n: int, seed: int = 1, half: float = 150.0) -> np.ndarray:
    """World points within the camera's field of view (depth ~ 900 mm)."""
    rng = np.random.default_rng(seed)
    Xc = np.column_stack(
        (rng.uniform(-half, half, n), rng.uniform(-half, half, n), rng.uniform(750, 1050, n))
    )
    return (Xc - cam.tvec) @ cam.R  # R^T (Xc - t)


def test_project_points_matches_cv2():
    for seed, skew in ((0, 0.0), (1, 0.0), (2, 3.5)):
        cam = make_camera(seed, skew=skew)
        X = points_in_front(cam, 200, seed)
        uv = project_points(
            torch.as_tensor(X), *(torch.as_tensor(a) for a in (cam.K, cam.R, cam.tvec, cam.dist))
        )
        if skew == 0.0:
            uv_cv, _ = cv2.projectPoints(X, cam.rvec, cam.tvec, cam.K, cam.dist)
            np.testing.assert_allclose(uv.numpy(), uv_cv[:, 0], atol=1e-8)
        else:  # cv2.projectPoints ignores skew; check P = K [R|t] on the undistorted model
            uv0 = project_points(
                torch.as_tensor(X), *(torch.as_tensor(a) for a in (cam.K, cam.R, cam.tvec))
            )
            xh = np.column_stack((X, np.ones(len(X)))) @ cam.P.T
            np.testing.assert_allclose(uv0.numpy(), xh[:, :2] / xh[:, 2:], atol=1e-8)


def test_project_cameras_shapes_and_depth():
    cams = [make_camera(s) for s in range(3)]
    ct = CameraTensors.from_cameras(cams)
    X = torch.as_tensor(points_in_front(cams[0], 4 * 5)).reshape(4, 5, 3)
    uv = project_cameras(X, ct)
    assert uv.shape == (4, 5, 3, 2)
    z = depth(X[..., None, :], ct.R, ct.t)
    assert z.shape == (4, 5, 3)
    assert (z[..., 0] > 700).all()
    torch.testing.assert_close(ct.centers[1], torch.as_tensor(cams[1].center))
    torch.testing.assert_close(ct.P[2], torch.as_tensor(cams[2].P))
    with pytest.raises(ValueError):
        project_points(X[..., :2], ct.K, ct.R, ct.t)


def test_gradcheck_project_points():
    cam = make_camera(3)
    X = torch.as_tensor(points_in_front(cam, 4)).requires_grad_(True)
    args = [torch.as_tensor(a).clone().requires_grad_(True) for a in (cam.K, cam.R, cam.tvec)]
    dist = torch.as_tensor(cam.dist).clone().requires_grad_(True)
    assert torch.autograd.gradcheck(project_points, (X, *args, dist))


def _undistort_cv2(uv, K, dist, crit):
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
        return cv2.undistortPointsIter(uv, K, dist, None, None, crit)
    return cv2.undistortPoints(uv, K, dist, None, None, None, crit)  # OpenCV >= 5


def test_undistort_matches_cv2_and_inverts_distort():
    cam = make_camera(4)
    X = points_in_front(cam, 500, 4, half=300.0)  # up to ~0.35 normalized radius, image corners
    uv_cv, _ = cv2.projectPoints(X, cam.rvec, cam.tvec, cam.K, cam.dist)
    uv = torch.as_tensor(uv_cv[:, 0])
    K, dist = torch.as_tensor(cam.K), torch.as_tensor(cam.dist)
    xy = undistort_points(uv, K, dist)
    # the truth: x/z in camera coordinates
    Xc = X @ cam.R.T + cam.tvec
    np.testing.assert_allclose(xy.numpy(), Xc[:, :2] / Xc[:, 2:], atol=1e-12)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    xy_cv = _undistort_cv2(uv_cv, cam.K, cam.dist, crit)[:, 0]
    np.testing.assert_allclose(xy.numpy(), xy_cv, atol=1e-9)
    xy_cv5 = cv2.undistortPoints(uv_cv, cam.K, cam.dist)[:, 0]  # OpenCV's 5 fixed-point steps
    np.testing.assert_allclose(xy.numpy(), xy_cv5, atol=1e-3)
    # pixels out, and the inverse of distort_normalized
    uv_ideal = undistort_points(uv, K, dist, pixels=True)
    np.testing.assert_allclose(uv_ideal.numpy(), normalized_to_pixels(xy, K).numpy())
    torch.testing.assert_close(distort_normalized(xy, dist), pixels_to_normalized(uv, K))
    xyd = torch.rand(3, 7, 2, dtype=D) - 0.5
    torch.testing.assert_close(
        distort_normalized(undistort_normalized(xyd, dist), dist), xyd, atol=1e-13, rtol=0
    )
    assert undistort_points(uv, K, None).shape == uv.shape
    with pytest.raises(ValueError):
        undistort_points(uv[:, :1], K, dist)


def test_undistort_nan_and_broadcast():
    cams = CameraTensors.from_cameras([make_camera(s) for s in range(3)])
    uv = torch.rand(5, 4, 3, 2, dtype=D) * 1000
    uv[0, 0, 1] = float("nan")
    xy = undistort_points(uv, cams.K, cams.dist)
    assert xy.shape == (5, 4, 3, 2)
    assert torch.isnan(xy[0, 0, 1]).all() and torch.isfinite(xy[1:]).all()


def test_gradcheck_undistort():
    cam = make_camera(5)
    uv = torch.tensor([[100.0, 80.0], [640.0, 500.0], [1200.0, 950.0]], dtype=D)
    K = torch.as_tensor(cam.K).clone().requires_grad_(True)
    dist = torch.as_tensor(cam.dist).clone().requires_grad_(True)
    assert torch.autograd.gradcheck(undistort_points, (uv.requires_grad_(True), K, dist))


def test_projection_matrix_and_decomposition_round_trip():
    cams = [make_camera(s, skew=2.0 * s) for s in range(4)]
    ct = CameraTensors.from_cameras(cams)
    P = projection_matrix(ct.K, ct.R, ct.t)
    assert P.shape == (4, 3, 4)
    scale = torch.tensor([1.0, -3.0, 1e-3, -2e4], dtype=D)[:, None, None]
    K, R, t = decompose_projection_matrix(P * scale)
    torch.testing.assert_close(K, ct.K, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(R, ct.R, rtol=0, atol=1e-12)
    torch.testing.assert_close(t, ct.t, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(4, dtype=D))
    with pytest.raises(ValueError):
        decompose_projection_matrix(torch.zeros(3, 4, dtype=D))
    with pytest.raises(ValueError):
        decompose_projection_matrix(torch.zeros(3, 3, dtype=D))


def test_decomposition_matches_cv2():
    rng = np.random.default_rng(7)
    for _ in range(20):
        P = rng.normal(size=(3, 4))
        K, R, t = (a.numpy() for a in decompose_projection_matrix(torch.as_tensor(P)))
        Kc, Rc, Ch = cv2.decomposeProjectionMatrix(P)[:3]
        assert np.all(np.diag(K) > 0) and abs(np.linalg.det(R) - 1) < 1e-12
        # P = s K [R | t] for some s
        KRt = K @ np.column_stack((R, t))
        s = (P * KRt).sum() / (KRt * KRt).sum()
        np.testing.assert_allclose(s * KRt, P, atol=1e-10)
        # the camera centre is unique; cv2's K, R agree up to OpenCV's sign choices
        np.testing.assert_allclose(-R.T @ t, Ch[:3, 0] / Ch[3, 0], rtol=1e-9, atol=1e-9)
        if np.all(np.diag(Kc) > 0) and np.linalg.det(Rc) > 0:
            np.testing.assert_allclose(K, Kc / Kc[2, 2], rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(R, Rc, atol=1e-9)


def test_gradcheck_decomposition():
    cam = make_camera(8, skew=1.5)
    P = torch.as_tensor(cam.P / 1000.0).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda P: decompose_projection_matrix(P), (P,))


def test_camera_constructors():
    cam = make_camera(9, skew=0.5)
    same = Camera.from_projection_matrix("x", -2.5 * cam.P, cam.dist, cam.size)
    np.testing.assert_allclose(same.K, cam.K, rtol=1e-12)
    np.testing.assert_allclose(same.rvec, cam.rvec, atol=1e-12)
    np.testing.assert_allclose(same.tvec, cam.tvec, rtol=1e-12)
    assert same.size == cam.size
    again = Camera.from_matrices("y", cam.K, cam.R, cam.tvec)
    np.testing.assert_allclose(again.P, cam.P, rtol=1e-12)
    assert np.all(again.dist == 0)
    with pytest.raises(ValueError):
        Camera.from_matrices("z", cam.K, np.eye(2), cam.tvec)
    ct = CameraTensors.from_cameras([cam]).to(torch.float32)
    assert ct.K.dtype == torch.float32 and ct.names == ("cam9",)
    torch.testing.assert_close(
        rodrigues_to_matrix(torch.as_tensor(cam.rvec)).float(), ct.R[0], atol=1e-6, rtol=0
    )


def test_small_helpers_shapes_values_gradients():
    cams = CameraTensors.from_cameras([make_camera(s, skew=1.0) for s in range(2)])
    K = cams.K.clone().requires_grad_(True)
    uv = (torch.rand(4, 2, 2, dtype=D) * 1000).requires_grad_(True)
    xy = pixels_to_normalized(uv, K)
    assert xy.shape == (4, 2, 2)
    torch.testing.assert_close(normalized_to_pixels(xy, K), uv)
    assert torch.autograd.gradcheck(pixels_to_normalized, (uv, K))
    assert torch.autograd.gradcheck(normalized_to_pixels, (xy.detach().requires_grad_(True), K))
    d = cams.dist.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(distort_normalized, (xy.detach().requires_grad_(True), d))
    R, t = cams.R.clone().requires_grad_(True), cams.t.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(projection_matrix, (K, R, t))
    assert projection_matrix(cams.K[0], cams.R[0], cams.t).shape == (2, 3, 4)  # broadcast
    with pytest.raises(ValueError):
        projection_matrix(cams.K, cams.R, cams.t[..., :2])
    with pytest.raises(ValueError):
        pixels_to_normalized(uv[..., :1], K)
    with pytest.raises(ValueError):
        normalized_to_pixels(xy, K[..., :2])
    with pytest.raises(ValueError):
        undistort_normalized(xy, cams.dist[..., :4])
    with pytest.raises(ValueError):
        undistort_normalized(xy, cams.dist, iters=-1)


def test_reprojection_errors_one_implementation():
    from adjust.camera import reprojection_errors
    from adjust.metrics import error_summary, stats
    from adjust.metrics import reprojection_errors as errors_np
    from adjust.triangulate import reprojection_errors as errors_tri

    assert errors_tri is reprojection_errors  # one function, re-exported
    cams = [make_camera(s) for s in range(3)]
    ct = CameraTensors.from_cameras(cams)
    X = torch.as_tensor(points_in_front(cams[0], 4 * 5)).reshape(4, 5, 3)
    uv = project_cameras(X, ct)
    uv[..., 1, :] += torch.tensor([3.0, 4.0], dtype=D)  # 5 px off in camera 1
    uv[0, 0, 2] = float("nan")
    observed = torch.ones(4, 5, 3, dtype=torch.bool)
    observed[1, :, 0] = False
    e = reprojection_errors(X, uv, ct, observed)
    assert e.shape == (4, 5, 3)
    torch.testing.assert_close(e[..., 1], torch.full((4, 5), 5.0, dtype=D))
    assert torch.isnan(e[0, 0, 2]) and torch.isnan(e[1, :, 0]).all()
    assert float(e[2:, :, 0].abs().max()) < 1e-9
    np.testing.assert_array_equal(errors_np(X.numpy(), uv.numpy(), cams, observed.numpy()), e)
    # a zero error has a zero (not NaN) gradient; gradcheck where it is not zero
    Xg = X[2:, :2].clone().requires_grad_(True)
    reprojection_errors(Xg, uv[2:, :2], ct)[..., 0].sum().backward()
    assert torch.isfinite(Xg.grad).all()
    f = lambda P: reprojection_errors(P, uv[2:, :2], ct)[..., 1]  # noqa: E731
    assert torch.autograd.gradcheck(f, (Xg.detach().requires_grad_(True),))
    with pytest.raises(ValueError):
        reprojection_errors(X, uv, ct, observed[..., :2])
    with pytest.raises(ValueError):
        reprojection_errors(X[..., :2], uv, ct)
    # the two summaries of such errors are one computation with two views
    s, t = error_summary(e.numpy()), stats(e.numpy())
    assert t == {"count": s["n"], "median": s["median"], "mean": s["mean"], "p90": s["p90"],
                 "max": s["max"]}  # fmt: skip
    assert stats(np.array([np.nan])) == {
        "count": 0, "median": None, "mean": None, "p90": None, "max": None
    }  # fmt: skip
