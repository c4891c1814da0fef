"""Behavior sessions' tracks: the points3d CSV layout `adjust-track` writes (`{part}_x/_y/_z`
columns, `pose_rx..pose_tz`, `fnum`; read here by column name, without `adjust`) read in a body
model's parts, the session they make, and the animal's size against the body model."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from deformnet.series import interpolate_gaps
from deformnet.so3 import kabsch, rodrigues_to_matrix, transform_points
from deformnet.tables import read_points3d_table, xyz_parts

log = logging.getLogger(__name__)

__all__ = ["POSE_COLUMNS", "POSE_MISMATCH", "pose_mismatch", "Session", "BODY_SCALE_RANGE",
           "body_scale", "read_tracks"]  # fmt: skip

POSE_COLUMNS = ("pose_rx", "pose_ry", "pose_rz", "pose_tx", "pose_ty", "pose_tz")

#: a track's pose columns belong to another body model than the one reading them when, over the
#: frames with at least 3 finite parts, the median angle between each pose's rotation and the
#: rotation fitted to the parts (Kabsch) exceeds "angle_deg", or the median distance between
#: the parts' centroid and the posed model's (same parts) exceeds "offset" times the model's rms
#: radius. Measured on adjust-track output posed with its own model: 3 degrees, 1.1 mm (the demo's
#: simulated mouse), 4.6 degrees, 2.3 mm (benchmarks/domain_gap.py's mouse with real-mouse
#: deformations); the demo scene tracked with body=auto, read with the mouse model: 170 degrees
POSE_MISMATCH = {"angle_deg": 30.0, "offset": 0.5}


# --------------------------------------------------------------------------------------------
# sessions: tracks and labels
# --------------------------------------------------------------------------------------------
@dataclass
class Session:
    """One recording: rigid, deformed (T, K, 3) global mm, observed (T, K) bool, fnum (T,)
    frame numbers, labels (T,) int64 class index (-1: not labelled); scale: the animal's size
    relative to the rigid model (`body_scale`), which the classifier divides out, or None (the
    points as they are); pose: where the rigid points' poses came from (`read_tracks`)."""

    name: str
    rigid: np.ndarray
    deformed: np.ndarray
    observed: np.ndarray
    fnum: np.ndarray
    labels: np.ndarray
    scale: float | None = None
    pose: str | None = None  # read_tracks' "pose": columns | fitted; None: not from a file

    def __len__(self) -> int:
        return len(self.fnum)


#: a session whose `body_scale` falls outside this range is an error: its points are not in mm,
#: or the body model is not this animal's
BODY_SCALE_RANGE = (0.5, 2.0)


def body_scale(
    body, rigid: np.ndarray, deformed: np.ndarray, observed: np.ndarray, name: str = "the track"
) -> float:
    """The animal's size relative to the rigid body model (a `deformnet.body.BodyModel`), from
    a session's tracks: rigid (this model moved by each frame's pose), deformed (T, K, 3) mm,
    observed (T, K) bool.

    `BodyModel.estimate_scale` given the posed model: per frame the least-squares scale of the
    observed parts about the posed model's centroid, over the frames with at least 3 observed
    parts; the median. 1 for an animal the model's size (its deformations average out), 1.2
    for one 20% larger. A session with no such frame, or a scale outside BODY_SCALE_RANGE, is
    a ValueError naming `name`.
    """
    rigid, deformed = np.asarray(rigid, np.float64), np.asarray(deformed, np.float64)
    observed = np.asarray(observed, bool)
    if rigid.ndim != 3 or rigid.shape[-1] != 3 or deformed.shape != rigid.shape:
        raise ValueError(
            f"rigid / deformed must be (T, K, 3) alike, got {rigid.shape} / {deformed.shape}"
        )
    if observed.shape != rigid.shape[:2]:
        raise ValueError(f"observed must be {rigid.shape[:2]}, got {observed.shape}")
    points = np.where(observed[..., None], deformed, np.nan)
    s, n = body.estimate_scale(points, min_parts=3, rigid=rigid)
    if n == 0:
        raise ValueError(
            f"{name}: no frame with 3 or more observed parts to measure the animal's size from "
            "(body_scale=none skips the size normalisation)"
        )
    lo, hi = BODY_SCALE_RANGE
    if not lo <= s <= hi:
        raise ValueError(
            f"{name}: the tracked parts are {s:.3g} times the body model's size (median over "
            f"{n} frames; allowed {lo:g}-{hi:g}): are the points in mm, and is the "
            "body model this animal's? (body_scale=none skips the size normalisation)"
        )
    return s


