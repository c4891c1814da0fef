"""adjust-track's settings, typed: one name per setting, each read once.

- `ConsensusConfig` (``consensus:``): the consensus triangulation, the session's 3D
  observations and detector noise (`adjust.estimate.consensus`); its ``max_error_px`` is also
  the robust triangulation's of a body estimated without them and of a net's inputs.
- `DeformConfig` (``deform:``): the deformation modes' settings (`adjust.deformation_modes`).
- `BodyConfig` (the ``body`` group: which body model and where its shape and size come from;
  its parts and aliases are `deformnet.body.BodyModel.from_config`'s).
- `BodyFitConfig` (``body_fit:``): how a body's shape is estimated from the data
  (`adjust.body_fit`).
- `ChunkConfig` (``chunk_frames``): a long session in chunks (`adjust.chunks`).
- `TrackConfig`: the above, the solver's (`adjust.lsq.SolverConfig`, ``solver.sigma_det_px``
  and ``solver.sigma_def_mm`` null: from the data), the ``input`` block
  (`adjust.settings.InputConfig`), the ``adapt`` block (`adjust.adapt.AdaptConfig`), the
  ``output`` block and ``threads`` (the one thread setting: torch's threads for the whole run,
  the solver's and the net's included). A key absent from the config keeps its dataclass
  default: the code holds one copy of each YAML default, never a second in a
  ``.get(key, default)``.

Deprecated names (`DEPRECATED`, kept for one release): a value given under an old name is used
for its new key, with a logged warning (`resolve_deprecated`); given under both names with
different values (the new one not at its default), a ValueError names both.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from adjust.adapt import AdaptConfig
from adjust.estimate import GATE_SIGMAS, MAX_ERROR_PX, RAYS_MIN_VIEWS
from adjust.io import InputError
from adjust.lsq.config import SolverConfig
from adjust.lsq.robust import KERNELS
from adjust.settings import InputConfig
from deformnet.confutil import checked_fields, to_plain

log = logging.getLogger(__name__)

__all__ = [
    "DEPRECATED",
    "DEFAULT_CHUNK_FRAMES",
    "BodyConfig",
    "BodyFitConfig",
    "ChunkConfig",
    "ConsensusConfig",
    "DeformConfig",
    "OutputConfig",
    "TrackConfig",
    "resolve_deprecated",
]

#: old name -> the one name it became (adjust-track; a value under the old name still works for
#: one release, with a warning)
DEPRECATED = {
    "stochastic.estimate": "consensus.estimate",
    "stochastic.max_error_px": "consensus.max_error_px",
    "stochastic.gate_sigmas": "consensus.gate_sigmas",
    "stochastic.sigma_det_px": "solver.sigma_det_px",
    "deform.max_error_px": "consensus.max_error_px",
    "body.max_error_px": "consensus.max_error_px",
    "deform.sigma_def_mm": "solver.sigma_def_mm",
    "body.sigma_def_mm": "solver.sigma_def_mm",
    "body.min_parts": "body_fit.min_parts",
    "body.robust": "body_fit.robust",
    "body.refine": "body_fit.refine",
    "body.rays_below": "body_fit.rays_below",
    "body.rays_min_views": "body_fit.rays_min_views",
    "body.scale_factor": "body_fit.scale_factor",
    "deform.threads": "threads",
    "adapt.threads": "threads",
    "solver.num_threads": "threads",
}
#: an old name's value that means "not given" (solver.num_threads: 0, leave torch's setting)
_UNSET = {"solver.num_threads": (None, 0)}


def resolve_deprecated(cfg: DictConfig) -> DictConfig:
    """`cfg` with every value given under a deprecated name (`DEPRECATED`) moved to its new
    key (a copy; a warning per name). ``body.sigma_def_mm=auto`` is ``solver.sigma_def_mm``'s
    null (from the data). Two old names for one key with different values, or an old and a new
    name with different values where the new one is not its default: a ValueError."""
    if not isinstance(cfg, DictConfig):
        return cfg
    cfg = cfg.copy()
    given: dict[str, tuple[str, Any]] = {}
    for old, new in DEPRECATED.items():
        value = OmegaConf.select(cfg, old, default=None)
        if value in _UNSET.get(old, (None,)):
            continue
        if old == "body.sigma_def_mm" and str(value).lower() == "auto":
            value = None
        if new in given and given[new][1] != value:
            raise ValueError(
                f"{given[new][0]}={given[new][1]} and {old}={value} are both {new} now: give "
                f"{new}=... once"
            )
        current = OmegaConf.select(cfg, new, default=None)
        if new not in given and current != value and current != _default(new):
            raise ValueError(
                f"{old}={value} and {new}={current} are one setting now: give {new}=... only"
            )
        given[new] = (old, value)
        log.warning("%s is deprecated (it goes in the next release): use %s=%s", old, new, value)
        with open_dict(cfg):
            OmegaConf.update(cfg, old, _UNSET.get(old, (None,))[-1], force_add=True)
            OmegaConf.update(cfg, new, value, force_add=True)
    return cfg


def _default(key: str) -> Any:
    """A deprecated name's new key's default (its dataclass's; the solver's sigmas: null)."""
    block, _, name = key.rpartition(".")
    cls = {"": TrackConfig, "consensus": ConsensusConfig, "body_fit": BodyFitConfig}.get(block)
    default = {f.name: f.default for f in fields(cls)}.get(name) if cls else None
    return None if default is MISSING else default


def _typed(cls, node: Mapping | None, prefix: str, ignore: tuple[str, ...] = ()):
    """`cls` from a config node: unknown keys (but `ignore`) a ValueError naming them."""
    return cls(**checked_fields(cls, node, prefix, ignore))


@dataclass(frozen=True)
class ConsensusConfig:
    """``consensus:``: the session's 3D observations from a consensus of its cameras."""

    estimate: bool = True  # false: no 3D observations (rigid or a checkpoint only)
    max_error_px: float = MAX_ERROR_PX  # robust triangulation: drop the worst view above this
    gate_sigmas: float = GATE_SIGMAS  # a triangulated point is a 3D observation within this x noise

    @classmethod
    def from_config(cls, node) -> ConsensusConfig:
        return _typed(cls, node, "consensus")


