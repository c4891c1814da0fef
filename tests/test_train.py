"""deformnet-train through the Hydra compose API: fast_dev_run of both nets, a short real run
(checkpoints, metric names, TensorBoard run per net), every config group composes."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import hydra
import pytest
import torch

from deformnet.paths import CONF_DIR
from deformnet.train import DataSettings, TrainSettings, run

torch.set_num_threads(1)

SMALL = {
    "lstm": ["net.hidden=16", "net.embed=16", "net.layers=1"],
    "transformer": ["net.d_model=16", "net.heads=2", "net.layers=1", "net.ff=32", "net.d_part=8"],
}


def _compose(overrides: list[str]):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose("train", overrides=overrides)


def _common(tmp_path: Path, net: str) -> list[str]:
    return [
        f"net={net}",
        *SMALL[net],
        f"output.dir={tmp_path / net}",
        f"logger.save_dir={tmp_path / 'tb'}",
        "progress_bar=none",
        "half_window=4",
        "data.num_frames=200",
        "data.train_sequences=1",
        "data.val_sequences=1",
        "data.batch_size=16",
        "data.val_windows=32",
        "trainer.enable_model_summary=false",
    ]


@pytest.mark.parametrize("net", ["lstm", "transformer"])
def test_fast_dev_run(tmp_path, net):
    cfg = _compose([*_common(tmp_path, net), "trainer.fast_dev_run=true"])
    assert cfg.data.source == "sim"  # the real simulator
    result = run(cfg)
    assert result["net"] == net
    assert Path(result["output_dir"]) == tmp_path / net
    assert (tmp_path / net / "metrics.json").exists()
    assert "train/loss" in result["metrics"]


def test_heading_frame_training_and_its_config(tmp_path):
    """up=[0,0,1]: the model reads the heading frame, a fast_dev_run trains; a fine-tuned net
    keeps its checkpoint's frame (a conflicting up is an error)."""
    from deformnet.train import build_model

    ov = [*_common(tmp_path, "lstm"), "trainer.fast_dev_run=true"]
    cfg = _compose([*ov, "up=[0,0,1]"])
    lit, _, _ = build_model(cfg)
    assert lit.model.up == (0.0, 0.0, 1.0)
    assert "train/loss" in run(cfg)["metrics"]
    lit_body, _, _ = build_model(_compose(ov))
    assert lit_body.model.up is None
    kept, _, _ = build_model(_compose(ov), pretrained=lit.model)
    assert kept.model.up == (0.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="keeps its checkpoint's frame"):
        build_model(cfg, pretrained=lit_body.model)
    with pytest.raises(ValueError, match="up must be"):
        build_model(_compose([*ov, "up=[1,2]"]))


