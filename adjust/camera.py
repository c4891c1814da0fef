"""Pinhole cameras with OpenCV's 5-coefficient distortion, or its fisheye model, as pure batched
torch functions.

The distortion polynomial, its derivative and its inverse live in `adjust.distortion`
(`undistort_points` is re-exported here); `camera_to_pixels` is the one forward projection
(camera coordinates -> pixels, optionally with its Jacobian) that `project_points`,
`project_cameras` and the solver's `adjust.lsq.geometry.project_components` all call.

Conventions (stated once): world -> camera ``x_cam = R X + t``; pixels with the origin at the
centre of the top-left pixel (OpenCV's convention); distortion (k1, k2, p1, p2, k3) as in
OpenCV, or a fisheye camera's (k1, k2, k3, k4, 0) as in ``cv2.fisheye`` (``fisheye``); 3D in
mm, angles in radians. Shapes: C cameras, leading dims ``...`` broadcast.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from adjust.distortion import check_shape, distort_components, undistort_points
from deformnet.so3 import matrix_to_rodrigues, rodrigues_to_matrix

__all__ = [
    "Camera",
    "CameraTensors",
    "camera_to_pixels",
    "decompose_projection_matrix",
    "depth",
    "look_at_pose",
    "project_cameras",
    "project_points",
    "projection_matrix",
    "reprojection_errors",
    "undistort_points",
]


def _check_shape(name: str, key: str, arr: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """`arr`, or a ValueError naming the camera and the matrix when it is not of `shape`."""
    if arr.shape != shape:
        raise ValueError(f"camera '{name}': {key} must have shape {shape}, got {arr.shape}")
    return arr


@dataclass(frozen=True)
class Camera:
    """One calibrated camera (numpy, float64).

    K: (3, 3) intrinsics; dist: (5,) k1 k2 p1 p2 k3; rvec: (3,) Rodrigues world->camera;
    tvec: (3,) translation (mm); size: (width, height) px; fisheye: OpenCV's fisheye model
    (``cv2.fisheye``, anipose's ``fisheye = true``), dist then (k1, k2, k3, k4, 0).
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    size: tuple[int, int] = (0, 0)
    extra: dict = field(default_factory=dict)  # other calibration keys, kept for round trips
    fisheye: bool = False

    def __post_init__(self) -> None:
        for key, shape in (("K", (3, 3)), ("dist", (5,)), ("rvec", (3,)), ("tvec", (3,))):
            arr = np.asarray(getattr(self, key), dtype=np.float64)
            if key == "dist" and arr.ndim == 1 and arr.size < 5:
                arr = np.concatenate([arr, np.zeros(5 - arr.size)])
            _check_shape(self.name, key, arr, shape)
            if not np.all(np.isfinite(arr)):
                raise ValueError(
                    f"camera '{self.name}': {key} has non-finite values: {arr.tolist()}"
                )
            object.__setattr__(self, key, arr)
        object.__setattr__(self, "fisheye", bool(self.fisheye))
        if self.fisheye and self.dist[4] != 0:
            raise ValueError(
                f"camera '{self.name}': a fisheye camera has 4 distortion coefficients (k1 k2 "
                f"k3 k4), got {self.dist.tolist()}"
            )

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
        fisheye: bool = False,
    ) -> Camera:
        """Camera from K (3, 3), a rotation matrix R (3, 3), t (3,) and optional dist (5,)."""
        R = _check_shape(name, "R", np.asarray(R, dtype=np.float64), (3, 3))
        rvec = matrix_to_rodrigues(torch.as_tensor(R)).numpy()
        d = np.zeros(5) if dist is None else dist
        return cls(name, K, d, rvec, t, size, fisheye=fisheye)

    @classmethod
    def from_projection_matrix(
        cls,
        name: str,
        P: np.ndarray,
        dist: np.ndarray | None = None,
        size: tuple[int, int] = (0, 0),
    ) -> Camera:
        """Camera from a (3, 4) projection matrix by RQ decomposition (paper eq. 2)."""
        P = _check_shape(name, "P", np.asarray(P, dtype=np.float64), (3, 4))
        K, R, t = decompose_projection_matrix(torch.as_tensor(P))
        return cls.from_matrices(name, K.numpy(), R.numpy(), t.numpy(), dist, size)


