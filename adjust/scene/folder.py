"""The scene folder writer: what a real user has (anipose calibration, DeepLabCut CSVs) plus the
truth (``truth.npz``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from adjust.camera import Camera
from adjust.io import save_calibration, write_dlc_csv
from adjust.scene.detector import SceneDetections
from deformnet.atomic import atomic_path

__all__ = ["write_scene"]


def write_scene(
    out_dir: Any,
    sim: Any,
    cameras: Sequence[Camera],
    det: SceneDetections,
    scorer: str = "DLC_mousetrack_sim",
    metadata: Mapping | None = None,
) -> dict:
    """Write a scene folder as a real user has it: ``calibration.toml`` (anipose),
    ``detections/<camera>.csv`` (DeepLabCut CSV) and ``truth.npz``; every file atomically.

    truth.npz: ``points (T, K, 3)`` true (deformed) parts, ``rigid (T, K, 3)``, ``poses (T, 6)``,
    ``labels (T,)``, ``parts (K,)``, ``behaviors``, ``cameras (C,)``, ``nviews (T, K)`` (cameras
    with an accepted, correct detection), ``visible / outlier / likelihood (T, K, C)``,
    ``time (T,)``, ``fps``, ``lockbox_corners (M, 3)``, ``arena_size (2,)``. The calibration's
    ``[metadata]`` holds ``lockbox_points`` and ``mechanisms`` (name -> [x, y, z] mm).
    Returns {"dir", "calibration", "detections": {camera: path}, "truth"}.
    """
    from pathlib import Path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = [c.name for c in cameras]
    if tuple(names) != tuple(det.cameras):
        raise ValueError(f"detections are for cameras {list(det.cameras)}, rig has {names}")
    T, K = det.xy.shape[:2]
    lockbox = np.asarray(getattr(sim, "lockbox_corners", np.zeros((0, 3))), dtype=np.float64)
    lockbox = lockbox.reshape(-1, 3)
    arena = np.asarray(getattr(sim, "arena_size", (np.nan, np.nan)), dtype=np.float64)
    meta = {"source": "adjust-simulate", "num_frames": int(T)}
    if np.all(np.isfinite(arena)):
        meta["arena_size"] = arena.tolist()
    if lockbox.size:
        meta["lockbox_points"] = lockbox.tolist()
    mech = getattr(sim, "mechanisms", None)
    if mech is not None and len(mech[0]):  # lock-box mechanisms: name -> [x, y, z] mm
        meta["mechanisms"] = {str(n): np.asarray(p, float).tolist() for n, p in zip(*mech)}
    meta.update(dict(metadata or {}))
    calib = save_calibration(out / "calibration.toml", list(cameras), metadata=meta)
    det_dir = out / "detections"
    det_dir.mkdir(exist_ok=True)
    paths = {}
    for c, name in enumerate(names):
        paths[name] = write_dlc_csv(
            det_dir / f"{name}.csv", det.parts, det.xy[:, :, c], det.likelihood[:, :, c], scorer
        )

    def field_or(name: str, default: Any) -> Any:
        v = getattr(sim, name, None)
        return default if v is None else v

    truth = {
        "points": np.asarray(sim.deformed, dtype=np.float64),
        "rigid": np.asarray(field_or("rigid", np.full((T, K, 3), np.nan)), dtype=np.float64),
        "poses": np.asarray(sim.poses, dtype=np.float64),
        "labels": np.asarray(field_or("labels", np.full(T, -1)), dtype=np.int64),
        "parts": np.asarray(det.parts, dtype=str),
        "behaviors": np.asarray(tuple(field_or("behaviors", ())), dtype=str),
        "cameras": np.asarray(names, dtype=str),
        "nviews": det.nviews.astype(np.int64),
        "visible": det.visible,
        "outlier": det.outlier,
        "likelihood": det.likelihood,
        "time": np.asarray(field_or("time", np.arange(T, dtype=np.float64)), dtype=np.float64),
        "fps": np.float64(field_or("fps", np.nan)),
        "lockbox_corners": lockbox,
        "arena_size": arena,
    }
    truth_path = out / "truth.npz"
    with atomic_path(truth_path) as tmp:
        np.savez_compressed(tmp, **truth)
    return {"dir": out, "calibration": calib, "detections": paths, "truth": truth_path}


def scene_fps(scene_dir: Any) -> float | None:
    """A scene folder's frame rate (Hz) from its ``truth.npz``; None where it has none."""
    from pathlib import Path

    with np.load(Path(scene_dir) / "truth.npz", allow_pickle=False) as z:
        fps = float(z["fps"]) if "fps" in z.files else float("nan")
    return fps if np.isfinite(fps) and fps > 0 else None


def write_truth_labels(scene_dir: Any, path: Any) -> Any:
    """The scene's true behavior labels (``truth.npz``: ``labels``, ``behaviors``) as the
    per-frame ``fnum,label`` CSV that `deformnet-classify` reads, written atomically at ``path``.
    A ValueError names the scene when it has no behavior labels (every label -1)."""
    from pathlib import Path

    import pandas as pd

    src = Path(scene_dir) / "truth.npz"
    with np.load(src) as z:
        labels = np.asarray(z["labels"], dtype=np.int64)
        behaviors = [str(b) for b in z["behaviors"]]
    if not behaviors or labels.size == 0 or np.all(labels < 0):
        raise ValueError(f"{src}: the scene has no behavior labels")
    bad = (labels >= len(behaviors)) | (labels < -1)
    if bad.any():
        f = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"{src}: frame {f} has label index {labels[f]}, not one of the "
            f"{len(behaviors)} behaviors"
        )
    keep = labels >= 0
    names = np.asarray(behaviors, dtype=object)[labels[keep]]
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        pd.DataFrame({"fnum": np.flatnonzero(keep), "label": names}).to_csv(tmp, index=False)
    return out
