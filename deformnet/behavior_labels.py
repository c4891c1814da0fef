"""Behavior sessions for `deformnet-classify`: 3D tracks and labels read, bouts, smoothing.

Tracks: the points3d CSV layout `adjust-track` writes (`{part}_x/_y/_z` columns, `pose_rx..pose_tz`,
`fnum`; read here by column name, without `adjust`). Labels: per frame (`fnum,label`) or bouts
(`start,stop,label`, stop inclusive); every error names the file and the row.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from deformnet.confutil import check_fps
from deformnet.series import interpolate_gaps
from deformnet.tables import read_csv, read_points3d_table, xyz_parts

log = logging.getLogger(__name__)

__all__ = [
    "POSE_COLUMNS",
    "POSE_MISMATCH",
    "pose_mismatch",
    "Session",
    "BODY_SCALE_RANGE",
    "body_scale",
    "read_tracks",
    "read_labels",
    "bouts",
    "smooth",
    "check_fps",
    "same_fps",
    "resample_session",
    "to_track_frames",
    "subsample_labels",
]

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
    from deformnet.so3 import kabsch, rodrigues_to_matrix, transform_points

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
    pose is fitted per frame by Kabsch (`deformnet.tokens.kabsch`) to the points ("fitted"),
    which then must all be finite (set `interpolate` to fill gaps linearly in time first).
    """
    from deformnet.so3 import transform_points
    from deformnet.tokens import kabsch

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


def same_fps(a: float, b: float) -> bool:
    """Whether two frame rates (Hz, > 0) are the same one (to 1e-6 relative): no resampling."""
    return abs(float(a) - float(b)) <= 1e-6 * max(float(a), float(b))


def _rate_times(fnum: np.ndarray, fps: float, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """A track's frame times (T,) (s, from its first frame: fnum / fps, gaps in the frame
    numbers kept) and those of the same span at `rate` (T',)."""
    t = (np.asarray(fnum, np.float64) - float(fnum[0])) / fps
    n = int(np.floor(t[-1] * rate + 1e-9)) + 1
    return t, np.arange(n) / rate


#: resampling to a lower rate low-passes first: a Gaussian of this many output frame periods (sd)
ANTIALIAS_SIGMA = 0.5


def lowpass_in_time(
    points: np.ndarray, observed: np.ndarray, fnum: np.ndarray, sigma: float
) -> np.ndarray:
    """Points (T, K, 3) smoothed in time with Gaussian weights of sd `sigma` frames (of the
    frame numbers fnum (T,), gaps in them kept as gaps in time), each part over its observed
    (T, K) frames only: a local linear fit (weighted least squares of a line in time about each
    frame, within 3 sd), which in the middle of the data is the Gaussian filter and at the ends
    of the data and of its gaps does not pull a moving part back (a one-sided mean would, by
    the slope times about 0.8 sd). Unobserved part-frames are returned as they are."""
    from scipy.ndimage import correlate1d

    P = np.asarray(points, np.float64)
    obs = np.asarray(observed, bool)
    g = np.asarray(fnum, np.int64) - int(fnum[0])
    n = int(g[-1]) + 1
    w = np.zeros((n, P.shape[1]))
    w[g] = obs
    x = np.zeros((n, *P.shape[1:]))
    x[g] = np.where(obs[..., None], P, 0.0)
    r = max(1, int(np.ceil(3.0 * sigma)))
    u = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (u / sigma) ** 2)

    def corr(a: np.ndarray, m: int) -> np.ndarray:  # sum_j a_j k(j - i) (j - i)^m
        return correlate1d(a, k * u**m, axis=0, mode="constant")[g]

    s0, s1, s2 = (corr(w, m) for m in range(3))
    t0, t1 = corr(x, 0), corr(x, 1)
    det = s0 * s2 - s1**2
    lin = det > 1e-6 * np.maximum(s0 * s2, 1e-300)  # a line is determined (>= 2 frames)
    with np.errstate(invalid="ignore", divide="ignore"):
        line = (s2[..., None] * t0 - s1[..., None] * t1) / np.where(lin, det, 1.0)[..., None]
        mean = t0 / np.where(s0 > 0, s0, 1.0)[..., None]
    est = np.where(lin[..., None], line, mean)
    return np.where((obs & (s0 > 0))[..., None], est, P)


