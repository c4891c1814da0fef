"""Simulator configuration: `SimConfig`, a frozen dataclass tree like ``conf/sim/default.yaml``.

Units: lengths mm, times s, angles deg. `SimConfig()` equals the YAML defaults;
`SimConfig.from_config(node)` builds one from a Hydra/OmegaConf node or a plain mapping (missing
keys keep their defaults, unknown keys and bad values raise ValueError naming the key).
Each group's dataclass (``WalkConfig``, ...) checks its own ranges in ``__post_init__``, naming
``sim.<group>.<key>``; `SimConfig` checks the top-level keys and what spans groups (the lock box
inside the arena). `from_config` parses the YAML's shape (rows keyed by behavior and mechanism
name, fixed-length lists), which a structured-config schema cannot express.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from deformnet.confutil import to_plain
from deformnet.paths import CONF_DIR

BEHAVIORS: tuple[str, ...] = ("walk", "scan", "rear", "groom", "lever", "splint", "ball", "slider")
MECHANISMS: tuple[str, ...] = ("lever", "splint", "ball", "slider")


@dataclass(frozen=True)
class ArenaConfig:
    size: tuple[float, float] = (300.0, 300.0)
    wall_margin: float = 45.0

    def __post_init__(self) -> None:
        _check(min(self.size) > 0, "arena.size", "must be > 0", self.size)
        _at_least(self, "arena", 0, "wall_margin")


@dataclass(frozen=True)
class WalkConfig:
    speed_mean: float = 60.0
    speed_sigma: float = 0.4
    speed_max: float = 200.0
    speed_tau: float = 0.7
    curvature_std: float = 0.012
    curvature_tau: float = 0.6
    stop_rate: float = 0.15
    stop_duration: tuple[float, float] = (0.3, 1.5)
    smooth: float = 0.12
    approach_speed: float = 70.0

    def __post_init__(self) -> None:
        _positive(self, "walk", "speed_mean", "speed_max", "speed_tau", "curvature_tau",
                  "approach_speed")  # fmt: skip
        _at_least(self, "walk", 0, "speed_sigma", "curvature_std", "stop_rate", "smooth")
        _check(self.speed_max >= self.speed_mean, "walk.speed_max", "must be >= walk.speed_mean",
               self.speed_max)  # fmt: skip
        _interval(self.stop_duration, "walk.stop_duration", 0.0)


@dataclass(frozen=True)
class GaitConfig:
    stride: float = 20.0
    swing_height: float = 2.0

    def __post_init__(self) -> None:
        _positive(self, "gait", "stride")
        _at_least(self, "gait", 0, "swing_height")


@dataclass(frozen=True)
class SwayConfig:
    """The head swept back and forth about the ears' midpoint: yaw, pitch, roll intervals (deg,
    in [-90, 90], each containing 0), run linearly back and forth over `period` (s, a full cycle
    of each). One shape for two groups: ``head`` (while walking; `HeadConfig`) and ``scan``
    (stopped, larger intervals; `ScanConfig`); their defaults are `SimConfig`'s."""

    GROUP: ClassVar[str] = ""

    yaw: tuple[float, float]
    pitch: tuple[float, float]
    roll: tuple[float, float]
    period: tuple[float, float, float]

    def __post_init__(self) -> None:
        for k in ("yaw", "pitch", "roll"):
            iv = getattr(self, k)
            _interval(iv, f"{self.GROUP}.{k}", -90.0, 90.0)
            _check(iv[0] <= 0.0 <= iv[1], f"{self.GROUP}.{k}", "the interval must contain 0", iv)
        _check(min(self.period) > 0, f"{self.GROUP}.period", "periods must be > 0", self.period)


@dataclass(frozen=True)
class HeadConfig(SwayConfig):
    """``head``: the sway while walking; blend: smoothing (s) of head motion at behavior
    changes."""

    GROUP: ClassVar[str] = "head"

    blend: float = 0.1

    def __post_init__(self) -> None:
        super().__post_init__()
        _at_least(self, "head", 0, "blend")


@dataclass(frozen=True)
class ScanConfig(SwayConfig):
    """``scan``: the sway while stopped (the scan behavior)."""

    GROUP: ClassVar[str] = "scan"


