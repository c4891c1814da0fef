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
- `board_frame` (`BoardFrame`): the same pair from a calibration board lying on the floor
  (a ChArUco board or checkerboard) seen by >= 2 calibrated cameras: its detected corners
  (`read_board_corners`: a CSV ``camera,corner,x,y`` of pixels, corner = row * columns +
  column) are triangulated (`adjust.triangulate.triangulate`), the board (rows x columns
  corners, ``square_mm`` apart) is fitted to them; x runs along the board's first row (corner
  0 -> corner columns - 1), z is the board's normal pointing up (to the side the cameras are
  on, or away from it with ``cameras_below``), y completes a right-handed frame, and the origin
  is corner 0. The fit's residuals (RMS distance to the best plane and to the fitted board, mm)
  are reported; too few cameras or corners, collinear or non-planar corners are refused with
  one line. `alignment_kwargs` turns the ``axes`` config node (named points or ``board``) into
  `align_tracks`' arguments.

Shapes: T frames, K parts; points (T, K, 3) mm, NaN where missing; N board corners, C cameras.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from adjust.camera import Camera
from adjust.io import read_points3d
from adjust.io.calibration import load_calibration
from adjust.io.errors import InputError
from adjust.triangulate import triangulate
from deformnet.atomic import atomic_path
from deformnet.behavior.tracks import POSE_COLUMNS
from deformnet.confutil import checked_fields
from deformnet.tables import read_csv

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


def align_tracks(tracks: dict, axes=None, origin=None) -> dict:
    """A `read_points3d` dict moved into an aligned frame (a new dict; the input untouched):
    ``points``, the body pose columns (``pose_r*`` rotated, ``pose_t*`` moved) and ``M``,
    ``center`` composed with the file's own (so they still relate the points to the
    calibration's world frame). Distances, errors and sigmas are unchanged.

    axes: named points (`axes_frame`'s mapping, with `origin`) or a `BoardFrame` (a frame of
    the calibration's world, placed relative to the tracks' own frame; `origin` must be None).
    No axes (None, or a mapping of None): the tracks as they are."""
    if isinstance(axes, BoardFrame):
        if origin is not None:
            raise ValueError("axes.origin goes with named axes; a board's origin is its corner 0")
        M, c = axes.relative_to(tracks)
        how = f"board: {axes.describe()}"
    elif not axes or all(v is None for v in axes.values()):
        return tracks
    else:
        M, c = axes_frame(tracks["points"], tracks["parts"], axes, origin)
        how = ", ".join(f"{k}={list(v)}" for k, v in axes.items() if v is not None)
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
        how,
        np.round(out["M"], 6).tolist(),
        np.round(out["center"], 3).tolist(),
    )
    return out


# ---------------------------------------------------------------------------------------------
# axes from a calibration board
# ---------------------------------------------------------------------------------------------
BOARD_COLUMNS = ("camera", "corner", "x", "y")


@dataclass(frozen=True)
class BoardConfig:
    """``axes.board`` of conf/export.yaml: a calibration board lying on the floor.

    detections: CSV ``camera,corner,x,y`` (`read_board_corners`); rows, columns: the board's
    inner corners (a ChArUco board of 8 x 6 squares has 7 x 5), corner ``r * columns + c`` at
    row r, column c; square_mm: the corners' spacing; min_corners: the corners a camera must see
    to count; max_residual_mm: the largest distance (mm) of a triangulated corner from the best
    plane, and the largest RMS distance from the fitted board, accepted; cameras_below: the
    cameras film the floor from below (z then points away from them)."""

    detections: str | None = None
    rows: int | None = None
    columns: int | None = None
    square_mm: float | None = None
    min_corners: int = 4
    max_residual_mm: float = 2.0
    cameras_below: bool = False

    @classmethod
    def from_mapping(cls, node: Mapping | None) -> BoardConfig:
        """From a config mapping (unknown keys and a board without detections: ValueError)."""
        node = checked_fields(cls, node, "axes.board")
        cfg = cls(**{k: v for k, v in node.items() if v is not None})
        if cfg.detections is None:
            return cfg
        for key in ("rows", "columns"):
            v = getattr(cfg, key)
            if not (isinstance(v, int | float) and np.isfinite(v) and v == int(v) and v >= 2):
                raise ValueError(
                    f"axes.board.{key}: the board's number of {key} of inner corners, an "
                    f"integer >= 2 (got {v!r})"
                )
        if not (isinstance(cfg.square_mm, int | float) and cfg.square_mm > 0):
            raise ValueError(
                f"axes.board.square_mm: the corners' spacing (mm) > 0, got {cfg.square_mm}"
            )
        if int(cfg.min_corners) < 3:
            raise ValueError(f"axes.board.min_corners must be >= 3, got {cfg.min_corners}")
        if not float(cfg.max_residual_mm) > 0:
            raise ValueError(f"axes.board.max_residual_mm must be > 0, got {cfg.max_residual_mm}")
        return cfg

    @property
    def num_corners(self) -> int:
        return int(self.rows) * int(self.columns)


