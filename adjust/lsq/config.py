"""Solver configuration: one small frozen dataclass per piece of the solver, as the config groups
in ``conf/solver/`` are one file per piece, and `SolverConfig` their union.

- `ConstraintConfig`: the motion-track constraint (eq. 10),
  ``conf/solver/constraint/{grid,spline,none}.yaml``;
- `StochasticConfig`: detector / deformation Gaussians, robust kernel,
  ``conf/solver/stochastic/default.yaml``;
- `LMConfig`: Levenberg-Marquardt, ``conf/solver/lm/default.yaml``;
- `InitConfig`: initialisation, ``conf/solver/init/{fit,kalman}.yaml``;
- `SolverConfig`: all of the above plus chunking, fusion, threads, dtype,
  ``conf/solver/default.yaml`` (whose defaults list picks one option per group; each option
  file is ``# @package solver``).

The groups' keys land flat in the ``solver`` node (``solver.max_iterations=5``,
``solver.constraint=spline``), so `SolverConfig` inherits the parts' fields and keeps one flat
attribute per setting. `SolverConfig.from_config` merges a node onto
``OmegaConf.structured(SolverConfig)``: OmegaConf checks the keys (unknown ones raise) and the
types (``max_iterations=2.5`` raises); each part's ``__post_init__`` checks its value ranges,
naming the setting (``solver.grid_size``) and its group file.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from adjust.lsq.robust import KERNELS

_CONSTRAINTS = ("spline", "grid", "none")
#: the detector noise (px) and unexplained deformation (mm) where nothing estimates them
SIGMA_DET_PX = 2.0
SIGMA_DEF_MM = 3.0
_KERNELS = tuple(KERNELS)
_INITS = ("fit", "kalman")
_DTYPES = {"float64": torch.float64, "float32": torch.float32}


def _bad(group: str, key: str, rule: str, value) -> ValueError:
    return ValueError(f"solver.{key} must be {rule}, got {value!r} (conf/solver/{group})")


def _positive(cfg, group: str, *keys: str) -> None:
    for key in keys:
        if not getattr(cfg, key) > 0:
            raise _bad(group, key, "> 0", getattr(cfg, key))


def _non_negative(cfg, group: str, *keys: str) -> None:
    for key in keys:
        if not getattr(cfg, key) >= 0:
            raise _bad(group, key, ">= 0", getattr(cfg, key))


@dataclass(frozen=True)
class ConstraintConfig:
    """Motion-track constraint (eq. 10; `adjust.lsq.constraint`), ``conf/solver/constraint/``."""

    constraint: str = "grid"  # motion-track constraint form: spline | grid | none
    track_weight: float = 1.0  # multiplier of the track constraint's weight (1 = its sigma below)
    track_sigma_mm: float = 0.2  # std of the track residual (deviation from the cubic), mm
    rotation_scale_mm: float | None = None  # spline form: mm per rad (None: body's rms radius)
    grid_size: int = 3  # grid form: points per axis (>= 3)

    def __post_init__(self) -> None:
        if self.constraint not in _CONSTRAINTS:
            raise _bad("constraint", "constraint", f"one of {_CONSTRAINTS}", self.constraint)
        if self.grid_size < 3:
            raise _bad("constraint/grid.yaml", "grid_size", ">= 3", self.grid_size)
        _positive(self, "constraint", "track_sigma_mm")
        _non_negative(self, "constraint", "track_weight")
        if self.rotation_scale_mm is not None:
            _non_negative(self, "constraint/spline.yaml", "rotation_scale_mm")


@dataclass(frozen=True)
class StochasticConfig:
    """The stochastic model (`adjust.lsq.robust`), ``conf/solver/stochastic/default.yaml``."""

    # detector accuracy, px (None: from the data, adjust-track's consensus; else, as
    # `SolverConfig.resolved` gives it to the solver, `SIGMA_DET_PX`)
    sigma_det_px: float | None = None
    # body deformation not explained by the model, mm (0: no mixture; None: from the data where
    # adjust-track estimates the body's shape; else `SIGMA_DEF_MM`)
    sigma_def_mm: float | None = None
    mixture_prior: float = 0.7  # initial share of detections in the narrow (detector) Gaussian
    robust: str = "cauchy"  # robust kernel against mis-detections: none | huber | cauchy
    robust_scale: float = 3.0  # kernel scale on the whitened residual norm
    min_weight: float = 0.0  # detections with weight (e.g. DLC likelihood) <= this are ignored

    def __post_init__(self) -> None:
        group = "stochastic/default.yaml"
        if self.robust not in _KERNELS:
            raise _bad(group, "robust", f"one of {_KERNELS}", self.robust)
        _positive(self, group, "robust_scale")
        if self.sigma_det_px is not None:
            _positive(self, group, "sigma_det_px")
        if self.sigma_def_mm is not None:
            _non_negative(self, group, "sigma_def_mm")
        if not 0 < self.mixture_prior < 1:
            raise _bad(group, "mixture_prior", "in (0, 1)", self.mixture_prior)


@dataclass(frozen=True)
class LMConfig:
    """Levenberg-Marquardt (`adjust.lsq.lm`), ``conf/solver/lm/default.yaml``."""

    max_iterations: int = 30
    min_iterations: int = 2
    ftol: float = 1e-7  # stop when the relative cost decrease of an accepted step is below
    dtol: float = 1e-2  # ... or by less than this per frame (and < 1e-3 relative)
    wtol: float = 1e-4  # ... or the cost changes by less than this between iterations (IRLS)
    xtol: float = 1e-10  # ... or the step is below this (relative to pose scale)
    stol: float = 0.05  # at the iteration cap: converged if the last step's rms (mm, rad) < this
    lm_lambda: float = 1e-6  # initial Levenberg-Marquardt damping (relative to diag)
    lm_up: float = 10.0
    lm_down: float = 0.3
    ridge: float = 1e-9  # relative ridge keeping the normal matrix definite

    def __post_init__(self) -> None:
        group = "lm/default.yaml"
        _positive(self, group, "lm_up")
        _non_negative(self, group, "max_iterations", "min_iterations", "ridge", "lm_lambda")


@dataclass(frozen=True)
class InitConfig:
    """Initialisation (`adjust.lsq.init.initial_poses`), ``conf/solver/init/{fit,kalman}.yaml``."""

    init: str = "fit"  # initialisation: fit (Kabsch/PnP + interpolation) | kalman (CV + RTS)
    kalman_accel_mm: float = 50.0  # kalman init: white-acceleration std per frame, mm
    kalman_accel_rad: float = 0.2  # kalman init: white-acceleration std per frame, rad

    def __post_init__(self) -> None:
        if self.init not in _INITS:
            raise _bad("init", "init", f"one of {_INITS}", self.init)
        _non_negative(self, "init/kalman.yaml", "kalman_accel_mm", "kalman_accel_rad")


#: the parts, in the order of their fields in `SolverConfig`
PARTS = (ConstraintConfig, StochasticConfig, LMConfig, InitConfig)


@dataclass(frozen=True)
class SolverConfig(InitConfig, LMConfig, StochasticConfig, ConstraintConfig):
    """Settings of the pose-track adjustment (units: px, mm, radians, frames): the fields of
    `ConstraintConfig`, `StochasticConfig`, `LMConfig` and `InitConfig` (flat, as the ``solver``
    node is), plus these (``conf/solver/default.yaml``)."""

    chunk_size: int = 10000  # frames per chunk (0: never chunk)
    overlap: int = 64  # frames of overlap on each side of a chunk
    fuse_iterations: int = 1  # Gauss-Newton steps of the per-part fusion
    num_threads: int = 0  # torch threads while solving (0: leave the caller's setting)
    dtype: str = "float64"

    def __post_init__(self) -> None:
        for part in PARTS:
            part.__post_init__(self)
        group = "default.yaml"
        if self.dtype not in _DTYPES:
            raise _bad(group, "dtype", f"one of {tuple(_DTYPES)}", self.dtype)
        if self.chunk_size and self.chunk_size < 5:
            raise _bad(group, "chunk_size", "0 or >= 5", self.chunk_size)
        _non_negative(self, group, "overlap", "fuse_iterations", "num_threads")

    @property
    def torch_dtype(self) -> torch.dtype:
        return _DTYPES[self.dtype]

    def part(self, cls: type):
        """This configuration's `cls` part (one of `PARTS`), e.g. ``cfg.part(LMConfig)``."""
        return cls(**{f.name: getattr(self, f.name) for f in dataclasses.fields(cls)})

    @classmethod
    def from_config(cls, cfg: Mapping | None = None, **overrides) -> SolverConfig:
        """From a Hydra/OmegaConf node or a mapping, with `overrides` on top, checked against the
        structured schema ``OmegaConf.structured(SolverConfig)``: unknown keys raise, naming
        them; values of the wrong type raise, naming the setting; then the ranges."""
        from omegaconf import OmegaConf
        from omegaconf.errors import ConfigKeyError, ValidationError

        data = {} if cfg is None else cfg
        if not OmegaConf.is_config(data):
            data = OmegaConf.create(dict(data))
        known = [f.name for f in dataclasses.fields(cls)]
        try:
            merged = OmegaConf.merge(OmegaConf.structured(cls), data, overrides)
        except ConfigKeyError:
            unknown = sorted((set(data) | set(overrides)) - set(known))
            raise ValueError(f"unknown solver settings {unknown}; known: {sorted(known)}") from None
        except ValidationError as exc:
            why = str(exc).splitlines()[0]
            raise ValueError(f"solver.{exc.full_key}={exc.value!r} is not valid: {why}") from None
        return cls(**OmegaConf.to_container(merged))

    def resolved(self) -> SolverConfig:
        """This configuration with a sigma left to the data (None) at `SIGMA_DET_PX` /
        `SIGMA_DEF_MM` (the solver needs numbers; adjust-track fills them from the session
        first)."""
        return self.replace(
            sigma_det_px=SIGMA_DET_PX if self.sigma_det_px is None else self.sigma_det_px,
            sigma_def_mm=SIGMA_DEF_MM if self.sigma_def_mm is None else self.sigma_def_mm,
        )

    def replace(self, **changes) -> SolverConfig:
        return dataclasses.replace(self, **changes)