@dataclass(frozen=True)
class RearConfig:
    pitch: tuple[float, float] = (35.0, 65.0)
    tuck: tuple[float, float, float] = (0.0, -4.0, 4.0)
    lift: float = 0.0  # mm: the body (all but hind paws and tail root) raised on extended legs
    stretch: float = 0.0  # relative: the parts ahead of the hind paws moved forward by this share
    paw_motion: float = 0.0  # mm: std of the free front paws' random motion while reared

    def __post_init__(self) -> None:
        _interval(self.pitch, "rear.pitch", 0.0, 89.0)
        _at_least(self, "rear", 0, "lift", "stretch", "paw_motion")


@dataclass(frozen=True)
class GroomConfig:
    pitch: tuple[float, float] = (10.0, 25.0)
    paw_offset: tuple[float, float, float] = (3.5, -4.0, -3.0)
    stroke_amplitude: float = 2.0
    stroke_frequency: float = 4.0

    def __post_init__(self) -> None:
        _interval(self.pitch, "groom.pitch", 0.0, 89.0)
        _at_least(self, "groom", 0, "stroke_amplitude", "stroke_frequency")


@dataclass(frozen=True)
class ReachConfig:
    gap: float = 5.0
    max_pitch: float = 60.0
    jitter: float = 0.8
    ramp: float = 0.3

    def __post_init__(self) -> None:
        _at_least(self, "reach", 0, "gap", "jitter")
        _check(0 <= self.max_pitch < 89, "reach.max_pitch", "must be in [0, 89)", self.max_pitch)
        _positive(self, "reach", "ramp")


_DEFAULT_DURATIONS: tuple[tuple[float, float], ...] = (
    (2.0, 6.0),
    (1.0, 3.0),
    (1.0, 2.5),
    (1.5, 4.0),
    (1.0, 2.5),
    (1.0, 2.5),
    (1.0, 2.5),
    (1.0, 2.5),
)
_DEFAULT_TRANSITIONS: tuple[tuple[float, ...], ...] = (
    (0.0, 0.25, 0.15, 0.12, 0.12, 0.12, 0.12, 0.12),
    (0.55, 0.0, 0.15, 0.06, 0.06, 0.06, 0.06, 0.06),
    (0.5, 0.2, 0.0, 0.1, 0.05, 0.05, 0.05, 0.05),
    (0.6, 0.2, 0.1, 0.0, 0.025, 0.025, 0.025, 0.025),
    (0.5, 0.1, 0.05, 0.05, 0.0, 0.1, 0.1, 0.1),
    (0.5, 0.1, 0.05, 0.05, 0.1, 0.0, 0.1, 0.1),
    (0.5, 0.1, 0.05, 0.05, 0.1, 0.1, 0.0, 0.1),
    (0.5, 0.1, 0.05, 0.05, 0.1, 0.1, 0.1, 0.0),
)


@dataclass(frozen=True)
class BehaviorConfig:
    """durations[i] = (min, max) s and transitions[i] = row i of the Markov matrix, in the order
    of `BEHAVIORS`."""

    durations: tuple[tuple[float, float], ...] = _DEFAULT_DURATIONS
    transitions: tuple[tuple[float, ...], ...] = _DEFAULT_TRANSITIONS

    def __post_init__(self) -> None:
        n = len(BEHAVIORS)
        _check(len(self.durations) == n, "behaviors.durations",
               f"need one [min, max] per behavior {list(BEHAVIORS)}", self.durations)  # fmt: skip
        for name, d in zip(BEHAVIORS, self.durations):
            _interval(d, f"behaviors.durations.{name}", 0.0)
            _check(d[1] > 0, f"behaviors.durations.{name}", "max must be > 0", d)
        _check(len(self.transitions) == n, "behaviors.transitions",
               f"need one row per behavior {list(BEHAVIORS)}", self.transitions)  # fmt: skip
        for name, row in zip(BEHAVIORS, self.transitions):
            key = f"behaviors.transitions.{name}"
            _check(len(row) == n, key, f"need {n} probabilities", row)
            _check(min(row) >= 0, key, "probabilities must be >= 0", row)
            _check(abs(sum(row) - 1.0) < 1e-6, key, "the row must sum to 1", row)


