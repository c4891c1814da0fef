"""The one thin LightningModule: trains any deformation net (a plain nn.Module built elsewhere).

Metrics: `train/loss`, `val/loss` (masked MSE, mm^2, canonical = global distances),
`val/rmse_mm` and `val/rmse_mm/<part>` of the net, and on the same validation windows the rigid
baseline `val/rmse_mm_rigid` (predict X̄), the linear-interpolation baseline
`val/rmse_mm_linear` (`deformnet.tokens.linear_baseline`) and the offset-interpolation baseline
`val/rmse_mm_interp` (`deformnet.tokens.offset_baseline`: the rigid model plus interpolated
offsets, what adjust-track's `interp` does). RMSE is over the mid frame's observed parts (3D
point distance); the sums are `deformnet.heldout.window_sums`.

Checkpoints carry a `deformation_model` entry that `DeformationModel.from_checkpoint` rebuilds
without Lightning.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import Any

import lightning as L
import torch
from torch import Tensor

from deformnet.deformation import CHECKPOINT_KEY, DeformationModel
from deformnet.heldout import window_sums
from deformnet.tokens import masked_mse

__all__ = ["DeformLit"]


class DeformLit(L.LightningModule):
    """model: the `DeformationModel` to train (its net: a canonical-coordinate predictor, see
    `deformnet.nets`; its net_config is needed to rebuild it from a checkpoint); lr,
    weight_decay, warmup_steps: AdamW with linear warm-up then cosine decay over the trainer's
    estimated steps, or over `time_budget_s` seconds of training when that comes first (set it
    to the trainer's max_time, so a slow shared machine still finishes the schedule); hparams:
    extra hyper-parameters to log (e.g. the flattened run config)."""

    def __init__(
        self,
        model: DeformationModel,
        lr: float = 2e-3,
        weight_decay: float = 1e-4,
        warmup_steps: int = 100,
        time_budget_s: float | None = None,
        hparams: Mapping[str, Any] | None = None,
    ) -> None:
        super().__init__()
        self.save_hyperparameters(ignore=["model"])
        self.model = model
        self.parts = tuple(model.body.parts)
        self.mid = model.half_window
        self._val_sums: dict[str, Tensor] = {}
        self._t_start: float | None = None

    def on_train_start(self) -> None:
        self._t_start = time.monotonic()

    def _progress(self, step: int, warm: int, total: int) -> float:
        p = (step - warm) / max(1, total - warm)
        budget = self.hparams.get("time_budget_s")
        if budget and self._t_start is not None:
            p = max(p, (time.monotonic() - self._t_start) / float(budget))
        return min(1.0, max(0.0, p))

    def forward(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> Tensor:
        return self.model(rigid, deformed, observed)

    def _canonical_loss(self, batch: Mapping[str, Tensor]) -> tuple[Tensor, Tensor]:
        pred_c, R, t = self.model.canonical(batch["rigid"], batch["deformed"], batch["observed"])
        target_c = (batch["target"] - t[:, None, :]) @ R
        loss = masked_mse(pred_c, target_c, batch["target_mask"])
        return loss, pred_c

    def training_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> Tensor:
        loss, _ = self._canonical_loss(batch)
        B = batch["rigid"].shape[0]
        self.log("train/loss", loss, prog_bar=True, batch_size=B)
        return loss

    def on_validation_epoch_start(self) -> None:
        self._val_sums = {}

    def validation_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> Tensor:
        rigid = batch["rigid"]
        loss, _ = self._canonical_loss(batch)
        for key, s in window_sums(self.model, batch, self.mid).items():
            self._val_sums[key] = self._val_sums[key] + s if key in self._val_sums else s
        self.log("val/loss", loss, batch_size=rigid.shape[0], sync_dist=True)
        return loss

    def on_validation_epoch_end(self) -> None:
        if not self._val_sums:
            return
        sums = {
            k: self.trainer.strategy.reduce(v, reduce_op="sum") for k, v in self._val_sums.items()
        }
        count = sums["count"]
        total = count.sum().clamp_min(1.0)

        def rmse(x: Tensor) -> Tensor:
            return (x.sum() / total).sqrt().float()

        # the sums are already reduced over processes: every rank logs the same value
        self.log("val/rmse_mm", rmse(sums["net"]), prog_bar=True, sync_dist=True)
        self.log("val/rmse_mm_rigid", rmse(sums["rigid"]), sync_dist=True)
        self.log("val/rmse_mm_linear", rmse(sums["linear"]), sync_dist=True)
        self.log("val/rmse_mm_interp", rmse(sums["offset"]), sync_dist=True)
        per_part = (sums["net"] / count.clamp_min(1.0)).sqrt().float()
        for name, value, c in zip(self.parts, per_part, count):
            if c > 0:
                self.log(f"val/rmse_mm/{name}", value, sync_dist=True)
        self._val_sums = {}

    def configure_optimizers(self):
        hp = self.hparams
        decay, no_decay = [], []
        for name, p in self.named_parameters():
            (no_decay if p.ndim < 2 or "embedding" in name else decay).append(p)
        opt = torch.optim.AdamW(
            [
                {"params": decay, "weight_decay": float(hp.weight_decay)},
                {"params": no_decay, "weight_decay": 0.0},
            ],
            lr=float(hp.lr),
        )
        total = self.trainer.estimated_stepping_batches if self.trainer is not None else 1000
        total = int(total) if math.isfinite(total) and total > 0 else 1000
        warm = max(1, min(int(hp.warmup_steps), total // 5))

        def factor(step: int) -> float:
            if step < warm:
                return (step + 1) / warm
            progress = self._progress(step, warm, total)
            return 0.02 + 0.98 * 0.5 * (1.0 + math.cos(math.pi * progress))

        sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        if self.model.net_config is not None:
            checkpoint[CHECKPOINT_KEY] = self.model.export()