def resample_session(session: Session, fps: float, rate: float, antialias: bool = True) -> Session:
    """The session recorded at `fps` (frame times fnum / fps) as it would be at `rate` (Hz):
    rigid and deformed points linearly interpolated in time at every 1 / rate s of its span, a
    part observed where both frames around it are (its deformed point the rigid one
    elsewhere), labels and frame numbers (0, 1, ...) at the new rate, the nearest frame's
    label. To a lower rate with `antialias`, the points are low-passed first
    (`lowpass_in_time`, sd `ANTIALIAS_SIGMA` / rate s: motion the new rate cannot carry, such
    as tracking jitter, is not folded into slower motion). The classifier of another frame
    rate labels the session so (`deformnet.classify.predict_session`), its results taken back
    by `to_track_frames`."""
    fps, rate = check_fps(fps, "fps"), check_fps(rate, "rate")
    if fps is None or rate is None:
        raise ValueError("resample_session needs both frame rates")
    fnum = np.asarray(session.fnum)
    if len(fnum) == 0 or np.any(np.diff(fnum) <= 0):
        raise ValueError(f"{session.name}: frame numbers must increase to be resampled in time")
    rigid, deformed = session.rigid, session.deformed
    obs = np.asarray(session.observed, bool)
    if antialias and rate < fps and len(fnum) > 1:
        sigma = ANTIALIAS_SIGMA * fps / rate  # source frames
        rigid = lowpass_in_time(rigid, np.ones_like(obs), fnum, sigma)
        deformed = lowpass_in_time(deformed, obs, fnum, sigma)
    t, tn = _rate_times(fnum, fps, rate)
    T = len(t)
    if T == 1:
        i0, i1, w = np.zeros(1, int), np.zeros(1, int), np.zeros(1)
    else:
        i0 = np.clip(np.searchsorted(t, tn, side="right") - 1, 0, T - 2)
        i1 = i0 + 1
        w = np.clip((tn - t[i0]) / (t[i1] - t[i0]), 0.0, 1.0)
    wv = w[:, None, None]

    def lerp(x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, np.float64)
        return ((1 - wv) * x[i0] + wv * x[i1]).astype(np.float32)

    observed = np.where(
        w[:, None] == 0, obs[i0], np.where(w[:, None] == 1, obs[i1], obs[i0] & obs[i1])
    )
    rigid = lerp(rigid)
    deformed = np.where(observed[..., None], lerp(deformed), rigid)
    nearest = np.where(w > 0.5, i1, i0)
    return Session(
        session.name,
        rigid,
        deformed,
        observed,
        np.arange(len(tn), dtype=np.int64),
        np.asarray(session.labels)[nearest],
        scale=session.scale,
        pose=session.pose,
    )


def to_track_frames(
    values: np.ndarray, fnum: np.ndarray, fps: float, rate: float, kind: str = "nearest"
) -> np.ndarray:
    """Per-frame results (T', ...) of a session resampled to `rate` (`resample_session`) back
    at the track's own frames fnum (T,) recorded at `fps`: "nearest" (labels, flags: the
    nearest resampled frame's) or "linear" (probabilities: interpolated in time)."""
    t, tn = _rate_times(np.asarray(fnum), fps, rate)
    values = np.asarray(values)
    if len(values) != len(tn):
        raise ValueError(
            f"values must have the resampled session's {len(tn)} frames, got {len(values)}"
        )
    if kind == "nearest":
        return values[np.clip(np.rint(t * rate).astype(np.int64), 0, len(tn) - 1)]
    if kind != "linear":
        raise ValueError(f"kind must be 'nearest' or 'linear', got {kind!r}")
    flat = values.reshape(len(tn), -1).astype(np.float64)
    out = np.stack([np.interp(t, tn, flat[:, j]) for j in range(flat.shape[1])], -1)
    return out.reshape((len(t),) + values.shape[1:])


#: BORIS's aggregated events export: the behavior, its start and stop (s; "Image index" columns,
#: when there, give frames), the frame rate
BORIS_COLUMNS = ("Behavior", "Start (s)", "Stop (s)")


