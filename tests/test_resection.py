"""adjust.resection: normalized DLT, LM refinement and PnP on a simulated lock-box target."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from test_triangulate import look_at

from adjust.camera import Camera, project_points
from adjust.resection import dlt, levenberg_marquardt, resect

D = torch.float64
DIST = np.array([-0.1, 0.05, 4e-4, -3e-4, 0.0])
# lock-box-sized target (mm): 8 corners of a 200 x 150 x 120 box plus 12 features on/in it
BOX = np.array([[x, y, z] for x in (-100, 100) for y in (-75, 75) for z in (0, 120)], float)
FEATURES = np.random.default_rng(0).uniform([-100, -75, 0], [100, 75, 120], size=(12, 3))
POINTS = np.vstack([BOX, FEATURES])


def true_camera() -> Camera:
    """~1.07 m from the box, looking at its centre."""
    return look_at("cam", (300, -900, 500), target=(0, 0, 60), dist=DIST)


def project(cam: Camera, X: np.ndarray) -> np.ndarray:
    args = (torch.as_tensor(a) for a in (X, cam.K, cam.R, cam.tvec, cam.dist))
    return project_points(*args).numpy()


def assert_same_camera(est: Camera, cam: Camera, rtol: float) -> None:
    np.testing.assert_allclose(est.K, cam.K, rtol=rtol, atol=rtol * 1e3)
    np.testing.assert_allclose(est.R, cam.R, atol=rtol)
    np.testing.assert_allclose(est.tvec, cam.tvec, rtol=rtol, atol=rtol * 1e3)
    np.testing.assert_allclose(est.center, cam.center, rtol=rtol, atol=rtol * 1e3)


def test_dlt_noiseless_recovers_P_and_is_batched():
    cam = look_at("c", (300, -900, 500), target=(0, 0, 60), dist=np.zeros(5))
    uv = project(cam, POINTS)
    P = dlt(POINTS, uv).numpy()
    assert P.shape == (3, 4)
    P_true = cam.P / np.linalg.norm(cam.P)
    np.testing.assert_allclose(P, P_true, atol=1e-10)
    Pb = dlt(np.stack([POINTS[:8], POINTS[4:12]]), np.stack([uv[:8], uv[4:12]]))
    assert Pb.shape == (2, 3, 4)
    np.testing.assert_allclose(Pb.numpy(), np.stack([P_true, P_true]), atol=1e-9)


def test_gradcheck_dlt():
    cam = look_at("c", (300, -900, 500), target=(0, 0, 60), dist=np.zeros(5))
    X = torch.as_tensor(POINTS[:8]).requires_grad_(True)
    uv = torch.as_tensor(project(cam, POINTS[:8]) + 0.3).requires_grad_(True)
    assert torch.autograd.gradcheck(dlt, (X, uv), atol=1e-6)


def test_resect_noiseless_unknown_intrinsics_with_distortion():
    cam = true_camera()
    uv = project(cam, POINTS)
    est = resect(POINTS, uv, fit_dist=("k1", "k2", "p1", "p2"), name="front", size=(1280, 1024))
    assert isinstance(est, Camera) and est.name == "front" and est.size == (1280, 1024)
    assert_same_camera(est, cam, 1e-6)
    np.testing.assert_allclose(est.dist, cam.dist, atol=1e-6)
    assert est.extra["rms_px"] < 1e-6 and est.extra["n_points"] == 20
    # the 8 box corners alone, distortion known
    est = resect(BOX, project(cam, BOX), dist=cam.dist)
    assert_same_camera(est, cam, 1e-6)


def test_resect_noiseless_known_K_four_points():
    cam = true_camera()
    est = resect(BOX[:4], project(cam, BOX[:4]), K=cam.K, dist=cam.dist)
    assert_same_camera(est, cam, 1e-6)
    # coplanar points are fine for PnP
    plane = BOX[BOX[:, 2] == 0]
    est = resect(plane, project(cam, plane), K=cam.K, dist=cam.dist)
    assert_same_camera(est, cam, 1e-6)


def test_resect_one_pixel_noise():
    """1 px noise, 20 points on a 200 x 150 x 120 mm target ~1.07 m away.

    Tolerances (from 20 seeds: known K centre error mean 5 mm, max 11 mm; unknown K mean
    38 mm, max 93 mm, as focal length, distance and principal point trade off over a target
    that spans ~12 deg): what is well determined is the image mapping, checked on held-out
    points within the box.
    """
    cam = true_camera()
    uv = project(cam, POINTS)
    held_out = np.random.default_rng(1).uniform([-100, -75, 0], [100, 75, 120], size=(100, 3))
    truth = project(cam, held_out)
    for seed in range(2):
        noisy = uv + np.random.default_rng(seed + 10).normal(size=uv.shape)
        known = resect(POINTS, noisy, K=cam.K, dist=cam.dist)
        assert np.linalg.norm(known.center - cam.center) < 20.0  # mm
        assert np.linalg.norm(project(known, held_out) - truth, axis=1).max() < 2.0  # px
        free = resect(POINTS, noisy, dist=cam.dist)
        assert np.linalg.norm(free.center - cam.center) < 150.0  # mm
        assert np.linalg.norm(project(free, held_out) - truth, axis=1).max() < 3.0  # px
        for est in (known, free):
            assert 0.5 < est.extra["rms_px"] < 1.5
            truth_rms = np.sqrt(((project(cam, POINTS) - noisy) ** 2).sum(1).mean())
            assert est.extra["rms_px"] <= truth_rms + 1e-9  # LM reached (at least) the truth's cost


def test_resect_errors(caplog):
    cam = true_camera()
    uv = project(cam, POINTS)
    with pytest.raises(ValueError, match=">= 6 points"):
        resect(POINTS[:5], uv[:5])
    with pytest.raises(ValueError, match=">= 4 points"):
        resect(POINTS[:3], uv[:3], K=cam.K)
    plane = BOX[BOX[:, 2] == 0]
    plane = np.vstack([plane, plane[:2] * 0.5 + plane[2:] * 0.5])
    with pytest.raises(ValueError, match="coplanar"):
        resect(plane, project(cam, plane))
    with pytest.raises(ValueError, match="coplanar"):
        dlt(plane, project(cam, plane))
    with pytest.raises(ValueError, match="same N"):
        resect(POINTS, uv[:-1])
    with pytest.raises(ValueError, match="finite"):
        bad = uv.copy()
        bad[0, 0] = np.nan
        resect(POINTS, bad)
    with pytest.raises(ValueError, match="fit_dist"):
        resect(POINTS, uv, fit_dist=("k9",))
    with caplog.at_level(logging.WARNING, logger="adjust.resection"):
        resect(POINTS, uv + np.random.default_rng(0).normal(size=uv.shape) * 30, K=cam.K)
    assert "large" in caplog.text


def test_levenberg_marquardt_rosenbrock():
    def fun(p):
        return torch.stack((10 * (p[1] - p[0] ** 2), 1 - p[0]))

    theta, cost, iters = levenberg_marquardt(fun, torch.tensor([-1.2, 1.0], dtype=D))
    assert theta.shape == (2,)
    np.testing.assert_allclose(theta.numpy(), [1.0, 1.0], atol=1e-8)
    assert cost < 1e-16 and 0 < iters < 200
