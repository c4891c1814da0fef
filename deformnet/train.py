"""`deformnet-train`: train a deformation net on simulated data (Hydra app over `run(cfg)`).

    deformnet-train net=transformer                 # one net
    deformnet-train -m net=lstm,transformer         # both, sequentially (multirun)
    deformnet-train trainer.accelerator=auto        # a GPU when there is one
    deformnet-train trainer=ddp                     # Lightning DDP
    tensorboard --logdir runs/tb                    # one run per net (name = net name)

Outputs under `deformnet.paths.output_dir(cfg)`: checkpoints/best.ckpt, checkpoints/last.ckpt
(load with `DeformationModel.from_checkpoint`), metrics.json, config.yaml.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from deformnet.confutil import to_plain
from deformnet.paths import CONF_DIR, output_dir

log = logging.getLogger(__name__)

__all__ = ["run", "main", "build_model", "build_datamodule"]


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
        import datetime

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


def build_model(cfg: DictConfig):
    """The LightningModule (and the body model, net name) for a run config."""
    from deformnet.body import BodyModel
    from deformnet.deformation import build_net
    from deformnet.lit import DeformLit

    body = BodyModel.from_config(cfg.body)
    name, ncfg = net_config(cfg, body.num_parts)
    hp = {k: v for k, v in _flatten(to_plain(cfg)).items() if not k.startswith(("sim/", "body/"))}
    lit = DeformLit(
        build_net(ncfg),
        body,
        int(cfg.half_window),
        net_config=ncfg,
        lr=float(cfg.optim.lr),
        weight_decay=float(cfg.optim.weight_decay),
        warmup_steps=int(cfg.optim.warmup_steps),
        time_budget_s=_seconds(cfg.trainer.get("max_time")),
        hparams=hp,
    )
    return lit, body, name


def build_datamodule(cfg: DictConfig, body):
    from deformnet.data import DeformDataModule

    data = dict(to_plain(cfg.data))
    data.pop("_target_", None)
    return DeformDataModule(
        body=body,
        half_window=int(cfg.half_window),
        sim=to_plain(cfg.get("sim")),
        seed=int(cfg.seed),
        **data,
    )


def _progress_bar(kind: str):
    from lightning.pytorch.callbacks import RichProgressBar, TQDMProgressBar

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
    "metrics"} (checkpoint paths None when not written, e.g. under fast_dev_run)."""
    import lightning as L
    import torch
    from lightning.pytorch.callbacks import ModelCheckpoint

    from deformnet.atomic import write_text

    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    out = output_dir(cfg)
    write_text(out / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))

    lit, body, name = build_model(cfg)
    dm = build_datamodule(cfg, body)

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
    bar = _progress_bar(str(cfg.get("progress_bar", "rich")))
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
    }
    if trainer.is_global_zero:
        write_text(out / "metrics.json", json.dumps(result, indent=2) + "\n")
        log.info(
            "%s: val/rmse_mm %.3f (rigid %.3f, linear %.3f); checkpoints in %s",
            name,
            metrics.get("val/rmse_mm", float("nan")),
            metrics.get("val/rmse_mm_rigid", float("nan")),
            metrics.get("val/rmse_mm_linear", float("nan")),
            Path(ckpt_dir),
        )
    return result


@hydra.main(config_path=str(CONF_DIR), config_name="train", version_base=None)
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