#: ``deform.measured``: a measured part-frame's prior in the net modes
MEASURED = ("cv", "interp", "rigid", "net")
JACOBIANS = ("frozen", "forward", "central")
#: ``deform.anchors``: how interp's second pass reads a part-frame one camera saw
ANCHORS = ("fused", "rays")


@dataclass(frozen=True)
class DeformConfig:
    """``deform:``: how the deformation modes run (conf/track.yaml documents each key)."""

    gate_mm: float = 30.0
    batch_size: int = 4096
    jacobian: str = "frozen"
    step: int | None = None
    far_steps: Any = "auto"
    refresh: int = 2
    beyond_window: str = "anchored"
    net_anchors: bool = True
    measured: str = "cv"
    rigid_first: bool = True
    rigid_robust: str | None = "none"
    max_iterations: int | None = 10
    require_better: str = "auto"
    single_views: bool = True
    anchors: str = "rays"
    ray_sd_factor: float = 6.0
    ray_disagreement: float = 0.5
    ray_outliers: bool = True
    world_prior: bool = True
    gate_pairs: bool = True

    def __post_init__(self) -> None:
        if self.measured not in MEASURED:
            raise ValueError(
                f"deform.measured must be cv, interp, rigid or net, got {self.measured!r}"
            )
        if self.anchors not in ANCHORS:
            raise InputError(
                f"deform.anchors must be one of {', '.join(ANCHORS)}, got {self.anchors!r}"
            )
        if self.rigid_robust is not None and self.rigid_robust not in KERNELS:
            raise InputError(
                f"deform.rigid_robust must be null or one of {', '.join(KERNELS)}, "
                f"got {self.rigid_robust!r}"
            )
        if not float(self.ray_sd_factor) >= 1.0:
            raise InputError(f"deform.ray_sd_factor must be >= 1, got {self.ray_sd_factor}")
        if not float(self.ray_disagreement) >= 0.0:
            raise InputError(f"deform.ray_disagreement must be >= 0, got {self.ray_disagreement}")
        if self.step is not None and int(self.step) < 1:
            raise InputError(f"deform.step must be an integer >= 1, got {self.step}")

    @classmethod
    def from_config(cls, node) -> DeformConfig:
        return _typed(cls, node, "deform", ignore=("threads", "max_error_px", "sigma_def_mm"))


