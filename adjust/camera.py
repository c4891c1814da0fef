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

from deformnet.so3 import matrix_to_rodrigues, rodrigues_to_matrix


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
                raise ValueError(
                    f"camera '{self.name}': {key} must have shape {shape}, got {arr.shape}"
                )
            if not np.all(np.isfinite(arr)):
                raise ValueError(
                    f"camera '{self.name}': {key} has non-finite values: {arr.tolist()}"
                )
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

    @classmethod
    def from_matrices(
        cls,
        name: str,
        K: np.ndarray,
        R: np.ndarray,
        t: np.ndarray,
        dist: np.ndarray | None = None,
        size: tuple[int, int] = (0, 0),
    ) -> Camera:
        """Camera from K (3, 3), a rotation matrix R (3, 3), t (3,) and optional dist (5,)."""
        R = np.asarray(R, dtype=np.float64)
        if R.shape != (3, 3):
            raise ValueError(f"camera '{name}': R must have shape (3, 3), got {R.shape}")
        rvec = matrix_to_rodrigues(torch.as_tensor(R)).numpy()
        return cls(name, K, np.zeros(5) if dist is None else dist, rvec, t, size)

    @classmethod
    def from_projection_matrix(
        cls,
        name: str,
        P: np.ndarray,
        dist: np.ndarray | None = None,
        size: tuple[int, int] = (0, 0),
    ) -> Camera:
        """Camera from a (3, 4) projection matrix by RQ decomposition (paper eq. 2)."""
        P = np.asarray(P, dtype=np.float64)
        if P.shape != (3, 4):
            raise ValueError(f"camera '{name}': P must have shape (3, 4), got {P.shape}")
        K, R, t = decompose_projection_matrix(torch.as_tensor(P))
        return cls.from_matrices(name, K.numpy(), R.numpy(), t.numpy(), dist, size)


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

        return cls(
            stack("K"),
            rodrigues_to_matrix(stack("rvec")),
            stack("tvec"),
            stack("dist"),
            tuple(c.name for c in cameras),
        )

    @property
    def num_cameras(self) -> int:
        return self.K.shape[0]

    @property
    def P(self) -> Tensor:
        """(C, 3, 4) projection matrices K [R | t] (ignore distortion)."""
        return projection_matrix(self.K, self.R, self.t)

    @property
    def centers(self) -> Tensor:
        """(C, 3) camera centres in world coordinates, -R^T t."""
        return -(self.R.transpose(-1, -2) @ self.t[..., None]).squeeze(-1)

    def to(self, dtype: torch.dtype | None = None, device=None) -> CameraTensors:
        """The same cameras with tensors cast to `dtype` / moved to `device`."""
        return CameraTensors(
            *(x.to(dtype=dtype, device=device) for x in (self.K, self.R, self.t, self.dist)),
            self.names,
        )


def distort_normalized(xy: Tensor, dist: Tensor) -> Tensor:
    """Apply OpenCV distortion to normalized image points.

    xy: (..., 2) normalized coordinates (x/z, y/z); dist: (..., 5) k1 k2 p1 p2 k3 -> (..., 2).
    """
    if xy.shape[-1] != 2 or dist.shape[-1] != 5:
        raise ValueError(
            f"xy must be (..., 2) and dist (..., 5), got {tuple(xy.shape)}, {tuple(dist.shape)}"
        )
    x, y = xy.unbind(-1)
    k1, k2, p1, p2, k3 = dist.unbind(-1)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack((xd, yd), -1)


def project_points(
    X: Tensor, K: Tensor, R: Tensor, t: Tensor, dist: Tensor | None = None
) -> Tensor:
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
    """Depth z of world points in camera coordinates.

    X (..., 3), R (..., 3, 3), t (..., 3) -> (...).
    """
    return (R[..., 2, :] * X).sum(-1) + t[..., 2]


