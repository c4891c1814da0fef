"""Training a deformation net: `run(cfg)`, behind `deformnet-train` (`deformnet.apps.train`).

    deformnet-train net=transformer                 # one net, on simulated mice
    deformnet-train data=sessions data.sessions=[runs/track/a,runs/track/b]   # a lab's own
        [pretrained=default|CKPT]                   # recordings (self-supervised), fine-tuned
    deformnet-train -m net=lstm,transformer         # both, sequentially (multirun)
    deformnet-train trainer.accelerator=auto        # a GPU when there is one
    deformnet-train trainer=ddp                     # Lightning DDP
    tensorboard --logdir runs/tb                    # one run per net (name = net name)

Outputs under `deformnet.paths.output_dir(cfg)`: checkpoints/best.ckpt, checkpoints/last.ckpt
(load with `DeformationModel.from_checkpoint`), metrics.json, config.yaml.
"""

from __future__ import annotations

import datetime
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import torch
from lightning.pytorch.callbacks import ModelCheckpoint, RichProgressBar, TQDMProgressBar
from omegaconf import DictConfig, OmegaConf

from deformnet.atomic import write_text
from deformnet.body import BodyModel
from deformnet.confutil import given_fields, to_plain
from deformnet.data import Augment, DeformDataModule
from deformnet.deformation import DeformationModel, build_net, check_track_up, frame_up
from deformnet.lit import DeformLit
from deformnet.paths import output_dir
from deformnet.pretrained import load_net, net_spec
from deformnet.sessions import (
    check_compatible,
    load_session_tokens,
    resolve_sessions,
    split_sessions,
)
from deformnet.threads import torch_threads

log = logging.getLogger(__name__)

__all__ = ["run", "build_model", "build_datamodule", "net_config"]


@dataclass(frozen=True)
class TrainSettings:
    """The top-level settings of deformnet-train's config that `run` reads (conf/train.yaml
    documents each); an absent key keeps the default here."""

    pretrained: str | None = None  # null | default | a checkpoint path (`load_net`)
    half_window: int = 16
    up: Any = None  # the world's up, e.g. [0, 0, 1] (`deformnet.deformation.frame_up`)
    seed: int = 0
    threads: int | None = 1
    progress_bar: str = "rich"  # rich | tqdm | none

    @classmethod
    def from_config(cls, cfg) -> TrainSettings:
        s = {k: to_plain(v) for k, v in given_fields(cls, cfg).items()}
        if "pretrained" in s:
            s["pretrained"] = net_spec(s["pretrained"])
        return cls(**s)


@dataclass(frozen=True)
class DataSettings:
    """The ``data`` block's keys that `run` reads itself (conf/data/*.yaml; the rest are
    `deformnet.data.DeformDataModule`'s arguments): the source, the token step and the
    augmentation's steps, and ``data=sessions``' sessions, split and token builder."""

    source: str = "sim"
    step: int = 1
    augment: Any = None  # `deformnet.windows.Augment.from_any`'s input
    sessions: tuple = ()
    val_fraction: float = 0.2
    block_frames: int = 500
    builder: Any = None  # a Hydra ``_partial_`` target: raw session -> tokens.npz

    @classmethod
    def from_config(cls, cfg) -> DataSettings:
        """From deformnet-train's config (its ``data`` block; absent: the defaults)."""
        data = cfg["data"] if "data" in cfg else None
        return cls(**given_fields(cls, data)) if data is not None else cls()


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}{k}/" if prefix or k else ""))
        return out
    key = prefix.rstrip("/")
    out[key] = d if isinstance(d, (int, float, str, bool)) else str(d)
    return out


def _seconds(max_time: Any) -> float | None:
    """Seconds of a Lightning max_time ("DD:HH:MM:SS" or a mapping of days/hours/...)."""
    if not max_time:
        return None
    if isinstance(max_time, str):
        d, h, m, s = (float(x) for x in max_time.split(":"))
        return ((d * 24 + h) * 60 + m) * 60 + s
    if OmegaConf.is_config(max_time) or isinstance(max_time, dict):
        return datetime.timedelta(**dict(to_plain(max_time))).total_seconds()
    return None


def net_config(cfg: DictConfig, num_parts: int) -> tuple[str, dict]:
    """(net name, `_target_` config with num_parts and half_window filled in)."""
    net = dict(to_plain(cfg.net))
    name = str(net.pop("name", net.get("_target_", "net").rsplit(".", 1)[-1]))
    net.pop("lr", None)  # the net's default learning rate (optim.lr), not a constructor argument
    net["num_parts"] = int(num_parts)
    net["half_window"] = int(cfg.half_window)
    return name, net