BODY_SHAPES = ("data", "table")
REFINE = ("views", "unplaced", "none")


#: the deprecated names' placeholders in the ``body`` group (`DEPRECATED`: conf/body/auto.yaml)
_BODY_DEPRECATED = tuple(old.split(".")[1] for old in DEPRECATED if old.startswith("body."))


@dataclass(frozen=True)
class BodyConfig:
    """The ``body`` group's settings adjust-track reads (``conf/body/``): which model, and
    where its shape and size come from; its parts and aliases are
    `deformnet.body.BodyModel.from_config`'s, the estimate's settings `BodyFitConfig`'s."""

    name: str = "auto"
    auto: bool = False  # the body estimated from the data (body=auto)
    shape: str = "table"  # data: estimated, moved into the named model's frame | table
    scale: Any = "auto"  # shape=table: auto (fitted to the data) | a number
    other_parts: str = "error"  # files with parts the model lacks: auto | error

    def __post_init__(self) -> None:
        shape = str(self.shape).lower()
        if shape not in BODY_SHAPES:
            raise InputError(
                f"body.shape must be one of {', '.join(BODY_SHAPES)}, got {self.shape!r}"
            )
        object.__setattr__(self, "shape", shape)

    @classmethod
    def from_config(cls, node) -> BodyConfig:
        return _typed(cls, node, "body", ignore=("parts", "aliases", "points", *_BODY_DEPRECATED))


@dataclass(frozen=True)
class BodyFitConfig:
    """``body_fit:``: how a body's shape is estimated from the data (``body=auto``,
    ``body.shape=data``; `adjust.body_fit`; conf/track.yaml documents each key)."""

    min_parts: int | None = None  # frames a shape is estimated from: >= this many parts
    robust: bool = True  # robust triangulation of a shape estimated without 3D observations
    refine: str = "views"  # the structure step: views | unplaced | none
    rays_below: int = 20
    rays_min_views: int = RAYS_MIN_VIEWS
    scale_factor: Any = 1.0  # a multiplier on the size (> 0)

    def __post_init__(self) -> None:
        if str(self.refine).lower() not in REFINE:
            raise ValueError(
                f"body_fit.refine must be views, unplaced or none, got {self.refine!r}"
            )
        object.__setattr__(self, "refine", str(self.refine).lower())

    @classmethod
    def from_config(cls, node) -> BodyFitConfig:
        return _typed(cls, node, "body_fit")


@dataclass(frozen=True)
class OutputConfig:
    """``output:``: the run folder (``dir``, read by `deformnet.paths.output_dir`) and the NWB
    file written beside points3d.csv (conf/track.yaml documents each key)."""

    dir: str | None = None
    nwb: bool = False  # also OUT/tracks.nwb (adjust.export.write_nwb)
    fps: float | None = None  # Hz; None: the calibration's [metadata] fps
    session_start_time: str | None = None  # ISO 8601; None: the calibration's
    subject: dict | None = None  # NWB subject fields (adjust.nwb_metadata.SUBJECT_KEYS)

    @classmethod
    def from_config(cls, node) -> OutputConfig:
        return _typed(cls, node, "output")


#: ``chunk_frames``' default (conf/track.yaml)
DEFAULT_CHUNK_FRAMES = 50_000
#: the least frames a chunk may have: twice the least overlap read on either side of it
MIN_CHUNK_FRAMES = 128


