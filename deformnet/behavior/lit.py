"""The thin LightningModule that fine-tunes a behavior classifier (`deformnet.behavior.heads`).

Batches are dicts: rigid, deformed (B, W, K, 3) global mm, observed (B, W, K) bool, label (B,)
int64 class index. Loss: cross-entropy, optionally class-weighted (imbalance). Metrics:
`train/loss`, `val/loss`, `val/macro_f1` and `val/f1/<class>` (scikit-learn, over the classes
present in the validation labels or predictions). With `freeze=True` the encoder's weights do
not change (no gradients, kept in eval mode); only the head trains. The best validation state
(by macro-F1) is kept in `best_state` for the app to export.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from typing import Any

import lightning as L
import numpy as np
import torch
from torch import Tensor, nn

from deformnet.behavior.heads import BehaviorClassifier
from deformnet.behavior.report import macro_f1

__all__ = ["ClassifyLit"]


class ClassifyLit(L.LightningModule):
    """model: encoder + head; classes: names (C,); class_weights: (C,) loss weights or None;
    freeze: train the head only (`head_only` switches this per fit, e.g. a probing phase on
    cached encoder features before fine-tuning); lr (head), encoder_lr, weight_decay: AdamW;
    token_dropout: during training, hide each input token (frame, part) with this probability
    (robustness to missing parts); hparams: extra hyper-parameters to log."""

    def __init__(
        self,
        model: BehaviorClassifier,
        classes: Sequence[str],
        class_weights: Sequence[float] | None = None,
        freeze: bool = False,
        lr: float = 1e-3,
        encoder_lr: float = 3e-4,
        weight_decay: float = 1e-4,
        token_dropout: float = 0.0,
        hparams: Mapping[str, Any] | None = None,
    ) -> None:
        super().__init__()
        self.save_hyperparameters(ignore=["model"])
        self.model = model
        self.classes = tuple(str(c) for c in classes)
        w = None if class_weights is None else torch.as_tensor(class_weights, dtype=torch.float32)
        self.register_buffer("class_weights", w, persistent=False)
        self.freeze = bool(freeze)
        self._head_only = False
        if self.freeze:
            self.model.encoder.requires_grad_(False)
        self._val_true: list[Tensor] = []
        self._val_pred: list[Tensor] = []
        self.best_score = -1.0
        self.best_state: dict[str, Tensor] | None = None

    @property
    def head_only(self) -> bool:
        return self.freeze or self._head_only

    @head_only.setter
    def head_only(self, value: bool) -> None:
        """Train the head only (the encoder frozen) until set back; with `freeze` always."""
        self._head_only = bool(value)
        self.model.encoder.requires_grad_(not self.head_only)

    def train(self, mode: bool = True):
        super().train(mode)
        if self.head_only:
            self.model.encoder.eval()
        return self

    def _logits(self, batch: Mapping[str, Tensor], augment: bool) -> Tensor:
        """Logits of a window batch, or of a batch of cached encoder `features` (B, D)."""
        if "features" in batch:
            return self.model.classify(batch["features"])
        observed = batch["observed"]
        p = float(self.hparams.token_dropout)
        if augment and p > 0:
            observed = observed & (torch.rand(observed.shape, device=observed.device) >= p)
        return self.model(batch["rigid"], batch["deformed"], observed, batch.get("scale"))

    def forward(
        self, rigid: Tensor, deformed: Tensor, observed: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        return self.model(rigid, deformed, observed, scale)

    def _loss(self, logits: Tensor, label: Tensor) -> Tensor:
        w = self.class_weights
        return nn.functional.cross_entropy(logits, label, weight=w)

    def training_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> Tensor:
        logits = self._logits(batch, augment=True)
        loss = self._loss(logits, batch["label"])
        self.log("train/loss", loss, prog_bar=True, batch_size=logits.shape[0])
        return loss

    def on_validation_epoch_start(self) -> None:
        self._val_true, self._val_pred = [], []

    def validation_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> Tensor:
        logits = self._logits(batch, augment=False)
        loss = self._loss(logits, batch["label"])
        self.log("val/loss", loss, batch_size=logits.shape[0])
        self._val_true.append(batch["label"].detach().cpu())
        self._val_pred.append(logits.argmax(-1).detach().cpu())
        return loss

    def on_validation_epoch_end(self) -> None:
        if not self._val_true:
            return
        y = torch.cat(self._val_true).numpy()
        p = torch.cat(self._val_pred).numpy()
        score, per = macro_f1(y, p, len(self.classes))
        self.log("val/macro_f1", score, prog_bar=True)
        for name, f in zip(self.classes, per):
            if np.isfinite(f):
                self.log(f"val/f1/{name}", float(f))
        if not self.trainer.sanity_checking and score > self.best_score:
            self.best_score = score
            self.best_state = copy.deepcopy(
                {k: v.detach().cpu() for k, v in self.model.state_dict().items()}
            )
        self._val_true, self._val_pred = [], []

    def configure_optimizers(self):
        hp = self.hparams
        groups = [{"params": list(self.model.head.parameters()), "lr": float(hp.lr)}]
        if not self.head_only:
            groups.append(
                {"params": self.model.encoder.encoder_parameters(), "lr": float(hp.encoder_lr)}
            )
        return torch.optim.AdamW(groups, lr=float(hp.lr), weight_decay=float(hp.weight_decay))
