"""The camera rig of a simulated scene: `Camera`s from position, look-at point and up vector.

World -> camera ``x_cam = R X + t``; pixel origin at the top-left pixel's centre, so the
principal point of a W x H image is ((W-1)/2, (H-1)/2). The pose itself is
`adjust.camera.look_at_pose`; this module adds the config forms and the arena check.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from adjust.camera import Camera, CameraTensors, depth, look_at_pose, project_cameras
from adjust.scene._checks import _vec
from deformnet.confutil import given_fields, to_plain
from deformnet.paths import CONF_DIR
from deformnet.so3 import matrix_to_rodrigues

log = logging.getLogger(__name__)

__all__ = ["RigConfig", "arena_in_view", "camera_look_at", "default_rig", "rig_from_config"]


def camera_look_at(
    name: str,
    position: Sequence[float],
    look_at: Sequence[float],
    up: Sequence[float] = (0.0, 0.0, 1.0),
    focal_px: float | Sequence[float] = 1000.0,
    size: Sequence[int] = (1280, 1024),
    dist: Sequence[float] | None = None,
    principal_point: Sequence[float] | None = None,
    fisheye: bool = False,
) -> Camera:
    """A pinhole camera at `position` (mm) looking at `look_at`, image "up" towards `up`.

    Camera axes (OpenCV): z along the viewing direction, x to the image right, y down the
    image. `focal_px` is one focal length or (fx, fy); `size` is (width, height) px; the
    principal point defaults to the image centre ((W-1)/2, (H-1)/2); `fisheye`: OpenCV's
    fisheye model, `dist` then k1 k2 k3 k4.
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
    if not isinstance(fisheye, bool):
        raise ValueError(f"camera '{name}': fisheye must be true or false, got {fisheye!r}")
    if fisheye and d.size > 4:
        raise ValueError(f"camera '{name}': a fisheye's dist has at most 4 coefficients (k1-k4)")
    return Camera(name=str(name), K=K, dist=d, rvec=rvec, tvec=t, size=w_h, fisheye=fisheye)


@dataclass(frozen=True)
class RigConfig:
    """A rig config's settings beside its ``cameras`` (the ``rig`` group,
    ``conf/rig/default.yaml``): the world vector a camera without its own ``up`` shows as up,
    and the height (mm) of the arena box `default_rig` checks is in every camera's view. A key
    absent from the config keeps its default here, the one copy of the YAML's."""

    up: Sequence[float] = (0.0, 0.0, 1.0)
    arena_view_height: float = 80.0

    @classmethod
    def from_config(cls, rig: Mapping) -> RigConfig:
        """From a rig config (a mapping: its ``up`` and ``arena_view_height``)."""
        d = given_fields(cls, rig)
        if "arena_view_height" in d:
            d["arena_view_height"] = float(d["arena_view_height"])
        return cls(**d)


_CAMERA_KEYS = {
    "size", "focal_px", "position", "look_at", "up", "dist", "principal_point", "fisheye"
}  # fmt: skip


def rig_from_config(rig_cfg: Any) -> list[Camera]:
    """Cameras from a rig config: ``{up: [..], cameras: {name: {size, focal_px, position,
    look_at, up?, dist?, principal_point?, fisheye?}}}`` (see ``conf/rig/default.yaml``)."""
    rig = to_plain(rig_cfg)
    if not isinstance(rig, Mapping) or not isinstance(rig.get("cameras"), Mapping):
        raise ValueError("rig config needs a 'cameras' mapping {name: {position, look_at, ...}}")
    if not rig["cameras"]:
        raise ValueError("rig config has no cameras")
    default_up = RigConfig.from_config(rig).up
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
                fisheye=spec.get("fisheye", False),
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
        height = RigConfig.from_config(rig).arena_view_height  # (a mapping: rig_from_config)
        bad = [n for n, ok in arena_in_view(cams, arena_size, height).items() if not ok]
        if bad:
            log.warning(
                "arena %s mm (up to %.0f mm high) is not fully in view of camera(s) %s",
                list(np.asarray(arena_size, dtype=float)),
                height,
                ", ".join(bad),
            )
    return cams
