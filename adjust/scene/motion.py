"""Real 3D motion filmed by simulated cameras: a scene with real truth.

A recorded 3D track of a real animal (e.g. ``shared/data/real-mouse-motion-3d/poses3d.csv``: a
real mouse, 34 keypoints, 3600 frames, in its rig's own world frame with no axis "up") is filmed
by a simulated rig placed around it (`motion_rig`) with the scene detector model
(`adjust.scene.detector.simulate_scene`: self-occlusion by body proxies moved with the animal,
dropout bursts, left/right swaps, far outliers, likelihoods). The result is what a user has,
with the truth of a real, deforming body (`film_motion`, written by `adjust.scene.write_scene`).

Conventions: mm; world -> camera ``x_cam = R X + t``. The cameras are expressed in the
recording's own world frame, so a tracker sees the arbitrary orientation a lab's calibration
leaves: the floor's normal (`floor_frame`) is estimated from the paws, not assumed to be z.
Shapes: T frames, K parts, C cameras.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import torch

from adjust.camera import Camera
from adjust.scene.detector import DetectorConfig, SceneDetections, detector_config, simulate_scene
from adjust.scene.folder import write_scene
from adjust.scene.occlusion import Ellipsoid
from adjust.scene.rig import camera_look_at
from deformnet.body import default_mouse
from deformnet.so3 import kabsch, matrix_to_rodrigues

__all__ = [
    "MOTION_FEET",
    "MOTION_PAPER8",
    "MOTION_PARTS22",
    "FilmedMotion",
    "film_motion",
    "film_part_set",
    "floor_frame",
    "load_motion",
    "motion_rig",
    "part_set",
    "write_motion_scene",
]

#: the paper's 8 parts (the default mouse's names) in the real-mouse-motion-3d recording
MOTION_PAPER8 = {
    "nose_tip": "Nose",
    "left_ear": "Ear_L",
    "right_ear": "Ear_R",
    "left_front_paw": "Forepaw_L",
    "right_front_paw": "Forepaw_R",
    "left_hind_paw": "MTP_L",
    "right_hind_paw": "MTP_R",
    "tail_root": "TTI",
}

#: a 22-part subset of its 34 (the 22 keypoints of the real-mouse-poses-3d set, by anatomy)
MOTION_PARTS22 = (
    "Nose", "Ear_L", "Ear_R", "Neck", "Trunk", "TTI", "Tail_2", "TailTip",
    "Forepaw_L", "Wrist_L", "Elbow_L", "Shoulder_L", "Forepaw_R", "Wrist_R", "Elbow_R",
    "Shoulder_R", "MTP_L", "Heel_L", "Knee_L", "MTP_R", "Heel_R", "Knee_R",
)  # fmt: skip

#: the paws that define the floor's plane (`floor_frame`) in the recording
MOTION_FEET = ("MTP_L", "MTP_R", "Forepaw_L", "Forepaw_R")

#: rig cameras by number of cameras (names as in conf/rig/default.yaml, plus "back")
RIG_CAMERAS = {
    2: ("side", "front"),
    3: ("top", "side", "front"),
    4: ("top", "side", "front", "back"),
}


def load_motion(path: str | Path) -> tuple[np.ndarray, tuple[str, ...]]:
    """A recorded 3D track: a CSV of ``{part}_x,_y,_z`` columns (mm), one row per frame (other
    columns, e.g. ``frame``, ignored). Returns points (T, K, 3) and the part names. A missing
    file is a FileNotFoundError, a part with a missing coordinate column or a file with no part
    a ValueError, each naming the file."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such recording (a CSV of {{part}}_x,_y,_z columns)")
    df = pd.read_csv(p)
    parts = [c[:-2] for c in df.columns if c.endswith("_x")]
    missing = [q for q in parts if f"{q}_y" not in df or f"{q}_z" not in df]
    if not parts or missing:
        raise ValueError(f"{p}: no complete {{part}}_x,_y,_z columns (incomplete: {missing})")
    X = np.stack([df[[f"{q}_x", f"{q}_y", f"{q}_z"]].to_numpy(np.float64) for q in parts], 1)
    return X, tuple(parts)


