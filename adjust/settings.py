"""Typed settings of the adjust apps: each read and checked once, a bad value a ValueError
naming the setting and what it accepts (`setting`, `check_settings`), required keys
(`required`), the detections' input block (`InputConfig`, `load_kwargs`), adjust-triangulate's
``triangulate`` block (`TriangulateConfig`) and the apps' switches (`EventsConfig`,
`DemoSteps`, `BatchConfig`). A key absent from a config keeps its dataclass default, the one
copy of the YAML's in the code."""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf

from adjust.io import InputError
from adjust.lsq.config import SolverConfig
from deformnet.confutil import checked_fields, given_fields

__all__ = [
    "BatchConfig",
    "DemoSteps",
    "EventsConfig",
    "InputConfig",
    "MAX_THREADS",
    "MIN_SIGMA_PX",
    "SETTINGS",
    "TRIANGULATE_WEIGHTS",
    "TriangulateConfig",
    "check_settings",
    "load_kwargs",
    "required",
    "setting",
]

_KINDS = {"int": "an integer", "float": "a number", "bool": "true or false"}


def setting(
    cfg,
    key: str,
    kind: str,
    default=None,
    *,
    lo: float | None = None,
    hi: float | None = None,
    allow_none: bool = False,
    prefix: str = "",
):
    """The value of config `key` (dotted) as `kind` ("int", "float", "bool"), or a ValueError
    naming the setting and what it accepts (``solver.max_iterations=abc``, ``=2.5``, ``=-3``).
    lo/hi: inclusive bounds. None (or absent) gives `default`; None is allowed only with
    allow_none (or a non-None default). prefix: how the messages name `cfg` (``"input."``)."""
    name = prefix + key
    value = OmegaConf.select(cfg, key, default=None) if isinstance(cfg, DictConfig) else None
    if value is None and not isinstance(cfg, DictConfig) and hasattr(cfg, "get"):
        value = cfg
        for part in key.split("."):
            value = value.get(part) if hasattr(value, "get") else None
    if value is None:
        if default is None and not allow_none:
            raise ValueError(f"{name} must be set ({_KINDS[kind]})")
        return default
    accepts = _KINDS[kind]
    if lo is not None and hi is not None:
        accepts += f" from {lo:g} to {hi:g}"
    elif lo is not None:
        accepts += f" >= {lo:g}"
    elif hi is not None:
        accepts += f" <= {hi:g}"
    bad = ValueError(f"{name}={value!r} is not valid: {name} accepts {accepts}")
    if kind == "bool":
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false"):
            return value.lower() == "true"
        raise bad
    if isinstance(value, bool):
        raise bad
    if kind == "int":
        if isinstance(value, int):
            out = int(value)
        elif isinstance(value, float) and value.is_integer():
            out = int(value)
        elif isinstance(value, str) and value.strip().lstrip("+-").isdigit():
            out = int(value)
        else:
            raise bad
    else:
        try:
            out = float(value)
        except (TypeError, ValueError):
            raise bad from None
        if not math.isfinite(out):
            raise bad
    if (lo is not None and out < lo) or (hi is not None and out > hi):
        raise bad
    return out


#: the most torch threads a setting may ask for (as `deformnet.threads.MAX_THREADS`, which
#: imports torch): more is no speed-up, and torch crashes on absurd counts (threads=100000)
MAX_THREADS = 4 * (os.cpu_count() or 1)
#: the least detector noise a setting may give, px (keypoint detectors are not this exact; a
#: smaller sigma gates every detection out: stochastic.sigma_det_px=1e-9 left part-frames empty)
MIN_SIGMA_PX = 0.01
#: typed settings of the apps, checked before any work: key -> (kind, lo, hi, may be null)
SETTINGS = {
    "threads": ("int", 1, MAX_THREADS, True),
    "progress": ("bool", None, None, False),
    "input.likelihood_threshold": ("float", 0.0, 1.0, False),
    "input.ignore_unknown_parts": ("bool", None, None, False),
    "input.allow_missing_parts": ("bool", None, None, False),
    "triangulate.robust": ("bool", None, None, False),
    "triangulate.max_error_px": ("float", 0.0, None, False),
    "triangulate.min_views": ("int", 2, None, False),
    "consensus.estimate": ("bool", None, None, False),
    "consensus.max_error_px": ("float", MIN_SIGMA_PX, None, False),
    "consensus.gate_sigmas": ("float", 0.1, None, False),
    # deprecated names (adjust.track_config.DEPRECATED), checked as they are given
    "stochastic.estimate": ("bool", None, None, True),
    "stochastic.max_error_px": ("float", MIN_SIGMA_PX, None, True),
    "stochastic.gate_sigmas": ("float", 0.1, None, True),
    "stochastic.sigma_det_px": ("float", MIN_SIGMA_PX, 1000.0, True),
    "deform.max_error_px": ("float", 0.0, None, True),
    "deform.gate_mm": ("float", 0.0, None, False),
    "deform.batch_size": ("int", 1, None, False),
    "deform.max_iterations": ("int", 0, None, True),
    "deform.rigid_first": ("bool", None, None, False),
    "deform.threads": ("int", 1, MAX_THREADS, True),
    "deform.sigma_def_mm": ("float", 0.0, None, True),
    "adapt.threads": ("int", 1, MAX_THREADS, True),
    "adapt.val_fraction": ("float", 0.01, 0.9, False),
    "adapt.augment.mirror": ("float", 0.0, 1.0, False),
    "adapt.augment.reverse": ("float", 0.0, 1.0, False),
    "inferred.below": ("float", 0.0, 1.0, False),
    "inferred.max_sigma_mm": ("float", 0.0, None, True),
    "contact.on_mm": ("float", 0.0, None, False),
    "contact.off_mm": ("float", 0.0, None, False),
}
#: bounds of solver settings beyond ">= 0" (SolverConfig checks the rest): key -> (lo, hi)
_SOLVER_BOUNDS = {
    "grid_size": (3, None),
    "sigma_det_px": (MIN_SIGMA_PX, 1000.0),
    "num_threads": (0, MAX_THREADS),
    "min_weight": (0.0, 1.0),
}


