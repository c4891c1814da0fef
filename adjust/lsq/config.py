"""Solver configuration: a frozen dataclass buildable from a Hydra/OmegaConf node or a dict.

Every field is documented in ``conf/solver/default.yaml``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import torch

from adjust.lsq.robust import KERNELS

_CONSTRAINTS = ("spline", "grid", "none")
_KERNELS = tuple(KERNELS)
_INITS = ("fit", "kalman")
_DTYPES = {"float64": torch.float64, "float32": torch.float32}


@dataclass(frozen=True)
class SolverConfig:
    """Settings of the pose-track adjustment (units: px, mm, radians, frames)."""

    constraint: str = "grid"  # motion-track constraint form: spline | grid | none
    track_weight: float = 1.0  # multiplier of the track constraint's weight (1 = its sigma below)
    track_sigma_mm: float = 0.2  # std of the track residual (deviation from the cubic), mm
    rotation_scale_mm: float | None = None  # spline form: mm per rad (None: body's rms radius)
    grid_size: int = 3  # grid form: points per axis (>= 3)
    sigma_det_px: float = 2.0  # detector accuracy, px
    sigma_def_mm: float = 3.0  # body deformation not explained by the model, mm (0: no mixture)
    mixture_prior: float = 0.7  # initial share of detections in the narrow (detector) Gaussian
    robust: str = "cauchy"  # robust kernel against mis-detections: none | huber | cauchy
    robust_scale: float = 3.0  # kernel scale on the whitened residual norm
    min_weight: float = 0.0  # detections with weight (e.g. DLC likelihood) <= this are ignored
    max_iterations: int = 30
    min_iterations: int = 2
    ftol: float = 1e-7  # stop when the relative cost decrease of an accepted step is below
    xtol: float = 1e-10  # ... or the step is below this (relative to pose scale)
    lm_lambda: float = 1e-6  # initial Levenberg-Marquardt damping (relative to diag)
    lm_up: float = 10.0
    lm_down: float = 0.3
    init: str = "fit"  # initialisation: fit (Kabsch/PnP + interpolation) | kalman (CV + RTS)
    kalman_accel_mm: float = 50.0  # kalman init: white-acceleration std per frame, mm
    kalman_accel_rad: float = 0.2  # kalman init: white-acceleration std per frame, rad
    chunk_size: int = 10000  # frames per chunk (0: never chunk)
    overlap: int = 64  # frames of overlap on each side of a chunk
    fuse_iterations: int = 1  # Gauss-Newton steps of the per-part fusion
    ridge: float = 1e-9  # relative ridge keeping the normal matrix definite
    dtol: float = 1e-2  # ... or by less than this per frame (and < 1e-3 relative)
    wtol: float = 1e-4  # ... or the cost changes by less than this between iterations (IRLS)
    num_threads: int = 1  # torch threads while solving (0: leave torch's setting)
    dtype: str = "float64"

    def __post_init__(self) -> None:
        if self.constraint not in _CONSTRAINTS:
            raise ValueError(
                f"solver.constraint must be one of {_CONSTRAINTS}, got {self.constraint!r}"
            )
        if self.robust not in _KERNELS:
            raise ValueError(f"solver.robust must be one of {_KERNELS}, got {self.robust!r}")
        if self.init not in _INITS:
            raise ValueError(f"solver.init must be one of {_INITS}, got {self.init!r}")
        if self.dtype not in _DTYPES:
            raise ValueError(f"solver.dtype must be one of {tuple(_DTYPES)}, got {self.dtype!r}")
        if self.grid_size < 3:
            raise ValueError(f"solver.grid_size must be >= 3, got {self.grid_size}")
        for key in ("track_sigma_mm", "sigma_det_px", "robust_scale", "lm_up"):
            if not getattr(self, key) > 0:
                raise ValueError(f"solver.{key} must be > 0, got {getattr(self, key)}")
        for key in ("track_weight", "sigma_def_mm", "ridge", "lm_lambda"):
            if not getattr(self, key) >= 0:
                raise ValueError(f"solver.{key} must be >= 0, got {getattr(self, key)}")
        if not 0 < self.mixture_prior < 1:
            raise ValueError(f"solver.mixture_prior must be in (0, 1), got {self.mixture_prior}")
        if self.chunk_size and self.chunk_size < 5:
            raise ValueError(f"solver.chunk_size must be 0 or >= 5, got {self.chunk_size}")
        if self.overlap < 0:
            raise ValueError(f"solver.overlap must be >= 0, got {self.overlap}")

    @property
    def torch_dtype(self) -> torch.dtype:
        return _DTYPES[self.dtype]

    @classmethod
    def from_config(cls, cfg: Mapping | None = None, **overrides) -> SolverConfig:
        """From a Hydra/OmegaConf node or a mapping (unknown keys raise, naming them)."""
        if cfg is None:
            data: dict = {}
        else:
            try:
                from omegaconf import OmegaConf

                if OmegaConf.is_config(cfg):
                    cfg = OmegaConf.to_container(cfg, resolve=True)
            except ImportError:  # pragma: no cover - omegaconf ships with hydra-core
                pass
            data = dict(cfg)
        data.pop("_target_", None)
        data.update(overrides)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown solver settings {unknown}; known: {sorted(known)}")
        return cls(**data)

    def replace(self, **changes) -> SolverConfig:
        return dataclasses.replace(self, **changes)
