"""`adjust-triangulate`: triangulate a calibration plus a folder of DeepLabCut files.

    adjust-triangulate input.calibration=calibration.toml input.detections=trial_000 \
        output.dir=out [body=mouse] [input.likelihood_threshold=0.6] [triangulate.robust=true]

Writes ``points3d.csv`` (anipose's 3D CSV layout, `adjust.io.points3d`) and ``summary.json``
(completeness, reprojection error statistics, counts) into the output folder. Without ``body=``
the files' own part names are used; ``body=mouse`` maps them through the model's aliases.

`run(cfg) -> dict` is the plain function behind the Hydra app (tests call it through Hydra's
compose API); it returns the summary.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from adjust.apps.common import finite_or_none, hydra_app, prepare_output, write_outputs
from adjust.camera import CameraTensors
from adjust.camera_check import check_from_config
from adjust.io import check_cameras_usable, load_scene, write_points3d
from adjust.metrics import stats
from adjust.settings import TriangulateConfig, load_kwargs, required
from adjust.triangulate import triangulate
from deformnet.body import BodyModel

log = logging.getLogger(__name__)


def run(cfg: DictConfig) -> dict:
    """Load, triangulate, write points3d.csv and summary.json; returns the summary."""

    calibration = required(cfg, "input.calibration", "triangulate")
    detections = required(cfg, "input.detections", "triangulate")
    inp = cfg.input
    tri = TriangulateConfig.from_config(cfg.get("triangulate"))
    kwargs = load_kwargs(inp)
    out = prepare_output(cfg)  # before any computing
    body_cfg = cfg.get("body")
    body = BodyModel.from_config(body_cfg) if body_cfg else None
    cameras, det = load_scene(calibration, detections, body, **kwargs)
    cameras, det, camera_report = check_from_config(cameras, det, inp)
    check_cameras_usable(det, str(detections))  # one camera cannot triangulate: refused
    weight = det.weight() if tri.weight == "likelihood" else det.observed.astype(np.float64)
    cams = CameraTensors.from_cameras(cameras, dtype=torch.float64)
    with torch.no_grad():
        res = triangulate(
            torch.as_tensor(det.xy),
            torch.as_tensor(weight),
            cams,
            robust=tri.robust,
            max_error_px=tri.max_error_px,
            min_views=tri.min_views,
        )
    points = res.points.numpy()
    error = res.error.numpy()
    ncams = res.ncams.numpy()
    used = res.used.numpy()
    done = np.isfinite(points).all(-1)
    score = np.where(used, det.likelihood, np.inf).min(-1)
    score = np.where(done & np.isfinite(score), score, np.nan)

    T, K, C = det.num_frames, det.num_parts, det.num_cameras
    observed = det.observed
    nviews = observed.sum(-1)
    summary = {
        "inputs": {
            "calibration": str(Path(calibration).resolve()),
            "detections": str(Path(detections).resolve()),
            "files": {c: str(f) for c, f in zip(det.cameras, det.files)},
        },
        "body": body.name if body is not None else "files",
        "cameras": list(det.cameras),
        "parts": list(det.parts),
        "num_frames": T,
        "likelihood_threshold": det.threshold,
        "individual": kwargs["individual"],
        "camera_check": camera_report,
        # the files' frame numbers (the fnum column), first and last
        "frames": np.asarray(det.frames)[[0, -1]].tolist() if T else [],
        "detections_set_aside": det.notes.get("absurd_or_nonfinite", {}),
        "triangulate": dataclasses.asdict(tri),
        # fraction of keypoint-frames with a 3D point
        "completeness": float(done.mean()) if done.size else 0.0,
        "completeness_per_part": {p: float(done[:, k].mean()) for k, p in enumerate(det.parts)},
        # mean reprojection error (px) over each point's used views, over all 3D points
        "reprojection_error_px": stats(error[done]),
        "reprojection_error_px_per_part": {
            p: stats(error[:, k][done[:, k]])["median"] for k, p in enumerate(det.parts)
        },
        "counts": {
            "keypoint_frames": int(T * K),
            "triangulated": int(done.sum()),
            "detections": int(observed.sum()),
            "detections_per_camera": det.usable_per_camera(),
            "views_used": int(used.sum()),
            "views_dropped": int((observed & done[..., None]).sum() - used.sum()),
            "observed_views_histogram": np.bincount(nviews.reshape(-1), minlength=C + 1).tolist(),
            "used_views_histogram": np.bincount(ncams.reshape(-1), minlength=C + 1).tolist(),
        },
    }
    summary = write_outputs(
        out,
        lambda path: write_points3d(path, det.parts, points, error, ncams, score, fnum=det.frames),
        finite_or_none(summary),
    )
    err = summary["reprojection_error_px"]
    log.info(
        "triangulated %d of %d keypoint-frames (%.1f%%); reprojection error median %s px, "
        "p90 %s px; wrote %s",
        summary["counts"]["triangulated"],
        T * K,
        100 * summary["completeness"],
        f"{err['median']:.2f}" if err["median"] is not None else "n/a",
        f"{err['p90']:.2f}" if err["p90"] is not None else "n/a",
        out,
    )
    return summary


main = hydra_app(run, "triangulate")


if __name__ == "__main__":  # pragma: no cover
    main()