@dataclass(frozen=True)
class MechanismConfig:
    position: tuple[
        float, float, float
    ]  # [along x, out of the front face, z] from face bottom centre
    effector: str


_DEFAULT_MECHANISMS: tuple[MechanismConfig, ...] = (
    MechanismConfig((-60.0, 15.0, 18.0), "right_front_paw"),
    MechanismConfig((-20.0, 2.0, 12.0), "nose_tip"),
    MechanismConfig((20.0, 12.0, 10.0), "left_front_paw"),
    MechanismConfig((60.0, 2.0, 20.0), "nose_tip"),
)


@dataclass(frozen=True)
class LockboxConfig:
    """An axis-aligned box; its front face (the -y side) faces the mouse. `mechanisms` in the
    order of `MECHANISMS`."""

    center: tuple[float, float] = (150.0, 280.0)
    size: tuple[float, float, float] = (180.0, 40.0, 45.0)
    mechanisms: tuple[MechanismConfig, ...] = _DEFAULT_MECHANISMS

    def __post_init__(self) -> None:
        _check(min(self.size) > 0, "lockbox.size", "must be > 0", self.size)
        _check(len(self.mechanisms) == len(MECHANISMS), "lockbox.mechanisms",
               f"need the mechanisms {list(MECHANISMS)}", self.mechanisms)  # fmt: skip
        for name, m in zip(MECHANISMS, self.mechanisms):
            key = f"lockbox.mechanisms.{name}.position"
            _check(abs(m.position[0]) <= self.size[0] / 2, key, "x offset must be on the box face",
                   m.position)  # fmt: skip
            _check(m.position[1] >= 0 and m.position[2] >= 0, key,
                   "out-of-face offset and height must be >= 0", m.position)  # fmt: skip


@dataclass(frozen=True)
class DeformConfig:
    """Extra deformations (``sim=mouse_b``); every amount 0 (the default) switches one off.

    spine_*: the parts behind model Y = spine_pivot (mm, before `SimConfig.body_scale`) bend
    about the vertical through it, with a weight rising linearly to 1 at the rearmost part; the
    bend angle is spine_bend times the heading change over the last spine_lag s (the rear follows
    the curved path), at most spine_max deg, plus random bending of std spine_wiggle deg.
    head_*: random head yaw, pitch, roll (std, deg) about the ears' midpoint and a random head
    translation (neck, std mm per model axis), added in every behavior, correlation time
    head_tau s; jitter: every part's own small smooth motion (skin, fur; std mm per axis,
    correlation time jitter_tau s), the paws excepted; paw_tau s: correlation time of the reared
    front paws' motion (`RearConfig.paw_motion`).
    The random motions are smooth Ornstein-Uhlenbeck noise, Gaussian-smoothed over a fifth of
    their correlation time.
    """

    spine_bend: float = 0.0
    spine_lag: float = 0.3
    spine_max: float = 40.0
    spine_pivot: float = 20.0
    spine_wiggle: float = 0.0
    spine_tau: float = 0.6
    head_yaw: float = 0.0
    head_pitch: float = 0.0
    head_roll: float = 0.0
    head_shift: float = 0.0
    head_tau: float = 0.4
    jitter: float = 0.0
    jitter_tau: float = 0.2
    paw_tau: float = 0.25

    def __post_init__(self) -> None:
        _at_least(self, "deform", 0, "spine_bend", "spine_max", "spine_wiggle", "head_yaw",
                  "head_pitch", "head_roll", "head_shift", "jitter")  # fmt: skip
        _check(self.spine_max < 90, "deform.spine_max", "must be < 90", self.spine_max)
        _positive(self, "deform", "spine_lag", "spine_tau", "head_tau", "jitter_tau", "paw_tau")


@dataclass(frozen=True)
class MissingConfig:
    dropout: float = 0.05
    occlusion_rate: float = 0.05
    occlusion_duration: tuple[float, float] = (0.2, 1.5)

    def __post_init__(self) -> None:
        _check(0 <= self.dropout < 1, "missing.dropout", "must be in [0, 1)", self.dropout)
        _at_least(self, "missing", 0, "occlusion_rate")
        _interval(self.occlusion_duration, "missing.occlusion_duration", 0.0)


