"""Synthetic rigid-body scenes for tests and benchmarks: a camera ring, a smooth trajectory
(turning through 180 degrees repeatedly), projected detections with noise and drop-outs."""

from __future__ import annotations

import numpy as np
import torch

from adjust.camera import Camera, CameraTensors, look_at_pose, project_cameras
from deformnet.so3 import matrix_to_rodrigues, transform_points


def ring_cameras(
    n: int = 3,
    radius: float = 700.0,
    height: float = 500.0,
    focal: float = 1000.0,
    distortion: float = 0.0,
) -> list[Camera]:
    """n cameras on a ring around the origin, looking at it (1280 x 960 px)."""
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n + 0.3
        R, t = look_at_pose(np.array([radius * np.cos(a), radius * np.sin(a), height]), np.zeros(3))
        r = matrix_to_rodrigues(torch.as_tensor(R)).numpy()
        K = np.array([[focal, 0.0, 640.0], [0.0, focal, 480.0], [0.0, 0.0, 1.0]])
        dist = np.array([distortion, -0.5 * distortion, 0.0005 * (distortion != 0), 0.0, 0.0])
        cams.append(Camera(f"cam{i}", K, dist, r, t, (1280, 960)))
    return cams


def smooth_trajectory(
    T: int, seed: int = 0, speed: float = 1.0, dtype=torch.float64
) -> torch.Tensor:
    """(T, 6) smooth poses: wandering translation (~150 mm), heading turning through pi again
    and again, small pitch/roll. `speed` scales the time axis."""
    rng = np.random.default_rng(seed)
    t = np.arange(T) * speed
    ph = rng.uniform(0, 2 * np.pi, 6)
    x = 150 * np.sin(0.011 * t + ph[0]) + 40 * np.sin(0.031 * t + ph[1])
    y = 150 * np.sin(0.013 * t + ph[2]) + 40 * np.cos(0.027 * t + ph[3])
    z = 20 + 3 * np.sin(0.05 * t + ph[4])
    yaw = 0.02 * t + 1.5 * np.sin(0.009 * t + ph[5])
    pitch = 0.1 * np.sin(0.04 * t)
    roll = 0.08 * np.sin(0.035 * t + 1.0)
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    o, i = np.zeros_like(t), np.ones_like(t)
    Rz = np.stack(
        [np.stack([cy, -sy, o], -1), np.stack([sy, cy, o], -1), np.stack([o, o, i], -1)], -2
    )
    Rx = np.stack(
        [np.stack([i, o, o], -1), np.stack([o, cp, -sp], -1), np.stack([o, sp, cp], -1)], -2
    )
    Ry = np.stack(
        [np.stack([cr, o, sr], -1), np.stack([o, i, o], -1), np.stack([-sr, o, cr], -1)], -2
    )
    R = Rz @ Rx @ Ry
    r = matrix_to_rodrigues(torch.as_tensor(R)).numpy()
    return torch.as_tensor(np.concatenate([r, np.stack([x, y, z], -1)], -1), dtype=dtype)


def simulate(
    poses: torch.Tensor,
    body: torch.Tensor,
    cams: CameraTensors,
    noise_px: float = 0.0,
    drop: float = 0.0,
    deform_mm: float = 0.0,
    outliers: float = 0.0,
    seed: int = 0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Detections of the moved body: xy (T, K, C, 2) NaN where dropped, weight (T, K, C), and
    the true 3D points (T, K, 3) (with deformation: Gaussian per-part offsets of deform_mm)."""
    g = torch.Generator().manual_seed(seed)
    X = transform_points(poses, body.to(poses.dtype))
    if deform_mm > 0:
        X = X + deform_mm * torch.randn(X.shape, generator=g, dtype=X.dtype)
    xy = project_cameras(X, cams)
    xy = xy + noise_px * torch.randn(xy.shape, generator=g, dtype=xy.dtype)
    if outliers > 0:
        bad = torch.rand(xy.shape[:-1], generator=g) < outliers
        xy = torch.where(
            bad[..., None], xy + 80 * torch.randn(xy.shape, generator=g, dtype=xy.dtype), xy
        )
    weight = torch.ones(xy.shape[:-1], dtype=xy.dtype)
    if drop > 0:
        gone = torch.rand(xy.shape[:-1], generator=g) < drop
        xy = torch.where(gone[..., None], torch.full_like(xy, float("nan")), xy)
    return xy, weight, X
