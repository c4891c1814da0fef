"""Simulated multi-camera scenes: a camera rig, per-camera self-occlusion and a detector model.

Turns simulated 3D body parts (``deformnet.sim.SimData``) into what a real user has: calibrated
cameras and DeepLabCut-like 2D detections per camera, with occlusions, misses, swaps, outliers,
pixel noise and likelihoods.

- `camera_look_at` / `rig_from_config` / `default_rig`: `Camera`s from position, look-at point
  and up vector (world -> camera ``x_cam = R X + t``; pixel origin at the top-left pixel's
  centre, so the principal point of a W x H image is ((W-1)/2, (H-1)/2)).
- `Ellipsoid` / `occluded_by_ellipsoids`: a part is hidden from a camera when the segment from
  the camera centre to the part passes through a body-proxy ellipsoid moved with the pose
  (the segment's last `surface_margin` mm, the part's own surface vicinity, is not tested).
- `DetectorConfig` / `simulate_scene`: the detector model, vectorised over (T, K, C) in numpy;
  deterministic for a seed.

Shapes: T frames, K parts, C cameras. Points in mm, pixels in px.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
import torch
from scipy.ndimage import convolve1d
from scipy.special import ndtri

from adjust.camera import Camera, CameraTensors, depth, look_at_pose, project_cameras
from deformnet.confutil import to_plain
from deformnet.so3 import kabsch, matrix_to_rodrigues, rodrigues_to_matrix

log = logging.getLogger(__name__)

__all__ = [
    "DetectorConfig",
    "Ellipsoid",
    "SceneDetections",
    "arena_in_view",
    "camera_look_at",
    "default_rig",
    "detector_config",
    "occluded_by_boxes",
    "occluded_by_ellipsoids",
    "rig_from_config",
    "simulate_scene",
]


# --------------------------------------------------------------------------------------------
# config helpers
# --------------------------------------------------------------------------------------------


def _vec(value: Any, n: int, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be {n} numbers, got {value!r}") from None
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be {n} finite numbers, got {value!r}")
    return arr


# --------------------------------------------------------------------------------------------
# rig
# --------------------------------------------------------------------------------------------
def camera_look_at(
    name: str,
    position: Sequence[float],
    look_at: Sequence[float],
    up: Sequence[float] = (0.0, 0.0, 1.0),
    focal_px: float | Sequence[float] = 1000.0,
    size: Sequence[int] = (1280, 1024),
    dist: Sequence[float] | None = None,
    principal_point: Sequence[float] | None = None,
) -> Camera:
    """A pinhole camera at `position` (mm) looking at `look_at`, image "up" towards `up`.

    Camera axes (OpenCV): z along the viewing direction, x to the image right, y down the
    image. `focal_px` is one focal length or (fx, fy); `size` is (width, height) px; the
    principal point defaults to the image centre ((W-1)/2, (H-1)/2).
    """
    pos = _vec(position, 3, f"camera '{name}': position")
    target = _vec(look_at, 3, f"camera '{name}': look_at")
    upv = _vec(up, 3, f"camera '{name}': up")
    R, t = look_at_pose(pos, target, upv, name)
    w_h = tuple(int(s) for s in np.asarray(size).reshape(-1))
    if len(w_h) != 2 or min(w_h) <= 0:
        raise ValueError(f"camera '{name}': size must be [width, height] > 0 px, got {size!r}")
    f = np.broadcast_to(np.asarray(focal_px, dtype=np.float64).reshape(-1), (2,))
    if not np.all(np.isfinite(f)) or np.any(f <= 0):
        raise ValueError(f"camera '{name}': focal_px must be > 0, got {focal_px!r}")
    if principal_point is None:
        c = np.array([(w_h[0] - 1) / 2.0, (w_h[1] - 1) / 2.0])
    else:
        c = _vec(principal_point, 2, f"camera '{name}': principal_point")
    K = np.array([[f[0], 0.0, c[0]], [0.0, f[1], c[1]], [0.0, 0.0, 1.0]])
    d = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)
    if d.size > 5:
        raise ValueError(f"camera '{name}': dist has at most 5 coefficients, got {d.size}")
    rvec = matrix_to_rodrigues(torch.as_tensor(R)).numpy()
    return Camera(name=str(name), K=K, dist=d, rvec=rvec, tvec=t, size=w_h)


_CAMERA_KEYS = {"size", "focal_px", "position", "look_at", "up", "dist", "principal_point"}


def rig_from_config(rig_cfg: Any) -> list[Camera]:
    """Cameras from a rig config: ``{up: [..], cameras: {name: {size, focal_px, position,
    look_at, up?, dist?, principal_point?}}}`` (see ``conf/rig/default.yaml``)."""
    rig = to_plain(rig_cfg)
    if not isinstance(rig, Mapping) or not isinstance(rig.get("cameras"), Mapping):
        raise ValueError("rig config needs a 'cameras' mapping {name: {position, look_at, ...}}")
    if not rig["cameras"]:
        raise ValueError("rig config has no cameras")
    default_up = rig.get("up", (0.0, 0.0, 1.0))
    cams = []
    for name, spec in rig["cameras"].items():
        if not isinstance(spec, Mapping):
            raise ValueError(f"rig camera '{name}' must be a mapping, got {spec!r}")
        unknown = set(spec) - _CAMERA_KEYS
        if unknown:
            raise ValueError(
                f"rig camera '{name}': unknown keys {sorted(unknown)} "
                f"(known: {sorted(_CAMERA_KEYS)})"
            )
        missing = {"position", "look_at", "focal_px", "size"} - set(spec)
        if missing:
            raise ValueError(f"rig camera '{name}': missing keys {sorted(missing)}")
        cams.append(
            camera_look_at(
                name,
                spec["position"],
                spec["look_at"],
                up=spec.get("up") or default_up,
                focal_px=spec["focal_px"],
                size=spec["size"],
                dist=spec.get("dist"),
                principal_point=spec.get("principal_point"),
            )
        )
    return cams


def arena_in_view(
    cameras: Sequence[Camera],
    arena_size: Sequence[float],
    height: float = 80.0,
    margin_px: float = 0.0,
) -> dict[str, bool]:
    """For each camera: are all corners of the arena box [0, ax] x [0, ay] x [0, height] (mm) in
    front of it and inside its image (`margin_px` from the border)? The box is convex and
    projection preserves straight lines (distortion aside), so corners suffice."""
    ax, ay = _vec(arena_size, 2, "arena_size")
    corners = np.array(
        [[x, y, z] for x in (0.0, ax) for y in (0.0, ay) for z in (0.0, float(height))]
    )
    X = torch.as_tensor(corners)
    ct = CameraTensors.from_cameras(list(cameras))
    uv = project_cameras(X, ct).numpy()  # (8, C, 2)
    z = depth(X[:, None, :], ct.R, ct.t).numpy()  # (8, C)
    out = {}
    for c, cam in enumerate(cameras):
        w, h = cam.size
        ok = (
            (z[:, c] > 0).all()
            and (uv[:, c, 0] >= margin_px - 0.5).all()
            and (uv[:, c, 0] <= w - 0.5 - margin_px).all()
            and (uv[:, c, 1] >= margin_px - 0.5).all()
            and (uv[:, c, 1] <= h - 0.5 - margin_px).all()
        )
        out[cam.name] = bool(ok)
    return out


def default_rig(cfg: Any = None, arena_size: Sequence[float] | None = None) -> list[Camera]:
    """The rig's cameras from a config: the full scene config (uses ``cfg.rig``; the arena
    check uses ``cfg.sim.arena.size`` when present) or a rig node. None -> the shipped
    ``conf/rig/default.yaml``. Logs a warning when the arena is not fully in a camera's view."""
    if cfg is None:
        from omegaconf import OmegaConf

        from deformnet.paths import CONF_DIR

        cfg = OmegaConf.load(CONF_DIR / "rig" / "default.yaml")
    plain = to_plain(cfg)
    if not isinstance(plain, Mapping):
        raise ValueError(f"rig config must be a mapping, got {type(plain).__name__}")
    rig = plain.get("rig", plain) if "cameras" not in plain else plain
    if arena_size is None:
        sim = plain.get("sim")
        if isinstance(sim, Mapping):
            arena = sim.get("arena")
            if isinstance(arena, Mapping) and arena.get("size") is not None:
                arena_size = arena["size"]
            elif sim.get("arena_size") is not None:
                arena_size = sim["arena_size"]
    cams = rig_from_config(rig)
    if arena_size is not None:
        height = float(rig.get("arena_view_height", 80.0)) if isinstance(rig, Mapping) else 80.0
        bad = [n for n, ok in arena_in_view(cams, arena_size, height).items() if not ok]
        if bad:
            log.warning(
                "arena %s mm (up to %.0f mm high) is not fully in view of camera(s) %s",
                list(np.asarray(arena_size, dtype=float)),
                height,
                ", ".join(bad),
            )
    return cams