@dataclass(frozen=True)
class SimConfig:
    """All simulator settings (see ``conf/sim/default.yaml`` for the meaning of each key)."""

    fps: float = 30.0
    num_frames: int = 9000
    seed: int = 0
    body_scale: float = 1.0  # the body model is scaled by this before simulating (truth included)
    arena: ArenaConfig = field(default_factory=ArenaConfig)
    walk: WalkConfig = field(default_factory=WalkConfig)
    gait: GaitConfig = field(default_factory=GaitConfig)
    head: HeadConfig = field(
        default_factory=lambda: HeadConfig(
            (-15.0, 15.0), (-10.0, 10.0), (-8.0, 8.0), (1.6, 1.2, 2.0)
        )
    )
    scan: ScanConfig = field(
        default_factory=lambda: ScanConfig(
            (-50.0, 50.0), (-15.0, 30.0), (-15.0, 15.0), (1.4, 2.2, 1.8)
        )
    )
    rear: RearConfig = field(default_factory=RearConfig)
    groom: GroomConfig = field(default_factory=GroomConfig)
    reach: ReachConfig = field(default_factory=ReachConfig)
    behaviors: BehaviorConfig = field(default_factory=BehaviorConfig)
    lockbox: LockboxConfig = field(default_factory=LockboxConfig)
    missing: MissingConfig = field(default_factory=MissingConfig)
    deform: DeformConfig = field(default_factory=DeformConfig)

    def __post_init__(self) -> None:
        """The top-level ranges and what spans groups (each group checks its own)."""
        _positive(self, "", "fps", "body_scale")
        _check(self.num_frames >= 1, "num_frames", "must be >= 1", self.num_frames)
        _check(self.seed >= 0, "seed", "must be >= 0", self.seed)
        a, lb = self.arena, self.lockbox
        x0, x1 = lb.center[0] - lb.size[0] / 2, lb.center[0] + lb.size[0] / 2
        y0, y1 = lb.center[1] - lb.size[1] / 2, lb.center[1] + lb.size[1] / 2
        _check(x0 >= 0 and x1 <= a.size[0] and y0 >= 0 and y1 <= a.size[1], "lockbox.center",
               f"the box must lie inside the arena [0, {a.size[0]}] x [0, {a.size[1]}]",
               lb.center)  # fmt: skip

    @classmethod
    def from_config(cls, cfg: Any) -> SimConfig:
        """From a Hydra/OmegaConf node, a mapping (partial is fine) or a SimConfig."""
        if isinstance(cfg, SimConfig):
            return cfg
        if cfg is None:
            return cls()
        data = to_plain(cfg)
        if not isinstance(data, Mapping):
            raise ValueError(f"sim: expected a mapping, got {type(data).__name__}")
        return _build(cls, data, "sim", cls())

    @classmethod
    def from_name(cls, name: str) -> SimConfig:
        """From ``conf/sim/<name>.yaml`` (e.g. ``"mouse_b"``), its ``defaults`` list followed
        as Hydra would (sibling sim configs, then ``_self_``) without Hydra."""
        return cls.from_config(_load_named(str(name), ()))

    def replace(self, **changes: Any) -> SimConfig:
        return dataclasses.replace(self, **changes)


def _merge(base: dict, over: Mapping) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), dict) else v
    return out


def _load_named(name: str, chain: tuple[str, ...]) -> dict:
    import yaml

    path = CONF_DIR / "sim" / f"{name}.yaml"
    if name in chain:
        raise ValueError(f"sim config '{name}': circular defaults {list(chain) + [name]}")
    if not path.is_file():
        known = sorted(p.stem for p in (CONF_DIR / "sim").glob("*.yaml"))
        raise ValueError(f"sim config '{name}' not found in {path.parent} (known: {known})")
    with open(path, encoding="utf-8") as fh:
        data = yaml.safe_load(fh) or {}
    own = {k: v for k, v in data.items() if k != "defaults"}
    order = data.get("defaults") or ["_self_"]
    if "_self_" not in order:
        order = list(order) + ["_self_"]
    merged: dict = {}
    for entry in order:
        if entry == "_self_":
            merged = _merge(merged, own)
        elif isinstance(entry, str):
            merged = _merge(merged, _load_named(entry, chain + (name,)))
        else:
            raise ValueError(f"{path}: unsupported defaults entry {entry!r}")
    return merged