def project_cameras(X: Tensor, cams: CameraTensors) -> Tensor:
    """Project points into every camera.  X: (..., 3) -> (..., C, 2) pixels."""
    return project_points(X[..., None, :], cams.K, cams.R, cams.t, cams.dist)


def _check_K(K: Tensor, name: str = "K") -> None:
    if not isinstance(K, Tensor) or K.dim() < 2 or K.shape[-2:] != (3, 3):
        shape = tuple(K.shape) if isinstance(K, Tensor) else type(K).__name__
        raise ValueError(f"{name} must be a tensor of shape (..., 3, 3), got {shape}")


def _check_last2(x: Tensor, name: str) -> None:
    if not isinstance(x, Tensor) or x.dim() < 1 or x.shape[-1] != 2:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"{name} must be a tensor of shape (..., 2), got {shape}")


def projection_matrix(K: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """P = K [R | t].  K: (..., 3, 3), R: (..., 3, 3), t: (..., 3) -> (..., 3, 4)."""
    _check_K(K)
    _check_K(R, "R")
    if not isinstance(t, Tensor) or t.dim() < 1 or t.shape[-1] != 3:
        raise ValueError(f"t must be a tensor of shape (..., 3), got {getattr(t, 'shape', t)}")
    batch = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    Rt = torch.cat((R.expand(*batch, 3, 3), t.expand(*batch, 3)[..., None]), -1)
    return K @ Rt


def decompose_projection_matrix(P: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Split P ~ K [R | t] into intrinsics, rotation and translation (paper eq. 2).

    P: (..., 3, 4), any non-zero scale and sign -> K (..., 3, 3) upper triangular with positive
    diagonal and K[2, 2] = 1, R (..., 3, 3) a proper rotation (det +1), t (..., 3) such that
    P = s K [R | t] with s != 0. RQ decomposition of P[:, :3] (via QR of its flipped transpose).
    Differentiable where P[:, :3] is non-singular; raises ValueError on a singular one.
    """
    if not isinstance(P, Tensor) or P.dim() < 2 or P.shape[-2:] != (3, 4):
        raise ValueError(f"P must be a tensor of shape (..., 3, 4), got {getattr(P, 'shape', P)}")
    M, p4 = P[..., :3], P[..., 3]
    det = torch.linalg.det(M)
    scale = M.abs().amax((-1, -2))
    if not bool(((det.abs() > 1e-12 * scale**3) & torch.isfinite(det)).all()):
        raise ValueError("P[:, :3] is singular (or non-finite): not a finite projective camera")
    sign = torch.sign(det)[..., None]
    M = M * sign[..., None]
    p4 = p4 * sign
    # RQ: with J the row-reversal, (J M)^T = Q U  =>  M = (J U^T J) (J Q^T)
    Q, U = torch.linalg.qr(M.flip(-2).transpose(-1, -2))
    K = U.transpose(-1, -2).flip(-1).flip(-2)
    R = Q.transpose(-1, -2).flip(-2)
    d = torch.sign(torch.diagonal(K, dim1=-2, dim2=-1))
    d = torch.where(d == 0, torch.ones_like(d), d)
    K = K * d[..., None, :]  # K D
    R = R * d[..., :, None]  # D R  (D D = I)
    t = torch.linalg.solve(K, p4[..., None]).squeeze(-1)
    K = K / K[..., 2:3, 2:3]
    return K, R, t


def pixels_to_normalized(uv: Tensor, K: Tensor) -> Tensor:
    """Invert the intrinsics (with skew): pixels -> (distorted) normalized coordinates.

    uv: (..., 2) px; K: (..., 3, 3) (broadcast) -> (..., 2).
    """
    _check_last2(uv, "uv")
    _check_K(K)
    y = (uv[..., 1] - K[..., 1, 2]) / K[..., 1, 1]
    x = (uv[..., 0] - K[..., 0, 2] - K[..., 0, 1] * y) / K[..., 0, 0]
    return torch.stack((x, y), -1)


def normalized_to_pixels(xy: Tensor, K: Tensor) -> Tensor:
    """Apply the intrinsics: normalized coordinates (..., 2), K (..., 3, 3) -> pixels (..., 2)."""
    _check_last2(xy, "xy")
    _check_K(K)
    u = K[..., 0, 0] * xy[..., 0] + K[..., 0, 1] * xy[..., 1] + K[..., 0, 2]
    v = K[..., 1, 1] * xy[..., 1] + K[..., 1, 2]
    return torch.stack((u, v), -1)


def _newton_step(
    x: Tensor, y: Tensor, xd: Tensor, yd: Tensor, k: tuple[Tensor, ...]
) -> tuple[Tensor, Tensor]:
    """One Newton step for distort(x, y) = (xd, yd), on planar components (no stacking)."""
    k1, k2, p1, p2, k3 = k
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2 * k2 + 3 * r2 * k3)  # d radial / d r2
    xy2 = 2 * x * y
    fx = x * radial + p1 * xy2 + p2 * (r2 + 2 * x * x) - xd
    fy = y * radial + p1 * (r2 + 2 * y * y) + p2 * xy2 - yd
    cross = xy2 * dradial + 2 * (p1 * x + p2 * y)  # Jacobian [[a, cross], [cross, d]]
    a = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
    d = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
    det = a * d - cross * cross
    det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
    return x - (d * fx - cross * fy) / det, y - (a * fy - cross * fx) / det


def undistort_normalized(xyd: Tensor, dist: Tensor, iters: int = 10) -> Tensor:
    """Invert OpenCV distortion: distorted normalized points -> ideal normalized points.

    xyd: (..., 2); dist: (..., 5) (broadcast) -> (..., 2). Newton's method from xd (at most
    ``iters`` steps, stopping once converged to machine precision; no graph), then one more
    step with the graph, so gradients w.r.t. xyd and dist are
    the exact implicit-function derivatives at the solution. Valid where the distortion is
    invertible (inside the lens's calibrated field); NaN inputs give NaN outputs.
    """
    _check_last2(xyd, "xyd")
    if not isinstance(dist, Tensor) or dist.dim() < 1 or dist.shape[-1] != 5:
        raise ValueError(
            f"dist must be a tensor of shape (..., 5), got {getattr(dist, 'shape', dist)}"
        )
    if iters < 0:
        raise ValueError(f"iters must be >= 0, got {iters}")
    xd, yd = xyd.unbind(-1)
    k = dist.unbind(-1)
    with torch.no_grad():
        x, y = xd.detach(), yd.detach()
        kd = tuple(c.detach() for c in k)
        tol = 4 * torch.finfo(x.dtype).eps
        for _ in range(iters):
            x_new, y_new = _newton_step(x, y, xd.detach(), yd.detach(), kd)
            step = torch.maximum((x_new - x).abs(), (y_new - y).abs()).nan_to_num(0.0, 0.0, 0.0)
            x, y = x_new, y_new
            size = 1 + torch.maximum(x.abs(), y.abs()).nan_to_num(0.0, 0.0, 0.0)
            if x.numel() == 0 or bool((step <= tol * size).all()):
                break
    return torch.stack(_newton_step(x, y, xd, yd, k), -1)


def undistort_points(
    uv: Tensor, K: Tensor, dist: Tensor | None = None, iters: int = 10, pixels: bool = False
) -> Tensor:
    """Undistort pixel coordinates (like ``cv2.undistortPoints``).

    uv: (..., 2) px; K: (..., 3, 3); dist: (..., 5) or None (leading dims broadcast, e.g. uv
    (T, K, C, 2) with K (C, 3, 3)). Returns ideal normalized coordinates (..., 2), or, with
    ``pixels=True``, ideal (undistorted) pixels in the same K. Differentiable (see
    `undistort_normalized`).
    """
    xy = pixels_to_normalized(uv, K)
    if dist is not None:
        xy = undistort_normalized(xy, dist, iters)
    return normalized_to_pixels(xy, K) if pixels else xy