# --------------------------------------------------------------------------------------------
# occlusion
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Ellipsoid:
    """An axis-aligned ellipsoid in the model frame: centre (3,) and semi-axes (3,) in mm.

    parts: empty -> it moves with the body pose; else it moves with the rigid best fit
    (Kabsch) of these parts' model positions onto their true positions in each frame (>= 3
    parts; e.g. the head triangle nose_tip, left_ear, right_ear for a head proxy).
    """

    name: str
    center: np.ndarray
    radii: np.ndarray
    parts: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        c = _vec(self.center, 3, f"ellipsoid '{self.name}': center")
        r = _vec(self.radii, 3, f"ellipsoid '{self.name}': radii")
        if np.any(r <= 0):
            raise ValueError(f"ellipsoid '{self.name}': radii must be > 0, got {r.tolist()}")
        parts = tuple(str(p) for p in (self.parts or ()))
        if parts and len(set(parts)) < 3:
            raise ValueError(
                f"ellipsoid '{self.name}': needs >= 3 distinct parts to follow, got {list(parts)}"
            )
        object.__setattr__(self, "center", c)
        object.__setattr__(self, "radii", r)
        object.__setattr__(self, "parts", parts)


def occluded_by_ellipsoids(
    points: np.ndarray,
    poses: np.ndarray,
    centers: np.ndarray,
    ellipsoids: Sequence[Ellipsoid],
    surface_margin: float = 3.0,
    model: np.ndarray | None = None,
    parts: Sequence[str] | None = None,
) -> np.ndarray:
    """Is each point hidden from each camera by one of the moving ellipsoids?

    points: (T, K, 3) true global mm; poses: (T, 6) Rodrigues + translation, model -> global;
    centers: (C, 3) camera centres; model (K, 3) and parts (K names): needed by ellipsoids that
    follow parts. Returns (T, K, C) bool: True where the segment from the camera centre to the
    point, less its last `surface_margin` mm, meets an ellipsoid's interior. A point inside an
    ellipsoid is tested as its radial projection onto that ellipsoid's surface (in the
    ellipsoid's unit-sphere coordinates). A camera inside an ellipsoid sees nothing through it.
    """
    P = np.asarray(points, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    O = np.asarray(centers, dtype=np.float64)
    if P.ndim != 3 or P.shape[-1] != 3:
        raise ValueError(f"points must be (T, K, 3), got {P.shape}")
    if poses.shape != (P.shape[0], 6):
        raise ValueError(f"poses must be ({P.shape[0]}, 6), got {poses.shape}")
    if O.ndim != 2 or O.shape[-1] != 3:
        raise ValueError(f"centers must be (C, 3), got {O.shape}")
    R_body = rodrigues_to_matrix(torch.as_tensor(poses[:, :3])).numpy()  # (T, 3, 3)
    tau_body = poses[:, 3:]
    hidden = np.zeros((P.shape[0], P.shape[1], O.shape[0]), dtype=bool)
    for e in ellipsoids:  # a handful of proxies, not a loop over frames
        if e.parts:
            if model is None or parts is None:
                raise ValueError(
                    f"ellipsoid '{e.name}' follows parts {list(e.parts)}: pass model and parts"
                )
            names = [str(p) for p in parts]
            missing = [p for p in e.parts if p not in names]
            if missing:
                raise ValueError(f"ellipsoid '{e.name}': parts {missing} are not among {names}")
            idx = [names.index(p) for p in e.parts]
            ref = torch.as_tensor(np.asarray(model, dtype=np.float64)[idx])
            R, tau = (a.numpy() for a in kabsch(torch.as_tensor(P[:, idx]), ref))
        else:
            R, tau = R_body, tau_body
        centre = np.einsum("tij,j->ti", R, e.center) + tau  # (T, 3)
        # into the ellipsoid's unit-sphere frame: u = D^-1 R^T (x - centre)
        p = np.einsum("tji,tkj->tki", R, P - centre[:, None, :]) / e.radii  # (T, K, 3)
        o = np.einsum("tji,tcj->tci", R, O[None, :, :] - centre[:, None, :]) / e.radii  # (T, C, 3)
        o = o[:, None, :, :]  # (T, 1, C, 3)
        # a part inside the proxy (where the proxy is cruder than the body) stands for its
        # radial projection onto the proxy's surface: a paw tucked to the chest is seen from
        # the front, not from behind
        r = np.linalg.norm(p, axis=-1, keepdims=True)
        p = np.where(r < 1.0, p / np.maximum(r, 1e-9), p)
        d = p[:, :, None, :] - o  # (T, K, C, 3), segment o + s d, s in [0, 1]
        seg = np.linalg.norm(d * e.radii, axis=-1)
        s_max = 1.0 - surface_margin / np.maximum(seg, 1e-9)
        a = (d * d).sum(-1)
        b = 2.0 * (o * d).sum(-1)
        c = (o * o).sum(-1) - 1.0
        disc = b * b - 4.0 * a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        a2 = np.maximum(2.0 * a, 1e-18)
        s0 = (-b - root) / a2
        s1 = (-b + root) / a2
        hidden |= (disc > 0) & (s1 > 0.0) & (s0 < s_max) & (s_max > 0.0)
    return hidden


def occluded_by_boxes(
    points: np.ndarray, centers: np.ndarray, boxes: np.ndarray, surface_margin: float = 3.0
) -> np.ndarray:
    """Is each point hidden from each camera by one of the fixed axis-aligned boxes (e.g. the
    lock box)? points (T, K, 3), centers (C, 3), boxes (N, 2, 3) [min corner, max corner] in
    global mm -> (T, K, C) bool, with the segment's last `surface_margin` mm not tested."""
    P = np.asarray(points, dtype=np.float64)
    O = np.asarray(centers, dtype=np.float64)
    B = np.asarray(boxes, dtype=np.float64).reshape(-1, 2, 3)
    hidden = np.zeros((P.shape[0], P.shape[1], O.shape[0]), dtype=bool)
    d = P[:, :, None, :] - O[None, None, :, :]  # (T, K, C, 3), segment O + s d
    seg_len = np.linalg.norm(d, axis=-1)
    s_max = 1.0 - surface_margin / np.maximum(seg_len, 1e-9)
    d = np.where(np.abs(d) < 1e-12, 1e-12, d)
    for lo, hi in B:  # a handful of boxes
        t1 = (lo - O) / d
        t2 = (hi - O) / d
        s_in = np.minimum(t1, t2).max(-1)
        s_out = np.maximum(t1, t2).min(-1)
        hidden |= (s_out >= np.maximum(s_in, 0.0)) & (s_in < s_max) & (s_max > 0.0)
    return hidden


def lockbox_boxes(sim: Any) -> np.ndarray:
    """(1, 2, 3) axis-aligned bounds of the simulator's lock-box corners, or (0, 2, 3)."""
    pts = getattr(sim, "lockbox_corners", None)
    if pts is None:
        return np.zeros((0, 2, 3))
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(-1)]
    if len(pts) < 2 or np.any(np.ptp(pts, axis=0) <= 0):
        return np.zeros((0, 2, 3))
    return np.stack([pts.min(0), pts.max(0)])[None]