def floor_frame(points: np.ndarray, parts: Sequence[str], feet: Sequence[str]) -> np.ndarray:
    """The floor's frame in the recording's world: (4, 4) homogeneous A with ``X_floor = A X``,
    z up (the normal of the plane the `feet` parts touch, by PCA of their positions; pointing
    towards the body's centroid), floor at z = 0 (the feet's 5th height percentile), the
    body's median position at x = y = 0. points (T, K, 3)."""
    X = np.asarray(points, dtype=np.float64)
    idx = [list(parts).index(f) for f in feet]
    F = X[:, idx].reshape(-1, 3)
    F = F[np.isfinite(F).all(-1)]
    c = F.mean(0)
    _, _, vt = np.linalg.svd(F - c, full_matrices=False)
    up = vt[2]
    body = np.nanmean(X.reshape(-1, 3), 0)
    if np.dot(body - c, up) < 0:
        up = -up
    x = vt[0] - np.dot(vt[0], up) * up
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(up, x), up])  # rows: floor axes in world coordinates
    Y = X.reshape(-1, 3) @ R.T
    t = -np.array([*np.nanmedian(Y[:, :2], 0), np.nanpercentile(F @ up, 5)])
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = R, t
    return A


def motion_rig(
    floor: np.ndarray, num_cameras: int = 3, distance_mm: float = 750.0, size=(1280, 1024)
) -> list[Camera]:
    """A rig around the floor frame's origin, expressed in the recording's world frame
    (`floor`: `floor_frame`'s A): ``top`` looking down from `distance_mm` + 50 (focal 2000 px),
    ``side`` / ``front`` / ``back`` on the -X / -Y / +Y sides ~17 degrees above the floor
    (focal 1800 px), as the default rig (conf/rig/default.yaml) sees its arena. 2 cameras: side
    and front; 3: top, side, front; 4: all."""
    if num_cameras not in RIG_CAMERAS:
        raise ValueError(f"num_cameras must be one of {sorted(RIG_CAMERAS)}, got {num_cameras}")
    A = np.asarray(floor, dtype=np.float64)
    Rt, t = A[:3, :3].T, A[:3, 3]

    def world(p) -> np.ndarray:  # floor frame -> recording world
        return Rt @ (np.asarray(p, dtype=np.float64) - t)

    h = distance_mm * np.tan(np.radians(17.0))
    spec = {
        "top": ([0.0, 0.0, distance_mm + 50.0], [0.0, 1.0, 0.0], 2000.0),
        "side": ([-distance_mm, 0.0, h], [0.0, 0.0, 1.0], 1800.0),
        "front": ([0.0, -distance_mm, h], [0.0, 0.0, 1.0], 1800.0),
        "back": ([0.0, distance_mm, h], [0.0, 0.0, 1.0], 1800.0),
    }
    target = world([0.0, 0.0, 20.0])
    cams = []
    for name in RIG_CAMERAS[num_cameras]:
        pos, up, f = spec[name]
        cams.append(camera_look_at(name, world(pos), target, Rt @ up, f, size))
    return cams


@dataclass(frozen=True)
class FilmedMotion:
    """A filmed recording: ``deformed`` (T, K, 3) truth, ``poses`` (T, 6) of the body proxies
    (Rodrigues + translation, model -> world), ``parts``, ``model`` (K, 3) the parts' median
    position in that body frame, ``scale`` of the default mouse fitted to the anchors (median
    similarity scale), the
    ``detections`` and the cameras; ``fps`` as given."""

    deformed: np.ndarray
    poses: np.ndarray
    parts: tuple[str, ...]
    model: np.ndarray
    scale: float
    detections: SceneDetections
    cameras: tuple[Camera, ...]
    fps: float


