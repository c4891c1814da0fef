"""What `adjust-track`'s summary.json says about a result: convergence, completeness,
reprojection errors, uncertainty and counts (the app adds its inputs and settings)."""

from __future__ import annotations

import numpy as np
import torch

from adjust.app import stats
from deformnet.so3 import rodrigues_to_matrix

__all__ = ["TrackingFailed", "result_summary", "track_health"]


def result_summary(res, det, error: np.ndarray, view_err: np.ndarray) -> dict:
    """res: the `adjust.lsq.AdjustmentResult` (points, weights, point_sd, cost history, ...);
    det: the `adjust.io.Detections`; error (T, K) px: each reported point's mean reprojection
    error over its accepted detections; view_err (T, K, C) px: per accepted detection (NaN
    elsewhere)."""
    T, K, C = det.num_frames, det.num_parts, det.num_cameras
    observed = res.weights > 0  # the detections the fused points rest on
    ncams = observed.sum(-1)
    sigma = res.point_sd
    done = np.isfinite(res.points).all(-1)
    seen2 = ncams >= 2
    costs = [c for chunk in res.cost_history for c in chunk[-1:]]
    history = res.cost_history[0] if len(res.cost_history) == 1 else res.cost_history
    return {
        "iterations": int(res.iterations),
        "converged": bool(res.converged),
        "chunks": int(res.chunks),
        "initial_cost": float(res.cost_history[0][0]) if res.cost_history else None,
        "final_cost": float(sum(costs)) if costs else None,
        "cost_history": history,
        "mixture_share": float(res.mixture_share),
        "initial_fit_frames": int(np.asarray(res.fitted).sum()),
        "frames_without_detections": int((ncams.sum(-1) == 0).sum()),
        # how much of the output rests on no accepted detection at all (the model alone)
        "from_model_only": {
            "fraction": float((ncams == 0).mean()) if ncams.size else 0.0,
            "per_part": {p: float((ncams[:, k] == 0).mean()) for k, p in enumerate(det.parts)},
        },
        # fraction of part-frames with a finite 3D point
        "completeness": float(done.mean()) if done.size else 0.0,
        "completeness_per_part": {p: float(done[:, k].mean()) for k, p in enumerate(det.parts)},
        # reprojection error (px) of the reported points: per point (mean over its accepted
        # detections), per camera and per part (over single detections)
        "reprojection_error_px": stats(error),
        "reprojection_error_px_per_camera": {
            c: stats(view_err[..., i]) for i, c in enumerate(det.cameras)
        },
        "reprojection_error_px_per_part": {
            p: stats(view_err[:, k]) for k, p in enumerate(det.parts)
        },
        "sigma_mm": {
            "seen_ge2": stats(sigma[seen2]),
            "seen_1": stats(sigma[ncams == 1]),
            "unseen": stats(sigma[ncams == 0]),
        },
        "counts": {
            "part_frames": int(T * K),
            "detections": int(observed.sum()),
            "detections_per_camera": {
                c: int(observed[..., i].sum()) for i, c in enumerate(det.cameras)
            },
            "downweighted_detections": int(((res.weights < 0.1) & observed).sum()),
            "ncams_histogram": np.bincount(ncams.reshape(-1), minlength=C + 1).tolist(),
        },
    }


class TrackingFailed(ValueError):
    """The adjustment produced tracks that cannot be trusted (non-finite values, or points
    whose own detections reproject far off); the message names the frames."""


def track_health(
    points: np.ndarray,
    view_err: np.ndarray,
    sigma_det_px: float,
    max_px: float = 100.0,
    poses: np.ndarray | None = None,
    max_turn_deg: float = 30.0,
) -> dict:
    """Whether a result can be trusted: ``failed`` when a point is not finite or the median of a
    frame's accepted detections reprojects more than ``max(max_px, 30 sigma_det_px)`` px from
    its points (the adjustment left the data: an exploding or diverged solve; one outlier
    detection does not count); else ``suspect`` when the body's pose (`poses` (T, 6), Rodrigues
    + translation) turns by more than `max_turn_deg` between two frames (no body does at a
    video's frame rate: the track was pulled into another basin there; `turn_frames`), else
    ``ok``. points (T, K, 3)
    mm; view_err (T, K, C) px per accepted detection (NaN elsewhere). Returns {status,
    limit_px, bad_frames (count), frames (the first 20, 0-based)}."""
    limit = max(float(max_px), 30.0 * float(sigma_det_px))
    nonfinite = ~np.isfinite(points).all(-1).all(-1)
    e = np.asarray(view_err, dtype=np.float64).reshape(len(points), -1)
    e = np.where(np.isnan(e), np.inf, e)  # sorted last; +inf (behind a camera) stays too
    n = np.isfinite(np.asarray(view_err, dtype=np.float64).reshape(len(points), -1)).sum(-1)
    n = n + np.isposinf(np.asarray(view_err, dtype=np.float64).reshape(len(points), -1)).sum(-1)
    med = np.take_along_axis(np.sort(e, -1), np.maximum((n - 1) // 2, 0)[:, None], -1)[:, 0]
    exploding = (n > 0) & (med > limit)  # most of a frame's detections far off, not one outlier
    bad = np.flatnonzero(nonfinite | exploding)
    turns = np.zeros(0, dtype=np.int64)
    if poses is not None and len(poses) > 1:
        R = rodrigues_to_matrix(torch.as_tensor(np.asarray(poses, dtype=np.float64)[:, :3]))
        cos = ((R[:-1] * R[1:]).sum((-1, -2)) - 1.0) / 2.0
        turn = np.degrees(np.arccos(np.clip(cos.numpy(), -1.0, 1.0)))
        turns = np.flatnonzero(turn > max_turn_deg) + 1
    status = "failed" if bad.size else ("suspect" if turns.size else "ok")
    return {
        "status": status,
        "limit_px": limit,
        "bad_frames": int(bad.size),
        "nonfinite_frames": int(nonfinite.sum()),
        "frames": [int(f) for f in bad[:20]],
        "max_turn_deg": float(max_turn_deg),
        "turn_frames_count": int(turns.size),
        "turn_frames": [int(f) for f in turns[:20]],
    }
