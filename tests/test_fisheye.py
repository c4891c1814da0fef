"""Fisheye cameras (OpenCV's ``cv2.fisheye`` model, anipose's ``fisheye = true``): the one
distortion primitive against OpenCV, its derivatives, the calibration file round trip, the
resection, and a session filmed through fisheye lenses tracked as a pinhole one is."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from adjust.camera import Camera, CameraTensors, project_cameras
from adjust.distortion import (
    distort_jacobian,
    distort_normalized,
    undistort_normalized,
    undistort_points,
)
from adjust.io import InputError, load_calibration, read_points3d, save_calibration, write_dlc_csv
from adjust.lsq import synthetic
from adjust.pipeline import run
from adjust.resection import resect
from adjust.triangulate import triangulate
from deformnet.body import default_mouse
from deformnet.paths import CONF_DIR

torch.set_num_threads(1)
K_FISH = np.array([[620.0, 0.0, 640.0], [0.0, 615.0, 480.0], [0.0, 0.0, 1.0]])
D_FISH = np.array([0.06, -0.02, 0.008, -0.001, 0.0])


def _points(n: int = 300, seed: int = 0) -> torch.Tensor:
    """(n, 2) normalized points out to 64 degrees off the axis."""
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 2, generator=g, dtype=torch.float64) * 2 - 1) * 1.45


def test_fisheye_model_is_opencvs():
    """Projection and undistortion agree with cv2.fisheye to rounding, far off the axis too."""
    xy = _points()
    flag = torch.tensor(True)
    xd = distort_normalized(xy, torch.as_tensor(D_FISH), flag).numpy()
    obj = np.concatenate([xy.numpy(), np.ones((len(xy), 1))], 1)[:, None]
    ref, _ = cv2.fisheye.projectPoints(obj, np.zeros(3), np.zeros(3), K_FISH, D_FISH[:4])
    np.testing.assert_allclose(xd @ K_FISH[:2, :2].T + K_FISH[:2, 2], ref[:, 0], atol=1e-9)
    und = undistort_points(
        torch.as_tensor(ref[:, 0]), torch.as_tensor(K_FISH), torch.as_tensor(D_FISH),
        fisheye=flag,
    ).numpy()  # fmt: skip
    np.testing.assert_allclose(und, xy.numpy(), atol=1e-9)
    cv_und = cv2.fisheye.undistortPoints(ref, K_FISH, D_FISH[:4])[:, 0]
    np.testing.assert_allclose(und, cv_und, atol=1e-8)


def test_fisheye_derivatives_and_mixed_rigs():
    """The analytic Jacobian is autograd's (also at the axis, where the closed form divides by
    r); gradcheck of distortion and undistortion (float64); in a rig of both kinds each
    camera keeps its own model."""
    d = torch.as_tensor(D_FISH)
    flag = torch.tensor(True)
    xy = torch.cat([_points(20), torch.tensor([[0.0, 0.0], [1e-7, -2e-7], [1e-3, 0.0]])])
    J = distort_jacobian(xy, d, flag)
    auto = torch.stack([torch.autograd.functional.jacobian(
        lambda p: distort_normalized(p, d, flag), q) for q in xy])  # fmt: skip
    torch.testing.assert_close(J, auto, atol=1e-9, rtol=1e-9)
    p = _points(6).requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda q, k: distort_normalized(q, k, flag), (p, d.clone().requires_grad_(True))
    )
    pd = distort_normalized(_points(6), d, flag).requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda q, k: undistort_normalized(q, k, 10, flag), (pd, d.clone().requires_grad_(True))
    )
    pin = torch.tensor([0.1, -0.05, 0.001, 0.0005, 0.0], dtype=torch.float64)
    both = distort_normalized(xy[:, None], torch.stack([d, pin]), torch.tensor([True, False]))
    torch.testing.assert_close(both[:, 0], distort_normalized(xy, d, flag))
    torch.testing.assert_close(both[:, 1], distort_normalized(xy, pin))


CAM_TOML = """[cam_0]
name = "wide"
size = [1280, 960]
matrix = [[620.0, 0.0, 640.0], [0.0, 615.0, 480.0], [0.0, 0.0, 1.0]]
distortions = [0.06, -0.02, 0.008, -0.001]
rotation = [0.1, 0.2, 0.3]
translation = [1.0, 2.0, 300.0]
fisheye = true
"""


def test_fisheye_calibration_round_trip_and_bad_files(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text(CAM_TOML)
    (cam,) = load_calibration(p)
    assert cam.fisheye and cam.dist.tolist() == [0.06, -0.02, 0.008, -0.001, 0.0]
    save_calibration(tmp_path / "back.toml", [cam])
    text = (tmp_path / "back.toml").read_text()
    assert "fisheye = true" in text and "distortions = [0.06, -0.02, 0.008, -0.001]" in text
    (again,) = load_calibration(tmp_path / "back.toml")
    assert again.fisheye and np.array_equal(again.dist, cam.dist) and again.extra == {}
    for old, new, words in (
        ("-0.001]", "-0.001, 0.0]", "at most 4"),
        ("fisheye = true", 'fisheye = "yes"', "'fisheye' must be true or false"),
        ("[0.06,", "[-3.0,", "not a real lens"),
    ):
        p.write_text(CAM_TOML.replace(old, new))
        with pytest.raises(InputError, match=words) as exc:
            load_calibration(p)
        assert "[cam_0]" in str(exc.value) and "'wide'" in str(exc.value)


def _fisheye_rig(n: int = 3) -> list[Camera]:
    """`synthetic.ring_cameras` with wide fisheye lenses (focal 620 px)."""
    return [
        dataclasses.replace(c, K=K_FISH.copy(), dist=D_FISH.copy(), fisheye=True)
        for c in synthetic.ring_cameras(n)
    ]


def test_triangulation_and_resection_through_fisheye_lenses():
    """Points seen by fisheye cameras triangulate to the truth; read as pinhole cameras they do
    not; a fisheye camera's pose is resected from its points."""
    cams = _fisheye_rig()
    g = torch.Generator().manual_seed(1)
    X = (torch.rand(200, 3, generator=g, dtype=torch.float64) - 0.5) * 300
    xy = project_cameras(X, CameraTensors.from_cameras(cams))
    res = triangulate(
        xy, torch.ones(xy.shape[:-1], dtype=torch.float64), CameraTensors.from_cameras(cams)
    )
    assert (res.points - X).norm(dim=-1).max() < 1e-6
    pinhole = [dataclasses.replace(c, fisheye=False) for c in cams]
    wrong = triangulate(
        xy, torch.ones(xy.shape[:-1], dtype=torch.float64), CameraTensors.from_cameras(pinhole)
    )
    off = (wrong.points - X).norm(dim=-1)
    assert off.median() > 0.5 and off.max() > 3  # a mm or so near the axis, more off it
    fit = resect(X.numpy(), xy[:, 1].numpy(), K=K_FISH, dist=D_FISH, fisheye=True, size=(1280, 960))
    assert fit.fisheye and np.abs(fit.center - cams[1].center).max() < 1e-3
    assert fit.extra["rms_px"] < 1e-6
    with pytest.raises(ValueError, match="intrinsics known"):
        resect(X.numpy(), xy[:, 1].numpy(), fisheye=True)


