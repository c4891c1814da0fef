"""Scene geometry derived from a `SimConfig` and a body model: the parts the simulator moves,
the walkable region, the lock box (corners, mechanisms) and the standing spots for reaching."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from deformnet.body import BodyModel
from deformnet.sim.config import MECHANISMS, SimConfig

log = logging.getLogger(__name__)

HEAD_PARTS = ("nose_tip", "left_ear", "right_ear")
PAWS = ("right_front_paw", "left_hind_paw", "left_front_paw", "right_hind_paw")  # pair A, pair B
FRONT_PAWS = ("left_front_paw", "right_front_paw")
HIND_PAWS = ("left_hind_paw", "right_hind_paw")
TAIL = "tail_root"
FACE_CLEARANCE = 3.0  # mm kept between the rigid body and the lock box's front face


@dataclass(frozen=True)
class Scene:
    body: BodyModel
    model: np.ndarray  # (K, 3)
    head: np.ndarray  # (3,) indices nose, left ear, right ear
    paws: np.ndarray  # (4,) indices in PAWS order (pair A = first two: stance on even cycles)
    front: np.ndarray  # (2,) indices left, right front paw
    tail: int  # index or -1
    head_pivot: np.ndarray  # (3,) model: midpoint of the ears
    pitch_pivot: np.ndarray  # (3,) model: midpoint of the hind paws
    ground: float  # body origin height that puts the paws on the ground
    margin: float  # used wall margin (origin <-> wall)
    free_lo: np.ndarray  # (2,) walkable rectangle for the body origin
    free_hi: np.ndarray
    arena: np.ndarray  # (2,)
    corners: np.ndarray  # (8, 3) lock-box corners
    mech_pos: np.ndarray  # (4, 3)
    mech_part: np.ndarray  # (4,) effector part index
    stand_xy: np.ndarray  # (4, 2) body origin while reaching (heading +y)
    stand_pitch: np.ndarray  # (4,) rad, body pitch at the reach's peak


def rot_x(theta: np.ndarray) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack(
        [np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2
    )


def _head_forward_reach(cfg: SimConfig, head: np.ndarray, pivot: np.ndarray) -> float:
    """Largest model Y any head point reaches while the head rotates within its intervals."""
    from scipy.spatial.transform import Rotation

    best = -np.inf
    for grp in (cfg.head, cfg.scan):
        axes = [np.linspace(*getattr(grp, k), 9) for k in ("yaw", "pitch", "roll")]
        ang = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        Rh = Rotation.from_euler("ZXY", ang, degrees=True).as_matrix()
        pts = np.einsum("nij,kj->nki", Rh, head - pivot) + pivot
        best = max(best, float(pts[..., 1].max()))
    return best + 0.5


def build_scene(cfg: SimConfig, body: BodyModel) -> Scene:
    def idx(name: str, key: str | None = None) -> int:
        try:
            return body.index(name)
        except KeyError as exc:
            if key is None:
                raise ValueError(
                    f"body model '{body.name}' lacks part '{name}', which the simulator moves "
                    f"(needs {', '.join(HEAD_PARTS + PAWS)})"
                ) from None
            raise ValueError(f"sim.{key}: {exc.args[0]}") from None

    model = np.asarray(body.points, dtype=np.float64)
    head = np.array([idx(n) for n in HEAD_PARTS])
    paws = np.array([idx(n) for n in PAWS])
    front = np.array([idx(n) for n in FRONT_PAWS])
    hind = np.array([idx(n) for n in HIND_PAWS])
    tail = body.resolve(TAIL)
    tail_i = body.parts.index(tail) if tail is not None else -1
    head_pivot = model[head[1:]].mean(0)
    pitch_pivot = model[hind].mean(0)
    ground = -float(model[paws, 2].mean())

    # wall margin: the farthest any part gets from the origin horizontally
    head_r = np.linalg.norm(head_pivot[:2]) + np.linalg.norm(model[head] - head_pivot, axis=1).max()
    paw_r = np.linalg.norm(model[paws, :2], axis=1).max() + cfg.gait.stride
    other = np.setdiff1d(np.arange(len(model)), np.concatenate([head, paws]))
    other_r = np.linalg.norm(model[other, :2], axis=1).max() if other.size else 0.0
    groom_r = np.linalg.norm(model[head[0], :2]) + np.linalg.norm(cfg.groom.paw_offset)
    need = float(max(head_r, paw_r, other_r, groom_r)) + 1.0
    margin = max(cfg.arena.wall_margin, need)
    if margin > cfg.arena.wall_margin:
        log.info(
            "wall margin raised from %.1f to %.1f mm to fit the body", cfg.arena.wall_margin, margin
        )

    arena = np.asarray(cfg.arena.size, dtype=np.float64)
    lb = cfg.lockbox
    cx, cy = lb.center
    w, d, h = lb.size
    x0, x1, y0, y1 = cx - w / 2, cx + w / 2, cy - d / 2, cy + d / 2
    corners = np.array(
        [[x, y, z] for z in (0.0, h) for y in (y0, y1) for x in (x0, x1)], dtype=np.float64
    )
    free_lo = np.array([margin, margin])
    free_hi = np.array([arena[0] - margin, min(arena[1], y0) - margin])
    if np.any(free_hi - free_lo < 1.0):
        raise ValueError(
            f"sim.arena.size: no room to walk: the body origin needs {margin:.1f} mm to the walls "
            f"and to the lock box front (y = {y0:.1f}); arena {arena.tolist()}"
        )

    mech_pos = np.array(
        [[cx + m.position[0], y0 - m.position[1], m.position[2]] for m in lb.mechanisms]
    )
    mech_part = np.array(
        [
            idx(m.effector, f"lockbox.mechanisms.{n}.effector")
            for n, m in zip(MECHANISMS, lb.mechanisms)
        ]
    )

    # standing spot per mechanism: heading +y (model axes = global axes), pitch chosen so that
    # the effector's rigid height is closest to the mechanism's height
    head_fwd = _head_forward_reach(cfg, model[head], head_pivot)  # head rotation's max reach
    thetas = np.deg2rad(np.linspace(0.0, cfg.reach.max_pitch, 181))
    Rx = rot_x(thetas)  # (P, 3, 3)
    pitched = np.einsum("pij,kj->pki", Rx, model - pitch_pivot) + pitch_pivot  # (P, K, 3)
    stand_xy = np.zeros((4, 2))
    stand_pitch = np.zeros(4)
    for j, (name, p) in enumerate(zip(MECHANISMS, mech_part)):
        z = pitched[:, p, 2] + ground
        best = int(np.argmin(np.abs(z - mech_pos[j, 2])))
        eff = pitched[best, p]
        front_y = max(pitched[best, :, 1].max(), model[:, 1].max(), head_fwd)
        oy = min(mech_pos[j, 1] - cfg.reach.gap - eff[1], y0 - FACE_CLEARANCE - front_y)
        ox = mech_pos[j, 0] - eff[0]
        stand_xy[j] = (ox, oy)
        stand_pitch[j] = thetas[best]
        if not (margin <= ox <= arena[0] - margin and margin <= oy):
            raise ValueError(
                f"sim.lockbox.mechanisms.{name}.position: the mouse cannot stand in front of it "
                f"(origin would be at ({ox:.1f}, {oy:.1f}) mm, needs {margin:.1f} mm to the walls)"
            )
    return Scene(
        body=body,
        model=model,
        head=head,
        paws=paws,
        front=front,
        tail=tail_i,
        head_pivot=head_pivot,
        pitch_pivot=pitch_pivot,
        ground=ground,
        margin=margin,
        free_lo=free_lo,
        free_hi=free_hi,
        arena=arena,
        corners=corners,
        mech_pos=mech_pos,
        mech_part=mech_part,
        stand_xy=stand_xy,
        stand_pitch=stand_pitch,
    )
