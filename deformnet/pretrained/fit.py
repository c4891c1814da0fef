"""Train one part-agnostic net on sessions of several skeletons (a plain, seeded torch loop).

    model = fit_sessions(sessions, FitConfig(steps=3000), seed=0)

sessions: `deformnet.sessions.SessionTokens` (tokens.npz of tracked recordings: the rigid
model's points, the measured deformed points, observed flags), any mix of skeletons (8, 22, 34
parts...). The objective is `deformation=self`'s and `deformnet-train data=sessions`'s: the
mid frame's measured parts, hidden from the net, predicted from the window (masked MSE in the
mid frame's canonical coordinates, `deformnet.tokens.masked_mse`), with the same masking
(`deformnet.windows.MaskConfig`) and augmentation (`Augment`: mirror, reverse, token steps).
Sessions with the same parts share a window bank; each optimiser step draws its batch from one
bank, in a fixed round-robin weighted by the banks' sizes, so the run is reproducible from its
seed (one thread: bit for bit on the same CPU). No Lightning (no trainer state to strip).

With ``truths`` (filmed motion whose true positions are known, `adjust.pretrain_real`), a
session's targets are its true positions at every part of the mid frame, measured or not
(`TruthWindowBank`): the net learns what the tracker asks of it, the parts a recording did not
measure, with the neighbours it really has (``FitConfig.real_masks``: the fraction of windows
with no masks beyond the recording's own missing part-frames and the mid frame).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from deformnet.deformation import DeformationModel, build_net
from deformnet.tokens import masked_mse
from deformnet.windows import (
    Augment,
    MaskConfig,
    RandomWindowBatches,
    SequenceArrays,
    WindowBank,
    mirror_permutation,
)

log = logging.getLogger(__name__)

__all__ = ["FitConfig", "TruthWindowBank", "fit_sessions"]


@dataclass(frozen=True)
class FitConfig:
    """The training recipe. net: the net's config (`_target_` one of `deformnet.nets.NETS`,
    part-agnostic for several skeletons); steps: optimiser steps (fixed: no time budget);
    batch_size; lr, weight_decay, warmup_steps: AdamW, linear warm-up then cosine decay to
    2% of lr; masking, augment: as `deformnet.windows`; noise_mm: Gaussian noise on the
    observed deformed inputs; real_masks: with true targets (`TruthWindowBank`), the fraction
    of windows that keep the recording's own missing part-frames only (no `masking` on top:
    the tracker's windows); log_every: steps between progress lines."""

    net: dict = field(
        default_factory=lambda: {"_target_": "deformnet.nets.PartTransformer", "half_window": 12}
    )
    steps: int = 3000
    batch_size: int = 128
    lr: float = 2e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 100
    masking: MaskConfig = MaskConfig()
    augment: Augment = Augment(mirror=0.5, reverse=0.5, steps=(1, 1, 2, 3))
    noise_mm: float = 0.0
    real_masks: float = 0.0
    log_every: int = 250


class TruthWindowBank(WindowBank):
    """A `WindowBank` whose targets are true positions: the inputs are the sequences' measured
    tokens as usual, the target of every part of the mid frame is its true position
    (target_mask all true), measured or not.

    truths: one (T, K, 3) global mm array per sequence (the sequences' frames and parts);
    real_masks: the probability that a window keeps only the sequence's own missing
    part-frames and the mid frame (its extra hidden flags dropped), so that the net sees the
    neighbours a tracked recording has."""

    def __init__(
        self,
        sequences: Sequence[SequenceArrays],
        truths: Sequence[np.ndarray],
        half_window: int,
        step: int = 1,
        real_masks: float = 0.0,
    ) -> None:
        if len(truths) != len(sequences):
            raise ValueError(f"{len(truths)} truths for {len(sequences)} sequences")
        for s, tr in zip(sequences, truths):
            if np.shape(tr) != s.rigid.shape:
                raise ValueError(f"truth {np.shape(tr)} does not match tokens {s.rigid.shape}")
        if not 0.0 <= float(real_masks) <= 1.0:
            raise ValueError(f"real_masks must be a probability, got {real_masks}")
        super().__init__(sequences, half_window, step)
        self.truth = torch.from_numpy(np.concatenate([np.asarray(truths[i], np.float32)
                                                      for i in self.kept]))  # fmt: skip
        if not bool(torch.isfinite(self.truth).all()):
            raise ValueError("truth holds non-finite positions")
        self.real_masks = float(real_masks)

    def batch(self, idx, hide, noise_mm=0.0, gen=None, step=None, flip=None, reverse=None,
              perm=None) -> dict:  # fmt: skip
        """`WindowBank.batch` with the true mid-frame positions as targets (all parts)."""
        if self.real_masks > 0:
            own = torch.rand(hide.shape[0], generator=gen) < self.real_masks
            mid_only = torch.zeros_like(hide)
            mid_only[:, self.n] = True
            hide = torch.where(own[:, None, None], mid_only, hide)
        out = super().batch(idx, hide, noise_mm, gen, step, flip, reverse, perm)
        step = self.step if step is None else int(step)
        mid = self.mids_for(step)[idx]  # the mid frame (reversal keeps it)
        target = self.truth[mid]  # (B, K, 3)
        if flip is not None and perm is not None and bool(flip.any()):
            sign = torch.tensor([-1.0, 1.0, 1.0], dtype=target.dtype)
            p = torch.as_tensor(list(perm), dtype=torch.long)
            target = torch.where(flip[:, None, None], (target * sign)[:, p], target)
        out["target"] = target
        out["target_mask"] = torch.ones(target.shape[:2], dtype=torch.bool)
        return out


