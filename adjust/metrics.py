"""Evaluation metrics shared by every method: numpy in, plain Python numbers out, NaN-aware.

Shapes: T frames, K parts, C cameras. A *part-frame* is one part in one frame. An estimate is
missing where any coordinate is NaN. "Seen" part-frames are those detected in >= 2 cameras
(triangulable); the others are "occluded" (the part-frames a model must fill in).
Every returned dict holds only str keys and float / int / list / dict values (JSON-ready;
NaN where a group is empty).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from adjust.camera import Camera, CameraTensors
from adjust.camera import reprojection_errors as _pixel_errors

WITHIN_MM = 5.0


def _finite_points(x: np.ndarray, name: str) -> np.ndarray:
    """(..., 3) -> (...) bool: all three coordinates finite."""
    if x.ndim < 1 or x.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {x.shape}")
    return np.isfinite(x).all(-1)


def completeness(est: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Fraction of part-frames with a finite estimate.

    est: (T, K, 3) mm (NaN = missing); mask: optional (T, K) bool selecting the part-frames
    to count (e.g. the occluded ones). NaN if nothing is selected.
    """
    ok = _finite_points(np.asarray(est, dtype=float), "est")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != ok.shape:
            raise ValueError(f"mask must have shape {ok.shape}, got {mask.shape}")
        ok = ok[mask]
    return float(ok.mean()) if ok.size else float("nan")


def error_summary(values: np.ndarray) -> dict:
    """n, mean, median, p90, rmse, max of the finite entries of any array (NaN if none)."""
    v = np.asarray(values, dtype=float).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        nan = float("nan")
        return {"n": 0, "mean": nan, "median": nan, "p90": nan, "rmse": nan, "max": nan}
    return {
        "n": int(v.size),
        "mean": float(v.mean()),
        "median": float(np.median(v)),
        "p90": float(np.percentile(v, 90)),
        "rmse": float(np.sqrt(np.mean(v * v))),
        "max": float(v.max()),
    }


def point_errors(
    est: np.ndarray,
    truth: np.ndarray,
    nviews: np.ndarray | None = None,
    min_views: int = 2,
    within_mm: float = WITHIN_MM,
    part_names: Sequence[str] | None = None,
) -> dict:
    """3D errors of estimates against ground truth, overall and split by visibility.

    est, truth: (T, K, 3) mm, NaN where missing; nviews: (T, K) number of cameras that
    detected each part-frame (None: no split). Errors are Euclidean distances over the
    part-frames where both est and truth are finite. Keys, for g in all / seen (nviews >=
    min_views) / occluded (nviews < min_views):
      rmse_g, median_g, mean_g, p90_g, max_g (mm), within5_g (fraction of evaluated part-frames
      with error <= within_mm), within5_strict_g (the same over all the group's part-frames
      with finite truth, a missing estimate counting as a miss), n_g (evaluated count),
      completeness_g (fraction of the group's part-frames with finite truth that have a
      finite estimate);
    plus completeness (all part-frames), frac_occluded, within_mm, and per_part:
    {part: {rmse, median, within5, completeness}}.
    """
    est = np.asarray(est, dtype=float)
    truth = np.asarray(truth, dtype=float)
    if est.shape != truth.shape or est.ndim != 3 or est.shape[-1] != 3:
        raise ValueError(f"est and truth must both be (T, K, 3), got {est.shape}, {truth.shape}")
    T, K, _ = est.shape
    has_est = _finite_points(est, "est")
    has_truth = _finite_points(truth, "truth")
    err = np.where(has_est & has_truth, np.linalg.norm(est - truth, axis=-1), np.nan)
    groups = {"all": np.ones((T, K), dtype=bool)}
    if nviews is not None:
        nviews = np.asarray(nviews)
        if nviews.shape != (T, K):
            raise ValueError(f"nviews must have shape {(T, K)}, got {nviews.shape}")
        groups["seen"] = nviews >= min_views
        groups["occluded"] = nviews < min_views
    out: dict = {"completeness": completeness(est), "within_mm": float(within_mm)}
    for g, m in groups.items():
        s = error_summary(err[m])
        e = err[m]
        e = e[np.isfinite(e)]
        out[f"rmse_{g}"] = s["rmse"]
        out[f"median_{g}"] = s["median"]
        out[f"mean_{g}"] = s["mean"]
        out[f"p90_{g}"] = s["p90"]
        out[f"max_{g}"] = s["max"]
        out[f"within5_{g}"] = float((e <= within_mm).mean()) if e.size else float("nan")
        denom = int((m & has_truth).sum())
        hits = int((err[m] <= within_mm).sum())  # NaN compares False: missing = miss
        out[f"within5_strict_{g}"] = hits / denom if denom else float("nan")
        out[f"n_{g}"] = s["n"]
        out[f"completeness_{g}"] = completeness(est, m & has_truth)
    if nviews is not None:
        out["frac_occluded"] = float(groups["occluded"].mean()) if T * K else float("nan")
    names = list(part_names) if part_names is not None else [str(k) for k in range(K)]
    if len(names) != K:
        raise ValueError(f"part_names has {len(names)} names for {K} parts")
    per_part = {}
    for k, name in enumerate(names):
        e = err[:, k]
        e = e[np.isfinite(e)]
        per_part[name] = {
            "rmse": float(np.sqrt(np.mean(e * e))) if e.size else float("nan"),
            "median": float(np.median(e)) if e.size else float("nan"),
            "within5": float((e <= within_mm).mean()) if e.size else float("nan"),
            "completeness": completeness(est[:, k : k + 1], has_truth[:, k : k + 1]),
        }
    out["per_part"] = per_part
    return out


