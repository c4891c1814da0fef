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

import json
import logging
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig

from adjust.app import finite_or_none, load_kwargs, required, run_or_exit, stats
from adjust.camera import CameraTensors
from adjust.io import load_scene, write_points3d
from deformnet.atomic import write_text
from deformnet.body import BodyModel
from deformnet.paths import CONF_DIR, output_dir

log = logging.getLogger(__name__)

WEIGHTS = ("likelihood", "uniform")


def run(cfg: DictConfig) -> dict:
    """Load, triangulate, write points3d.csv and summary.json; returns the summary."""
    from adjust.triangulate import triangulate

    calibration = required(cfg, "input.calibration", "triangulate")
    detections = required(cfg, "input.detections", "triangulate")
    inp = cfg.input
    tri = cfg.triangulate
    weight_mode = str(tri.get("weight", "likelihood"))
    if weight_mode not in WEIGHTS:
        raise ValueError(f"triangulate.weight must be one of {WEIGHTS}, got {weight_mode!r}")
    body_cfg = cfg.get("body")
    body = BodyModel.from_config(body_cfg) if body_cfg else None
    cameras, det = load_scene(
        calibration,
        detections,
        body,
        **load_kwargs(inp),
    )
    weight = det.weight() if weight_mode == "likelihood" else det.observed.astype(np.float64)
    cams = CameraTensors.from_cameras(cameras, dtype=torch.float64)
    with torch.no_grad():
        res = triangulate(
            torch.as_tensor(det.xy),
            torch.as_tensor(weight),
            cams,
            robust=bool(tri.get("robust", False)),
            max_error_px=float(tri.get("max_error_px", 20.0)),
            min_views=int(tri.get("min_views", 2)),
        )
    points = res.points.numpy()
    error = res.error.numpy()
    ncams = res.ncams.numpy()
    used = res.used.numpy()
    done = np.isfinite(points).all(-1)
    score = np.where(used, det.likelihood, np.inf).min(-1)
    score = np.where(done & np.isfinite(score), score, np.nan)

    out = output_dir(cfg)
    points_path = write_points3d(out / "points3d.csv", det.parts, points, error, ncams, score)
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
        "individual": inp.get("individual"),
        "triangulate": {
            "robust": bool(tri.get("robust", False)),
            "max_error_px": float(tri.get("max_error_px", 20.0)),
            "min_views": int(tri.get("min_views", 2)),
            "weight": weight_mode,
        },
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
            "detections_per_camera": {
                c: int(observed[..., i].sum()) for i, c in enumerate(det.cameras)
            },
            "views_used": int(used.sum()),
            "views_dropped": int((observed & done[..., None]).sum() - used.sum()),
            "observed_views_histogram": np.bincount(nviews.reshape(-1), minlength=C + 1).tolist(),
            "used_views_histogram": np.bincount(ncams.reshape(-1), minlength=C + 1).tolist(),
        },
        "outputs": {"points3d": str(points_path), "summary": str(out / "summary.json")},
    }
    summary = finite_or_none(summary)
    write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
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


@hydra.main(config_path=str(CONF_DIR), config_name="triangulate", version_base=None)
def main(cfg: DictConfig) -> None:
    run_or_exit(run, cfg)


if __name__ == "__main__":  # pragma: no cover
    main()