def ellipsoids_from_config(occ_cfg: Any) -> list[Ellipsoid]:
    """``{name: {center: [x,y,z], radii: [a,b,c], parts?: [...]}}`` (model frame, mm) ->
    ellipsoids."""
    occ = to_plain(occ_cfg) or {}
    if not isinstance(occ, Mapping):
        raise ValueError(f"occluders must map name -> {{center, radii}}, got {occ!r}")
    out = []
    for name, spec in occ.items():
        if not isinstance(spec, Mapping) or {"center", "radii"} - set(spec):
            raise ValueError(f"occluder '{name}' needs 'center' and 'radii' (mm), got {spec!r}")
        unknown = set(spec) - {"center", "radii", "parts"}
        if unknown:
            raise ValueError(f"occluder '{name}': unknown keys {sorted(unknown)}")
        out.append(Ellipsoid(str(name), spec["center"], spec["radii"], spec.get("parts") or ()))
    return out


# --------------------------------------------------------------------------------------------
# detector model
# --------------------------------------------------------------------------------------------
def _range(value: Any, what: str, lo: float = 0.0, hi: float = 1.0) -> tuple[float, float]:
    v = _vec(value, 2, what)
    if not (lo <= v[0] <= v[1] <= hi):
        raise ValueError(
            f"{what} must be [low, high] with {lo} <= low <= high <= {hi}, got {value!r}"
        )
    return float(v[0]), float(v[1])