def _boris_bouts(df: pd.DataFrame, path: Path, fps: float | None, fnum0: int) -> pd.DataFrame:
    """A BORIS aggregated events table -> `start,stop,label` (frames; stop inclusive): frames
    from its "Image index start/stop" columns, else its times at its "FPS" column's rate or
    ``fps`` (frame ``fnum0`` at 0 s); a point event (stop = start) labels one frame."""
    if {"Image index start", "Image index stop"} <= set(df.columns):
        start = pd.to_numeric(df["Image index start"], errors="coerce")
        stop = pd.to_numeric(df["Image index stop"], errors="coerce")
        return pd.DataFrame({"start": start + fnum0, "stop": stop + fnum0,
                             "label": df["Behavior"]})  # fmt: skip
    rate = pd.to_numeric(df["FPS"], errors="coerce") if "FPS" in df.columns else None
    if rate is None or not np.all(np.isfinite(rate) & (rate > 0)):
        if fps is None:
            raise ValueError(f"{path}: BORIS events in seconds: give the frame rate (fps=)")
        rate = pd.Series(float(fps), index=df.index)
    start = pd.to_numeric(df["Start (s)"], errors="coerce") * rate
    stop = pd.to_numeric(df["Stop (s)"], errors="coerce") * rate
    bad = ~(np.isfinite(start) & np.isfinite(stop))
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{path}: row {r + 1}: 'Start (s)' / 'Stop (s)' must be numbers")
    first = np.round(start).astype(np.int64)
    last = np.maximum(first, np.ceil(stop - 1e-6).astype(np.int64) - 1)  # [start, stop) in time
    return pd.DataFrame({"start": first + fnum0, "stop": last + fnum0, "label": df["Behavior"]})


def _simba_frames(df: pd.DataFrame, path: Path, classes: Sequence[str], fnum0: int):
    """SimBA's per-frame behavior columns (0 / 1, one per class; row i = frame i) ->
    `fnum,label` (a frame with none unlabelled, with two an error naming it)."""
    names = [c for c in classes if c in df.columns]
    flags = df[names].apply(pd.to_numeric, errors="coerce")
    if not np.all(flags.isin([0, 1]).to_numpy()):
        raise ValueError(f"{path}: SimBA behavior columns {names} must hold 0 or 1")
    on = flags.to_numpy(dtype=bool)
    many = np.flatnonzero(on.sum(1) > 1)
    if many.size:
        r = int(many[0])
        raise ValueError(f"{path}: row {r + 1}: several behaviors at once "
                         f"({[n for n, f in zip(names, on[r]) if f]})")  # fmt: skip
    rows = np.flatnonzero(on.any(1))
    label = np.asarray(names, dtype=object)[on[rows].argmax(1)]
    return pd.DataFrame({"fnum": rows + fnum0, "label": label})


def read_labels(
    path: str | os.PathLike,
    fnum: np.ndarray,
    classes: Sequence[str],
    tracks: str = "the track",
    fps: float | None = None,
) -> np.ndarray:
    """Labels (T,) int64 (-1: unlabelled) for frames `fnum` from a labels CSV as labs export
    them: `fnum,label` (one row per frame), `start,stop,label` (bouts, frame numbers, stop
    inclusive), BORIS's aggregated events (`BORIS_COLUMNS`: seconds at its FPS column's rate
    or ``fps``, or its image indices; 0 s is the track's first frame) or SimBA's per-frame
    behavior columns (one 0 / 1 column per class, row i the track's i-th frame). Unknown
    labels, duplicate frames, overlapping bouts and frames outside the track are errors naming
    the file and row (rows count data rows from 1)."""
    path = Path(path)
    df = read_csv(path, "labels file", dtype={"label": str, "Behavior": str})
    fnum0 = int(np.min(fnum)) if len(fnum) else 0
    if set(BORIS_COLUMNS) <= set(df.columns):
        df = _boris_bouts(df, path, fps, fnum0)
    elif "label" not in df.columns and any(c in df.columns for c in classes):
        df = _simba_frames(df, path, classes, fnum0)
    index = {str(c): i for i, c in enumerate(classes)}
    pos = {int(f): i for i, f in enumerate(fnum)}
    lo, hi = int(np.min(fnum)), int(np.max(fnum))
    out = np.full(len(fnum), -1, dtype=np.int64)
    cols = set(df.columns)
    if {"fnum", "label"} <= cols:
        kind, frame_cols = "frames", ("fnum",)
    elif {"start", "stop", "label"} <= cols:
        kind, frame_cols = "bouts", ("start", "stop")
    else:
        raise ValueError(
            f"{path}: expected columns 'fnum,label' (per frame), 'start,stop,label' (bouts), "
            f"BORIS's aggregated events ({', '.join(BORIS_COLUMNS)}) or SimBA's behavior "
            f"columns (one per class: {', '.join(classes)}), got {list(df.columns)}"
        )

    def frame(r: int, col: str) -> int:
        v = df[col].iloc[r]
        try:
            f = float(v)
        except (TypeError, ValueError):
            f = float("nan")
        if not np.isfinite(f) or f != int(f):
            raise ValueError(f"{path}: row {r + 1}: '{col}' must be a frame number, got {v!r}")
        f = int(f)
        if f not in pos:
            raise ValueError(
                f"{path}: row {r + 1}: frame {f} is outside {tracks} (frames {lo}..{hi})"
            )
        return f

    owner = np.zeros(len(fnum), dtype=np.int64)  # 1-based row that labelled each frame
    for r in range(len(df)):
        name = df["label"].iloc[r]
        if not isinstance(name, str) or str(name).strip() not in index:
            raise ValueError(
                f"{path}: row {r + 1}: unknown label {name!r} (known: {', '.join(classes)})"
            )
        c = index[str(name).strip()]
        if kind == "frames":
            i = pos[frame(r, "fnum")]
            if owner[i]:
                raise ValueError(
                    f"{path}: row {r + 1}: frame {fnum[i]} is labelled again (row {owner[i]})"
                )
            sel = np.array([i])
        else:
            a, b = frame(r, frame_cols[0]), frame(r, frame_cols[1])
            if b < a:
                raise ValueError(f"{path}: row {r + 1}: stop {b} < start {a}")
            sel = np.flatnonzero((fnum >= a) & (fnum <= b))
            clash = sel[owner[sel] > 0]
            if clash.size:
                raise ValueError(
                    f"{path}: row {r + 1}: bout {a}-{b} overlaps the bout in row "
                    f"{owner[clash[0]]} (frame {fnum[clash[0]]})"
                )
        owner[sel] = r + 1
        out[sel] = c
    return out


