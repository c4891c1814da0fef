"""Shape statistics of a (deforming) point set: the rigid floor, pair distances, real poses.

- `rigid_floor(points)`: the best rigid body for a track (generalized Procrustes, no scale, via
  `BodyModel.from_observations`), posed perfectly in every frame (`deformnet.body._align_to`);
  the RMS 3D distance of the parts from it, overall and per part. No rigid tracker can get
  closer to the truth than this on average.
- `pair_distances(points, pairs)`: per-frame distances of part pairs (bone lengths).
- `load_real_poses(path)`: the hand-labelled real 3D mouse poses in
  ``shared/data/real-mouse-poses-3d/poses3d.csv`` (22 keypoints, NaN where not labelled).
- `REAL_TO_MOUSE`: the real keypoint names of the paper's 8 parts -> `conf/body/mouse.yaml` names.

NumPy only (imports `deformnet.body`, no torch or Lightning).
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deformnet.body import BodyModel, _align_to
from deformnet.paths import real_mouse_poses_dir

#: the paper's 8 parts: real-data keypoint name -> default mouse model part name
REAL_TO_MOUSE: dict[str, str] = {
    "Snout": "nose_tip",
    "EarL": "left_ear",
    "EarR": "right_ear",
    "ForepawL": "left_front_paw",
    "ForepawR": "right_front_paw",
    "HindpawL": "left_hind_paw",
    "HindpawR": "right_hind_paw",
    "Tail_base": "tail_root",
}


@dataclass(frozen=True)
class RigidFloor:
    """The rigid floor of a track.

    rms: overall RMS 3D distance (mm) of the observed part-frames from the posed best rigid body;
    per_part: (K,) RMS per part; body: the Procrustes body (`BodyModel`, model frame = principal
    axes); aligned: (T, K, 3) every frame rigidly aligned onto ``body.points`` (NaN where
    missing); residual: (T, K) 3D distance of each part-frame from the body (NaN where missing).
    """

    rms: float
    per_part: np.ndarray
    body: BodyModel
    aligned: np.ndarray
    residual: np.ndarray

    def as_dict(self) -> dict:
        return {
            "rms": self.rms,
            "per_part": {p: float(v) for p, v in zip(self.body.parts, self.per_part)},
        }


def _points(points: np.ndarray) -> np.ndarray:
    X = np.asarray(points, dtype=np.float64)
    if X.ndim != 3 or X.shape[-1] != 3 or X.shape[1] < 3:
        raise ValueError(f"points must have shape (T, K >= 3, 3), got {X.shape}")
    return X


def rigid_floor(
    points: np.ndarray,
    parts: Sequence[str] | None = None,
    min_parts: int | None = None,
    max_frames: int = 20000,
) -> RigidFloor:
    """The rigid floor of `points` (T, K, 3) mm, NaN for missing (see the module docstring).

    The body is fitted on the frames with >= `min_parts` observed parts (default as in
    `BodyModel.from_observations`), the RMS taken over the frames with >= 3 observed parts.
    """
    X = _points(points)
    body = BodyModel.from_observations(
        X, parts=parts, min_parts=min_parts, max_frames=max_frames, name="procrustes"
    )
    seen = np.isfinite(X).all(-1)
    use = seen.sum(1) >= 3
    w = seen.astype(np.float64)
    aligned = np.full(X.shape, np.nan)
    if use.any():
        Xz = np.where(seen[use][..., None], X[use], 0.0)
        aligned[use] = np.where(seen[use][..., None], _align_to(Xz, w[use], body.points), np.nan)
    residual = np.linalg.norm(aligned - body.points[None], axis=-1)  # NaN where missing
    sq = residual**2
    n = np.isfinite(sq).sum(0)
    per_part = np.sqrt(np.nansum(sq, 0) / np.maximum(n, 1))
    per_part = np.where(n > 0, per_part, np.nan)
    rms = float(np.sqrt(np.nansum(sq) / max(int(np.isfinite(sq).sum()), 1)))
    return RigidFloor(rms, per_part, body, aligned, residual)


def pair_distances(
    points: np.ndarray, parts: Sequence[str], pairs: Sequence[tuple[str, str]]
) -> np.ndarray:
    """(T, P) distances (mm) of the named part pairs in every frame (NaN where one is missing).

    points: (T, K, 3); parts: K names; pairs: P (name, name) pairs.
    """
    X = _points(points)
    names = list(parts)
    if len(names) != X.shape[1]:
        raise ValueError(f"{len(names)} part names for {X.shape[1]} parts")
    idx = []
    for a, b in pairs:
        for p in (a, b):
            if p not in names:
                raise ValueError(f"part '{p}' is not among {names}")
        idx.append((names.index(a), names.index(b)))
    if not idx:
        return np.zeros((X.shape[0], 0))
    i, j = np.array(idx).T
    return np.linalg.norm(X[:, i] - X[:, j], axis=-1)


def load_real_poses(path: str | Path | None = None) -> tuple[tuple[str, ...], np.ndarray]:
    """Real 3D mouse poses: (parts (22 names), points (N, 22, 3) mm, NaN where not labelled).

    path: the ``poses3d.csv`` file or its folder (default: `deformnet.paths.
    real_mouse_poses_dir()`). Columns ``sample_ms`` then ``{part}_x, _y, _z``; an empty cell is
    a missing value. Raises ValueError naming the file, row and column on bad content.
    """
    if path is None:
        path = real_mouse_poses_dir()
    path = Path(path)
    if path.is_dir():
        path = path / "poses3d.csv"
    if not path.is_file():
        raise ValueError(f"{path}: real mouse poses file not found")
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise ValueError(f"{path}: empty file")
    header = [h.strip() for h in rows[0]]
    cols = [h for h in header if h != "sample_ms"]
    if len(cols) % 3:
        raise ValueError(f"{path}: expected {{part}}_x, _y, _z columns, got {len(cols)} columns")
    parts: list[str] = []
    for k in range(0, len(cols), 3):
        trio = cols[k : k + 3]
        base = trio[0][:-2]
        if [c[-2:] for c in trio] != ["_x", "_y", "_z"] or any(c[:-2] != base for c in trio):
            raise ValueError(f"{path}: columns {trio}: expected {base}_x, {base}_y, {base}_z")
        parts.append(base)
    index = [header.index(c) for c in cols]
    data = np.full((len(rows) - 1, len(cols)), np.nan)
    for r, row in enumerate(rows[1:]):
        if len(row) != len(header):
            raise ValueError(f"{path}: row {r + 2} has {len(row)} cells, expected {len(header)}")
        for c, i in enumerate(index):
            cell = row[i].strip()
            if cell:
                try:
                    data[r, c] = float(cell)
                except ValueError:
                    raise ValueError(
                        f"{path}: row {r + 2}, column {cols[c]}: not a number: {cell!r}"
                    ) from None
    return tuple(parts), data.reshape(len(rows) - 1, len(parts), 3)


def real_paper_parts(
    path: str | Path | None = None,
) -> tuple[tuple[str, ...], np.ndarray]:
    """The real poses' 8 paper parts, renamed to the mouse model's names (`REAL_TO_MOUSE` order):
    (names, points (N, 8, 3))."""
    parts, pts = load_real_poses(path)
    missing = [p for p in REAL_TO_MOUSE if p not in parts]
    if missing:
        raise ValueError(f"real mouse poses lack the parts {missing}")
    idx = [parts.index(p) for p in REAL_TO_MOUSE]
    return tuple(REAL_TO_MOUSE.values()), pts[:, idx]
