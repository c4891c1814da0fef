"""anipose's everyday kinematics on 3D tracks: joint angles and a world frame aligned to points.

- `joint_angles`: anipose's ``angles`` (its "flex" angles): for a named triplet ``[a, b, c]`` the
  angle at the middle part ``b`` between ``a - b`` and ``c - b``, in degrees (0..180), per frame;
  `write_angles` writes them as anipose's ``angles.csv`` (one column per named angle, then
  ``fnum``).
- `axes_frame` / `align_tracks`: anipose's ``triangulation.axes`` and ``reference_point``: two
  axes, each given by two points (``x: [a, b]`` points from ``a`` to ``b``), the first exact,
  the second made orthogonal to it, the third completing a right-handed frame; the origin at a
  reference point. A point is a part of the tracks (its median position over the frames where it
  is finite) or three coordinates in the tracks' frame (mm; e.g. arena corners measured on the
  floor). The result is anipose's pair ``M`` (3, 3) rotation and ``center`` (3,) mm with
  ``X_out = M X_in - center`` (the ``M_..`` and ``center_..`` columns of points3d.csv).

Shapes: T frames, K parts; points (T, K, 3) mm, NaN where missing. numpy and scipy only.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from adjust.io.errors import InputError
from deformnet.atomic import atomic_path
from deformnet.behavior_labels import POSE_COLUMNS

log = logging.getLogger(__name__)

AXES = ("x", "y", "z")


# ---------------------------------------------------------------------------------------------
# joint angles
# ---------------------------------------------------------------------------------------------
def parse_angles(spec) -> dict[str, tuple[str, str, str]]:
    """Named part triplets from a mapping ``{name: [a, b, c]}`` (anipose's ``[angles]``) or a
    list of triplets ``[[a, b, c], ...]`` (named after the middle part, or ``a_b_c`` when two
    triplets share it). A triplet of other than 3 names is a ValueError naming it."""
    if spec is None:
        return {}
    if isinstance(spec, Mapping):
        items = [(str(k), v) for k, v in spec.items()]
    else:
        triplets = [list(t) for t in spec]
        mids = [str(t[1]) if len(t) == 3 else "" for t in triplets]
        items = [
            (m if mids.count(m) == 1 else "_".join(str(p) for p in t), t)
            for m, t in zip(mids, triplets)
        ]
    out: dict[str, tuple[str, str, str]] = {}
    for name, t in items:
        t = [str(p) for p in (t if isinstance(t, Sequence) and not isinstance(t, str) else [t])]
        if len(t) != 3:
            raise ValueError(f"angle '{name}': give three part names [a, b, c], got {t}")
        out[name] = (t[0], t[1], t[2])
    return out


def joint_angles(
    points: np.ndarray, parts: Sequence[str], angles: Mapping[str, Sequence[str]]
) -> dict[str, np.ndarray]:
    """{name: (T,) degrees}: the angle at ``b`` between ``a - b`` and ``c - b`` for each named
    triplet ``[a, b, c]`` (anipose's flex angle); NaN where a point is missing or coincides
    with ``b``. points: (T, K, 3); an unknown part is an InputError listing the parts."""
    X = np.asarray(points, dtype=np.float64)
    parts = [str(p) for p in parts]
    if X.ndim != 3 or X.shape[1:] != (len(parts), 3):
        raise ValueError(f"points must be (T, {len(parts)}, 3), got {X.shape}")
    index = {p: k for k, p in enumerate(parts)}
    out = {}
    for name, triplet in parse_angles(angles).items():
        unknown = [p for p in triplet if p not in index]
        if unknown:
            raise InputError(f"angle '{name}': unknown part(s) {unknown} (parts: {parts})")
        a, b, c = (X[:, index[p]] for p in triplet)
        u, v = a - b, c - b
        nu, nv = np.linalg.norm(u, axis=-1), np.linalg.norm(v, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos = np.einsum("ti,ti->t", u, v) / (nu * nv)
        cos = np.where((nu > 0) & (nv > 0), cos, np.nan)
        out[name] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return out


def write_angles(path: str | os.PathLike, angles: Mapping[str, np.ndarray], fnum) -> Path:
    """anipose's ``angles.csv`` atomically: one column per named angle (degrees, empty where
    NaN), then ``fnum``. angles: {name: (T,)}; fnum: (T,)."""
    cols = {str(k): np.asarray(v, dtype=np.float64) for k, v in angles.items()}
    f = np.asarray(fnum)
    for name, v in cols.items():
        if v.shape != f.shape:
            raise ValueError(f"angle '{name}' has shape {v.shape}, fnum {f.shape}")
    if "fnum" in cols:
        raise ValueError("an angle cannot be named 'fnum'")
    cols["fnum"] = f
    with atomic_path(path) as tmp:
        pd.DataFrame(cols).to_csv(tmp, index=False)
    return Path(path)


# ---------------------------------------------------------------------------------------------
# axes alignment
# ---------------------------------------------------------------------------------------------
def _point(spec, points: np.ndarray, index: Mapping[str, int], what: str) -> np.ndarray:
    """A part's median position over its finite frames, or 3 coordinates (mm)."""
    if isinstance(spec, Sequence) and not isinstance(spec, str):
        p = np.asarray([float(v) for v in spec], dtype=np.float64)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise ValueError(f"{what}: a point is a part name or 3 finite coordinates, got {spec}")
        return p
    name = str(spec)
    if name not in index:
        raise InputError(f"{what}: unknown part '{name}' (parts: {list(index)})")
    X = points[:, index[name]]
    X = X[np.isfinite(X).all(-1)]
    if not len(X):
        raise InputError(f"{what}: part '{name}' is never tracked")
    return np.median(X, axis=0)


def axes_frame(
    points: np.ndarray,
    parts: Sequence[str],
    axes: Mapping[str, Sequence],
    origin=None,
) -> tuple[np.ndarray, np.ndarray]:
    """anipose's axes alignment: (M (3, 3) rotation, center (3,) mm) with ``X_out = M X -
    center``.

    axes: exactly two of ``x``, ``y``, ``z`` (others absent or None), each ``[from, to]``: the
    axis points from ``from`` to ``to``. The first given (in the mapping's order) is exact, the
    second is made orthogonal to it, the third completes a right-handed frame. origin: the point
    placed at 0 (default: the first axis's ``from``). Points: part names (median over frames) or
    coordinates in the tracks' frame. points: (T, K, 3)."""
    X = np.asarray(points, dtype=np.float64)
    index = {str(p): k for k, p in enumerate(parts)}
    given = [(str(k), v) for k, v in axes.items() if v is not None and str(k) in AXES]
    other = [str(k) for k, v in axes.items() if v is not None and str(k) not in AXES]
    if other:
        raise ValueError(f"axes: unknown axis {other} (use x, y, z)")
    if len(given) != 2:
        raise ValueError(
            f"axes: give exactly two of x, y, z as [from, to] (e.g. axes.x=[a,b] axes.y=[a,c]); "
            f"got {[k for k, _ in given] or 'none'}"
        )
    ends = []
    for name, pair in given:
        pair = list(pair) if isinstance(pair, Sequence) and not isinstance(pair, str) else [pair]
        if len(pair) != 2:
            raise ValueError(f"axes.{name}: give [from, to], got {pair}")
        ends.append([_point(p, X, index, f"axes.{name}") for p in pair])
    (a_name, _), (b_name, _) = given
    a_dir, b_dir = AXES.index(a_name), AXES.index(b_name)
    c_dir = 3 - a_dir - b_dir
    a = ends[0][1] - ends[0][0]
    b = ends[1][1] - ends[1][0]
    b = b - a * (a @ b) / (a @ a) if a @ a > 0 else b
    for name, v in ((a_name, a), (b_name, b)):
        if not np.linalg.norm(v) > 1e-9:
            raise InputError(
                f"axes.{name}: its two points coincide (or it is parallel to the other axis)"
            )
    M = np.zeros((3, 3))
    M[a_dir], M[b_dir] = a, b
    # right-handed: rows x, y, z with z = x cross y (and cyclic)
    M[c_dir] = np.cross(a, b) if (a_dir, b_dir) in ((0, 1), (1, 2), (2, 0)) else np.cross(b, a)
    M /= np.linalg.norm(M, axis=1, keepdims=True)
    o = ends[0][0] if origin is None else _point(origin, X, index, "axes.origin")
    return M, M @ o


def apply_axes(points: np.ndarray, M: np.ndarray, center: np.ndarray) -> np.ndarray:
    """(..., 3) points -> ``M X - center`` (NaN stays NaN)."""
    return np.asarray(points, dtype=np.float64) @ np.asarray(M).T - np.asarray(center)


def align_tracks(tracks: dict, axes: Mapping[str, Sequence] | None, origin=None) -> dict:
    """A `read_points3d` dict moved into the frame of `axes_frame` (a new dict; the input
    untouched): ``points``, the body pose columns (``pose_r*`` rotated, ``pose_t*`` moved) and
    ``M``, ``center`` composed with the file's own (so they still relate the points to the
    calibration's world frame). Distances, errors and sigmas are unchanged. No axes (None or all
    None): the tracks as they are."""
    if not axes or all(v is None for v in axes.values()):
        return tracks
    M, c = axes_frame(tracks["points"], tracks["parts"], axes, origin)
    out = dict(tracks)
    out["points"] = apply_axes(tracks["points"], M, c)
    M0 = np.asarray(tracks.get("M", np.eye(3)), dtype=np.float64)
    c0 = np.asarray(tracks.get("center", np.zeros(3)), dtype=np.float64)
    out["M"], out["center"] = M @ M0, M @ c0 + c
    extra = dict(tracks.get("extra", {}))
    if all(k in extra for k in POSE_COLUMNS):
        pose = np.stack([np.asarray(extra[k], dtype=np.float64) for k in POSE_COLUMNS], -1)
        ok = np.isfinite(pose).all(-1)
        new = np.full_like(pose, np.nan)
        if ok.any():
            R = Rotation.from_matrix(M) * Rotation.from_rotvec(pose[ok, :3])
            new[ok, :3] = R.as_rotvec()
            new[ok, 3:] = apply_axes(pose[ok, 3:], M, c)
        for i, k in enumerate(POSE_COLUMNS):
            extra[k] = new[:, i]
    out["extra"] = extra
    log.info(
        "axes aligned (%s): M = %s, center = %s mm",
        ", ".join(f"{k}={list(v)}" for k, v in axes.items() if v is not None),
        np.round(out["M"], 6).tolist(),
        np.round(out["center"], 3).tolist(),
    )
    return out


def angles_csv(
    path: str | os.PathLike, tracks: str | os.PathLike, angles: Mapping | Sequence
) -> Path:
    """``angles.csv`` (anipose's) of a points3d file: `joint_angles` of the named triplets,
    then ``fnum``. No triplet is a ValueError saying how to give them."""
    from adjust.io import read_points3d

    spec = parse_angles(angles)
    if not spec:
        raise ValueError(
            "no angles: give named part triplets, e.g. +angles.knee=[hip,knee,ankle] (the angle "
            "at knee, degrees) or angles=[[hip,knee,ankle]]"
        )
    d = read_points3d(tracks)
    values = joint_angles(d["points"], d["parts"], spec)
    out = write_angles(path, values, d["fnum"])
    log.info("wrote %s: %d angles x %d frames", out, len(values), len(d["fnum"]))
    return out
