"""What `adjust-track`'s summary.json says about a result: convergence, completeness,
reprojection errors, uncertainty and counts (the app adds its inputs and settings)."""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from adjust.metrics import reprojection_errors, stats
from deformnet.behavior.tracks import POSE_COLUMNS
from deformnet.so3 import rodrigues_to_matrix

log = logging.getLogger(__name__)

__all__ = [
    "TrackColumns",
    "TrackingFailed",
    "report_result",
    "result_summary",
    "track_columns",
    "track_health",
]


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


@dataclass
class TrackColumns:
    """points3d.csv's columns of one result (`track_columns`): points (T, K, 3) mm, observed
    (T, K, C) the detections each point rests on, ncams (T, K), view_err (T, K, C) px per
    accepted detection (NaN elsewhere), error (T, K) px their mean, score (T, K) the lowest
    likelihood among them (NaN with none), extra: the pose and uncertainty columns."""

    points: np.ndarray
    observed: np.ndarray
    ncams: np.ndarray
    view_err: np.ndarray
    error: np.ndarray
    score: np.ndarray
    extra: dict


def track_columns(res, det, cams) -> TrackColumns:
    """points3d.csv's columns of the adjustment result `res` on the detections `det` seen by
    `cams` (`adjust.camera.CameraTensors`)."""
    T, K, C = det.num_frames, det.num_parts, det.num_cameras
    points = res.points
    observed = res.weights > 0  # the detections the fused points rest on
    ncams = observed.sum(-1)
    view_err = reprojection_errors(points, det.xy, cams, observed)
    with warnings.catch_warnings():  # all-NaN rows (no detection) are expected
        warnings.simplefilter("ignore", RuntimeWarning)
        error = np.nanmean(view_err, axis=-1) if C else np.full((T, K), np.nan)
    score = np.where(observed, det.likelihood, np.inf).min(-1)
    score = np.where((ncams > 0) & np.isfinite(score), score, np.nan)
    pc = res.pose_cov
    extra: dict[str, np.ndarray] = {n: res.poses[:, i] for i, n in enumerate(POSE_COLUMNS)}
    extra["pose_sigma_r"] = np.sqrt(np.clip(np.trace(pc[:, :3, :3], axis1=-2, axis2=-1), 0, None))
    extra["pose_sigma_t"] = np.sqrt(np.clip(np.trace(pc[:, 3:, 3:], axis1=-2, axis2=-1), 0, None))
    # root of the trace of each point's covariance (mm)
    extra["{part}_sigma"] = res.point_sd
    return TrackColumns(points, observed, ncams, view_err, error, score, extra)


def report_result(summary: dict, where: str, out, fnum) -> None:
    """Judge and log a written result: `TrackingFailed` when its health is ``failed`` (the
    outputs are kept for inspection), a warning when it is ``suspect`` or when much of it rests
    on the model alone, then one line of figures. fnum: the detections' frame numbers (None:
    0-based)."""
    health = summary["health"]
    if health["status"] == "failed":
        frames = health["frames"] if fnum is None else [int(fnum[f]) for f in health["frames"]]
        raise TrackingFailed(
            f"{where}: the tracks cannot be trusted: {health['bad_frames']} frames "
            f"(e.g. {frames}) have non-finite points or points whose own detections reproject "
            f"beyond {health['limit_px']:.0f} px (summary.json 'health'; outputs kept in {out} "
            "for inspection)"
        )
    if health["status"] == "suspect":
        frames = health["turn_frames"]
        log.warning(
            "the body's pose turns by more than %.0f degrees between two frames at %d frames "
            "(e.g. %s): the track may have left the animal there (summary.json 'health')",
            health["max_turn_deg"],
            health["turn_frames_count"],
            frames if fnum is None else [int(fnum[f]) for f in frames],
        )
    alone = summary["from_model_only"]["fraction"]
    if alone > 0.25:
        worst = sorted(summary["from_model_only"]["per_part"].items(), key=lambda kv: -kv[1])[:3]
        log.warning(
            "%.0f%% of the part-frames rest on no accepted detection (tracked from the model "
            "alone; their _ncams is 0 and their _sigma large): most for %s",
            100 * alone,
            ", ".join(f"{p} {100 * v:.0f}%" for p, v in worst),
        )
    err = summary["reprojection_error_px"]
    log.info(
        "tracked %d frames x %d parts (completeness %.1f%%) in %d iterations (%.1f s); "
        "reprojection error median %s px, p90 %s px; wrote %s",
        summary["num_frames"],
        len(summary["parts"]),
        100 * summary["completeness"],
        summary["iterations"],
        summary["time_s"]["total_s"],
        f"{err['median']:.2f}" if err["median"] is not None else "n/a",
        f"{err['p90']:.2f}" if err["p90"] is not None else "n/a",
        out,
    )