def board_corners(rows: int, columns: int, square_mm: float) -> np.ndarray:
    """(rows * columns, 3) mm: corner ``r * columns + c`` at ``(c, r, 0) * square_mm`` in the
    board's own frame (x along a row, y along a column)."""
    r, c = np.divmod(np.arange(int(rows) * int(columns)), int(columns))
    return np.stack([c, r, np.zeros_like(c)], -1).astype(np.float64) * float(square_mm)


def read_board_corners(
    path: str | os.PathLike, cameras: Sequence[str], num_corners: int
) -> np.ndarray:
    """A board's detected corners: CSV with columns ``camera,corner,x,y`` (pixels; one image
    per camera; a corner not detected is absent or has empty x, y) -> (N, C, 2) pixels, NaN
    where not seen, cameras in the order of `cameras`. A missing column, an unknown camera, a
    corner outside 0..N-1, a non-numeric value or a corner given twice for one camera is an
    InputError naming the file and row."""
    path = Path(path)
    df = read_csv(path, "board corners file", InputError)
    missing = [c for c in BOARD_COLUMNS if c not in df.columns]
    if missing:
        raise InputError(
            f"{path}: missing column(s) {missing} (a board corners file has columns "
            f"{','.join(BOARD_COLUMNS)}: camera name, corner id, pixel x, pixel y)"
        )
    index = {str(c): i for i, c in enumerate(cameras)}
    xy = np.full((int(num_corners), len(index), 2), np.nan)
    seen: dict[tuple[int, int], int] = {}
    for r, row in enumerate(df[list(BOARD_COLUMNS)].itertuples(index=False)):
        cam, corner, x, y = row
        if str(cam) not in index:
            raise InputError(
                f"{path}: camera '{cam}' at row {r} is not in the calibration (cameras: "
                f"{list(index)})"
            )
        try:
            k = float(corner)
            u, v = float(x), float(y)
        except (TypeError, ValueError):
            raise InputError(
                f"{path}: non-numeric corner, x or y at row {r}: {corner!r}, {x!r}, {y!r}"
            ) from None
        if not (k == int(k) and 0 <= k < num_corners):
            raise InputError(
                f"{path}: corner {corner!r} at row {r} is not a corner of the board (0.."
                f"{num_corners - 1}: corner = row * columns + column)"
            )
        if not (np.isfinite(u) and np.isfinite(v)):
            continue  # not detected in this camera
        key = (int(k), index[str(cam)])
        if key in seen:
            raise InputError(
                f"{path}: camera '{cam}' corner {int(k)} is given twice (rows {seen[key]} and "
                f"{r}); give one image per camera"
            )
        seen[key] = r
        xy[key] = (u, v)
    return xy