# --------------------------------------------------------------------------------------------


def _num(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{key}: expected a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{key}: must be finite, got {value!r}")
    return v


def _vec(value: Any, n: int, key: str) -> tuple[float, ...]:
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != n:
        raise ValueError(f"{key}: expected a list of {n} numbers, got {value!r}")
    return tuple(_num(v, f"{key}[{i}]") for i, v in enumerate(value))


def _per_name(value: Any, names: tuple[str, ...], key: str, default: tuple) -> dict:
    if not isinstance(value, Mapping):
        raise ValueError(f"{key}: expected a mapping with keys {list(names)}, got {value!r}")
    unknown = sorted(set(value) - set(names))
    if unknown:
        raise ValueError(f"{key}: unknown name(s) {unknown}; expected some of {list(names)}")
    return {n: value.get(n, d) for n, d in zip(names, default)}


def _build(cls: type, data: Mapping, key: str, defaults: Any) -> Any:
    """`cls` from `data`, the keys absent from it as in `defaults` (an instance of `cls`)."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(f"{key}: unknown key(s) {unknown}; known: {sorted(fields)}")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        sub = f"{key}.{name}"
        default = getattr(defaults, name)
        if dataclasses.is_dataclass(default) and not isinstance(default, type):
            if not isinstance(value, Mapping):
                raise ValueError(f"{sub}: expected a mapping, got {value!r}")
            kwargs[name] = _build(type(default), value, sub, default)
        elif cls is BehaviorConfig:
            rows = _per_name(value, BEHAVIORS, sub, default)
            width = 2 if name == "durations" else len(BEHAVIORS)
            kwargs[name] = tuple(_vec(rows[b], width, f"{sub}.{b}") for b in BEHAVIORS)
        elif cls is LockboxConfig and name == "mechanisms":
            mech = _per_name(value, MECHANISMS, sub, default)
            out = []
            for m in MECHANISMS:
                v = mech[m]
                if isinstance(v, MechanismConfig):
                    out.append(v)
                    continue
                if not isinstance(v, Mapping) or set(v) - {"position", "effector"}:
                    raise ValueError(f"{sub}.{m}: expected {{position: [x, out, z], effector}}")
                d = default[MECHANISMS.index(m)]
                out.append(
                    MechanismConfig(
                        _vec(v.get("position", d.position), 3, f"{sub}.{m}.position"),
                        str(v.get("effector", d.effector)),
                    )
                )
            kwargs[name] = tuple(out)
        elif isinstance(default, tuple):
            kwargs[name] = _vec(value, len(default), sub)
        elif isinstance(default, bool):
            kwargs[name] = bool(value)
        elif isinstance(default, int):
            v = _num(value, sub)
            if v != int(v):
                raise ValueError(f"{sub}: expected an integer, got {value!r}")
            kwargs[name] = int(v)
        else:
            kwargs[name] = _num(value, sub)
    return dataclasses.replace(defaults, **kwargs)  # each checks its ranges (sim.<group>.<key>)


def _check(cond: bool, key: str, msg: str, value: Any) -> None:
    if not cond:
        raise ValueError(f"sim.{key}: {msg} (got {value!r})")


def _interval(v: tuple, key: str, lo: float = -math.inf, hi: float = math.inf) -> None:
    _check(len(v) == 2 and v[0] <= v[1], key, "expected [min, max] with min <= max", v)
    _check(lo <= v[0] and v[1] <= hi, key, f"values must lie in [{lo}, {hi}]", v)


def _positive(cfg: Any, group: str, *keys: str) -> None:
    for k in keys:
        _check(getattr(cfg, k) > 0, f"{group}.{k}".lstrip("."), "must be > 0", getattr(cfg, k))


def _at_least(cfg: Any, group: str, lo: float, *keys: str) -> None:
    for k in keys:
        v = getattr(cfg, k)
        _check(v >= lo, f"{group}.{k}", f"must be >= {lo}", v)
