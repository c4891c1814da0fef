"""Multi-view linear triangulation of body parts: the baseline every adjustment is compared with.

Every part in every frame seen by at least two cameras is triangulated independently by a
likelihood-weighted linear (DLT-type) least-squares solve on undistorted, normalized image
points; the algebraic residuals are reweighted by focal length / depth so they approximate
pixel reprojection errors. The optional robust mode drops, for points seen by >= 3 cameras
whose worst view reprojects worse than ``max_error_px``, the view whose removal leaves the most
consistent set (leave-one-out), repeatedly while >= 3 views remain.

Shapes: T frames, K parts, C cameras (any leading dims ``...`` may replace (T, K)).
All batched in torch; differentiable w.r.t. image points, weights and cameras (the robust
view choice is discrete and made without gradients).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from adjust.camera import Camera, CameraTensors, reprojection_errors
from adjust.distortion import undistort_points
from adjust.sym3 import sym3_solve
from deformnet.threads import torch_threads


@dataclass(frozen=True)
class TriangulationResult:
    """Result of `triangulate` (shapes for inputs xy (T, K, C, 2)).

    points: (T, K, 3) mm, NaN where fewer than ``min_views`` usable views (or degenerate rays).
    error: (T, K) mean reprojection error (px) over the used views, NaN likewise.
    ncams: (T, K) int64, number of views used for the point (0 where the point is NaN).
    used: (T, K, C) bool, the views the point rests on (all False where the point is NaN).
    nviews: (T, K) int64, number of observed views (finite xy and weight > 0), used or not.
    view_error: (T, K, C) reprojection error (px) of every observed view (used or dropped),
        NaN where the view is missing or the point is NaN.
    """

    points: Tensor
    error: Tensor
    ncams: Tensor
    used: Tensor
    nviews: Tensor
    view_error: Tensor


def _linear_triangulate(
    x: Tensor,
    y: Tensor,
    w: Tensor,
    R: Tensor,
    t: Tensor,
    f2: Tensor,
    reweight_iters: int,
    rel_eps: float,
) -> tuple[Tensor, Tensor]:
    """Weighted linear triangulation, camera-major (fast broadcasting over cameras).

    x, y: (C, N) undistorted normalized points; w: (C, N) weights (0 = unused); R: (C, 3, 3);
    t: (C, 3); f2: (C,) squared focal length (px^2 per normalized unit^2) -> X (N, 3), ok (N,).
    Each view contributes the rows (x r3 - r1) X = t1 - x t3 and (y r3 - r2) X = t2 - y t3,
    whose residuals are depth z times the normalized error; weights f^2 / z^2 turn them into
    pixel errors (z from the previous pass; the first pass uses z = 1).
    """
    Rc = R[..., None]  # (C, 3, 3, 1): Rc[:, a, i] broadcasts against (C, N)
    A1 = [x * Rc[:, 2, i] - Rc[:, 0, i] for i in range(3)]  # 3 x (C, N)
    A2 = [y * Rc[:, 2, i] - Rc[:, 1, i] for i in range(3)]
    b1 = t[:, 0, None] - x * t[:, 2, None]  # (C, N)
    b2 = t[:, 1, None] - y * t[:, 2, None]
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    ww = w * f2[:, None]
    X = ok = None
    for it in range(reweight_iters + 1):
        M = tuple((ww * (A1[i] * A1[j] + A2[i] * A2[j])).sum(0) for i, j in pairs)
        wb1, wb2 = ww * b1, ww * b2
        v = torch.stack([(wb1 * A1[i] + wb2 * A2[i]).sum(0) for i in range(3)], -1)
        X, ok = sym3_solve(M, v, rel_eps)
        if it < reweight_iters:
            z = X[:, 0] * Rc[:, 2, 0] + X[:, 1] * Rc[:, 2, 1] + X[:, 2] * Rc[:, 2, 2]
            z = z + t[:, 2, None]  # (C, N)
            z = torch.where(ok & (z.abs() > 1e-9), z, torch.ones_like(z))
            ww = w * f2[:, None] / (z * z)
    return X, ok


def _view_errors(X: Tensor, xy: Tensor, observed: Tensor, cams: CameraTensors) -> Tensor:
    """Pixel errors (N, C) of points X (N, 3) against xy (N, C, 2); NaN where missing."""
    return reprojection_errors(X, xy, cams, observed)


def _mean_over(err: Tensor, mask: Tensor) -> Tensor:
    """Mean of err (N, C) over mask (N, C); NaN where the mask is empty."""
    n = mask.sum(-1)
    s = torch.where(mask, err, torch.zeros_like(err)).sum(-1)
    return torch.where(n > 0, s / n.clamp_min(1), torch.full_like(s, float("nan")))


def triangulate(
    xy: Tensor | np.ndarray,
    weight: Tensor | np.ndarray,
    cams: CameraTensors | Sequence[Camera],
    robust: bool = False,
    max_error_px: float = 20.0,
    min_views: int = 2,
    *,
    reweight_iters: int = 1,
    undistort_iters: int = 10,
    chunk_size: int = 8192,
    num_threads: int | None = 1,
) -> TriangulationResult:
    """Triangulate every part in every frame seen by >= ``min_views`` cameras.

    xy: (T, K, C, 2) pixels, NaN where missing; weight: (T, K, C) >= 0 (0 = missing; e.g.
    DeepLabCut likelihoods); cams: C cameras (a list of `Camera` is converted, float64).
    Any leading dims may replace (T, K). Numpy inputs are converted; outputs are torch
    tensors in the promoted dtype of xy and cams (float64 recommended).

    Points are undistorted first, then solved by weighted linear least squares (see module
    docstring) with ``reweight_iters`` depth reweightings. Work proceeds in chunks of
    ``chunk_size`` points (small tensors stay in cache: several times faster than
    whole-array ops), with torch limited to ``num_threads`` intra-op threads during the call
    (restored after; None leaves torch's setting): chunk-sized elementwise work gains
    nothing from threads, and on the shared 2-core CPU 2 threads measured 2-30x slower.

    robust: if True, for points with >= 3 used views whose worst view error exceeds
    ``max_error_px`` (px), drop the view whose removal leaves the smallest mean reprojection
    error, while more than ``max(min_views, 2)`` views remain.
    Points with fewer views (0 or 1 included) or degenerate geometry are NaN, never an error.
    Returns a `TriangulationResult`.
    """
    if isinstance(cams, (list, tuple)) and cams and all(isinstance(c, Camera) for c in cams):
        cams = CameraTensors.from_cameras(list(cams))
    if not isinstance(cams, CameraTensors):
        raise TypeError(
            f"cams must be a CameraTensors (or list of Camera), got {type(cams).__name__}"
        )
    C = cams.num_cameras
    dtype = cams.K.dtype
    xy = torch.as_tensor(xy, device=cams.K.device)
    weight = torch.as_tensor(weight, device=cams.K.device)
    if xy.dim() < 2 or xy.shape[-2:] != (C, 2):
        raise ValueError(
            f"xy must have shape (T, K, {C}, 2) for {C} cameras, got {tuple(xy.shape)}"
        )
    if weight.shape != xy.shape[:-1]:
        raise ValueError(
            f"weight must have shape {tuple(xy.shape[:-1])} (xy without its last dim), "
            f"got {tuple(weight.shape)}"
        )
    if min_views < 2:
        raise ValueError(f"min_views must be >= 2 (a point needs two rays), got {min_views}")
    if not max_error_px > 0:
        raise ValueError(f"max_error_px must be > 0, got {max_error_px}")
    if num_threads is not None and num_threads < 1:
        raise ValueError(f"num_threads must be >= 1 or None, got {num_threads}")
    if reweight_iters < 0 or undistort_iters < 0 or chunk_size < 1:
        raise ValueError(
            f"need reweight_iters >= 0, undistort_iters >= 0, chunk_size >= 1; got "
            f"{reweight_iters}, {undistort_iters}, {chunk_size}"
        )
    dtype = torch.promote_types(torch.promote_types(xy.dtype, dtype), weight.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    if cams.K.dtype != dtype:
        cams = cams.to(dtype)
    lead = xy.shape[:-2]
    xy = xy.to(dtype).reshape(-1, C, 2)
    weight = weight.to(dtype).reshape(-1, C)
    if bool((weight < 0).any()):
        raise ValueError("weights must be >= 0 (0 = missing)")

    with torch_threads(num_threads):
        parts = [
            _triangulate_flat(
                xy[s : s + chunk_size],
                weight[s : s + chunk_size],
                cams,
                robust,
                max_error_px,
                min_views,
                reweight_iters,
                undistort_iters,
            )
            for s in range(0, max(xy.shape[0], 1), chunk_size)
        ]
    X, error, ncams, used, nviews, view_error = (torch.cat(z) for z in zip(*parts))
    return TriangulationResult(
        points=X.reshape(*lead, 3),
        error=error.reshape(lead),
        ncams=ncams.reshape(lead),
        used=used.reshape(*lead, C),
        nviews=nviews.reshape(lead),
        view_error=view_error.reshape(*lead, C),
    )


def _triangulate_flat(
    xy: Tensor,
    weight: Tensor,
    cams: CameraTensors,
    robust: bool,
    max_error_px: float,
    min_views: int,
    reweight_iters: int,
    undistort_iters: int,
) -> tuple[Tensor, ...]:
    """`triangulate` on flat inputs xy (N, C, 2), weight (N, C) (checked, cast)."""
    C = cams.num_cameras
    dtype = xy.dtype
    observed = torch.isfinite(xy).all(-1) & torch.isfinite(weight) & (weight > 0)  # (N, C)
    pp = cams.K[:, :2, 2]  # missing views -> principal point (finite, weight 0)
    xy0 = torch.where(observed[..., None], xy, pp.expand_as(xy))
    w = torch.where(observed, weight, torch.zeros_like(weight))
    # camera-major (C, N) layout: per-camera constants broadcast along contiguous rows
    fish = None if cams.fisheye is None else cams.fisheye[:, None]
    xn = undistort_points(
        xy0.transpose(0, 1), cams.K[:, None], cams.dist[:, None], undistort_iters, fisheye=fish
    )
    xnx, xny = xn[..., 0].contiguous(), xn[..., 1].contiguous()  # (C, N)
    f2 = cams.K[:, 0, 0] * cams.K[:, 1, 1]
    rel_eps = torch.finfo(dtype).eps * 1e4
    nviews = observed.sum(-1)
    enough = nviews >= min_views

    def solve(weights: Tensor, rows: Tensor | slice = slice(None)) -> tuple[Tensor, Tensor]:
        """weights (n, C) for the points `rows` -> X (n, 3), ok (n,)."""
        return _linear_triangulate(
            xnx[:, rows],
            xny[:, rows],
            weights.transpose(0, 1),
            cams.R,
            cams.t,
            f2,
            reweight_iters,
            rel_eps,
        )

    used = observed & enough[:, None]
    if robust and C >= 3:
        floor = max(min_views, 2)
        with torch.no_grad():
            X, ok = solve(w.detach() * used)
            used = used & ok[:, None]
            err = _view_errors(X, xy0.detach(), used, cams)
            for _ in range(C - 2):
                worst = torch.where(used, err, torch.full_like(err, -1.0)).amax(-1)
                need = (used.sum(-1) > floor) & (worst > max_error_px)
                if not bool(need.any()):
                    break
                idx = need.nonzero()[:, 0]
                u = used[idx]
                best_err = torch.full((len(idx),), float("inf"), dtype=dtype, device=xy.device)
                best_c = torch.full((len(idx),), -1, dtype=torch.long, device=xy.device)
                for c in range(C):
                    cand = u.clone()
                    cand[:, c] = False
                    Xc, okc = solve(w[idx].detach() * cand, idx)
                    e = _mean_over(_view_errors(Xc, xy0[idx].detach(), cand, cams), cand)
                    better = u[:, c] & okc & (e < best_err)
                    best_err = torch.where(better, e, best_err)
                    best_c = torch.where(better, torch.full_like(best_c, c), best_c)
                sel = best_c >= 0
                used[idx[sel], best_c[sel]] = False
                Xn, okn = solve(w[idx].detach() * used[idx], idx)
                used[idx] = used[idx] & okn[:, None]
                X[idx], ok[idx] = Xn, okn
                err[idx] = _view_errors(Xn, xy0[idx].detach(), observed[idx], cams)
        inputs = (xy, weight, cams.K, cams.R, cams.t, cams.dist)
        if torch.is_grad_enabled() and any(z.requires_grad for z in inputs):
            X, ok = solve(w * used)  # again, with the graph, on the final views
    else:
        X, ok = solve(w * used)
    ncams = used.sum(-1)
    valid = ok & (ncams >= min_views)
    used = used & valid[:, None]
    ncams = used.sum(-1)
    X = torch.where(valid[:, None], X, torch.full_like(X, float("nan")))
    view_error = _view_errors(X, xy0, observed, cams)
    error = _mean_over(view_error, used)
    return X, error, ncams, used, nviews, view_error