def build_model(cfg: DictConfig, body=None, pretrained=None):
    """The LightningModule (and the body model, net name) for a run config.

    body: the body model (default: ``cfg.body``); pretrained: a `DeformationModel` whose net
    (config, window and weights) is fine-tuned instead of a fresh ``cfg.net``."""
    body = BodyModel.from_config(cfg.body) if body is None else body
    name, ncfg = net_config(cfg, body.num_parts)
    ts = TrainSettings.from_config(cfg)
    half_window = int(ts.half_window)
    up = frame_up(ts.up, pretrained, str(ts.pretrained or ""))
    if pretrained is not None:
        if not pretrained.part_agnostic and pretrained.num_parts != body.num_parts:
            raise ValueError(
                f"pretrained net has {pretrained.num_parts} parts "
                f"({', '.join(pretrained.body.parts)}), the data {body.num_parts} "
                f"({', '.join(body.parts)}): train from scratch (pretrained=null), or start "
                "from a part-agnostic net (net=parts, e.g. the shipped default)"
            )
        ncfg = dict(pretrained.net_config)
        half_window = int(pretrained.half_window)
        name = f"{name}_ft"
    hp = {k: v for k, v in _flatten(to_plain(cfg)).items() if not k.startswith(("sim/", "body/"))}
    net = build_net(ncfg)
    if pretrained is not None:
        net.load_state_dict(pretrained.net.state_dict())
    lit = DeformLit(
        DeformationModel(net, body, half_window, ncfg, data_step(cfg), data_steps(cfg), up),
        lr=float(cfg.optim.lr),
        weight_decay=float(cfg.optim.weight_decay),
        warmup_steps=int(cfg.optim.warmup_steps),
        time_budget_s=_seconds(cfg.trainer.get("max_time")),
        hparams=hp,
    )
    return lit, body, name


def data_step(cfg: DictConfig) -> int:
    """``data.step``: frames between a window's tokens (1: consecutive frames)."""
    step = DataSettings.from_config(cfg).step
    if step is None or int(step) < 1:
        raise ValueError(f"data.step must be an integer >= 1, got {step}")
    return int(step)


def data_steps(cfg: DictConfig) -> tuple[int, ...] | None:
    """The token steps training draws from (``data.augment.steps``; None: ``data.step``)."""
    return Augment.from_any(to_plain(DataSettings.from_config(cfg).augment)).steps


def build_datamodule(cfg: DictConfig, body, half_window: int | None = None, arrays=None):
    """The data module; ``arrays`` = (train, val) sequences for ``data.source=sessions``."""
    data = dict(to_plain(cfg.data))
    for key in ("sessions", "val_fraction", "block_frames", "builder"):
        data.pop(key, None)
    if arrays is not None:
        data["source"] = "arrays"
        data["train_data"], data["val_data"] = arrays
    return DeformDataModule(
        body=body,
        half_window=int(cfg.half_window if half_window is None else half_window),
        sim=to_plain(cfg.get("sim")),
        seed=int(cfg.seed),
        **data,
    )


def session_data(cfg: DictConfig, out: Path, window: int, up=None):
    """``data=sessions``: the sessions' tokens, their body model and the train/val split;
    up: the world up of a heading-frame net (each session's world must have it)."""
    ds = DataSettings.from_config(cfg)
    paths = resolve_sessions(list(ds.sessions or []))
    if not paths:
        raise ValueError("data=sessions needs data.sessions=[DIR_OR_GLOB, ...]")
    builder = None
    if ds.builder is not None and "_target_" in ds.builder and ds.builder["_target_"]:
        partial = hydra.utils.instantiate(ds.builder)
        root = out / "sessions"

        def builder(session: Path) -> Path:
            return partial(session, root)

    tokens = [load_session_tokens(p, builder) for p in paths]
    check_compatible(tokens)
    if up is not None:
        for t in tokens:
            check_track_up(t.rigid, t.body_points, up, t.source or "a session")
    first = tokens[0]
    body = first.body_model()
    train, val, facts = split_sessions(
        tokens,
        float(ds.val_fraction),
        int(ds.block_frames),
        min_frames=window,
    )
    facts["sessions"] = [t.source for t in tokens]
    log.info(
        "data=sessions: %d session(s), split %s: %d train / %d val frames (%d / %d measured "
        "targets)",
        len(tokens),
        facts["split"],
        facts["train_frames"],
        facts["val_frames"],
        facts["train_targets"],
        facts["val_targets"],
    )
    return body, (train, val), facts