#: the default body proxies (mouse model frame, mm), as in ``conf/detector/default.yaml``
DEFAULT_OCCLUDERS = (
    Ellipsoid("trunk", (0.0, -1.0, 3.0), (12.0, 26.0, 10.0)),
    Ellipsoid("head", (0.0, 22.0, 8.0), (7.0, 11.0, 7.0), ("nose_tip", "left_ear", "right_ear")),
)


@dataclass(frozen=True)
class DetectorConfig:
    """The detector model (``conf/detector/default.yaml``); rates are probabilities per
    part-frame-camera.

    dropout_rate: a truly visible part is missed (reported as a low-likelihood guess);
    dropout_correlation_frames: misses come in runs of about this many frames (0: independent);
    swap_rate: per left/right pair, both truly visible: the detector reports each at the
    other's position (high likelihood); swap_correlation_frames likewise;
    outlier_rate: any in-image part-frame-camera becomes a far outlier (random offset of
    outlier_px [min, max] px, high likelihood outlier_likelihood);
    noise_px: Gaussian pixel noise (sigma) on correct detections;
    visible_likelihood / hidden_likelihood: uniform ranges for found / guessed parts;
    guess_px: sigma (px) of the offset of a guess from the true projection;
    out_of_image: 'clip' (report a clipped position with out_of_image_likelihood) or 'nan';
    threshold: likelihood at or above which a detection is accepted (for nviews and fractions);
    occluders: body-proxy ellipsoids in the model frame; lockbox_occludes: the simulator's
    lock box (bounds of ``sim.lockbox_corners``) hides what is behind it; surface_margin: mm of
    the segment ending at the part that is not tested (the part's own surface vicinity).
    """

    dropout_rate: float = 0.34
    dropout_correlation_frames: float = 4.0
    swap_rate: float = 0.01
    swap_correlation_frames: float = 3.0
    outlier_rate: float = 0.01
    outlier_px: tuple[float, float] = (40.0, 250.0)
    outlier_likelihood: tuple[float, float] = (0.6, 1.0)
    noise_px: float = 1.5
    visible_likelihood: tuple[float, float] = (0.9, 1.0)
    hidden_likelihood: tuple[float, float] = (0.01, 0.3)
    guess_px: float = 15.0
    out_of_image: str = "clip"
    out_of_image_likelihood: tuple[float, float] = (0.0, 0.05)
    threshold: float = 0.5
    occluders: tuple[Ellipsoid, ...] = field(default_factory=lambda: DEFAULT_OCCLUDERS)
    lockbox_occludes: bool = True
    surface_margin: float = 3.0

    def __post_init__(self) -> None:
        for key in ("dropout_rate", "swap_rate", "outlier_rate", "threshold"):
            v = float(getattr(self, key))
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"detector.{key} must be in [0, 1], got {v}")
            object.__setattr__(self, key, v)
        for key in (
            "dropout_correlation_frames",
            "swap_correlation_frames",
            "noise_px",
            "guess_px",
            "surface_margin",
        ):
            v = float(getattr(self, key))
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"detector.{key} must be >= 0, got {v}")
            object.__setattr__(self, key, v)
        for key in (
            "visible_likelihood",
            "hidden_likelihood",
            "outlier_likelihood",
            "out_of_image_likelihood",
        ):
            object.__setattr__(self, key, _range(getattr(self, key), f"detector.{key}"))
        object.__setattr__(
            self, "outlier_px", _range(self.outlier_px, "detector.outlier_px", 0.0, math.inf)
        )
        if self.out_of_image not in ("clip", "nan"):
            raise ValueError(
                f"detector.out_of_image must be 'clip' or 'nan', got {self.out_of_image!r}"
            )
        if not isinstance(self.lockbox_occludes, bool | np.bool_):
            raise ValueError(
                f"detector.lockbox_occludes must be true/false, got {self.lockbox_occludes!r}"
            )
        object.__setattr__(self, "lockbox_occludes", bool(self.lockbox_occludes))
        occ = self.occluders
        occ = ellipsoids_from_config(occ) if isinstance(occ, Mapping) else tuple(occ or ())
        if not all(isinstance(e, Ellipsoid) for e in occ):
            raise ValueError("detector.occluders must be Ellipsoids or {name: {center, radii}}")
        object.__setattr__(self, "occluders", tuple(occ))


