"""Behavior labels as labs write them, per session: per frame (`fnum,label`), bouts
(`start,stop,label`, stop inclusive), BORIS's aggregated events, SimBA's behavior columns (every
error names the file and the row); bouts of a label sequence, smoothing, label subsampling."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from deformnet.behavior.tracks import Session
from deformnet.tables import read_csv

__all__ = ["read_labels", "bouts", "smooth", "subsample_labels"]


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
