"""The settings of deformnet-classify's recipe that the code reads, typed (`ClassifySettings`;
conf/classify.yaml documents each)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any

from deformnet.confutil import given_fields, to_plain

__all__ = ["ClassifySettings", "ContextSettings", "MechanismSettings", "UnfamiliarSettings"]


@dataclass(frozen=True)
class ContextSettings:  # ``context``: the head's temporal context (deformnet.behavior.heads)
    frames: list[int] = field(default_factory=lambda: [15, 33, 91])
    stride: int = 1


@dataclass(frozen=True)
class MechanismSettings:  # ``mechanisms``: the lock-box context (model.mechanism_setup)
    positions: Any = None  # {name: [x, y, z]} | sim | None
    calibration: str | None = None
    parts: list[str] = field(
        default_factory=lambda: ["nose_tip", "left_front_paw", "right_front_paw"]
    )
    scale: float = 50.0


@dataclass(frozen=True)
class UnfamiliarSettings:  # ``unfamiliar``: when a frame, a recording, is unlike the training's
    frame_share: float = 0.05
    warn_share: float = 0.1

    def __post_init__(self) -> None:
        for k in ("frame_share", "warn_share"):
            if not 0.0 <= float(getattr(self, k)) < 1.0:
                raise ValueError(f"unfamiliar.{k} must be in [0, 1), got {getattr(self, k)}")


@dataclass(frozen=True)
class ClassifySettings:
    """An absent key keeps the default here, the YAML's (a test compares them), and so does a
    block (a dataclass field) given as null."""

    mode: str = "train"  # train | predict
    frame_features: bool = True
    measurements: bool = True
    heights_up: Any = None
    body_scale: str = "session"  # session | none (features.BODY_SCALE_MODES)
    antialias: bool = True
    label_segment: int = 1
    head_l2: float = 1.0
    head_max_iter: int = 200
    progress_bar: str = "none"
    context: ContextSettings = field(default_factory=ContextSettings)
    mechanisms: MechanismSettings = field(default_factory=MechanismSettings)
    unfamiliar: UnfamiliarSettings = field(default_factory=UnfamiliarSettings)
    sim: Any = None  # an optional +sim block: the simulator whose lock box positions=sim takes

    @classmethod
    def from_config(cls, cfg) -> ClassifySettings:
        s = {k: to_plain(v) for k, v in given_fields(cls, cfg).items()}
        for f in fields(cls):
            if f.name in s and is_dataclass(f.default_factory):
                s[f.name] = f.default_factory(**given_fields(f.default_factory, s[f.name]))
        return cls(**s)
