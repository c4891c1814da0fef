"""adjust.lsq end to end on synthetic rigid scenes (small T: runs in seconds)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from adjust.camera import CameraTensors
from adjust.lsq import SolverConfig, adjust_poses, synthetic
from adjust.lsq.geometry import pose_difference, so3_exp, so3_log
from adjust.triangulate import triangulate
from deformnet.body import default_mouse

F64 = torch.float64


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def scene():
    body = torch.tensor(default_mouse().points)
    cams = CameraTensors.from_cameras(synthetic.ring_cameras(3, distortion=0.05))
    return body, cams


def _cfg(**kw) -> SolverConfig:
    return SolverConfig(num_threads=1, **kw)


def _errors(est: np.ndarray, truth: torch.Tensor) -> tuple[float, float]:
    d = pose_difference(torch.as_tensor(est), truth)
    return float(d[:, :3].norm(dim=-1).max()), float(d[:, 3:].norm(dim=-1).max())


def _cubic_turning(T: int, rate: float = 0.3) -> torch.Tensor:
    t = torch.arange(T, dtype=F64) - T / 2
    axis = torch.tensor([0.1, -0.1, 1.0], dtype=F64)
    axis = axis / axis.norm()
    R = so3_exp((rate * t)[:, None] * axis)
    tr = torch.stack([2 * t - 0.02 * t**2 + 0.0005 * t**3, -t + 0.001 * t**3, 20 + 0 * t], -1)
    return torch.cat([so3_log(R), tr], -1)


@pytest.mark.parametrize("constraint", ["none", "spline", "grid"])
def test_noiseless_scene_gives_exact_poses(scene, constraint):
    body, cams = scene
    truth = _cubic_turning(40)  # turns through 180 degrees; exactly cubic / constant rate
    xy, w, _ = synthetic.simulate(truth, body, cams, drop=0.3, seed=1)
    res = adjust_poses(
        xy,
        w,
        cams,
        body,
        _cfg(constraint=constraint, robust="none", sigma_def_mm=0.0),
        progress=False,
    )
    rot, tr = _errors(res.poses, truth)
    assert rot < 1e-12 and tr < 1e-10, (rot, tr)  # measured 1.5e-15 rad, 3.3e-14 mm
    assert res.converged
    assert np.all(np.isfinite(res.pose_cov))


def test_frames_without_observations_are_filled_by_the_track_constraint(scene):
    body, cams = scene
    T = 80
    truth = synthetic.smooth_trajectory(T, seed=2)
    xy, w, _ = synthetic.simulate(truth, body, cams, noise_px=0.5, seed=2)
    xy[30] = float("nan")  # one frame
    xy[50:55] = float("nan")  # a run of five
    res = adjust_poses(xy, w, cams, body, _cfg(track_sigma_mm=0.05), progress=False)
    d = pose_difference(torch.as_tensor(res.poses), truth)
    gap = [30, 50, 51, 52, 53, 54]
    # measured 0.26 mm, 0.021 rad; the one-frame gap 0.0019 rad
    assert float(d[gap, 3:].norm(dim=-1).max()) < 0.4  # mm
    assert float(d[gap, :3].norm(dim=-1).max()) < 0.03  # rad
    assert float(d[30, :3].norm()) < 0.005
    assert not res.observed[gap].any() and res.observed[[29, 31, 49, 55]].all()
    # the gap frames' uncertainty is larger than their observed neighbours'
    assert res.pose_sigma[52, 3:].max() > res.pose_sigma[45, 3:].max()
    assert np.all(np.isfinite(res.points)) and np.all(np.isfinite(res.point_sigma))


@pytest.mark.parametrize(
    "case",
    [
        "all_missing",
        "no_frames",
        "one_frame",
        "T2",
        "T4",
        "nan_coordinates",
        "zero_weights",
        "one_camera",
    ],
)
def test_no_nan_for_degenerate_inputs(scene, case):
    body, cams = scene
    truth = synthetic.smooth_trajectory(12, seed=3)
    xy, w, _ = synthetic.simulate(truth, body, cams, noise_px=1.0, seed=3)
    if case == "all_missing":
        xy[:] = float("nan")
    elif case == "no_frames":
        xy, w = xy[:0], w[:0]
    elif case == "one_frame":
        xy, w = xy[:1], w[:1]
    elif case == "T2":
        xy, w = xy[:2], w[:2]
        xy[1] = float("nan")
    elif case == "T4":
        xy, w = xy[:4], w[:4]
    elif case == "nan_coordinates":
        xy[::2, :, :, 0] = float("nan")  # half-missing coordinates, NaN in every other frame
        xy[3:6] = float("nan")
    elif case == "zero_weights":
        w[:, 2:] = 0.0
        w[5] = 0.0
    elif case == "one_camera":
        xy[:, :, 1:] = float("nan")
    res = adjust_poses(xy, w, cams, body, _cfg(), progress=False)
    T = xy.shape[0]
    for name in (
        "poses",
        "points",
        "point_sigma",
        "model_points",
        "model_sigma",
        "pose_cov",
        "weights",
    ):
        arr = getattr(res, name)
        assert arr.shape[0] == T
        assert np.all(np.isfinite(arr)), name
    if case == "one_camera":  # PnP initialisation; depth is weakly determined by one camera
        assert res.fitted.all()
        rot, tr = _errors(res.poses, truth)
        assert rot < 0.08 and tr < 15.0, (rot, tr)  # measured 0.042 rad, 9.0 mm
    if case in ("one_frame", "T4"):
        rot, tr = _errors(res.poses, truth[:T])
        assert rot < 0.05 and tr < 0.7, (rot, tr)  # measured <= 0.032 rad, 0.35 mm


def test_chunked_equals_unchunked(scene):
    body, cams = scene
    T = 300
    truth = synthetic.smooth_trajectory(T, seed=4)
    xy, w, _ = synthetic.simulate(truth, body, cams, noise_px=1.0, drop=0.3, seed=4)
    strict = dict(dtol=0.0, wtol=0.0, ftol=1e-13, xtol=1e-12, max_iterations=50)
    full = adjust_poses(xy, w, cams, body, _cfg(chunk_size=0, **strict), progress=False)
    chunked = adjust_poses(
        xy, w, cams, body, _cfg(chunk_size=90, overlap=40, **strict), progress=False
    )
    assert chunked.chunks == 4 and full.chunks == 1
    d = pose_difference(torch.as_tensor(chunked.poses), torch.as_tensor(full.poses))
    # the same minimum (measured 3e-10 mm, 3e-11 rad, sigma 2e-7 relative, points 3e-9 mm)
    assert float(d[:, 3:].abs().max()) < 1e-7  # mm
    assert float(d[:, :3].abs().max()) < 1e-8  # rad
    np.testing.assert_allclose(chunked.pose_sigma, full.pose_sigma, rtol=1e-5)
    np.testing.assert_allclose(chunked.points, full.points, atol=1e-6)
    # with the default (looser) stopping rules the seams stay far below the uncertainty
    a = adjust_poses(xy, w, cams, body, _cfg(chunk_size=0), progress=False)
    b = adjust_poses(xy, w, cams, body, _cfg(chunk_size=90, overlap=40), progress=False)
    d = pose_difference(torch.as_tensor(b.poses), torch.as_tensor(a.poses)).abs().numpy()
    assert np.all(d < 0.1 * a.pose_sigma)  # measured 0.035 sigma at most


def test_fused_points_at_least_as_accurate_as_triangulation(scene):
    body, cams = scene
    T = 150
    truth = synthetic.smooth_trajectory(T, seed=5)
    xy, w, X = synthetic.simulate(truth, body, cams, noise_px=2.0, deform_mm=2.0, seed=5)
    two = torch.rand(xy.shape[:2], generator=torch.Generator().manual_seed(0)) < 0.5
    xy[..., 2, :] = torch.where(
        two[..., None], torch.full_like(xy[..., 2, :], float("nan")), xy[..., 2, :]
    )
    res = adjust_poses(xy, w, cams, body, _cfg(sigma_def_mm=2.0), progress=False)
    valid = torch.isfinite(xy).all(-1)
    tri = triangulate(xy, valid.to(xy.dtype), cams)
    Xt, ok = tri.points, tri.ncams >= 2
    sel = (valid.sum(-1) == 2) & ok
    err_tri = ((Xt - X)[sel] ** 2).sum(-1).mean().sqrt()
    err_fused = ((torch.as_tensor(res.points) - X)[sel] ** 2).sum(-1).mean().sqrt()
    assert err_fused <= err_tri, (float(err_fused), float(err_tri))
    # the reported sigma is of the right size (measured: 2.26 vs triangulation's 2.81 mm)
    sig = torch.as_tensor(res.point_sigma)[sel].pow(2).sum(-1).mean().sqrt()
    assert 0.8 < float(sig / err_fused) < 1.3  # measured 1.06
    # occluded parts fall back to the model
    xy2 = xy.clone()
    xy2[:, 0] = float("nan")
    res2 = adjust_poses(xy2, w, cams, body, _cfg(sigma_def_mm=2.0), progress=False)
    np.testing.assert_allclose(res2.points[:, 0], res2.model_points[:, 0], atol=1e-9)


@pytest.mark.parametrize("init", ["fit", "kalman"])
def test_initialisations_and_robustness(scene, init):
    body, cams = scene
    T = 120
    truth = synthetic.smooth_trajectory(T, seed=6)
    xy, w, _ = synthetic.simulate(truth, body, cams, noise_px=1.0, drop=0.4, outliers=0.03, seed=6)
    xy[40:46] = float("nan")
    res = adjust_poses(xy, w, cams, body, _cfg(init=init), progress=False)
    rot, tr = _errors(res.init_poses, truth)
    assert rot < 0.35 and tr < 20.0, (rot, tr)  # a usable start (measured <= 0.21, 12.9)
    rot, tr = _errors(res.poses, truth)
    # worst frame: inside the 6-frame gap (measured 0.076 rad, 1.55 mm with either start)
    assert rot < 0.1 and tr < 2.0, (rot, tr)
    d = pose_difference(torch.as_tensor(res.poses), truth)
    assert float(d[:, :3].norm(dim=-1).median()) < 0.02  # measured 0.015
    assert res.converged
    # mis-detections are down-weighted
    bad = np.nan_to_num(np.linalg.norm(res.residuals, axis=-1)) > 30
    assert bad.any() and res.weights[bad].max() < 0.05


def test_config_from_mapping_and_errors():
    cfg = SolverConfig.from_config({"constraint": "spline", "track_weight": 2.0})
    assert cfg.constraint == "spline" and cfg.track_weight == 2.0
    with pytest.raises(ValueError, match="unknown solver settings"):
        SolverConfig.from_config({"constrant": "grid"})
    with pytest.raises(ValueError, match="constraint"):
        SolverConfig(constraint="quintic")
    from hydra import compose, initialize_config_dir

    from deformnet.paths import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        node = compose("track").solver  # conf/solver/default.yaml with its groups
    assert SolverConfig.from_config(node) == SolverConfig()