def film_motion(
    points: np.ndarray,
    parts: Sequence[str],
    cameras: Sequence[Camera],
    anchors: Mapping[str, str] | None = None,
    detector: DetectorConfig | Mapping | None = None,
    seed: int | Sequence[int] = 0,
    fps: float = 100.0,
) -> FilmedMotion:
    """Film `points` (T, K, 3) of `parts` with `cameras` through the scene detector model.

    The detector's body proxies (the default mouse's trunk and head ellipsoids) follow the
    default mouse fitted to the recording: `anchors` maps its 8 part names to the recording's
    (default `MOTION_PAPER8`); the model is scaled by its similarity fit to the anchors (median over
    frames) and posed per frame by Kabsch; the head proxy follows the recording's nose and ears.
    """
    X = np.asarray(points, dtype=np.float64)
    parts = tuple(str(p) for p in parts)
    if X.ndim != 3 or X.shape[1:] != (len(parts), 3):
        raise ValueError(f"points must be (T, {len(parts)}, 3), got {X.shape}")
    anchors = dict(MOTION_PAPER8 if anchors is None else anchors)
    mouse = default_mouse()
    idx = [parts.index(anchors[p]) for p in mouse.parts]
    B = np.array(mouse.points, dtype=np.float64)  # writable (torch.as_tensor)
    P = X[:, idx]
    # similarity scale (Umeyama) of the model to each frame's anchors; its median over frames
    R, _ = kabsch(torch.as_tensor(P), torch.as_tensor(B))
    Pc, Bc = P - P.mean(1, keepdims=True), B - B.mean(0)
    s = np.einsum("tki,tij,kj->t", Pc, R.numpy(), Bc) / (Bc**2).sum()
    scale = float(np.median(s))
    R, tau = kabsch(torch.as_tensor(P), torch.as_tensor(scale * B))
    poses = np.concatenate([matrix_to_rodrigues(R).numpy(), tau.numpy()], -1)
    body = np.einsum("tji,tkj->tki", R.numpy(), X - tau.numpy()[:, None])
    model = np.median(body, 0)
    cfg = detector_config(detector)
    head = (anchors["nose_tip"], anchors["left_ear"], anchors["right_ear"])
    occ = tuple(
        Ellipsoid(e.name, scale * np.asarray(e.center), scale * np.asarray(e.radii),
                  head if e.parts else ())
        for e in cfg.occluders
    )  # fmt: skip
    cfg = replace(cfg, occluders=occ, lockbox_occludes=False)
    sim = SimpleNamespace(deformed=X, poses=poses, parts=parts, model=model)
    det = simulate_scene(sim, cameras, cfg, seed=seed)
    return FilmedMotion(X, poses, parts, model, scale, det, tuple(cameras), float(fps))


def write_motion_scene(
    out: str | Path,
    points: np.ndarray,
    parts: Sequence[str],
    cameras: Sequence[Camera],
    keep: Sequence[str] | None = None,
    rename: Mapping[str, str] | None = None,
    detector: DetectorConfig | Mapping | None = None,
    seed: int | Sequence[int] = 0,
    fps: float = 100.0,
) -> dict:
    """`film_motion`, then the scene folder (`write_scene`: calibration.toml, detections/ as
    DeepLabCut CSVs, truth.npz) of the parts `keep` (default all; the whole body is filmed, so
    occlusion is the same whichever parts are kept), named by `rename` (recording name -> file
    name; e.g. the paper's 8 as the default mouse's names: ``{v: k for k, v in
    MOTION_PAPER8.items()}``). Returns `write_scene`'s paths and the detections' fractions."""
    parts = tuple(str(p) for p in parts)
    fm = film_motion(points, parts, cameras, detector=detector, seed=seed, fps=fps)
    keep = parts if keep is None else tuple(keep)
    idx = [parts.index(p) for p in keep]
    names = tuple((rename or {}).get(p, p) for p in keep)
    det = fm.detections
    arrays = {
        f.name: getattr(det, f.name)[:, idx]
        for f in fields(det)
        if isinstance(getattr(det, f.name), np.ndarray)
    }
    det = replace(det, **arrays, parts=names)
    sim = SimpleNamespace(deformed=fm.deformed[:, idx], poses=fm.poses, parts=names, fps=fps)
    res = write_scene(out, sim, cameras, det, metadata={"fps": float(fps), "seed": str(seed)})
    return {**res, "fractions": det.fractions(), "scale": fm.scale}


def part_set(n: int, parts: Sequence[str]) -> tuple[list[str], list[str]]:
    """The recording's names of its `n`-part set and the scene's names for them: 8, the paper's
    (`MOTION_PAPER8`, named as the default mouse so ``adjust-track``'s default body applies);
    22 (`MOTION_PARTS22`) or all of `parts`, under the recording's own names."""
    if n == 8:
        return list(MOTION_PAPER8.values()), list(MOTION_PAPER8)
    if n == 22:
        return list(MOTION_PARTS22), list(MOTION_PARTS22)
    if n == len(parts):
        return list(parts), list(parts)
    raise ValueError(f"part set must be 8, 22 or {len(parts)}, got {n}")


def film_part_set(
    out: str | Path,
    points: np.ndarray,
    parts: Sequence[str],
    floor: np.ndarray,
    cameras: int,
    num_parts: int,
    seed: int = 0,
) -> dict:
    """`write_motion_scene` of the recording's frames `points` (T, P, 3) mm filmed by the
    `cameras`-camera `motion_rig` on `floor` (`floor_frame`'s frame), keeping its
    `num_parts`-part set (`part_set`) under the scene's names; detector seed `seed`."""
    src, names = part_set(num_parts, parts)
    rig = motion_rig(floor, cameras)
    return write_motion_scene(out, points, parts, rig, src, dict(zip(src, names)), seed=seed)