@dataclass(frozen=True)
class ChunkConfig:
    """``chunk_frames``: a session longer than this many frames is tracked in chunks of it
    (None or 0: never)."""

    chunk_frames: int | None = DEFAULT_CHUNK_FRAMES

    def __post_init__(self) -> None:
        value = self.chunk_frames
        if value is None:
            return
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(
                f"chunk_frames must be a whole number of frames >= 0 (0 or null: never chunk), "
                f"got {value!r}"
            )
        if 0 < value < MIN_CHUNK_FRAMES:
            raise ValueError(f"chunk_frames must be 0 or at least {MIN_CHUNK_FRAMES}, got {value}")
        object.__setattr__(self, "chunk_frames", int(value) or None)

    @classmethod
    def from_config(cls, cfg) -> ChunkConfig:
        """From adjust-track's config (or a mapping): its ``chunk_frames``."""
        return cls(**_given(cfg, ("chunk_frames",)))


def _given(cfg, keys: tuple[str, ...]) -> dict:
    """The top-level `keys` that `cfg` (an OmegaConf node or a mapping) holds: those absent
    keep their dataclass defaults."""
    return {k: cfg[k] for k in keys if k in cfg}


@dataclass(frozen=True)
class TrackConfig:
    """adjust-track's settings the library reads (the ``input`` block is the apps' own,
    `adjust.settings`)."""

    deformation: str | None
    body: BodyConfig
    consensus: ConsensusConfig
    deform: DeformConfig
    solver: SolverConfig
    #: solver.sigma_det_px: None = estimated by the consensus (2 px where nothing estimates it)
    sigma_det_px: float | None
    #: solver.sigma_def_mm: None = the data's rms deviation from the rigid model where the
    #: body's shape is estimated, else the solver's default (3 mm)
    sigma_def_mm: float | None
    progress: bool = True
    threads: int | None = 1
    output: OutputConfig = field(default_factory=OutputConfig)
    input: InputConfig = field(default_factory=InputConfig)
    adapt: AdaptConfig = field(default_factory=AdaptConfig)
    chunk: ChunkConfig = field(default_factory=ChunkConfig)
    body_fit: BodyFitConfig = field(default_factory=BodyFitConfig)

    @classmethod
    def from_config(cls, cfg: DictConfig) -> TrackConfig:
        """From adjust-track's composed config (after `resolve_deprecated`)."""
        blocks = {k: cfg[k] for k in ("solver", "body", "body_fit", "consensus", "deform",
                                      "output", "input", "adapt") if k in cfg}  # fmt: skip
        solver = blocks.get("solver")  # (plain dict: the blocks given)
        solver = {} if solver is None else OmegaConf.to_container(solver, resolve=True)
        sigma_det = solver.pop("sigma_det_px", None)
        sigma_def = solver.pop("sigma_def_mm", None)
        solver.pop("num_threads", None)  # the one thread setting: `threads`
        defaults = {}
        if sigma_det is not None:
            defaults["sigma_det_px"] = float(sigma_det)
        if sigma_def is not None:
            defaults["sigma_def_mm"] = float(sigma_def)
        top = _given(cfg, ("deformation", "progress", "threads"))
        if top.get("deformation") is not None:
            top["deformation"] = str(top["deformation"])
        if "progress" in top:
            top["progress"] = bool(top["progress"])
        return cls(
            deformation=top.pop("deformation", None),
            body=BodyConfig.from_config(blocks.get("body")),
            body_fit=BodyFitConfig.from_config(blocks.get("body_fit")),
            consensus=ConsensusConfig.from_config(blocks.get("consensus")),
            deform=DeformConfig.from_config(blocks.get("deform")),
            # num_threads 0: the solver runs in the app's threads (`threads`)
            solver=SolverConfig.from_config(solver, num_threads=0, **defaults).resolved(),
            sigma_det_px=None if sigma_det is None else float(sigma_det),
            sigma_def_mm=None if sigma_def is None else float(sigma_def),
            output=OutputConfig.from_config(blocks.get("output")),
            input=InputConfig.from_config(blocks.get("input")),
            adapt=AdaptConfig.from_any(to_plain(blocks.get("adapt"))),
            chunk=ChunkConfig.from_config(cfg),
            **top,
        )