def _session(root, cams, T: int = 300):
    body = default_mouse()
    poses = synthetic.smooth_trajectory(T, seed=3)
    xy, _, X = synthetic.simulate(
        poses, torch.tensor(np.array(body.points)), CameraTensors.from_cameras(cams),
        noise_px=1.0, drop=0.1, seed=3,
    )  # fmt: skip
    (root / "detections").mkdir(parents=True)
    xy = xy.numpy()
    lik = np.where(np.isfinite(xy).all(-1), 0.9, 0.05)
    for c, cam in enumerate(cams):
        write_dlc_csv(
            root / "detections" / f"{cam.name}.csv", body.parts, xy[:, :, c], lik[:, :, c]
        )
    return X.numpy()


def _track(root, calib, out):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose("track", [
            f"input.calibration={calib}", f"input.detections={root / 'detections'}",
            f"output.dir={out}", "progress=false", "threads=1",
        ])  # fmt: skip
    summary = run(cfg)
    return summary, read_points3d(out / "points3d.csv")["points"]


def test_a_session_through_fisheye_lenses_tracks(tmp_path):
    """adjust-track on a session filmed through fisheye lenses, its calibration.toml with
    ``fisheye = true``: every camera kept, the tracks within 2 mm rms of the truth (0.66); the
    same file with one camera's ``fisheye`` flag dropped tracks worse (0.95: near the image's
    centre the two models differ by a few px, under the camera check's 25 px)."""
    cams = _fisheye_rig()
    truth = _session(tmp_path / "s", cams)
    save_calibration(tmp_path / "fish.toml", cams)
    s, pts = _track(tmp_path / "s", tmp_path / "fish.toml", tmp_path / "out")
    assert s["camera_check"]["excluded"] == {}
    rmse = float(np.sqrt(np.nanmean(np.sum((pts - truth) ** 2, -1))))
    assert rmse < 2.0, rmse
    wrong = [dataclasses.replace(cams[0], fisheye=False), *cams[1:]]
    save_calibration(tmp_path / "wrong.toml", wrong)
    s2, pts2 = _track(tmp_path / "s", tmp_path / "wrong.toml", tmp_path / "out2")
    rmse2 = float(np.sqrt(np.nanmean(np.sum((pts2 - truth) ** 2, -1))))
    assert rmse2 > 1.3 * rmse, (rmse, rmse2)
