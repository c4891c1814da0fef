"""A behavior model where rules are not enough: the simulator's sessions labelled with a lab's
ethogram, animals that differ from each other, and labels written the way a person annotates.

The default simulator (`deformnet.sim.simulate`) labels what it animates: a behavior is a
threshold on something a classifier sees (walking is the only movement, a lock-box behavior is a
part at a mechanism). Here the same animation gets the labels a lab's ethogram gives, where
behaviors share kinematics and differ in context, duration and sequence:

- ``walk`` / ``approach``: the same gait; an approach is the walk that ends at a mechanism (the
  simulator's walk to the box), told apart by where it goes and what follows;
- ``rear_wall`` / ``rear_free``: the same rear, against a wall or the lock box (the body origin
  within `WALL_ZONE` mm of the walkable region's edge) or in the open;
- ``sniff`` / ``splint`` / ``slider``: the same nose reach to a mechanism; a short one (under
  `SNIFF_SECONDS`) is sniffing, a longer one operating it;
- ``scan``, ``groom``, ``lever``, ``ball`` as the simulator animates them.

Each session is one animal (`animal_config`): its size, walking speed, bout durations, rearing
and grooming posture and head sweeps are drawn from its own seed, so test animals are ones the
labels never saw. `annotate` writes a person's bouts: onsets and offsets jittered, some bouts
given a confusable label, some short bouts missed (merged into the bout before).

    data, labels = simulate_ethogram(SimConfig(), num_frames=6000, seed=7)
    rows = annotate(labels, data.fps, np.random.default_rng(7))   # (start, stop, class) bouts
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from deformnet.body import BodyModel, default_mouse
from deformnet.sim.config import BEHAVIORS, SimConfig
from deformnet.sim.dataset import SimData
from deformnet.sim.engine import simulate
from deformnet.sim.scene import build_scene
from deformnet.sim.trajectory import FIRST_MECH, GROOM, REAR, SCAN, WALK, make_plan

ETHOGRAM: tuple[str, ...] = (
    "walk", "approach", "scan", "rear_wall", "rear_free", "groom", "sniff",
    "lever", "splint", "ball", "slider",
)  # fmt: skip
#: mm: a rear with the body origin this close to the walkable region's edge is against the wall
WALL_ZONE = 25.0
#: s: a nose reach to a mechanism shorter than this is sniffing it, a longer one operating it
SNIFF_SECONDS = 1.5
#: labels a person confuses (`annotate` gives a mislabelled bout its partner's label)
CONFUSABLE = {
    "walk": "approach", "approach": "walk", "rear_wall": "rear_free", "rear_free": "rear_wall",
    "sniff": "splint", "splint": "sniff", "slider": "sniff", "scan": "groom", "groom": "scan",
    "lever": "ball", "ball": "lever",
}  # fmt: skip


def _scaled(lo_hi: Sequence[float], factor: float) -> tuple[float, float]:
    return (float(lo_hi[0]) * factor, float(lo_hi[1]) * factor)


def animal_config(cfg: SimConfig, animal: int) -> SimConfig:
    """``cfg`` with one animal's own traits drawn from the seed ``animal``: size (body scale
    0.9-1.15), walking and approach speed (x 0.75-1.35), bout durations (x 0.8-1.25), rearing
    pitch (+- 8 deg), grooming posture and stroke (pitch +- 5 deg, 3-6 strokes per s) and head
    sweeps while scanning (x 0.7-1.2)."""
    rng = np.random.default_rng([int(animal), 0xE7])
    u = rng.uniform
    speed, dur, sweep = u(0.75, 1.35), u(0.8, 1.25), u(0.7, 1.2)
    rear_shift, groom_shift = u(-8.0, 8.0), u(-5.0, 5.0)
    rear = cfg.rear.pitch
    groom = cfg.groom.pitch
    return cfg.replace(
        body_scale=float(u(0.9, 1.15)),
        walk=dataclasses.replace(
            cfg.walk,
            speed_mean=cfg.walk.speed_mean * speed,
            speed_max=max(cfg.walk.speed_max, cfg.walk.speed_mean * speed * 2),
            approach_speed=cfg.walk.approach_speed * speed,
        ),
        behaviors=dataclasses.replace(
            cfg.behaviors, durations=tuple(_scaled(d, dur) for d in cfg.behaviors.durations)
        ),
        rear=dataclasses.replace(
            cfg.rear, pitch=(max(5.0, rear[0] + rear_shift), min(85.0, rear[1] + rear_shift))
        ),
        groom=dataclasses.replace(
            cfg.groom,
            pitch=(max(0.0, groom[0] + groom_shift), groom[1] + groom_shift),
            stroke_frequency=float(u(3.0, 6.0)),
        ),
        scan=dataclasses.replace(
            cfg.scan,
            yaw=_scaled(cfg.scan.yaw, sweep),
            pitch=_scaled(cfg.scan.pitch, sweep),
            roll=_scaled(cfg.scan.roll, sweep),
        ),
    )


def ethogram_labels(cfg: SimConfig, num_frames: int, seed: int, body: BodyModel) -> np.ndarray:
    """The ethogram's labels (T,) (indices into `ETHOGRAM`) of the session `simulate` draws
    for this config, length and seed: its plan of episodes (drawn again, the same way) read
    with the context each episode happens in."""
    cfg = cfg.replace(num_frames=int(num_frames), seed=int(seed))
    if cfg.body_scale != 1.0:
        body = body.scaled(cfg.body_scale)
    scene = build_scene(cfg, body)
    rng_plan = np.random.default_rng(np.random.SeedSequence(cfg.seed).spawn(5)[0])
    plan = make_plan(cfg, scene, cfg.num_frames, rng_plan)
    T = cfg.num_frames
    index = {name: i for i, name in enumerate(ETHOGRAM)}
    out = np.empty(T, dtype=np.int64)
    nose_mechs = {m for m in range(4) if scene.mech_part[m] == scene.head[0]}
    for e, (a, n, lab) in enumerate(zip(plan.ep_start, plan.ep_len, plan.ep_label)):
        b = min(a + n, T)
        if lab == WALK:
            nxt = plan.ep_label[e + 1] if e + 1 < len(plan.ep_label) else WALK
            name = "approach" if nxt >= FIRST_MECH else "walk"
        elif lab == SCAN:
            name = "scan"
        elif lab == GROOM:
            name = "groom"
        elif lab == REAR:
            xy = plan.xy[a:b].mean(0)
            edge = np.minimum(xy - scene.free_lo, scene.free_hi - xy).min()
            name = "rear_wall" if edge < WALL_ZONE else "rear_free"
        else:
            m = int(lab) - FIRST_MECH
            short = n < SNIFF_SECONDS * cfg.fps
            name = "sniff" if (m in nose_mechs and short) else BEHAVIORS[lab]
        out[a:b] = index[name]
    return out


def simulate_ethogram(
    cfg: SimConfig | None = None,
    num_frames: int = 6000,
    seed: int = 0,
    animal: int | None = None,
    body: BodyModel | None = None,
) -> tuple[SimData, np.ndarray]:
    """One session of one animal: (the simulator's data, its `ETHOGRAM` labels (T,)). The
    animal's traits come from ``animal`` (`animal_config`; None: the seed's own animal);
    the simulator's own labels stay in ``data.labels``."""
    body = default_mouse() if body is None else body
    cfg = animal_config(cfg or SimConfig(), seed if animal is None else animal)
    data = simulate(cfg, num_frames=int(num_frames), seed=int(seed), body=body)
    labels = ethogram_labels(cfg, num_frames, seed, body)
    return data, labels