@dataclass(frozen=True)
class BoardFrame:
    """Axes of the calibration's world frame from a board (`board_frame`): ``X_board = M
    X_world - center`` (M (3, 3) rotation, center (3,) mm), x along the board's first row, z
    its normal pointing up, the origin at corner 0. plane_rms_mm / plane_max_mm: the
    triangulated corners' distance from their best plane; fit_rms_mm: their RMS distance from
    the fitted board; square_mm_measured: the corners' spacing the triangulation gives (the
    scale of the best similarity fit); corners: how many corners were triangulated; cameras:
    {camera: corners it saw} of the cameras used."""

    M: np.ndarray
    center: np.ndarray
    plane_rms_mm: float
    plane_max_mm: float
    fit_rms_mm: float
    square_mm_measured: float
    corners: int
    cameras: dict

    def relative_to(self, tracks: Mapping) -> tuple[np.ndarray, np.ndarray]:
        """(M, c) taking points of `tracks` (in their own frame: ``X_in = M0 X_world - c0``,
        the file's axes columns) to the board's frame: ``X_board = M X_in - c``."""
        M0 = np.asarray(tracks.get("M", np.eye(3)), dtype=np.float64)
        c0 = np.asarray(tracks.get("center", np.zeros(3)), dtype=np.float64)
        M = self.M @ M0.T
        return M, self.center - M @ c0

    def describe(self) -> str:
        return (
            f"{self.corners} corners from cameras {self.cameras}, {self.plane_rms_mm:.3f} mm RMS "
            f"off their plane (max {self.plane_max_mm:.3f}), {self.fit_rms_mm:.3f} mm RMS off the "
            f"fitted board, square {self.square_mm_measured:.3f} mm measured"
        )

    def summary(self) -> dict:
        """The fit's facts as plain values (for logs and summaries)."""
        return {
            "M": self.M.tolist(),
            "center_mm": self.center.tolist(),
            "plane_rms_mm": self.plane_rms_mm,
            "plane_max_mm": self.plane_max_mm,
            "fit_rms_mm": self.fit_rms_mm,
            "square_mm_measured": self.square_mm_measured,
            "corners": self.corners,
            "cameras": dict(self.cameras),
        }


def board_frame(xy: np.ndarray, cameras: Sequence[Camera], board: BoardConfig) -> BoardFrame:
    """Fit a board's axes (`BoardFrame`) to its corners' pixels xy (N, C, 2) (NaN: not seen)
    in the calibrated `cameras` (C).

    The cameras that see >= ``board.min_corners`` corners (fewer than 2: InputError) give each
    corner's 3D position (`adjust.triangulate.triangulate`, >= 2 views); the corners found must
    be >= ``min_corners`` and not on one line, within ``max_residual_mm`` of their best plane
    (else: not planar) and of the board fitted to them (Kabsch: rotation and translation of
    `board_corners`; else: wrong rows / columns / square_mm / numbering)."""
    xy = np.asarray(xy, dtype=np.float64)
    N, C = board.num_corners, len(cameras)
    if xy.shape != (N, C, 2):
        raise ValueError(f"xy must be (N, C, 2) = ({N}, {C}, 2), got {xy.shape}")
    names = [c.name for c in cameras]
    seen = np.isfinite(xy).all(-1)  # (N, C)
    counts = seen.sum(0)
    enough = counts >= board.min_corners
    per_camera = {n: int(k) for n, k in zip(names, counts)}
    if enough.sum() < 2:
        raise InputError(
            f"axes.board: {int(enough.sum())} camera(s) see >= {board.min_corners} corners "
            f"(corners per camera: {per_camera}); the board must be seen by >= 2 cameras to be "
            "triangulated"
        )
    weight = (seen & enough).astype(np.float64)
    res = triangulate(np.where(seen[..., None], xy, np.nan)[None], weight[None], list(cameras))
    X = res.points[0].numpy()
    ok = np.isfinite(X).all(-1)
    model = board_corners(board.rows, board.columns, board.square_mm)
    if ok.sum() < board.min_corners:
        raise InputError(
            f"axes.board: {int(ok.sum())} corners seen by >= 2 of the cameras with >= "
            f"{board.min_corners} corners (corners per camera: {per_camera}); need "
            f"{board.min_corners}"
        )
    X, m = X[ok], model[ok]
    mc = m - m.mean(0)
    if np.linalg.svd(mc, compute_uv=False)[1] < 1e-6 * float(board.square_mm):
        raise InputError(
            "axes.board: the corners seen by >= 2 cameras lie on one line (one row or column "
            "of the board): its plane is undetermined"
        )
    Xc = X - X.mean(0)
    normal = np.linalg.svd(Xc)[2][2]
    dist = Xc @ normal
    plane_rms, plane_max = float(np.sqrt(np.mean(dist**2))), float(np.abs(dist).max())
    if plane_max > board.max_residual_mm:
        raise InputError(
            f"axes.board: the corners are not planar: up to {plane_max:.2f} mm (RMS "
            f"{plane_rms:.2f}) off their best plane, over axes.board.max_residual_mm="
            f"{board.max_residual_mm}: check the corner ids, the cameras' names and the "
            "calibration"
        )
    # Kabsch: X ~ R m + t (m the board's own coordinates of the corners found)
    U, S, Vt = np.linalg.svd(mc.T @ Xc)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    t = X.mean(0) - R @ m.mean(0)
    fit_rms = float(np.sqrt(np.mean(np.sum((m @ R.T + t - X) ** 2, -1))))
    scale = float(np.sum(S * np.diag(D)) / np.sum(mc**2))  # the best similarity's scale
    if fit_rms > board.max_residual_mm:
        raise InputError(
            f"axes.board: the corners are {fit_rms:.2f} mm RMS off a {board.rows} x "
            f"{board.columns} board of {board.square_mm} mm squares (measured spacing "
            f"{scale * float(board.square_mm):.2f} mm), over axes.board.max_residual_mm="
            f"{board.max_residual_mm}: check rows, columns, square_mm and the corner numbering "
            "(corner = row * columns + column)"
        )
    x_axis, n = R[:, 0], R[:, 2]
    origin = t  # corner 0 sits at the board's own origin
    centers = np.stack([c.center for c, e in zip(cameras, enough) if e])
    up = np.sign(np.mean((centers - origin) @ n)) or 1.0
    z_axis = n * up * (-1.0 if board.cameras_below else 1.0)
    y_axis = np.cross(z_axis, x_axis)
    M = np.stack([x_axis, y_axis, z_axis])
    frame = BoardFrame(
        M=M,
        center=M @ origin,
        plane_rms_mm=plane_rms,
        plane_max_mm=plane_max,
        fit_rms_mm=fit_rms,
        square_mm_measured=scale * float(board.square_mm),
        corners=int(ok.sum()),
        cameras={n: k for (n, k), e in zip(per_camera.items(), enough) if e},
    )
    log.info("board axes: %s", frame.describe())
    return frame