def check_settings(cfg) -> None:
    """Settings of the wrong type or range (``solver.max_iterations=abc``, ``=2.5``, ``=-3``,
    ``threads=abc``, ``threads=100000``, ``stochastic.sigma_det_px=1e-9``) are a ValueError
    naming the setting and what it accepts. Checks the keys of `SETTINGS` (those the app has)
    and every number of the ``solver`` node (typed by `adjust.lsq.SolverConfig`)."""
    if not isinstance(cfg, DictConfig):
        return
    for key, (kind, lo, hi, nullable) in SETTINGS.items():
        if OmegaConf.select(cfg, key, default="<absent>") == "<absent>":
            continue
        if OmegaConf.select(cfg, key, default=None) is None:
            if not nullable:
                raise ValueError(f"{key} must be set ({_KINDS[kind]})")
            continue
        setting(cfg, key, kind, lo=lo, hi=hi)
    solver = cfg.get("solver")
    if solver is None or not hasattr(solver, "keys"):
        return
    for f in dataclasses.fields(SolverConfig):
        if f.name not in solver:
            continue
        kind = {"int": "int", "float": "float", "float | None": "float", "bool": "bool"}.get(
            str(f.type)
        )
        if kind is None:
            continue
        lo, hi = _SOLVER_BOUNDS.get(f.name, (0, None)) if kind != "bool" else (None, None)
        setting(solver, f.name, kind, lo=lo, hi=hi, allow_none=True, prefix="solver.")


def required(cfg: DictConfig, key: str, config_name: str) -> str:
    """The string value of a required config key, or a ValueError saying how to set it."""
    value = OmegaConf.select(cfg, key, throw_on_missing=False)
    if value is None or OmegaConf.is_missing(cfg, key) or str(value) == "":
        raise ValueError(f"set {key}=... (see conf/{config_name}.yaml)")
    return str(value)


#: the input block's typed settings: key -> (kind, lo, hi) (`setting`)
_INPUT_SETTINGS = {
    "likelihood_threshold": ("float", 0.0, 1.0),
    "ignore_unknown_parts": ("bool", None, None),
    "allow_missing_parts": ("bool", None, None),
    "max_frame_offset": ("int", 0, None),
    "max_camera_moves": ("int", 0, None),
    "subframe_sync": ("bool", None, None),
    "rate_check": ("bool", None, None),
    "pixel_check": ("bool", None, None),
    "side_check": ("bool", None, None),
}