def _progress_bar(kind: str):
    if kind == "rich":
        try:
            return RichProgressBar()
        except (ImportError, ModuleNotFoundError):  # pragma: no cover - rich is a dependency
            log.warning("rich is not installed; using a tqdm progress bar")
            return TQDMProgressBar()
    if kind == "tqdm":
        return TQDMProgressBar()
    return None


def run(cfg: DictConfig) -> dict:
    """Train one net; returns {"net", "output_dir", "best_checkpoint", "last_checkpoint",
    "metrics"} (checkpoint paths None when not written, e.g. under fast_dev_run).

    ``threads`` (torch's intra-op threads) applies for the call and is restored after it."""
    with torch_threads(TrainSettings.from_config(cfg).threads):
        return _run(cfg)


def _run(cfg: DictConfig) -> dict:
    ts = TrainSettings.from_config(cfg)
    L.seed_everything(int(ts.seed), workers=True, verbose=False)
    out = output_dir(cfg)
    write_text(out / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))

    pretrained = load_net(ts.pretrained, "pretrained")
    body, arrays, data_facts = None, None, None
    n = int(pretrained.half_window if pretrained is not None else ts.half_window)
    window = 2 * n * data_step(cfg) + 1  # frames a window spans (wider steps: where they fit)
    if str(DataSettings.from_config(cfg).source) == "sessions":
        up = frame_up(ts.up, pretrained, str(ts.pretrained or ""))
        body, arrays, data_facts = session_data(cfg, out, window, up)
    lit, body, name = build_model(cfg, body, pretrained)
    dm = build_datamodule(cfg, body, lit.mid, arrays)

    tcfg = dict(to_plain(cfg.trainer))
    ckpt_dir = out / "checkpoints"
    checkpoint = ModelCheckpoint(
        dirpath=ckpt_dir,
        filename="best",
        monitor=str(cfg.checkpoint.monitor),
        mode=str(cfg.checkpoint.mode),
        save_last=True,
        auto_insert_metric_name=False,
    )
    callbacks: list = [checkpoint]
    bar = _progress_bar(str(ts.progress_bar))
    if bar is not None:
        callbacks.append(bar)
    logger: Any = False
    lcfg = to_plain(cfg.get("logger")) or {}
    if lcfg.get("_target_"):
        logger = hydra.utils.instantiate(lcfg)
    trainer = L.Trainer(
        **tcfg,
        logger=logger,
        callbacks=callbacks,
        enable_progress_bar=bar is not None,
        default_root_dir=str(out),
    )
    trainer.fit(lit, datamodule=dm)

    metrics = {
        k: float(v) for k, v in trainer.callback_metrics.items() if torch.as_tensor(v).numel() == 1
    }
    best = checkpoint.best_model_path or None
    last = ckpt_dir / "last.ckpt"
    last = str(last) if last.exists() else None
    best_score = checkpoint.best_model_score
    if best_score is not None:
        metrics["best/val_rmse_mm"] = float(best_score)
    if logger and trainer.is_global_zero and best_score is not None:
        logger.log_hyperparams(
            lit.hparams.get("hparams") or {}, metrics={"hp/best_val_rmse_mm": float(best_score)}
        )
    result = {
        "net": name,
        "output_dir": str(out),
        "best_checkpoint": best,
        "last_checkpoint": last,
        "metrics": {k: v for k, v in sorted(metrics.items()) if math.isfinite(v)},
        "pretrained": None if pretrained is None else str(ts.pretrained),
        "data": data_facts,
    }
    if trainer.is_global_zero:
        write_text(out / "metrics.json", json.dumps(result, indent=2) + "\n")
        log.info(
            "%s: val/rmse_mm %.3f (rigid %.3f, linear %.3f, interp %.3f); checkpoints in %s",
            name,
            metrics.get("val/rmse_mm", float("nan")),
            metrics.get("val/rmse_mm_rigid", float("nan")),
            metrics.get("val/rmse_mm_linear", float("nan")),
            metrics.get("val/rmse_mm_interp", float("nan")),
            Path(ckpt_dir),
        )
    return result