@dataclass(frozen=True)
class CameraTensors:
    """C cameras stacked as tensors: K (C, 3, 3), R (C, 3, 3), t (C, 3), dist (C, 5), fisheye
    (C,) bool or None (no fisheye camera)."""

    K: Tensor
    R: Tensor
    t: Tensor
    dist: Tensor
    names: tuple[str, ...] = ()
    fisheye: Tensor | None = None

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
            fisheye_mask(cameras, device),
        )

    @property
    def num_cameras(self) -> int:
        return self.K.shape[0]

    @property
    def P(self) -> Tensor:
        """(C, 3, 4) projection matrices K [R | t] (ignore distortion)."""
        return projection_matrix(self.K, self.R, self.t)

    @property
    def focal(self) -> Tensor:
        """(C,) px: each camera's focal length, sqrt(|f_x f_y|)."""
        return torch.sqrt(self.K[:, 0, 0].abs() * self.K[:, 1, 1].abs())

    @property
    def centers(self) -> Tensor:
        """(C, 3) camera centres in world coordinates, -R^T t."""
        return -(self.R.transpose(-1, -2) @ self.t[..., None]).squeeze(-1)

    def to(self, dtype: torch.dtype | None = None, device=None) -> CameraTensors:
        """The same cameras with tensors cast to `dtype` / moved to `device`."""
        return CameraTensors(
            *(x.to(dtype=dtype, device=device) for x in (self.K, self.R, self.t, self.dist)),
            self.names,
            None if self.fisheye is None else self.fisheye.to(device=device),
        )


def fisheye_mask(cameras, device=None) -> Tensor | None:
    """(C,) bool tensor of the cameras' ``fisheye`` flags, or None where none is one."""
    flags = [bool(c.fisheye) for c in cameras]
    return torch.tensor(flags, device=device) if any(flags) else None


