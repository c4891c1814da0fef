"""adjust-track's settings: one name per setting, typed (`adjust.track_config`); the old names
still work for one release, with a warning, and two names for one setting with different
values are refused naming both."""

from __future__ import annotations

import logging
from dataclasses import fields

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from adjust.adapt import AdaptConfig
from adjust.deformation_modes import mode_from_config
from adjust.io import InputError
from adjust.lsq.config import SolverConfig
from adjust.settings import BatchConfig, InputConfig
from adjust.track_config import (
    DEPRECATED,
    BodyConfig,
    BodyFitConfig,
    ChunkConfig,
    DeformConfig,
    OutputConfig,
    TrackConfig,
    resolve_deprecated,
)
from deformnet.paths import CONF_DIR


def _cfg(overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose("track", overrides=overrides)


def test_defaults_are_typed_and_each_setting_has_one_name():
    tc = TrackConfig.from_config(resolve_deprecated(_cfg([])))
    assert tc.consensus.estimate and tc.consensus.max_error_px == 20.0
    assert tc.sigma_det_px is None and tc.sigma_def_mm is None  # from the data
    assert tc.solver.sigma_det_px == 2.0 and tc.solver.sigma_def_mm == 3.0  # where nothing does
    assert tc.solver.num_threads == 0 and tc.threads == 1  # the solver runs in `threads`
    assert tc.deform == DeformConfig() and tc.body.shape == "data" and not tc.body.auto
    # the old names are placeholders only: none of them holds a value by default
    for body in ("mouse", "auto"):
        cfg = _cfg([f"body={body}"])
        for old in DEPRECATED:
            assert OmegaConf.select(cfg, old, default=None) in (None, 0), (body, old)


def test_the_blocks_read_typed_and_an_absent_key_keeps_the_dataclass_default():
    """The YAML's defaults are the dataclasses' (the input, adapt, output blocks and
    chunk_frames); a config without a key gets the dataclass's, the one copy in the code."""
    tc = TrackConfig.from_config(resolve_deprecated(_cfg([])))
    assert tc.input == InputConfig() and tc.adapt == AdaptConfig()
    assert tc.chunk == ChunkConfig() and not any(tc.output.subject.values())
    cfg = _cfg([])
    assert BatchConfig.from_config(cfg) == BatchConfig() and cfg.force == BatchConfig().force
    assert tc.output == OutputConfig(subject=tc.output.subject)  # (the YAML lists the fields)
    given = {"input": {"likelihood_threshold": 0.7, "exclude_cameras": "side",
                       "camera_check": False},
             "chunk_frames": 0, "adapt": {"max_steps": 7}}  # fmt: skip
    tc = TrackConfig.from_config(OmegaConf.create(given))
    assert tc.input.likelihood_threshold == 0.7 and tc.input.exclude_cameras == ("side",)
    assert tc.input.camera_check == "off"  # YAML's bare `off` is false
    assert tc.chunk.chunk_frames is None and tc.adapt.max_steps == 7
    assert tc.threads == 1 and tc.progress and tc.deformation is None  # absent: the defaults
    assert tc.input.load_kwargs()["likelihood_threshold"] == 0.7
    with pytest.raises(ValueError, match="input.likelihood_threshold=2"):
        InputConfig.from_config({"likelihood_threshold": 2})
    with pytest.raises(ValueError, match="input.typo"):
        InputConfig.from_config({"typo": 1})


@pytest.mark.parametrize(
    ("old", "new", "value"),
    [
        ("stochastic.sigma_det_px", "solver.sigma_det_px", 1.5),
        ("stochastic.estimate", "consensus.estimate", False),
        ("deform.max_error_px", "consensus.max_error_px", 12.0),
        ("body.sigma_def_mm", "solver.sigma_def_mm", 2.5),
        ("body.min_parts", "body_fit.min_parts", 5),
        ("body.robust", "body_fit.robust", False),
        ("body.refine", "body_fit.refine", "unplaced"),
        ("body.rays_below", "body_fit.rays_below", 7),
        ("body.rays_min_views", "body_fit.rays_min_views", 3),
        ("body.scale_factor", "body_fit.scale_factor", 1.05),
        ("deform.threads", "threads", 2),
        ("adapt.threads", "threads", 2),
        ("solver.num_threads", "threads", 2),
    ],
)
def test_an_old_name_still_works_with_a_warning(old, new, value, caplog):
    with caplog.at_level(logging.WARNING, logger="adjust.track_config"):
        cfg = resolve_deprecated(_cfg([f"{old}={value}"]))
    assert OmegaConf.select(cfg, new) == value
    assert f"{old} is deprecated" in caplog.text and new in caplog.text
    tc = TrackConfig.from_config(cfg)
    if new == "solver.sigma_det_px":
        assert tc.sigma_det_px == value and tc.solver.sigma_det_px == value
    if new == "consensus.estimate":
        assert tc.consensus.estimate is False
    if new.startswith("body_fit."):  # the estimate reads its one name (not its default)
        name = new.split(".")[1]
        assert getattr(tc.body_fit, name) == value != getattr(BodyFitConfig(), name)


def test_the_body_estimate_has_its_own_block_and_the_body_group_describes_a_model():
    """body_fit.* (conf/track.yaml) is read typed, its YAML defaults the dataclass's; the body
    group holds the model (name, parts, aliases, where its shape and size come from) and none of
    the estimate's settings but the deprecated placeholders."""
    cfg = resolve_deprecated(_cfg(["body_fit.refine=none", "body_fit.scale_factor=1.1"]))
    tc = TrackConfig.from_config(cfg)
    assert tc.body_fit == BodyFitConfig(refine="none", scale_factor=1.1)
    assert TrackConfig.from_config(_cfg([])).body_fit == BodyFitConfig()  # YAML == dataclass
    for body in ("mouse", "auto"):
        node = OmegaConf.to_container(_cfg([f"body={body}"]).body)
        given = {k for k, v in node.items() if v is not None}
        model = {f.name for f in fields(BodyConfig)} | {"parts", "aliases"}
        assert given <= model, (body, given - model)
        assert not given & {f.name for f in fields(BodyFitConfig)}
    assert TrackConfig.from_config(_cfg(["body=auto"])).body == BodyConfig(auto=True)
    with pytest.raises(ValueError, match=r"unknown body_fit settings \['body_fit.typo'\]"):
        BodyFitConfig.from_config({"typo": 1})
    with pytest.raises(ValueError, match="body_fit.refine must be views, unplaced or none"):
        TrackConfig.from_config(_cfg(["body_fit.refine=all"]))


@pytest.mark.parametrize(
    ("old", "new"),
    [
        ("body.refine=none", "body_fit.refine=unplaced"),
        ("body.scale_factor=0.95", "body_fit.scale_factor=1.05"),
        ("deform.max_error_px=12", "consensus.max_error_px=15"),
    ],
)
def test_an_old_and_a_new_name_with_two_values_are_refused(old, new):
    with pytest.raises(ValueError, match=f"{old} and {new} are one setting now") as err:
        resolve_deprecated(_cfg([old, new]))
    assert "\n" not in str(err.value)
    # the same value under both names is one setting given twice: accepted
    key, value = old.split("=")
    cfg = resolve_deprecated(_cfg([old, f"{new.split('=')[0]}={value}"]))
    assert str(OmegaConf.select(cfg, new.split("=")[0])) == value
    assert OmegaConf.select(cfg, key) is None


def test_auto_is_the_data_and_two_names_with_two_values_are_refused(caplog):
    cfg = resolve_deprecated(_cfg(["body.sigma_def_mm=auto"]))
    assert TrackConfig.from_config(cfg).sigma_def_mm is None
    with pytest.raises(ValueError, match="deform.threads=2 and adapt.threads=3 are both threads"):
        resolve_deprecated(_cfg(["deform.threads=2", "adapt.threads=3"]))


def test_unknown_and_bad_settings_name_themselves():
    with pytest.raises(ValueError, match=r"unknown deform settings \['deform.gate'\]"):
        DeformConfig.from_config({"gate": 3})
    with pytest.raises(ValueError, match="deform.measured must be"):
        DeformConfig(measured="best")
    with pytest.raises(ValueError, match="body.shape must be one of data, table"):
        TrackConfig.from_config(_cfg(["body.shape=blob"]))


def test_the_rigid_start_kernel_is_checked_and_the_rigid_mode_keeps_the_solvers():
    """``deform.rigid_robust`` names a kernel (or null); the deformable modes start from a
    rigid adjustment with it, ``deformation=rigid`` (whose rigid adjustment is the result)
    keeps ``solver.robust``."""
    with pytest.raises(InputError, match="deform.rigid_robust must be null or one of"):
        DeformConfig(rigid_robust="tukey")
    solver = SolverConfig(robust="cauchy")
    interp, rigid = mode_from_config("interp"), mode_from_config("rigid")
    assert interp.start_cfg(solver, DeformConfig()).robust == "none"
    assert interp.start_cfg(solver, DeformConfig(rigid_robust=None)).robust == "cauchy"
    assert rigid.start_cfg(solver, DeformConfig()).robust == "cauchy"
