"""The settings of deformnet-classify's recipe that the code reads, typed (`ClassifySettings`;
conf/classify.yaml documents each)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, is_dataclass
from typing import Any

from deformnet.confutil import check_fields, checked_fields, given_fields, to_plain

__all__ = [
    "ClassifySettings", "ContextSettings", "DataSettings", "HeadSettings", "MechanismSettings",
    "PseudoLabelSettings", "SequenceSettings", "SmoothingSettings", "UnfamiliarSettings",
]  # fmt: skip


@dataclass(frozen=True)
class ContextSettings:  # ``context``: the head's temporal context (deformnet.behavior.heads)
    frames: list[int] = field(default_factory=lambda: [15, 33, 91])
    stride: int = 1


@dataclass(frozen=True)
class HeadSettings:  # ``head``'s own keys (conf/head/*.yaml; the others: the head's arguments)
    name: str = "linear"  # one of heads.HEADS
    ensemble: int = 1  # > 1: an EnsembleHead of that many heads

    def __post_init__(self) -> None:
        check_fields(self, "head", name=(str, None, "a head's name"),
                     ensemble=(int, lambda v: v >= 1, "an integer >= 1"))  # fmt: skip


@dataclass(frozen=True)
class SmoothingSettings:  # ``smoothing``: of the predicted labels (model.predict_session)
    median: int = 9
    min_bout: int = 5

    def __post_init__(self) -> None:
        off = (int, lambda v: v >= 0, "an integer >= 0 (0: off)")
        check_fields(self, "smoothing", median=off, min_bout=off)


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
        share = (float, lambda v: 0.0 <= v < 1.0, "in [0, 1)")
        check_fields(self, "unfamiliar", frame_share=share, warn_share=share)


@dataclass(frozen=True)
class DataSettings:  # ``data``'s keys with a default (train.py reads the others as given)
    interpolate: bool = False
    val_frames: int | None = 2048  # None: every labelled validation frame
    token_dropout: float = 0.1


@dataclass(frozen=True)
class SequenceSettings:  # ``pseudo_labels.sequence``: the cotrain teacher's sequence encoder
    encoder: str | None = None  # a saved sequence_encoder.pt (None or "": pretrain one)
    steps: int = 1000
    channels: int = 128
    dilations: list[int] = field(default_factory=lambda: [1, 2, 4, 8, 16, 32, 64])
    mask_ratio: float = 0.75
    longest_span: int = 60
    crop: int = 256
    batch: int = 32
    lr: float = 1e-3
    target: str = "frame"  # frame | all
    context: list[int] = field(default_factory=lambda: [15, 33])
    seed: int = 0

    def __post_init__(self) -> None:
        at_least = lambda low: (int, lambda v: v >= low, f"an integer >= {low}")  # noqa: E731
        check_fields(self, "pseudo_labels.sequence", steps=at_least(0), channels=at_least(1),
               longest_span=at_least(4), crop=at_least(16), batch=at_least(1),
               seed=(int, None, "an integer"), lr=(float, lambda v: v > 0, "a number > 0"),
               mask_ratio=(float, lambda v: 0.0 < v < 1.0, "in (0, 1)"),
               target=(str, lambda v: v in ("frame", "all"), "'frame' or 'all'"),
               dilations=(list, lambda v: v and min(v) >= 1,
                          "a non-empty list of integers >= 1"),
               context=(list, lambda v: all(c >= 3 and c % 2 for c in v),
                        "odd frame counts >= 3"))  # fmt: skip


@dataclass(frozen=True)
class PseudoLabelSettings:  # ``pseudo_labels``: the forest head's teacher (behavior.teachers)
    teacher: str = "linear"  # one of TEACHERS
    keep: float = 0.3
    smooth: int = 9
    labelled_weight: float = 5.0
    embedding_keep: float = 0.5
    bins: int = 4
    unlabelled: bool = True
    balanced: bool = False  # true: the self-trained forest's classes weighed alike
    sequence: SequenceSettings = field(default_factory=SequenceSettings)

    TEACHERS = ("none", "linear", "cotrain")

    def __post_init__(self) -> None:
        share, flag = (float, lambda v: 0.0 < v <= 1.0, "in (0, 1]"), (bool, None, "true or false")
        check_fields(self, "pseudo_labels", keep=share, embedding_keep=share,
               teacher=(str, lambda v: v in self.TEACHERS, f"one of {self.TEACHERS}"),
               smooth=(int, lambda v: v >= 1, "an integer >= 1"),
               labelled_weight=(float, lambda v: v > 0, "a number > 0"),
               bins=(int, lambda v: v >= 2, "an integer >= 2"),
               unlabelled=flag, balanced=flag)  # fmt: skip
        if not isinstance(self.sequence, SequenceSettings):  # a block (None: the defaults)
            seq = to_plain(self.sequence) or {}
            if "bins" in seq:
                raise ValueError("pseudo_labels.sequence.bins: unknown (it is pseudo_labels.bins)")
            seq = checked_fields(SequenceSettings, seq, "pseudo_labels.sequence")
            object.__setattr__(self, "sequence", SequenceSettings(**seq))

    def facts(self) -> dict | None:
        """What classifier.pt keeps of how the forest head was taught: None (teacher none), or
        the settings its teacher reads (the sequence block and embedding_keep: cotrain's)."""
        if self.teacher == "none":
            return None
        drop = () if self.teacher == "cotrain" else ("sequence", "embedding_keep")
        return {k: v for k, v in asdict(self).items() if k not in drop}


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
    smoothing: SmoothingSettings = field(default_factory=SmoothingSettings)
    data: DataSettings = field(default_factory=DataSettings)
    pseudo_labels: PseudoLabelSettings = field(default_factory=PseudoLabelSettings)
    sim: Any = None  # an optional +sim block: the simulator whose lock box positions=sim takes

    @classmethod
    def from_config(cls, cfg) -> ClassifySettings:
        s = {k: to_plain(v) for k, v in given_fields(cls, cfg).items()}
        for f in fields(cls):
            if f.name in s and is_dataclass(f.default_factory):
                s[f.name] = f.default_factory(**given_fields(f.default_factory, s[f.name]))
        return cls(**s)
