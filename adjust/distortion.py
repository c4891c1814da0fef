"""OpenCV's lens distortion, written once: distort, its derivative and undistort side by side.

In the manner of kornia's ``geometry.calibration`` (``distort_points`` / ``undistort_points``):
pure, batched torch functions, differentiable, leading dims broadcast. The model (OpenCV's five
coefficients ``dist = (k1, k2, p1, p2, k3)``) on normalized image coordinates (x, y) = (X/Z, Y/Z)
of a point in camera coordinates:

    r^2 = x^2 + y^2,  radial = 1 + k1 r^2 + k2 r^4 + k3 r^6
    xd = x radial + 2 p1 x y + p2 (r^2 + 2 x^2)
    yd = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y

and OpenCV's fisheye model (``cv2.fisheye``; anipose's ``fisheye = true``), whose four
coefficients sit in the same slots, ``dist = (k1, k2, k3, k4, 0)``, for the cameras flagged
``fisheye``:

    r = sqrt(x^2 + y^2),  theta = atan(r),
    theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8),
    (xd, yd) = (theta_d / r) (x, y)

Both Jacobians d(xd, yd)/d(x, y) are symmetric. Undistortion inverts them by Newton's method
(the fisheye's start solved for theta first, along the ray).
Intrinsics K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] map normalized coordinates to pixels (origin
at the centre of the top-left pixel, as OpenCV).

- `distort_components`: the polynomial (and optionally its Jacobian) on planar components, the
  one implementation every projection in the project calls (`adjust.camera.camera_to_pixels`);
  ``fisheye`` (a bool tensor broadcasting like ``dist``'s leading dims, or None: none) picks
  the fisheye model per camera;
- `distort_normalized` / `distort_jacobian` / `undistort_normalized`: the same on (..., 2);
- `pixels_to_normalized` / `normalized_to_pixels`: the intrinsics and their inverse;
- `distort_points` / `undistort_points`: pixels to pixels (like ``cv2.undistortPoints``).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "check_shape",
    "distort_components",
    "distort_jacobian",
    "distort_normalized",
    "distort_points",
    "normalized_to_pixels",
    "pixels_to_normalized",
    "undistort_normalized",
    "undistort_points",
]


def check_shape(x: Tensor, tail: tuple[int, ...], name: str) -> None:
    """ValueError unless `x` is a tensor of shape (..., *tail)."""
    n = len(tail)
    if not isinstance(x, Tensor) or x.dim() < n or tuple(x.shape[x.dim() - n :]) != tail:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(
            f"{name} must be a tensor of shape (..., {', '.join(map(str, tail))}), got {shape}"
        )


def _fisheye_components(
    x: Tensor, y: Tensor, dist: Tensor, jacobian: bool
) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor, Tensor] | None]:
    """OpenCV's fisheye model on planar components (`distort_components`' fisheye branch):
    dist (..., 5) = k1 k2 k3 k4 (0). Series for r < 1e-4 (the ratio theta_d / r and its
    derivative / r are smooth there; the closed forms divide by r)."""
    k1, k2, k3, k4 = dist[..., :4].unbind(-1)
    r2 = x * x + y * y
    small = r2 < 1e-8
    r2s = torch.where(small, torch.ones_like(r2), r2)  # no 0/0 in the unused branch
    r = torch.sqrt(r2s)
    th = torch.atan(r)
    t2 = th * th
    poly = 1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
    s_far = th * poly / r
    # theta / r = 1 - r^2 / 3 + ..., theta^2 = r^2 + ...: s = 1 + (k1 - 1/3) r^2 + O(r^4)
    s_near = 1 + (k1 - 1.0 / 3.0) * r2
    s = torch.where(small, s_near, s_far)
    xd, yd = x * s, y * s
    if not jacobian:
        return xd, yd, None
    dpoly = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))  # d(th poly)/d th
    ds_dr = (dpoly / (1 + r2s) * r - th * poly) / r2s  # d s / d r
    g = torch.where(small, 2 * (k1 - 1.0 / 3.0) * torch.ones_like(r2), ds_dr / r)  # s'(r) / r
    return xd, yd, (s + x * x * g, x * y * g, s + y * y * g)


def distort_components(
    x: Tensor,
    y: Tensor,
    dist: Tensor,
    jacobian: bool = False,
    fisheye: Tensor | None = None,
) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor, Tensor] | None]:
    """OpenCV's distortion polynomial on planar components (no stacking: the solver's fast path).

    x, y: (...) normalized coordinates; dist: (..., 5) k1 k2 p1 p2 k3, its leading dims
    broadcasting against x's (e.g. x (T, K, C) with dist (C, 5)); fisheye: None, or a bool
    tensor of dist's leading dims (e.g. (C,)) whose True entries use the fisheye model, their
    dist k1 k2 k3 k4 0. Returns xd, yd (...) and, with `jacobian`, the three distinct entries
    (dxd/dx, dxd/dy = dyd/dx, dyd/dy) (...) of the symmetric Jacobian, else None.
    """
    check_shape(dist, (5,), "dist")
    if fisheye is not None and bool(fisheye.any()):
        pin = _pinhole_components(x, y, dist, jacobian)
        fish = _fisheye_components(x, y, dist, jacobian)
        if bool(fisheye.all()):
            return fish
        f = fisheye.to(torch.bool)
        xd, yd = torch.where(f, fish[0], pin[0]), torch.where(f, fish[1], pin[1])
        if not jacobian:
            return xd, yd, None
        return xd, yd, tuple(torch.where(f, a, b) for a, b in zip(fish[2], pin[2]))
    return _pinhole_components(x, y, dist, jacobian)


def _pinhole_components(
    x: Tensor, y: Tensor, dist: Tensor, jacobian: bool
) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor, Tensor] | None]:
    """OpenCV's 5-coefficient polynomial (`distort_components`' pinhole branch)."""
    k1, k2, p1, p2, k3 = dist.unbind(-1)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy2 = 2 * x * y
    xd = x * radial + p1 * xy2 + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * xy2
    if not jacobian:
        return xd, yd, None
    dr = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))  # 2 d radial / d r^2
    cross = xy2 * 0.5 * dr + 2 * p1 * x + 2 * p2 * y
    dxd_dx = radial + x * x * dr + 2 * p1 * y + 6 * p2 * x
    dyd_dy = radial + y * y * dr + 6 * p1 * y + 2 * p2 * x
    return xd, yd, (dxd_dx, cross, dyd_dy)


def distort_normalized(xy: Tensor, dist: Tensor, fisheye: Tensor | None = None) -> Tensor:
    """Apply OpenCV distortion to normalized image points.

    xy: (..., 2) normalized coordinates (x/z, y/z); dist: (..., 5) k1 k2 p1 p2 k3 (leading dims
    broadcast); fisheye as in `distort_components` -> (..., 2) distorted normalized coordinates.
    """
    check_shape(xy, (2,), "xy")
    check_shape(dist, (5,), "dist")
    xd, yd, _ = distort_components(xy[..., 0], xy[..., 1], dist, fisheye=fisheye)
    return torch.stack((xd, yd), -1)


def distort_jacobian(xy: Tensor, dist: Tensor, fisheye: Tensor | None = None) -> Tensor:
    """The derivative of `distort_normalized` with respect to the point.

    xy: (..., 2); dist: (..., 5) (broadcast); fisheye as in `distort_components` -> (..., 2, 2)
    symmetric d(xd, yd)/d(x, y).
    """
    check_shape(xy, (2,), "xy")
    check_shape(dist, (5,), "dist")
    _, _, (a, b, d) = distort_components(xy[..., 0], xy[..., 1], dist, True, fisheye)
    return torch.stack((torch.stack((a, b), -1), torch.stack((b, d), -1)), -2)


def _newton_step(
    x: Tensor, y: Tensor, xd: Tensor, yd: Tensor, dist: Tensor, fisheye: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """One Newton step for distort(x, y) = (xd, yd), on planar components."""
    fx, fy, (a, cross, d) = distort_components(x, y, dist, True, fisheye)
    fx, fy = fx - xd, fy - yd
    det = a * d - cross * cross
    det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
    return x - (d * fx - cross * fy) / det, y - (a * fy - cross * fx) / det


def _fisheye_start(xd: Tensor, yd: Tensor, dist: Tensor, fisheye: Tensor) -> tuple[Tensor, Tensor]:
    """The fisheye cameras' undistorted points solved along the ray (1-D Newton on theta for
    theta_d = |(xd, yd)|), the others' (xd, yd) as they are: Newton's start (no graph)."""
    k1, k2, k3, k4 = dist[..., :4].unbind(-1)
    rd = torch.sqrt(xd * xd + yd * yd)
    th = rd.clone()
    for _ in range(20):
        t2 = th * th
        f = th * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - rd
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        th = (th - f / torch.where(df.abs() < 1e-12, torch.full_like(df, 1e-12), df)).clamp(
            0.0, 1.5
        )
    scale = torch.where(rd > 1e-12, torch.tan(th) / torch.where(rd > 1e-12, rd, 1.0), 1.0)
    f = fisheye.to(torch.bool)
    return torch.where(f, xd * scale, xd), torch.where(f, yd * scale, yd)


def undistort_normalized(
    xyd: Tensor, dist: Tensor, iters: int = 10, fisheye: Tensor | None = None
) -> Tensor:
    """Invert OpenCV distortion: distorted normalized points -> ideal normalized points.

    xyd: (..., 2); dist: (..., 5) (broadcast); fisheye as in `distort_components` -> (..., 2).
    Newton's method from xd (the fisheye's from its solution along the ray; at most ``iters``
    steps, stopping once converged to machine precision; no graph), then one more step with
    the graph, so gradients w.r.t. xyd and dist are the exact implicit-function derivatives at
    the solution. Valid where the distortion is invertible (inside the lens's calibrated
    field); NaN inputs give NaN outputs.
    """
    check_shape(xyd, (2,), "xyd")
    check_shape(dist, (5,), "dist")
    if iters < 0:
        raise ValueError(f"iters must be >= 0, got {iters}")
    if fisheye is not None and not bool(fisheye.any()):
        fisheye = None
    xd, yd = xyd.unbind(-1)
    with torch.no_grad():
        x, y = xd.detach(), yd.detach()
        kd = dist.detach()
        if fisheye is not None:
            x, y = _fisheye_start(x, y, kd, fisheye)
        tol = 4 * torch.finfo(x.dtype).eps
        for _ in range(iters):
            x_new, y_new = _newton_step(x, y, xd.detach(), yd.detach(), kd, fisheye)
            step = torch.maximum((x_new - x).abs(), (y_new - y).abs()).nan_to_num(0.0, 0.0, 0.0)
            x, y = x_new, y_new
            size = 1 + torch.maximum(x.abs(), y.abs()).nan_to_num(0.0, 0.0, 0.0)
            if x.numel() == 0 or bool((step <= tol * size).all()):
                break
    return torch.stack(_newton_step(x, y, xd, yd, dist, fisheye), -1)


def pixels_to_normalized(uv: Tensor, K: Tensor) -> Tensor:
    """Invert the intrinsics (with skew): pixels -> (distorted) normalized coordinates.

    uv: (..., 2) px; K: (..., 3, 3) (broadcast) -> (..., 2).
    """
    check_shape(uv, (2,), "uv")
    check_shape(K, (3, 3), "K")
    y = (uv[..., 1] - K[..., 1, 2]) / K[..., 1, 1]
    x = (uv[..., 0] - K[..., 0, 2] - K[..., 0, 1] * y) / K[..., 0, 0]
    return torch.stack((x, y), -1)


def normalized_to_pixels(xy: Tensor, K: Tensor) -> Tensor:
    """Apply the intrinsics: normalized coordinates (..., 2), K (..., 3, 3) -> pixels (..., 2)."""
    check_shape(xy, (2,), "xy")
    check_shape(K, (3, 3), "K")
    u = K[..., 0, 0] * xy[..., 0] + K[..., 0, 1] * xy[..., 1] + K[..., 0, 2]
    v = K[..., 1, 1] * xy[..., 1] + K[..., 1, 2]
    return torch.stack((u, v), -1)


def distort_points(uv: Tensor, K: Tensor, dist: Tensor, fisheye: Tensor | None = None) -> Tensor:
    """Distort ideal (undistorted) pixels into the pixels the lens shows (kornia's
    ``distort_points``).

    uv: (..., 2) px; K: (..., 3, 3); dist: (..., 5) (leading dims broadcast); fisheye as in
    `distort_components` -> (..., 2) px. The inverse of `undistort_points(..., pixels=True)`.
    """
    xy = distort_normalized(pixels_to_normalized(uv, K), dist, fisheye)
    return normalized_to_pixels(xy, K)


def undistort_points(
    uv: Tensor,
    K: Tensor,
    dist: Tensor | None = None,
    iters: int = 10,
    pixels: bool = False,
    fisheye: Tensor | None = None,
) -> Tensor:
    """Undistort pixel coordinates (like ``cv2.undistortPoints``, ``cv2.fisheye.undistortPoints``
    for the cameras flagged ``fisheye``).

    uv: (..., 2) px; K: (..., 3, 3); dist: (..., 5) or None (leading dims broadcast, e.g. uv
    (T, K, C, 2) with K (C, 3, 3)); fisheye as in `distort_components`. Returns ideal
    normalized coordinates (..., 2), or, with ``pixels=True``, ideal (undistorted) pixels in
    the same K. Differentiable (see `undistort_normalized`).
    """
    xy = pixels_to_normalized(uv, K)
    if dist is not None:
        xy = undistort_normalized(xy, dist, iters, fisheye)
    return normalized_to_pixels(xy, K) if pixels else xy