def bouts(labels: np.ndarray) -> list[tuple[int, int, int]]:
    """Runs of equal labels: [(start index, stop index inclusive, label)], -1 runs skipped."""
    labels = np.asarray(labels)
    if labels.size == 0:
        return []
    change = np.flatnonzero(np.diff(labels) != 0) + 1
    starts = np.concatenate(([0], change))
    stops = np.concatenate((change, [len(labels)])) - 1
    return [(int(a), int(b), int(labels[a])) for a, b in zip(starts, stops) if labels[a] >= 0]


def smooth(probs: np.ndarray, median: int = 0, min_bout: int = 0) -> np.ndarray:
    """Smoothed labels (T,) from per-frame probabilities (T, C): a running median of each class's
    probability over `median` frames (0/1: none), argmax, then bouts shorter than `min_bout`
    frames merged into the longer neighbour (repeated until none is left)."""
    from scipy.ndimage import median_filter

    p = np.asarray(probs, dtype=np.float64)
    if median and median > 1:
        p = median_filter(p, size=(int(median), 1), mode="nearest")
    lab = p.argmax(-1)
    if min_bout and min_bout > 1:
        for _ in range(len(lab)):
            runs = bouts(lab)
            short = [i for i, (a, b, _) in enumerate(runs) if b - a + 1 < min_bout]
            if not short or len(runs) == 1:
                break
            i = min(short, key=lambda j: runs[j][1] - runs[j][0])
            a, b, _ = runs[i]
            left = runs[i - 1] if i > 0 else None
            right = runs[i + 1] if i + 1 < len(runs) else None
            cand = [x for x in (left, right) if x is not None]
            best = max(cand, key=lambda x: x[1] - x[0])
            lab[a : b + 1] = best[2]
    return lab


def subsample_labels(sessions: list[Session], fraction: float, segment: int, seed: int) -> None:
    """Keep the labels of a random `fraction` of each session's labelled frames (in segments of
    `segment` frames), unlabel the rest (in place)."""
    if not 0 < fraction <= 1:
        raise ValueError(f"label_fraction must be in (0, 1], got {fraction}")
    if fraction >= 1:
        return
    rng = np.random.default_rng(seed)
    seg = max(1, int(segment))
    for s in sessions:
        lab = np.flatnonzero(s.labels >= 0)
        if lab.size == 0:
            continue
        chunks = [lab[i : i + seg] for i in range(0, lab.size, seg)]
        k = max(1, int(round(fraction * len(chunks))))
        keep = np.concatenate([chunks[i] for i in rng.choice(len(chunks), k, replace=False)])
        new = np.full_like(s.labels, -1)
        new[keep] = s.labels[keep]
        s.labels = new
