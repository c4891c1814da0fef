"""Occlusion geometry of a simulated scene.

A part is hidden from a camera when the segment from the camera centre to the part passes
through a body-proxy ellipsoid moved with the pose or with the rigid fit of a few parts
(`Ellipsoid`, `occluded_by_ellipsoids`; the segment's last `surface_margin` mm, the part's own
surface vicinity, is not tested), or through an axis-aligned box such as the lock box
(`occluded_by_boxes`). Shapes: T frames, K parts, C cameras; mm.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from adjust.scene._checks import _vec
from deformnet.confutil import to_plain
from deformnet.so3 import kabsch, rodrigues_to_matrix

__all__ = [
    "Ellipsoid",
    "ellipsoids_from_config",
    "lockbox_boxes",
    "occluded_by_boxes",
    "occluded_by_ellipsoids",
]


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
