"""deformnet-simulate through Hydra's compose API."""

from __future__ import annotations

import json
import subprocess
import sys

import hydra
import numpy as np
import pytest

from deformnet.apps.simulate import run
from deformnet.paths import CONF_DIR
from deformnet.sim import load_sim


def _compose(overrides):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose("simulate", overrides=overrides)


def test_run_writes_data_and_figure(tmp_path):
    cfg = _compose(["num_frames=900", "seed=4", f"output.dir={tmp_path}"])
    out = run(cfg)
    npz, png = tmp_path / "sim.npz", tmp_path / "sim.png"
    assert out["data"] == str(npz) and out["figure"] == str(png)
    assert npz.is_file() and png.is_file()
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20000
    data = load_sim(npz)
    assert data.num_frames == 900 and data.seed == 4
    assert out["num_frames"] == 900 and out["seed"] == 4
    assert abs(sum(out["behavior_fractions"].values()) - 1.0) < 1e-9
    assert 0.5 < out["observed_fraction"] <= 1.0
    assert out["mean_speed_mm_s"] > 0
    json.dumps(out)  # plain types only
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp files left


def test_run_applies_sim_overrides(tmp_path):
    cfg = _compose(
        [
            "num_frames=300",
            "sim.arena.size=[400,350]",
            "sim.missing.dropout=0.0",
            "sim.missing.occlusion_rate=0.0",
            f"output.dir={tmp_path}",
        ]
    )
    run(cfg)
    data = load_sim(tmp_path / "sim.npz")
    assert data.arena_size.tolist() == [400.0, 350.0]
    assert data.observed.all()


@pytest.mark.parametrize(
    "override, key",
    [("num_frames=0", "num_frames"), ("seed=-1", "seed"), ("sim.fps=-5", "sim.fps")],
)
def test_run_rejects_bad_values(tmp_path, override, key):
    cfg = _compose([override, f"output.dir={tmp_path}"])
    with pytest.raises(ValueError, match=key):
        run(cfg)


def test_body_config_is_used(tmp_path):
    cfg = _compose(["num_frames=200", "body.parts.nose_tip=[0,40,2.5]", f"output.dir={tmp_path}"])
    run(cfg)
    data = load_sim(tmp_path / "sim.npz")
    np.testing.assert_array_equal(data.model[data.part_index("nose_tip")], [0, 40, 2.5])


@pytest.mark.slow
def test_console_script(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "deformnet.apps.simulate",
            "num_frames=300",
            f"output.dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "sim.npz").is_file() and (tmp_path / "sim.png").is_file()


def test_paper_variant_walks_only(tmp_path):
    cfg = _compose(["sim=paper", "num_frames=1500", f"output.dir={tmp_path}"])
    assert cfg.sim.walk.speed_mean == 60.0  # the rest comes from sim/default
    from deformnet.sim import simulate

    data = simulate(cfg)
    assert np.all(data.labels == 0)