def _banks(sessions, half_window: int, cfg: FitConfig, seed: int, truths=None) -> list[dict]:
    """One window bank per skeleton (sessions with the same parts), with its batch stream;
    with `truths` (one (T, K, 3) array per session), `TruthWindowBank`s."""
    groups: dict[tuple[str, ...], list] = {}
    for i, t in enumerate(sessions):
        groups.setdefault(tuple(t.parts), []).append(i)
    out = []
    for g, (parts, ids) in enumerate(sorted(groups.items(), key=lambda kv: (len(kv[0]), kv[0]))):
        toks = [sessions[i] for i in ids]
        seqs = [t.to_sequence() for t in toks]
        if truths is None:
            bank = WindowBank(seqs, half_window)
        else:
            bank = TruthWindowBank(seqs, [truths[i] for i in ids], half_window, 1,
                                   cfg.real_masks)  # fmt: skip
        stream = RandomWindowBatches(
            bank, cfg.batch_size, cfg.steps, cfg.masking, seed + 101 * g, cfg.noise_mm,
            cfg.augment, mirror_permutation(parts),
        )  # fmt: skip
        out.append({"parts": parts, "body": toks[0].body_model(), "bank": bank,
                    "iter": iter(stream), "windows": len(bank)})  # fmt: skip
    return out


def _schedule(steps: int, weights: Sequence[float]) -> list[int]:
    """Which bank each step draws from: a deterministic interleaving with each bank's share
    of the steps proportional to its weight (largest remainder first)."""
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    order, credit = [], np.zeros(len(w))
    for _ in range(int(steps)):
        credit += w
        i = int(np.argmax(credit))
        credit[i] -= 1.0
        order.append(i)
    return order


def fit_sessions(
    sessions: Sequence,
    cfg: FitConfig = FitConfig(),
    seed: int = 0,
    extra: Sequence = (),
    truths: Sequence[np.ndarray] | None = None,
) -> tuple[DeformationModel, dict]:
    """Train `cfg.net` on the sessions' tokens (and `extra`: (body, [SequenceArrays]) pairs,
    e.g. simulated mice with their truth as measurements); returns (the model on the largest
    skeleton's body, facts: windows per skeleton, the final training losses). truths: one
    (T, K, 3) array of true positions per session (its frames and parts): the targets
    (`TruthWindowBank`) instead of the measured mid frame."""
    torch.manual_seed(int(seed))
    net_cfg = dict(cfg.net)
    net_cfg.setdefault("num_parts", None)
    net = build_net(net_cfg)
    half_window = int(net.half_window)  # the net's own (its config's, else its default)
    if not getattr(net, "part_agnostic", False) and len({tuple(t.parts) for t in sessions}) > 1:
        raise ValueError(f"{net_cfg['_target_']} knows parts by index: one skeleton only")
    if truths is not None and len(truths) != len(sessions):
        raise ValueError(f"{len(truths)} truths for {len(sessions)} sessions")
    banks = _banks(sessions, half_window, cfg, int(seed), truths)
    for g, (body, seqs) in enumerate(extra):
        bank = WindowBank([SequenceArrays.of(s) for s in seqs], half_window)
        stream = RandomWindowBatches(
            bank, cfg.batch_size, cfg.steps, cfg.masking, int(seed) + 7919 + g, cfg.noise_mm,
            cfg.augment, mirror_permutation(body.parts),
        )  # fmt: skip
        banks.append({"parts": tuple(body.parts), "body": body, "bank": bank,
                      "iter": iter(stream), "windows": len(bank)})  # fmt: skip
    if not banks:
        raise ValueError("fit_sessions: no sessions to train on")
    ref = max(banks, key=lambda b: (len(b["parts"]), b["windows"]))
    steps = cfg.augment.steps  # the token steps it sees (the tracker's far steps use them)
    models = [DeformationModel(net, b["body"], half_window, net_cfg, 1, steps) for b in banks]
    decay = [p for n, p in net.named_parameters() if p.ndim >= 2]
    no_decay = [p for n, p in net.named_parameters() if p.ndim < 2]
    opt = torch.optim.AdamW(
        [{"params": decay, "weight_decay": cfg.weight_decay},
         {"params": no_decay, "weight_decay": 0.0}],
        lr=cfg.lr,
    )  # fmt: skip
    warm = max(1, min(int(cfg.warmup_steps), cfg.steps // 5))

    def factor(step: int) -> float:
        if step < warm:
            return (step + 1) / warm
        p = min(1.0, (step - warm) / max(1, cfg.steps - warm))
        return 0.02 + 0.98 * 0.5 * (1.0 + math.cos(math.pi * p))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
    order = _schedule(cfg.steps, [math.sqrt(b["windows"]) * len(b["parts"]) for b in banks])
    net.train()
    recent: list[float] = []
    for step, g in enumerate(order):
        batch = next(banks[g]["iter"])
        pred_c, R, t = models[g].canonical(batch["rigid"], batch["deformed"], batch["observed"])
        target_c = (batch["target"] - t[:, None, :]) @ R
        loss = masked_mse(pred_c, target_c, batch["target_mask"])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        sched.step()
        recent.append(float(loss.detach()))
        if cfg.log_every and (step + 1) % cfg.log_every == 0:
            log.info("step %d/%d: rms %.3f mm (last %d steps)", step + 1, cfg.steps,
                     math.sqrt(np.mean(recent)), len(recent))  # fmt: skip
            recent = []
    net.eval()
    model = DeformationModel(net, ref["body"], half_window, net_cfg, 1, steps).eval()
    facts = {
        "skeletons": [
            {"parts": len(b["parts"]), "windows": b["windows"], "steps": order.count(i)}
            for i, b in enumerate(banks)
        ],  # fmt: skip
        "steps": cfg.steps,
    }
    return model, facts
