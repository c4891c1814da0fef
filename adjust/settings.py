"""Typed settings of the adjust apps: each read and checked once, a bad value a ValueError
naming the setting and what it accepts (`setting`, `check_settings`), required keys
(`required`), the detections' input block (`load_kwargs`)."""

from __future__ import annotations

import dataclasses
import math
import os

from omegaconf import DictConfig, OmegaConf

from adjust.lsq.config import SolverConfig

__all__ = [
    "MAX_THREADS",
    "MIN_SIGMA_PX",
    "SETTINGS",
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


def load_kwargs(inp: DictConfig) -> dict:
    """`adjust.io.load_scene` keyword arguments from an app's `input` config node (settings of
    the wrong type or range are a ValueError naming them)."""
    individual = inp.get("individual")
    pattern = inp.get("pattern")
    return {
        "likelihood_threshold": setting(inp, "likelihood_threshold", "float", 0.5, lo=0.0, hi=1.0),
        "individual": None if individual is None else str(individual),
        "pattern": None if pattern is None else str(pattern),
        "ignore_unknown_parts": setting(
            inp, "ignore_unknown_parts", "bool", False, prefix="input."
        ),
        "allow_missing_parts": setting(inp, "allow_missing_parts", "bool", False, prefix="input."),
    }
