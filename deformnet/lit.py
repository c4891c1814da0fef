"""The one thin LightningModule: trains any deformation net (a plain nn.Module built elsewhere).

Metrics: `train/loss`, `val/loss` (masked MSE, mm^2, canonical = global distances),
`val/rmse_mm` and `val/rmse_mm/<part>` of the net, and on the same validation windows the rigid
baseline `val/rmse_mm_rigid` (predict X̄), the linear-interpolation baseline
`val/rmse_mm_linear` (`deformnet.tokens.linear_baseline`) and the offset-interpolation baseline
`val/rmse_mm_interp` (`deformnet.tokens.offset_baseline`: the rigid model plus interpolated
offsets, what adjust-track's `interp` does). RMSE is over the mid frame's observed parts (3D
point distance); the sums are `deformnet.heldout.window_sums`.

With `contrast` (weight > 0) a temporal-contrastive term (InfoNCE, in-batch negatives) is added
for behavior pretraining: each training window and its `pair` (the same sequence a few frames
away, `RandomWindowBatches(pair_shift)`) are summarised by the net's encoder (`encode`: the mid
frame's output and the window's mean, in the mid frame's canonical coordinates), projected
(a small MLP, training only) and must pick each other out of the batch. Behaviors last tens to
hundreds of frames, so this pulls a bout's windows together and pushes other bouts' apart, with
no labels. Logged: `train/loss` (the sum), `train/deform_loss`, `train/contrast_loss`,
`train/contrast_acc` (how often the pair is the nearest).

With `forecast` (weight > 0) a forecasting term is added, also for behavior pretraining: from
the same window summary a small MLP (training only) predicts where every body part will be (or
was) `shift` token steps from the mid frame, beyond what the window shows (`ahead`,
`RandomWindowBatches(ahead_shift)`), in the mid frame's canonical coordinates. To do that the
encoder must carry the animal's motion state and what it is doing (a walking mouse moves on, a
grooming one stays, a rearing one comes down), not only the local deformation the masked-frame
objective needs. Logged: `train/forecast_loss` (mean squared 3D error / scale_mm^2) and
`train/forecast_rmse_mm`.

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
from torch import Tensor, nn

from deformnet.deformation import CHECKPOINT_KEY, DeformationModel
from deformnet.heldout import window_sums
from deformnet.tokens import masked_mse
from deformnet.windows import window_summary

__all__ = ["DeformLit"]


class DeformLit(L.LightningModule):
    """model: the `DeformationModel` to train (its net: a canonical-coordinate predictor, see
    `deformnet.nets`; its net_config is needed to rebuild it from a checkpoint); lr,
    weight_decay, warmup_steps: AdamW with linear warm-up then cosine decay over the trainer's
    estimated steps, or over `time_budget_s` seconds of training when that comes first (set it
    to the trainer's max_time, so a slow shared machine still finishes the schedule); hparams:
    extra hyper-parameters to log (e.g. the flattened run config); contrast: {weight,
    temperature, dim} of the temporal-contrastive term (weight 0 or None: off); forecast: {weight,
    min_shift, max_shift, hidden, scale_mm} of the forecasting term (weight 0 or None: off; the
    shifts are the data's, `ahead_shift`)."""

    def __init__(
        self,
        model: DeformationModel,
        lr: float = 2e-3,
        weight_decay: float = 1e-4,
        warmup_steps: int = 100,
        time_budget_s: float | None = None,
        hparams: Mapping[str, Any] | None = None,
        contrast: Mapping[str, Any] | None = None,
        forecast: Mapping[str, Any] | None = None,
    ) -> None:
        super().__init__()
        self.save_hyperparameters(ignore=["model"])
        self.model = model
        c = dict(contrast or {})
        unknown = set(c) - {"weight", "temperature", "dim", "max_shift"}
        if unknown:
            raise ValueError(f"contrast: unknown keys {sorted(unknown)}")
        self.contrast_weight = float(c.get("weight") or 0.0)
        self.contrast_temperature = float(c.get("temperature", 0.1))
        if self.contrast_weight < 0 or self.contrast_temperature <= 0:
            raise ValueError(f"contrast.weight must be >= 0 and contrast.temperature > 0, got {c}")
        self.contrast_head: nn.Module | None = None
        if self.contrast_weight > 0:
            d = 2 * int(model.net.encode_dim)
            self.contrast_head = nn.Sequential(
                nn.Linear(d, d), nn.GELU(), nn.Linear(d, int(c.get("dim", 64)))
            )
        f = dict(forecast or {})
        unknown = set(f) - {"weight", "min_shift", "max_shift", "hidden", "scale_mm"}
        if unknown:
            raise ValueError(f"forecast: unknown keys {sorted(unknown)}")
        self.forecast_weight = float(f.get("weight") or 0.0)
        self.forecast_scale = float(f.get("scale_mm", 100.0))
        if self.forecast_weight < 0 or self.forecast_scale <= 0:
            raise ValueError(f"forecast.weight must be >= 0 and forecast.scale_mm > 0, got {f}")
        self.forecast_head: nn.Module | None = None
        if self.forecast_weight > 0:
            d, h = 2 * int(model.net.encode_dim), int(f.get("hidden", 128))
            self.forecast_head = nn.Sequential(
                nn.Linear(d + 1, h), nn.GELU(), nn.Linear(h, h), nn.GELU(),
                nn.Linear(h, 3 * model.body.num_parts),
            )  # fmt: skip
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

    def summary(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> Tensor:
        """The encoder's window summaries (B, 2 encode_dim): the mid frame's output and the
        window's mean, in the mid frame's canonical coordinates (as `deformnet.heads`
        reads them)."""
        m = self.model
        return window_summary(m.net, m.body_points, rigid, deformed, observed, m.up_tensor(rigid))[
            0
        ]

    def contrast_loss(self, batch: Mapping[str, Any]) -> tuple[Tensor, Tensor]:
        """Symmetric InfoNCE between the windows and their pairs; (loss, top-1 accuracy)."""
        if self.contrast_head is None:
            raise ValueError("contrast_loss needs contrast.weight > 0")
        pair = batch["pair"]
        B = batch["rigid"].shape[0]
        both = {
            k: torch.cat((batch[k], pair[k])) for k in ("rigid", "deformed", "observed")
        }  # fmt: skip
        z = self.contrast_head(self.summary(both["rigid"], both["deformed"], both["observed"]))
        z = nn.functional.normalize(z, dim=-1)
        logits = z[:B] @ z[B:].T / self.contrast_temperature
        target = torch.arange(B, device=logits.device)
        loss = 0.5 * (
            nn.functional.cross_entropy(logits, target)
            + nn.functional.cross_entropy(logits.T, target)
        )
        acc = (logits.argmax(-1) == target).float().mean()
        return loss, acc

    def forecast_loss(self, batch: Mapping[str, Any]) -> tuple[Tensor, Tensor]:
        """The forecasting term: (mean squared 3D error of the predicted positions `shift`
        steps away, in units of scale_mm, RMSE in mm), over the parts with a true position."""
        if self.forecast_head is None:
            raise ValueError("forecast_loss needs forecast.weight > 0")
        ahead, m = batch["ahead"], self.model
        summary, (_, _, R, t) = window_summary(
            m.net, m.body_points, batch["rigid"], batch["deformed"], batch["observed"],
            m.up_tensor(batch["rigid"]),
        )  # fmt: skip
        shift = ahead["shift"].to(summary.dtype)[:, None] / max(1, self.mid)
        B = summary.shape[0]
        pred = self.forecast_head(torch.cat((summary, shift), -1)).reshape(B, -1, 3)
        target = (ahead["points"].to(summary.dtype) - t[:, None, :]) @ R / self.forecast_scale
        loss = masked_mse(pred, target, ahead["mask"])
        return loss, loss.detach().sqrt() * self.forecast_scale

    def training_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> Tensor:
        loss, _ = self._canonical_loss(batch)
        B = batch["rigid"].shape[0]
        if self.forecast_weight > 0 or self.contrast_weight > 0:
            self.log("train/deform_loss", loss, batch_size=B)
        if self.forecast_weight > 0:
            if "ahead" not in batch:
                raise ValueError(
                    "forecast.weight > 0 needs training batches with forecasting targets "
                    "(RandomWindowBatches(ahead_shift), data from forecast.min/max_shift)"
                )
            f, rmse = self.forecast_loss(batch)
            self.log("train/forecast_loss", f, batch_size=B)
            self.log("train/forecast_rmse_mm", rmse, batch_size=B)
            loss = loss + self.forecast_weight * f
        if self.contrast_weight > 0:
            if "pair" not in batch:
                raise ValueError(
                    "contrast.weight > 0 needs training batches with pairs "
                    "(RandomWindowBatches(pair_shift > 0), data from contrast.max_shift)"
                )
            c, acc = self.contrast_loss(batch)
            self.log("train/contrast_loss", c, batch_size=B)
            self.log("train/contrast_acc", acc, batch_size=B)
            loss = loss + self.contrast_weight * c
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