def _bouts(labels: np.ndarray) -> list[list[int]]:
    """[[start, stop (inclusive), label], ...] of a label sequence (T,)."""
    cut = np.flatnonzero(np.diff(labels)) + 1
    starts = np.r_[0, cut]
    stops = np.r_[cut - 1, len(labels) - 1]
    return [[int(a), int(b), int(labels[a])] for a, b in zip(starts, stops)]


def annotate(
    labels: np.ndarray,
    fps: float,
    rng: np.random.Generator,
    jitter_s: float = 0.2,
    mislabel: float = 0.05,
    miss: float = 0.05,
    classes: Sequence[str] = ETHOGRAM,
) -> list[tuple[int, int, int]]:
    """A person's bouts of a session whose true labels are ``labels`` (T,): each boundary
    between two bouts moved by a normal draw of sd ``jitter_s`` seconds (kept inside its
    neighbours), a share ``mislabel`` of the bouts given a confusable class (`CONFUSABLE`),
    a share ``miss`` of the bouts shorter than 1 s missed (their frames given to the bout
    before). Returns (start, stop inclusive, class index) covering every frame."""
    bouts = _bouts(np.asarray(labels))
    index = {c: i for i, c in enumerate(classes)}
    kept: list[list[int]] = []
    for a, b, c in bouts:
        short = b - a + 1 < fps
        if kept and short and rng.random() < miss:
            kept[-1][1] = b
            continue
        if rng.random() < mislabel:
            c = index.get(CONFUSABLE.get(classes[c], classes[c]), c)
        if kept and kept[-1][2] == c:
            kept[-1][1] = b
        else:
            kept.append([a, b, c])
    for i in range(1, len(kept)):  # boundary i between bout i-1 and bout i
        lo, hi = kept[i - 1][0] + 1, kept[i][1]
        edge = int(round(kept[i][0] + rng.normal(0.0, jitter_s * fps)))
        edge = min(max(edge, lo), hi)
        kept[i][0], kept[i - 1][1] = edge, edge - 1
    return [(a, b, c) for a, b, c in kept]