def detector_config(cfg: Any = None) -> DetectorConfig:
    """A `DetectorConfig` from a config node/dict (the ``detector`` group or a full scene
    config holding it; keys not given take the dataclass defaults), a `DetectorConfig`
    (returned as is) or None (the shipped ``conf/detector/default.yaml``)."""
    if cfg is None:
        from omegaconf import OmegaConf

        from deformnet.paths import CONF_DIR

        cfg = OmegaConf.load(CONF_DIR / "detector" / "default.yaml")
    if isinstance(cfg, DetectorConfig):
        return cfg
    d = to_plain(cfg)
    if not isinstance(d, Mapping):
        raise ValueError(f"detector config must be a mapping, got {type(d).__name__}")
    if "detector" in d and isinstance(d["detector"], Mapping):
        d = d["detector"]
    d = dict(d)
    d.pop("_target_", None)
    known = {f.name for f in fields(DetectorConfig)}
    unknown = set(d) - known
    if unknown:
        raise ValueError(f"unknown detector config keys {sorted(unknown)} (known: {sorted(known)})")
    if "occluders" in d:
        d["occluders"] = tuple(ellipsoids_from_config(d["occluders"]))
    return DetectorConfig(**d)


@dataclass(frozen=True)
class SceneDetections:
    """Simulated detections for T frames, K parts, C cameras.

    xy: (T, K, C, 2) reported pixels (NaN only with out_of_image='nan'); likelihood (T, K, C);
    visible: (T, K, C) true visibility (in front, in image, not occluded); in_image (T, K, C);
    occluded (T, K, C) by the body proxy; dropped (T, K, C) visible but missed; swapped and
    outlier (T, K, C): the reported position is not the part's (swap or far outlier);
    truth_xy (T, K, C, 2) noise-free projections; threshold: acceptance likelihood.
    """

    xy: np.ndarray
    likelihood: np.ndarray
    visible: np.ndarray
    outlier: np.ndarray
    swapped: np.ndarray
    dropped: np.ndarray
    occluded: np.ndarray
    in_image: np.ndarray
    truth_xy: np.ndarray
    cameras: tuple[str, ...] = ()
    parts: tuple[str, ...] = ()
    threshold: float = 0.5

    @property
    def accepted(self) -> np.ndarray:
        """(T, K, C) likelihood >= threshold."""
        return self.likelihood >= self.threshold

    @property
    def correct(self) -> np.ndarray:
        """(T, K, C) accepted, and the reported position is the part's own (noisy) projection."""
        return self.accepted & self.visible & ~self.dropped & ~self.outlier

    @property
    def nviews(self) -> np.ndarray:
        """(T, K) number of cameras with an accepted, correct detection."""
        return self.correct.sum(-1)

    @property
    def accepted_xy(self) -> np.ndarray:
        """(T, K, C, 2) reported pixels, NaN below the threshold (as `adjust.io` loads them)."""
        return np.where(self.accepted[..., None], self.xy, np.nan)

    def to_detections(self):
        """The in-memory twin of what `adjust.io.load_detections` reads from the written
        scene folder: an `adjust.io.Detections` (xy NaN below the threshold, no files)."""
        from adjust.io import Detections

        return Detections(
            cameras=tuple(self.cameras),
            parts=tuple(self.parts),
            xy=self.accepted_xy,
            likelihood=np.nan_to_num(self.likelihood, nan=0.0),
            files=(),
            threshold=self.threshold,
        )

    def fractions(self) -> dict[str, float]:
        """Measured fractions of part-frames (and rates over part-frame-cameras)."""
        nv = self.nviews
        acc = self.accepted.sum(-1)
        vis = self.visible
        n_vis = max(int(vis.sum()), 1)
        pair_cand = self.in_image.sum()
        return {
            "ge2_views": float((nv >= 2).mean()),
            "one_view": float((nv == 1).mean()),
            "no_view": float((nv == 0).mean()),
            "ge2_accepted": float((acc >= 2).mean()),
            "no_accepted": float((acc == 0).mean()),
            "visible": float(vis.mean()),
            "occluded": float(self.occluded.mean()),
            "in_image": float(self.in_image.mean()),
            "dropout_given_visible": float(self.dropped.sum() / n_vis),
            "outlier": float((self.outlier & ~self.swapped).sum() / max(int(pair_cand), 1)),
            "swapped": float(self.swapped.mean()),
            "accepted_wrong": float((self.accepted & ~self.correct).mean()),
        }