def test_short_run_writes_checkpoints_and_metrics(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from deformnet.body import default_mouse
    from deformnet.deformation import DeformationModel

    cfg = _compose(
        [
            *_common(tmp_path, "lstm"),
            "trainer.max_epochs=2",
            "data.steps_per_epoch=2",
            "trainer.log_every_n_steps=1",
        ]
    )
    result = run(cfg)
    best, last = result["best_checkpoint"], result["last_checkpoint"]
    assert (
        best
        and Path(best).name == "best.ckpt"
        and Path(best).parent == tmp_path / "lstm" / "checkpoints"
    )
    assert last and Path(last).exists()
    parts = default_mouse().parts
    want = {"train/loss", "val/loss", "val/rmse_mm", "val/rmse_mm_rigid", "val/rmse_mm_linear"}
    want |= {"val/rmse_mm_interp"}
    want |= {f"val/rmse_mm/{p}" for p in parts}
    assert want <= set(result["metrics"])
    m = result["metrics"]
    assert 0 < m["val/rmse_mm"] < 1e3 and 0 < m["val/rmse_mm_rigid"] < 1e3
    # one TensorBoard run named after the net, under the configured root, with those scalars
    runs = list((tmp_path / "tb" / "lstm").glob("version_*"))
    assert len(runs) == 1
    ea = EventAccumulator(str(runs[0]))
    ea.Reload()
    assert want <= set(ea.Tags()["scalars"])
    model = DeformationModel.from_checkpoint(best)
    assert model.window == 9 and model.half_window == 4 and model.body.parts == parts
    x = torch.zeros(2, 9, len(parts), 3)
    x[:] = torch.tensor(default_mouse().points, dtype=torch.float32)
    out = model(x, x, torch.ones(2, 9, len(parts), dtype=torch.bool))
    assert out.shape == (2, len(parts), 3) and torch.isfinite(out).all()


@pytest.mark.parametrize(
    "overrides",
    [
        ["trainer=gpu"],
        ["trainer=ddp"],
        ["logger=none"],
        ["experiment=quick"],
        ["experiment=long", "net=transformer"],
        ["trainer.accelerator=auto"],
    ],
)
def test_config_groups_compose(overrides):
    cfg = _compose(overrides)
    assert cfg.net.name in ("lstm", "transformer") and cfg.half_window >= 1
    if overrides == ["trainer=ddp"]:
        assert cfg.trainer.strategy == "ddp"
    if overrides == ["experiment=quick"]:
        assert cfg.data.source == "toy"


def test_the_settings_run_reads_are_typed_with_the_yamls_defaults():
    """conf/train.yaml's and conf/data/*.yaml's defaults are the dataclasses'; an absent key
    keeps them (the one copy in the code); given ones are read."""
    assert TrainSettings.from_config(_compose([])) == TrainSettings()
    sim = DataSettings.from_config(_compose([]))
    assert (sim.source, sim.step, sim.sessions) == ("sim", 1, ())
    ses = DataSettings.from_config(_compose(["data=sessions"]))
    d = DataSettings()
    assert (ses.source, ses.val_fraction, ses.block_frames) == ("sessions", d.val_fraction,
                                                                d.block_frames)  # fmt: skip
    assert ses.builder["_target_"] == "adjust.tokens.build_session_tokens"
    given = _compose(["pretrained=none", "threads=2", "data.step=3", "progress_bar=tqdm"])
    ts = TrainSettings.from_config(given)
    assert ts.pretrained is None and ts.threads == 2 and ts.progress_bar == "tqdm"
    assert DataSettings.from_config(given).step == 3
    assert TrainSettings.from_config({}) == TrainSettings()  # nothing given: the defaults


@pytest.mark.slow
def test_multirun_trains_both_nets(tmp_path):
    cmd = [
        sys.executable,
        "-m",
        "deformnet.apps.train",
        "-m",
        "net=lstm,transformer",
        f"hydra.sweep.dir={tmp_path / 'sweep'}",
        f"logger.save_dir={tmp_path / 'tb'}",
        "progress_bar=none",
        "half_window=4",
        "data.num_frames=200",
        "data.train_sequences=1",
        "data.val_windows=32",
        "data.batch_size=16",
        "data.steps_per_epoch=2",
        "trainer.max_epochs=1",
    ]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    subprocess.run(cmd, check=True, cwd=tmp_path, env=env, capture_output=True)
    assert sorted(p.name for p in (tmp_path / "tb").iterdir()) == ["lstm", "transformer"]
    ckpts = sorted(
        p.parent.parent.name for p in (tmp_path / "sweep").glob("*/checkpoints/best.ckpt")
    )
    assert ckpts == ["0_lstm", "1_transformer"]


def test_training_beats_rigid_and_linear_baselines(tmp_path):
    """Training works: a short LSTM run on simulated data predicts the masked mid frame better
    than the rigid model and than linear interpolation on its validation windows."""
    cfg = _compose(
        [
            *_common(tmp_path, "lstm"),
            "net.hidden=32",
            "net.embed=16",
            "data.num_frames=1500",
            "data.train_sequences=2",
            "data.batch_size=64",
            "data.steps_per_epoch=25",
            "data.val_windows=256",
            "trainer.max_epochs=12",
            "trainer.max_time=null",
        ]
    )
    m = run(cfg)["metrics"]
    assert m["val/rmse_mm"] < 0.8 * m["val/rmse_mm_rigid"], m
    assert m["val/rmse_mm"] < 0.95 * m["val/rmse_mm_linear"], m


def test_console_shows_no_lightning_tips_or_deprecations(tmp_path):
    """`deformnet-train` (the console script): Lightning's cloud-logger tip and torch's pytree
    deprecation inside Lightning are not on the console, and its info lines appear once."""
    cmd = [
        str(Path(sys.executable).parent / "deformnet-train"),
        *_common(tmp_path, "lstm"),
        "data.steps_per_epoch=2",
        "trainer.max_epochs=1",
        "threads=1",
    ]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env.pop("MOUSETRACK_CONFIG", None)
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    for noise in ("💡 Tip", "litlogger", "LeafSpec"):
        assert noise not in out, (noise, out[-3000:])
    assert out.count("GPU available") == 1  # not also through Lightning's own handler
    assert (tmp_path / "lstm" / "checkpoints" / "last.ckpt").is_file()