@dataclass(frozen=True)
class InputConfig:
    """The detections' ``input`` block (``conf/input/default.yaml`` documents each key; the
    files themselves, ``calibration`` / ``detections`` / ``session``, are read by `required`
    and `adjust.session.with_session`). A missing key keeps its default here, the one copy of
    the YAML's; a bad value is a ValueError naming ``input.<key>``."""

    likelihood_threshold: float = 0.5
    individual: str | None = None
    pattern: str | None = None
    ignore_unknown_parts: bool = False
    allow_missing_parts: bool = False
    camera_check: str = "warn"  # error | warn | off (adjust.camera_check)
    exclude_cameras: tuple[str, ...] = ()
    max_frame_offset: int = 30  # frames a camera may be out of step (adjust.sync; 0: no check)
    max_camera_moves: int = 3  # cameras moved mid-session undone (adjust.moves; 0: no check)
    subframe_sync: bool = True  # a fraction of a frame out of step: interpolated (adjust.subframe)
    rate_check: bool = True  # another frame rate or clock (adjust.rates, adjust.clocks)
    pixel_check: bool = True  # detections on edited videos (adjust.pixels, adjust.lens)
    side_check: bool = True  # a camera with left and right the other way round (adjust.sides)

    @classmethod
    def from_config(cls, node) -> InputConfig:
        """From an app's ``input`` node (OmegaConf or a mapping; None: the defaults)."""
        if isinstance(node, InputConfig):
            return node
        d = checked_fields(cls, node, "input", ignore=("calibration", "detections", "session"))
        d = {k: v for k, v in d.items() if v is not None}  # null: the default
        for key, (kind, lo, hi) in _INPUT_SETTINGS.items():
            if key in d:
                d[key] = setting(d, key, kind, lo=lo, hi=hi, prefix="input.")
        for key in ("individual", "pattern"):
            if key in d:
                d[key] = str(d[key])
        if "camera_check" in d:  # YAML reads a bare `off` as false
            d["camera_check"] = "off" if d["camera_check"] is False else str(d["camera_check"])
        if "exclude_cameras" in d:
            d["exclude_cameras"] = _names(d["exclude_cameras"])
        return cls(**d)

    def load_kwargs(self) -> dict:
        """`adjust.io.load_scene`'s keyword arguments."""
        return {
            "likelihood_threshold": self.likelihood_threshold,
            "individual": self.individual,
            "pattern": self.pattern,
            "ignore_unknown_parts": self.ignore_unknown_parts,
            "allow_missing_parts": self.allow_missing_parts,
        }


def _names(value) -> tuple[str, ...]:
    """``input.exclude_cameras``: a list of camera names, or one name."""
    if isinstance(value, str | int):
        value = [value]
    try:
        return tuple(str(n) for n in value)
    except TypeError:
        raise InputError(
            f"input.exclude_cameras must be a list of camera names, got {value!r}"
        ) from None


def load_kwargs(inp) -> dict:
    """`adjust.io.load_scene` keyword arguments from an app's `input` config node (settings of
    the wrong type or range are a ValueError naming them; `InputConfig`)."""
    return InputConfig.from_config(inp).load_kwargs()


#: ``triangulate.weight``: likelihood (views weighted by the detector's likelihood), uniform
TRIANGULATE_WEIGHTS = ("likelihood", "uniform")


@dataclass(frozen=True)
class TriangulateConfig:
    """adjust-triangulate's ``triangulate`` block (conf/triangulate.yaml documents each key); a
    bad value is a ValueError naming ``triangulate.<key>``, null keeps the default."""

    robust: bool = False
    max_error_px: float = 20.0
    min_views: int = 2
    weight: str = "likelihood"

    @classmethod
    def from_config(cls, node) -> TriangulateConfig:
        """From the ``triangulate`` node (OmegaConf or a mapping; None: the defaults)."""
        d = {k: v for k, v in checked_fields(cls, node, "triangulate").items() if v is not None}
        for key, kind, lo in (("robust", "bool", None), ("max_error_px", "float", 0.0),
                              ("min_views", "int", 2)):  # fmt: skip
            if key in d:
                d[key] = setting(d, key, kind, lo=lo, prefix="triangulate.")
        if "weight" in d:
            d["weight"] = str(d["weight"])
            if d["weight"] not in TRIANGULATE_WEIGHTS:
                raise ValueError(
                    f"triangulate.weight must be one of {TRIANGULATE_WEIGHTS}, got {d['weight']!r}"
                )
        return cls(**d)


@dataclass(frozen=True)
class _Switches:
    """A frozen dataclass of true/false switches (the subclasses' fields)."""

    @classmethod
    def from_config(cls, cfg):
        """From the keys of `cfg` (OmegaConf or a mapping; None: none) that are fields, each
        checked (`setting`: a bad value is a ValueError naming the key); absent or null: the
        dataclass's default, the one copy of the YAML's."""
        given = {k: v for k, v in given_fields(cls, cfg).items() if v is not None}
        return cls(**{k: setting(given, k, "bool") for k in given})


@dataclass(frozen=True)
class EventsConfig(_Switches):
    """adjust-events' switches (conf/events.yaml): ``interpolate``, fill the tracks' NaN gaps
    linearly in time first (a raw triangulation's)."""

    interpolate: bool = False


@dataclass(frozen=True)
class DemoSteps(_Switches):
    """adjust-demo's optional steps (conf/demo.yaml): the behavior classifier, with the lock-box
    context, and the events."""

    behavior: bool = True
    behavior_box: bool = True
    events: bool = True


@dataclass(frozen=True)
class BatchConfig(_Switches):
    """adjust-track's batch switch (conf/track.yaml): ``force``, re-run sessions an earlier
    batch already tracked with the same inputs and settings."""

    force: bool = False
