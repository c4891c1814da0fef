"""The solver's config groups (conf/solver/<group>/) mirror its schemas (adjust/lsq/config.py):
each option file holds only its schema's settings, every option composes into a valid
SolverConfig, and the flat overrides (``solver.constraint=spline``) select what the group
choices (``solver/constraint=spline``) do."""

from __future__ import annotations

import dataclasses

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from adjust.lsq.config import (
    PARTS,
    ConstraintConfig,
    InitConfig,
    LMConfig,
    SolverConfig,
    StochasticConfig,
)
from deformnet.paths import CONF_DIR

GROUPS = {
    "constraint": ConstraintConfig,
    "stochastic": StochasticConfig,
    "lm": LMConfig,
    "init": InitConfig,
}


def _solver(overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose("track", overrides=overrides).solver


def _names(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def test_groups_are_the_schemas_parts():
    assert {GROUPS[g] for g in GROUPS} == set(PARTS)
    folders = {p.name for p in (CONF_DIR / "solver").iterdir() if p.is_dir()}
    assert folders == set(GROUPS)
    own = _names(SolverConfig) - set().union(*(_names(c) for c in PARTS))
    raw = OmegaConf.load(CONF_DIR / "solver" / "default.yaml")
    assert set(raw) - {"defaults"} == own  # default.yaml: chunking, fusion, threads, dtype


@pytest.mark.parametrize(
    ("group", "option"),
    [(g, p.stem) for g in GROUPS for p in sorted((CONF_DIR / "solver" / g).glob("*.yaml"))],
)
def test_every_option_holds_its_schemas_settings_and_composes(group, option):
    node = OmegaConf.load(CONF_DIR / "solver" / group / f"{option}.yaml")
    assert node and set(node) <= _names(GROUPS[group]), (group, option)
    cfg = SolverConfig.from_config(_solver([f"solver/{group}={option}"]))
    for key, value in node.items():
        assert getattr(cfg, key) == value
    if group in ("constraint", "init"):  # the form is the option's name
        assert getattr(cfg, group) == option


@pytest.mark.parametrize(("group", "option"), [("constraint", "spline"), ("constraint", "none"),
                                               ("init", "kalman")])  # fmt: skip
def test_flat_override_selects_what_the_group_choice_does(group, option):
    flat = SolverConfig.from_config(_solver([f"solver.{group}={option}"]))
    choice = SolverConfig.from_config(_solver([f"solver/{group}={option}"]))
    assert flat == choice


def test_schema_checks_keys_types_and_ranges():
    with pytest.raises(ValueError, match=r"unknown solver settings \['constrant'\]"):
        SolverConfig.from_config({"constrant": "grid"})
    with pytest.raises(ValueError, match=r"^solver.max_iterations=2.5 is not valid"):
        SolverConfig.from_config({"max_iterations": 2.5})
    with pytest.raises(ValueError, match=r"^solver.chunk_size='abc' is not valid"):
        SolverConfig.from_config(OmegaConf.create({"chunk_size": "abc"}))
    with pytest.raises(ValueError, match=r"solver.grid_size must be >= 3.*constraint/grid.yaml"):
        SolverConfig.from_config(_solver(["solver.grid_size=2"]))
    with pytest.raises(ValueError, match=r"solver.mixture_prior must be in \(0, 1\)"):
        SolverConfig(mixture_prior=1.0)
    with pytest.raises(ValueError, match=r"solver.robust must be one of"):
        StochasticConfig(robust="tukey")
    assert SolverConfig.from_config({"track_weight": 2}).track_weight == 2.0  # typed: float
    cfg = SolverConfig(max_iterations=7, init="kalman")
    assert cfg.part(LMConfig) == LMConfig(max_iterations=7)
    assert cfg.part(InitConfig).init == "kalman"
