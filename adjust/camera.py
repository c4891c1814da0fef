"""Pinhole cameras with OpenCV's 5-coefficient distortion, as pure batched torch functions.

Conventions (stated once): world -> camera ``x_cam = R X + t``; pixels with the origin at the
centre of the top-left pixel (OpenCV's convention); distortion (k1, k2, p1, p2, k3) as in
OpenCV; 3D in mm, angles in radians. Shapes: C cameras, leading dims ``...`` broadcast.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from deformnet.so3 import rodrigues_to_matrix


@dataclass(frozen=True)
class Camera:
    """One calibrated camera (numpy, float64).

    K: (3, 3) intrinsics; dist: (5,) k1 k2 p1 p2 k3; rvec: (3,) Rodrigues world->camera;
    tvec: (3,) translation (mm); size: (width, height) px.
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    size: tuple[int, int] = (0, 0)
    extra: dict = field(default_factory=dict)  # other calibration keys, kept for round trips

    def __post_init__(self) -> None:
        for key, shape in (("K", (3, 3)), ("dist", (5,)), ("rvec", (3,)), ("tvec", (3,))):
            arr = np.asarray(getattr(self, key), dtype=np.float64)
            if key == "dist" and arr.ndim == 1 and arr.size < 5:
                arr = np.concatenate([arr, np.zeros(5 - arr.size)])
            if arr.shape != shape:
                raise ValueError(f"camera '{self.name}': {key} must have shape {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"camera '{self.name}': {key} has non-finite values: {arr.tolist()}")
            object.__setattr__(self, key, arr)

    @property
    def R(self) -> np.ndarray:
        """(3, 3) world -> camera rotation."""
        return rodrigues_to_matrix(torch.as_tensor(self.rvec)).numpy()

    @property
    def P(self) -> np.ndarray:
        """(3, 4) projection matrix K [R | t] (ignores distortion)."""
        return self.K @ np.concatenate([self.R, self.tvec[:, None]], axis=1)

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, -R^T t."""
        return -self.R.T @ self.tvec


@dataclass(frozen=True)
class CameraTensors:
    """C cameras stacked as tensors: K (C, 3, 3), R (C, 3, 3), t (C, 3), dist (C, 5)."""

    K: Tensor
    R: Tensor
    t: Tensor
    dist: Tensor
    names: tuple[str, ...] = ()

    @classmethod
    def from_cameras(
        cls, cameras: list[Camera], dtype: torch.dtype = torch.float64, device=None
    ) -> CameraTensors:
        if not cameras:
            raise ValueError("no cameras given")

        def stack(key: str) -> Tensor:
            return torch.as_tensor(
                np.stack([getattr(c, key) for c in cameras]), dtype=dtype, device=device
            )

        return cls(stack("K"), rodrigues_to_matrix(stack("rvec")), stack("tvec"), stack("dist"),
                   tuple(c.name for c in cameras))

    @property
    def num_cameras(self) -> int:
        return self.K.shape[0]


def distort_normalized(xy: Tensor, dist: Tensor) -> Tensor:
    """Apply OpenCV distortion to normalized image points.

    xy: (..., 2) normalized coordinates (x/z, y/z); dist: (..., 5) k1 k2 p1 p2 k3 -> (..., 2).
    """
    if xy.shape[-1] != 2 or dist.shape[-1] != 5:
        raise ValueError(f"xy must be (..., 2) and dist (..., 5), got {tuple(xy.shape)}, {tuple(dist.shape)}")
    x, y = xy.unbind(-1)
    k1, k2, p1, p2, k3 = dist.unbind(-1)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack((xd, yd), -1)


def project_points(X: Tensor, K: Tensor, R: Tensor, t: Tensor, dist: Tensor | None = None) -> Tensor:
    """Project world points to pixels.

    X: (..., 3) mm; K: (..., 3, 3); R: (..., 3, 3); t: (..., 3); dist: (..., 5) or None.
    Leading dims broadcast (e.g. X (T, K, 1, 3) with cameras (C, ...) -> (T, K, C, 2)).
    Returns (..., 2) pixels. Points at or behind the camera give non-finite-free but
    meaningless values; use `depth` to test visibility.
    """
    if X.shape[-1] != 3 or K.shape[-2:] != (3, 3) or R.shape[-2:] != (3, 3) or t.shape[-1] != 3:
        raise ValueError(
            f"expected X (..., 3), K (..., 3, 3), R (..., 3, 3), t (..., 3); got {tuple(X.shape)}, "
            f"{tuple(K.shape)}, {tuple(R.shape)}, {tuple(t.shape)}"
        )
    Xc = (R @ X[..., None]).squeeze(-1) + t
    z = Xc[..., 2:]
    z = torch.where(z.abs() < 1e-9, torch.full_like(z, 1e-9), z)
    xy = Xc[..., :2] / z
    if dist is not None:
        xy = distort_normalized(xy, dist)
    u = K[..., 0, 0] * xy[..., 0] + K[..., 0, 1] * xy[..., 1] + K[..., 0, 2]
    v = K[..., 1, 1] * xy[..., 1] + K[..., 1, 2]
    return torch.stack((u, v), -1)


def depth(X: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """Depth z of world points in camera coordinates.  X (..., 3), R (..., 3, 3), t (..., 3) -> (...)."""
    return (R[..., 2, :] * X).sum(-1) + t[..., 2]


def project_cameras(X: Tensor, cams: CameraTensors) -> Tensor:
    """Project points into every camera.  X: (..., 3) -> (..., C, 2) pixels."""
    return project_points(X[..., None, :], cams.K, cams.R, cams.t, cams.dist)