def _events(
    rng: np.random.Generator, shape: tuple[int, ...], rate: float, corr_frames: float
) -> np.ndarray:
    """Bernoulli(rate) events over `shape` (time first), in runs of about `corr_frames` frames:
    a Gaussian field smoothed along time (unit marginal variance) thresholded at its
    (1 - rate) quantile, so the marginal rate is exact for any correlation length."""
    if rate <= 0.0:
        return np.zeros(shape, dtype=bool)
    if rate >= 1.0:
        return np.ones(shape, dtype=bool)
    z = rng.standard_normal(shape)
    if corr_frames > 0.0 and shape[0] > 1:
        sigma = corr_frames / 2.0
        half = max(1, math.ceil(3 * sigma))
        k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
        k /= np.sqrt((k * k).sum())  # unit variance after smoothing
        z = convolve1d(z, k, axis=0, mode="wrap")
    return z > ndtri(1.0 - rate)


def _uniform(rng: np.random.Generator, lo_hi: tuple[float, float], shape) -> np.ndarray:
    return rng.uniform(lo_hi[0], lo_hi[1], size=shape)


def _lr_partner(parts: Sequence[str]) -> np.ndarray:
    """Index of each part's left/right counterpart (-1 if none): left_x <-> right_x."""
    idx = {p: i for i, p in enumerate(parts)}
    out = np.full(len(parts), -1, dtype=np.int64)
    for i, p in enumerate(parts):
        for a, b in (("left", "right"), ("right", "left"), ("Left", "Right"), ("Right", "Left")):
            if a in p:
                q = p.replace(a, b, 1)
                if q in idx and q != p:
                    out[i] = idx[q]
                    break
    return out