def pose_mismatch(body, poses: np.ndarray, points: np.ndarray, observed: np.ndarray) -> dict | None:
    """Whether a track's poses (T, 6) (`POSE_COLUMNS`: Rodrigues rad, mm; model -> global)
    belong to the body model `body` (a `deformnet.body.BodyModel`), given its parts' points
    (T, K, 3) mm in the model's part order and observed (T, K) bool.

    Over the frames with at least 3 observed parts: each pose's rotation against the one the
    Kabsch fit of the model to the observed parts gives, and the observed parts' centroid
    against the posed model's (same parts). Returns None when the poses fit (medians within
    `POSE_MISMATCH`), else {"angle_deg", "offset_mm", "frames"} (the medians, the frames used);
    None as well without such a frame (nothing to compare).
    """
    obs = np.asarray(observed, bool)
    use = obs.sum(-1) >= 3
    if not use.any():
        return None
    model = torch.tensor(np.array(body.points, dtype=np.float64))
    P = torch.as_tensor(np.where(obs[use][..., None], points[use], 0.0), dtype=torch.float64)
    w = torch.as_tensor(obs[use], dtype=torch.float64)
    pz = torch.as_tensor(np.asarray(poses, np.float64)[use])
    R, _ = kabsch(P, model, w)
    Rp = rodrigues_to_matrix(pz[:, :3])
    cos = ((Rp.transpose(-1, -2) @ R).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    angle = float(torch.rad2deg(torch.arccos(cos.clamp(-1, 1))).median())
    rigid = transform_points(pz, model.expand(len(pz), -1, -1))
    n = w.sum(-1, keepdim=True)
    offset = float((((P - rigid) * w[..., None]).sum(-2) / n).norm(dim=-1).median())
    radius = float(((model - model.mean(0)) ** 2).sum(-1).mean().sqrt())
    if angle <= POSE_MISMATCH["angle_deg"] and offset <= POSE_MISMATCH["offset"] * radius:
        return None
    return {"angle_deg": angle, "offset_mm": offset, "frames": int(use.sum())}


def read_tracks(path: str | os.PathLike, body, interpolate: bool = False) -> dict:
    """A points3d CSV -> {"rigid", "deformed" (T, K, 3), "observed" (T, K), "fnum" (T,), "pose"}
    in the body model's part order (parts found by name or alias).

    With pose columns that belong to this body model (`pose_mismatch`) the rigid points are the
    model moved by each frame's pose ("pose": "columns"); without, or when they belong to
    another model (a track made with `adjust-track body=auto`, say: logged as a warning), the
    pose is fitted per frame by Kabsch (`deformnet.so3.kabsch`) to the points ("fitted"),
    which then must all be finite (set `interpolate` to fill gaps linearly in time first).
    """
    path = Path(path)
    df = read_points3d_table(path, "tracks file")  # with its sidecar's pose columns
    cols = set(df.columns)
    found: dict[str, str] = {}
    unused: list[str] = []  # the file's parts that name none of the model's
    for part in xyz_parts(df.columns):
        name = body.resolve(part)
        if name is None:
            unused.append(part)
            continue
        if name in found:
            raise ValueError(
                f"{path}: parts '{found[name]}' and '{part}' both map to body part '{name}' of "
                f"model '{body.name}' (keep one, or rename the other)"
            )
        found[name] = part
    missing = [p for p in body.parts if p not in found]
    if missing:
        raise ValueError(
            f"{path}: no {{part}}_x/_y/_z columns for body part(s) {missing} of model "
            f"'{body.name}' (matched: {found or 'none'}; the file's other parts: "
            f"{unused or 'none'})"
            ". Map the file's names to the model's parts with deformnet-classify "
            f"'aliases={{<name in the file>: {missing[0]}, ...}}'; a part the file lacks cannot "
            "be mapped (the classifier needs every part of its body model)"
        )
    T = len(df)
    if T == 0:
        raise ValueError(f"{path}: no rows")

    def numeric(col: str) -> np.ndarray:
        v = pd.to_numeric(df[col], errors="coerce")
        bad = v.isna() & df[col].notna()
        if bad.any():
            r = int(np.flatnonzero(bad.to_numpy())[0])
            raise ValueError(f"{path}: non-numeric value {df[col].iloc[r]!r} in '{col}', row {r}")
        return v.to_numpy(np.float64)

    pts = np.stack(
        [np.stack([numeric(f"{found[p]}_{a}") for a in "xyz"], -1) for p in body.parts], 1
    )
    observed = np.isfinite(pts).all(-1)
    if interpolate:
        pts = interpolate_gaps(pts)
        never = [p for k, p in enumerate(body.parts) if not np.isfinite(pts[:, k]).all()]
        if never:
            raise ValueError(f"{path}: part(s) {never} have no finite value to interpolate from")
        observed = np.ones_like(observed)
    model = torch.tensor(np.array(body.points, dtype=np.float64))
    pose_source = "fitted"  # the body model fitted to the parts per frame (Kabsch)
    if all(c in cols for c in POSE_COLUMNS):
        poses = np.stack([numeric(c) for c in POSE_COLUMNS], -1)
        bad = ~np.isfinite(poses).all(-1)
        if bad.any():
            raise ValueError(
                f"{path}: non-finite pose in row {int(np.flatnonzero(bad)[0])} (pose columns "
                "must be complete; adjust-track writes them so)"
            )
        bad = pose_mismatch(body, poses, pts, observed)
        if bad is None:
            rigid = transform_points(torch.as_tensor(poses), model.expand(T, -1, -1)).numpy()
            pose_source = "columns"
        else:
            why = (
                f"{path}: the pose columns do not belong to body model '{body.name}' (median "
                f"{bad['angle_deg']:.0f} degrees from the rotation its parts give, centroids "
                f"{bad['offset_mm']:.1f} mm apart, over {bad['frames']} frames): was it tracked "
                "with another body model (e.g. adjust-track body=auto)?"
            )
            if not observed.all():
                t, k = np.argwhere(~observed)[0]
                raise ValueError(
                    f"{why} The pose cannot be fitted to this model's parts instead: part "
                    f"'{body.parts[k]}' is missing in row {t}. Track it with body={body.name} "
                    "(or fill gaps first: data.interpolate=true)"
                )
            log.warning("%s Its pose is fitted to this model's parts per frame instead", why)
    if pose_source != "columns":
        if not observed.all():
            t, k = np.argwhere(~observed)[0]
            raise ValueError(
                f"{path}: no pose columns and part '{body.parts[k]}' is missing in row {t}: "
                "fill gaps first (data.interpolate=true) or use adjust-track output"
            )
        P = torch.as_tensor(pts)
        R, t = kabsch(P, model)
        rigid = (model @ R.transpose(-1, -2) + t[:, None, :]).numpy()
    deformed = np.where(observed[..., None], pts, rigid)
    fnum = numeric("fnum").astype(np.int64) if "fnum" in cols else np.arange(T, dtype=np.int64)
    if len(np.unique(fnum)) != T:
        raise ValueError(f"{path}: duplicate frame numbers in column 'fnum'")
    return {
        "rigid": rigid.astype(np.float32),
        "deformed": deformed.astype(np.float32),
        "observed": observed,
        "fnum": fnum,
        "pose": pose_source,
    }