def project_points(
    X: Tensor,
    K: Tensor,
    R: Tensor,
    t: Tensor,
    dist: Tensor | None = None,
    fisheye: Tensor | None = None,
) -> Tensor:
    """Project world points to pixels.

    X: (..., 3) mm; K: (..., 3, 3); R: (..., 3, 3); t: (..., 3); dist: (..., 5) or None;
    fisheye: None or a bool tensor of dist's leading dims (`adjust.distortion`).
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
    u, v, _ = camera_to_pixels(Xc, K, dist, fisheye=fisheye)
    return torch.stack((u, v), -1)


def camera_to_pixels(
    Xc: Tensor,
    K: Tensor,
    dist: Tensor | None = None,
    jacobian: bool = False,
    skew: bool = True,
    fisheye: Tensor | None = None,
) -> tuple[Tensor, Tensor, tuple[Tensor, ...] | None]:
    """The one forward projection: camera coordinates -> pixels (pinhole, OpenCV distortion
    (`adjust.distortion`), skew), optionally with its analytic derivative.

    Xc: (..., 3) mm in camera coordinates; K: (..., 3, 3); dist: (..., 5) or None (no
    distortion); fisheye: None or a bool tensor of dist's leading dims (those cameras use the
    fisheye model); the leading dims of K and dist broadcast against Xc's (e.g. Xc (T, K, C,
    3) with K (C, 3, 3)). Returns u, v (...) px and, with `jacobian`, the six entries
    (A00, A01, A02, A10, A11, A12) (...) of d(u, v)/dXc (px/mm), else None. Depths below
    1e-9 mm in magnitude are clamped to 1e-9 (points at or behind the camera give finite but
    meaningless pixels: test visibility with `depth`). ``skew=False`` drops the K[0, 1] terms
    (exact where they are zero: the solver's fast path); so does ``dist=None`` for all-zero
    distortion. Differentiable.
    """
    check_shape(Xc, (3,), "Xc")
    check_shape(K, (3, 3), "K")
    z = Xc[..., 2]
    z = torch.where(z.abs() < 1e-9, torch.full_like(z, 1e-9), z)
    iz = 1.0 / z
    x, y = Xc[..., 0] * iz, Xc[..., 1] * iz
    fx, s, cx = K[..., 0, 0], K[..., 0, 1], K[..., 0, 2]
    fy, cy = K[..., 1, 1], K[..., 1, 2]
    if dist is not None:
        xd, yd, D = distort_components(x, y, dist, jacobian, fisheye)
    else:
        xd, yd, D = x, y, None
    u = fx * xd + cx
    if skew:
        u = u + s * yd
    v = fy * yd + cy
    if not jacobian:
        return u, v, None
    if D is not None:
        jxx, jxy, jyy = D
        du_dx, du_dy = fx * jxx, fx * jxy
        dv_dx, dv_dy = fy * jxy, fy * jyy
        if skew:
            du_dx = du_dx + s * jxy
            du_dy = du_dy + s * jyy
    else:
        shape = torch.broadcast_shapes(x.shape, fx.shape)
        du_dx = fx.expand(shape)
        du_dy = s.expand(shape) if skew else x.new_zeros(shape)
        dv_dx, dv_dy = x.new_zeros(shape), fy.expand(shape)
    a00, a01 = du_dx * iz, du_dy * iz
    a10, a11 = dv_dx * iz, dv_dy * iz
    a02 = -(a00 * x + a01 * y)
    a12 = -(a10 * x + a11 * y)
    return u, v, (a00, a01, a02, a10, a11, a12)


def depth(X: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """Depth z of world points in camera coordinates.

    X (..., 3), R (..., 3, 3), t (..., 3) -> (...).
    """
    return (R[..., 2, :] * X).sum(-1) + t[..., 2]


def project_cameras(X: Tensor, cams: CameraTensors) -> Tensor:
    """Project points into every camera.  X: (..., 3) -> (..., C, 2) pixels."""
    return project_points(X[..., None, :], cams.K, cams.R, cams.t, cams.dist, cams.fisheye)


def look_at_pose(
    position: np.ndarray,
    target: np.ndarray,
    up: np.ndarray = (0.0, 0.0, 1.0),
    name: str = "camera",
) -> tuple[np.ndarray, np.ndarray]:
    """World -> camera pose of a camera at `position` looking at `target` (numpy, float64).

    position, target, up: (3,) mm (up: any length). Camera axes (OpenCV): z along the viewing
    direction, x to the image right, y down the image, so the image "up" leans towards `up`.
    Returns R (3, 3), a proper rotation, and t (3,) with x_cam = R X + t. Raises ValueError
    (naming camera `name`) when position and target coincide or `up` is parallel to the view.
    """
    pos = np.asarray(position, dtype=np.float64)
    upv = np.asarray(up, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - pos
    if pos.shape != (3,) or fwd.shape != (3,) or upv.shape != (3,):
        raise ValueError(
            f"camera '{name}': position, target and up must be (3,), got {pos.shape}, "
            f"{np.shape(target)}, {upv.shape}"
        )
    if np.linalg.norm(fwd) < 1e-9:
        raise ValueError(f"camera '{name}': position and look_at coincide ({pos.tolist()})")
    z = fwd / np.linalg.norm(fwd)
    x = np.cross(z, upv)
    if np.linalg.norm(x) < 1e-6 * max(np.linalg.norm(upv), 1e-12):
        raise ValueError(
            f"camera '{name}': up vector {upv.tolist()} is parallel to the viewing direction "
            f"{z.round(6).tolist()}; give the camera its own 'up' (e.g. [0, 1, 0] for a camera "
            "looking straight down)"
        )
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ pos


def reprojection_errors(
    points: Tensor, xy: Tensor, cams: CameraTensors, observed: Tensor | None = None
) -> Tensor:
    """Pixel distance between projected points and detections (the one implementation).

    points: (..., 3) mm (NaN allowed); xy: (..., C, 2) px (NaN where missing); observed:
    (..., C) bool or None (all) -> (..., C) px, NaN where either is missing or not observed.
    Differentiable, with a zero (not NaN) gradient where an error is exactly zero.
    """
    C = cams.num_cameras
    if points.shape[-1] != 3 or xy.shape[-2:] != (C, 2) or points.shape[:-1] != xy.shape[:-2]:
        raise ValueError(
            f"expected points (..., 3) and xy (..., {C}, 2) with equal leading dims, "
            f"got {tuple(points.shape)} and {tuple(xy.shape)}"
        )
    if observed is not None and observed.shape != xy.shape[:-1]:
        raise ValueError(f"observed must have shape {tuple(xy.shape[:-1])}, got {observed.shape}")
    proj = project_points(points[..., None, :], cams.K, cams.R, cams.t, cams.dist, cams.fisheye)
    sq = ((proj - xy) ** 2).sum(-1)
    good = torch.isfinite(sq) if observed is None else observed & torch.isfinite(sq)
    sq = torch.where(good, sq, torch.ones_like(sq))
    err = torch.where(sq > 0, sq.clamp_min(1e-300).sqrt(), torch.zeros_like(sq))
    return torch.where(good, err, torch.full_like(err, float("nan")))


def projection_matrix(K: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """P = K [R | t].  K: (..., 3, 3), R: (..., 3, 3), t: (..., 3) -> (..., 3, 4)."""
    check_shape(K, (3, 3), "K")
    check_shape(R, (3, 3), "R")
    check_shape(t, (3,), "t")
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