def simulate_scene(
    sim: Any,
    cameras: Sequence[Camera],
    detector_cfg: Any = None,
    seed: int | Sequence[int] | None = 0,
) -> SceneDetections:
    """Simulated DeepLabCut-like detections of `sim`'s deformed parts in every camera.

    sim: a ``deformnet.sim.SimData`` (uses ``deformed (T, K, 3)``, ``poses (T, 6)``, ``parts``)
    or anything with those attributes; cameras: the rig; detector_cfg: a `DetectorConfig`, a
    detector config node/dict, or None for the defaults; seed: the detector's random seed (an
    int or a sequence of ints, as numpy's `default_rng` takes).
    """
    cfg = detector_config(detector_cfg)
    X = np.asarray(sim.deformed, dtype=np.float64)
    poses = np.asarray(sim.poses, dtype=np.float64)
    parts = tuple(str(p) for p in sim.parts)
    if X.ndim != 3 or X.shape[-1] != 3:
        raise ValueError(f"sim.deformed must be (T, K, 3), got {X.shape}")
    T, K, _ = X.shape
    if len(parts) != K:
        raise ValueError(f"{len(parts)} part names for {K} parts")
    if poses.shape != (T, 6):
        raise ValueError(f"sim.poses must be ({T}, 6), got {poses.shape}")
    cams = list(cameras)
    if not cams:
        raise ValueError("no cameras given")
    C = len(cams)
    rng = np.random.default_rng(seed)

    ct = CameraTensors.from_cameras(cams)
    Xt = torch.as_tensor(X)
    uv = project_cameras(Xt, ct).numpy()  # (T, K, C, 2)
    z = depth(Xt[..., None, :], ct.R, ct.t).numpy()  # (T, K, C)
    wh = np.array([c.size for c in cams], dtype=np.float64)  # (C, 2)
    if np.any(wh <= 0):
        raise ValueError("every camera needs an image size (width, height) > 0")
    lo, hi = -0.5, wh - 0.5  # pixel-centre origin: the image spans [-0.5, W - 0.5)
    finite = np.isfinite(uv).all(-1)
    in_image = (z > 0) & finite & (uv >= lo).all(-1) & (uv < hi).all(-1)
    centers = np.stack([c.center for c in cams])
    model = getattr(sim, "model", None)
    occluded = occluded_by_ellipsoids(
        X, poses, centers, cfg.occluders, cfg.surface_margin, model=model, parts=parts
    )
    if cfg.lockbox_occludes:
        occluded |= occluded_by_boxes(X, centers, lockbox_boxes(sim), cfg.surface_margin)
    occluded &= in_image
    visible = in_image & ~occluded

    shape = (T, K, C)
    # detector misses among the visible
    dropped = visible & _events(rng, shape, cfg.dropout_rate, cfg.dropout_correlation_frames)
    found = visible & ~dropped
    # pixel noise on correct detections, guesses for the rest
    noisy = uv + rng.standard_normal(uv.shape) * cfg.noise_px
    guess = uv + rng.standard_normal(uv.shape) * cfg.guess_px
    xy = np.where(found[..., None], noisy, guess)
    lik_found = _uniform(rng, cfg.visible_likelihood, shape)
    lik = np.where(found, lik_found, _uniform(rng, cfg.hidden_likelihood, shape))
    # left/right swaps: both parts of a pair truly found; each reported at the other's place
    partner = _lr_partner(parts)
    swapped = np.zeros(shape, dtype=bool)
    has = np.flatnonzero(partner >= 0)
    if has.size:
        first = has[has < partner[has]]  # one event per pair
        ev = _events(rng, (T, first.size, C), cfg.swap_rate, cfg.swap_correlation_frames)
        both = found[:, first] & found[:, partner[first]]
        ev &= both
        swapped[:, first] = ev
        swapped[:, partner[first]] = ev
        src = np.arange(K)
        src[first] = partner[first]
        src[partner[first]] = first
        xy = np.where(swapped[..., None], noisy[:, src], xy)
    # far outliers: anywhere a detector looks, with a high likelihood
    far = in_image & _events(rng, shape, cfg.outlier_rate, 0.0)
    ang = rng.uniform(0.0, 2 * np.pi, shape)
    rad = _uniform(rng, cfg.outlier_px, shape)
    off = np.stack([np.cos(ang), np.sin(ang)], -1) * rad[..., None]
    far_xy = np.clip(uv + off, lo, hi - 1e-6)
    xy = np.where(far[..., None], far_xy, xy)
    lik = np.where(far, _uniform(rng, cfg.outlier_likelihood, shape), lik)
    outlier = far | swapped
    # outside the image (or behind the camera): missing / low likelihood
    out_lik = _uniform(rng, cfg.out_of_image_likelihood, shape)
    if cfg.out_of_image == "nan":
        xy = np.where(in_image[..., None], xy, np.nan)
        lik = np.where(in_image, lik, np.nan)
    else:
        safe = np.where(finite[..., None], uv, 0.0)
        clipped = np.clip(safe, lo, hi - 1e-6)
        xy = np.where(in_image[..., None], xy, clipped)
        lik = np.where(in_image, lik, out_lik)
    # every reported in-image position stays inside the image
    xy = np.where(in_image[..., None], np.clip(xy, lo, hi - 1e-6), xy)
    return SceneDetections(
        xy=xy,
        likelihood=lik,
        visible=visible,
        outlier=outlier,
        swapped=swapped & ~far,
        dropped=dropped,
        occluded=occluded,
        in_image=in_image,
        truth_xy=uv,
        cameras=tuple(c.name for c in cams),
        parts=parts,
        threshold=cfg.threshold,
    )


# --------------------------------------------------------------------------------------------
# scene folder
# --------------------------------------------------------------------------------------------
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

    from adjust.io import save_calibration, write_dlc_csv
    from deformnet.atomic import atomic_path

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