def board_frame_from_files(board: BoardConfig, calibration: str | os.PathLike | None) -> BoardFrame:
    """`board_frame` of ``board.detections`` seen by the cameras of `calibration` (the
    calibration the tracks were made with; None: InputError saying so)."""
    if calibration is None:
        raise InputError(
            "axes.board needs calibration=calibration.toml (the cameras that filmed the board, "
            "the calibration the tracks were made with)"
        )
    cameras = load_calibration(calibration)
    xy = read_board_corners(board.detections, [c.name for c in cameras], board.num_corners)
    return board_frame(xy, cameras, board)


def alignment_kwargs(node: Mapping | None, calibration=None) -> dict:
    """`align_tracks`' ``axes`` and ``origin`` from the ``axes`` config node: named points
    (``x``, ``y``, ``z``: [from, to]; ``origin``) or ``board`` (`BoardConfig`, with the
    cameras of `calibration`), not both; {} without either."""
    if not isinstance(node or {}, Mapping):
        raise ValueError(f"axes must be a mapping (axes.x=[a,b] axes.y=[a,c]), got {node!r}")
    node = dict(node or {})
    board = BoardConfig.from_mapping(node.pop("board", None))
    axes = {k: v for k, v in node.items() if k != "origin" and v is not None}
    if board.detections is not None:
        if axes or node.get("origin") is not None:
            raise ValueError(
                "axes: give named points (axes.x, axes.y, axes.origin) or a board "
                "(axes.board.detections=...), not both"
            )
        return {"axes": board_frame_from_files(board, calibration), "origin": None}
    if not axes:
        if node.get("origin") is not None:
            raise ValueError("axes.origin needs two axes (axes.x=[a,b] axes.y=[a,c])")
        return {}
    return {"axes": axes, "origin": node.get("origin")}


def angles_csv(
    path: str | os.PathLike, tracks: str | os.PathLike, angles: Mapping | Sequence
) -> Path:
    """``angles.csv`` (anipose's) of a points3d file: `joint_angles` of the named triplets,
    then ``fnum``. No triplet is a ValueError saying how to give them."""
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