def reprojection_errors(
    points: np.ndarray,
    xy: np.ndarray,
    cams: CameraTensors | Sequence[Camera],
    observed: np.ndarray | None = None,
) -> np.ndarray:
    """Pixel distances (T, K, C) between projected points (T, K, 3) and detections
    xy (T, K, C, 2); NaN where either is missing or not `observed` ((T, K, C) bool, default
    all). numpy in and out around `adjust.camera.reprojection_errors`."""
    if not isinstance(cams, CameraTensors):
        cams = CameraTensors.from_cameras(list(cams))
    p = torch.as_tensor(np.asarray(points, dtype=float), dtype=cams.K.dtype)
    d = torch.as_tensor(np.asarray(xy, dtype=float), dtype=cams.K.dtype)
    obs = None if observed is None else torch.as_tensor(np.asarray(observed, dtype=bool))
    with torch.no_grad():
        return _pixel_errors(p, d, cams, obs).numpy()


def reprojection_stats(
    errors: np.ndarray,
    camera_names: Sequence[str] | None = None,
    part_names: Sequence[str] | None = None,
) -> dict:
    """Reprojection error statistics (px) overall, per camera and per part.

    errors: (T, K, C) px, NaN where not observed or not estimated (e.g. from
    `reprojection_errors` or `TriangulationResult.view_error`). Returns {"all": summary,
    "per_camera": {name: summary}, "per_part": {name: summary}}, each summary as in
    `error_summary` (n, mean, median, p90, rmse, max).
    """
    errors = np.asarray(errors, dtype=float)
    if errors.ndim != 3:
        raise ValueError(f"errors must have shape (T, K, C), got {errors.shape}")
    _, K, C = errors.shape
    cn = list(camera_names) if camera_names is not None else [str(c) for c in range(C)]
    pn = list(part_names) if part_names is not None else [str(k) for k in range(K)]
    if len(cn) != C or len(pn) != K:
        raise ValueError(f"need {C} camera names and {K} part names, got {len(cn)}, {len(pn)}")
    return {
        "all": error_summary(errors),
        "per_camera": {name: error_summary(errors[:, :, c]) for c, name in enumerate(cn)},
        "per_part": {name: error_summary(errors[:, k]) for k, name in enumerate(pn)},
    }


def stats(values: np.ndarray) -> dict:
    """count, median, mean, p90 and max of the finite values (None when there are none): the
    summary.json view of `adjust.metrics.error_summary`, the one statistics summary."""
    s = error_summary(values)
    if s["n"] == 0:
        return {"count": 0, "median": None, "mean": None, "p90": None, "max": None}
    return {"count": s["n"], **{k: s[k] for k in ("median", "mean", "p90", "max")}}
