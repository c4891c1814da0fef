"""``adjust-track deformation=self``: fine-tune the shipped net on the recording's own tokens.

A plain torch loop, no Lightning trainer: one recording's fine-tune is a few hundred small
steps, and a trainer's start-up, checkpoint files and per-epoch machinery cost as much as the
steps themselves (importing Lightning alone takes seconds). The objective is deformnet-train's
(``data=sessions``): the masked mid token of the recording's windows (`deformnet.windows`,
masked and augmented as ``deformnet-train data=sessions`` does), split by time blocks
(`deformnet.sessions.split_sessions`); the held-out blocks' windows are scored every
``adapt.eval_every`` steps (`deformnet.heldout.window_sums`: the net, rigid, linear and offset
interpolation on the same windows), the best weights are kept, and training stops after
``adapt.max_steps`` steps, after ``adapt.patience`` scores without improvement, or at
``adapt.max_time``, whichever comes first. ``adapt.accelerator=auto`` trains on a GPU when
torch sees one (`select_device`).

The starting net is whatever `deformnet.pretrained.load_default` returns (`starting_model`):
the same parts, or a part-agnostic net (one that identifies parts by their rest coordinates,
``net.part_agnostic``), fine-tune it on this recording's body; another skeleton gets a net of
its architecture built for its parts and trained from scratch.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from deformnet.atomic import write_text
from deformnet.body import BodyModel
from deformnet.deformation import DeformationModel, build_net, check_track_up
from deformnet.heldout import summed_over, window_sums
from deformnet.pretrained import load_default, load_net, net_spec
from deformnet.sessions import split_sessions
from deformnet.threads import torch_threads
from deformnet.tokens import masked_mse
from deformnet.windows import (
    Augment,
    FixedWindowBatches,
    MaskConfig,
    RandomWindowBatches,
    WindowBank,
    mirror_asymmetry,
    mirror_permutation,
)

log = logging.getLogger("adjust.track")

__all__ = ["AdaptConfig", "adapt_net", "select_device", "starting_model", "fine_tune"]

ACCELERATORS = ("auto", "cpu", "cuda", "gpu")


def _seconds(max_time: Any) -> float | None:
    """Seconds of ``DD:HH:MM:SS`` (or a number of seconds); None or "" for no limit."""
    if max_time is None or max_time == "":
        return None
    if isinstance(max_time, (int, float)):
        return float(max_time)
    try:
        d, h, m, s = (float(x) for x in str(max_time).split(":"))
    except ValueError:
        raise ValueError(
            f"adapt.max_time must be DD:HH:MM:SS (e.g. 00:00:03:00), got {max_time!r}"
        ) from None
    return ((d * 24 + h) * 60 + m) * 60 + s


@dataclass(frozen=True)
class AdaptConfig:
    """The ``adapt:`` block of adjust-track's config (conf/track.yaml documents each key)."""

    pretrained: str | None = "default"
    max_steps: int = 150
    eval_every: int = 25
    patience: int = 2
    min_improvement: float = 0.002
    max_time: float | None = 180.0  # seconds (the config's DD:HH:MM:SS)
    accelerator: str = "auto"
    val_fraction: float = 0.2
    block_frames: int = 500
    val_windows: int = 512
    batch_size: int = 128
    lr: float = 1e-3
    weight_decay: float = 1e-4
    warmup_steps: int = 10
    seed: int = 0
    step: int = 1
    #: as conf/track.yaml's (a config without the key: still augmented, as the YAML says)
    augment: Augment = dataclasses.field(
        default_factory=lambda: Augment(mirror=0.5, reverse=0.5, steps=(1, 1, 2, 3))
    )
    threads: int | None = None
    tensorboard: bool = False
    require_better: bool = True
    min_gain: float = 0.02

    @classmethod
    def from_any(cls, cfg: Mapping[str, Any] | AdaptConfig | None) -> AdaptConfig:
        """From the config's mapping (unknown keys: a ValueError naming them)."""
        if isinstance(cfg, AdaptConfig):
            return cfg
        d = dict(cfg or {})
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown adapt options {sorted(unknown)}; known: {sorted(names)}")
        if "max_time" in d:
            d["max_time"] = _seconds(d["max_time"])
        if "augment" in d:
            d["augment"] = Augment.from_any(d["augment"])
        if "pretrained" in d:  # absent: the field's default
            d["pretrained"] = net_spec(d["pretrained"])
        out = cls(**d)
        for key in ("max_steps", "eval_every", "batch_size", "val_windows", "step"):
            if int(getattr(out, key)) < 1:
                raise ValueError(f"adapt.{key} must be >= 1, got {getattr(out, key)}")
        if int(out.patience) < 1:
            raise ValueError(f"adapt.patience must be >= 1 evaluation, got {out.patience}")
        if str(out.accelerator) not in ACCELERATORS:
            raise ValueError(
                f"adapt.accelerator must be one of {', '.join(ACCELERATORS)}, "
                f"got {out.accelerator!r}"
            )
        return out


def select_device(accelerator: str) -> torch.device:
    """``adapt.accelerator`` -> the torch device to train on: auto = CUDA when
    `torch.cuda.is_available()`, else the CPU; cuda / gpu = CUDA (a ValueError when there is
    none); cpu = the CPU."""
    acc = str(accelerator).lower()
    if acc not in ACCELERATORS:
        raise ValueError(
            f"adapt.accelerator must be one of {', '.join(ACCELERATORS)}, got {accelerator!r}"
        )
    if acc == "cpu":
        return torch.device("cpu")
    if torch.cuda.is_available():
        return torch.device("cuda")
    if acc == "auto":
        return torch.device("cpu")
    raise ValueError(f"adapt.accelerator={accelerator}: torch sees no CUDA device on this machine")


def mirror_perm(body: BodyModel, augment: Augment) -> list[int] | None:
    """The part permutation of a mirrored window when ``augment.mirror`` > 0 and the body is
    its own mirror image (left/right pairs, `deformnet.windows.mirror_permutation`, and the
    model within 10% of its size of its reflection: deformnet-train's rule,
    `deformnet.data.DeformDataModule`); else None (no mirroring)."""
    if augment.mirror <= 0:
        return None
    perm = mirror_permutation(body.parts)
    if perm is None:
        return None
    pts = np.asarray(body.points, dtype=np.float64)
    size = float(np.sqrt(((pts - pts.mean(0)) ** 2).sum(-1).mean()))
    return None if mirror_asymmetry(pts, perm) > 0.1 * size else perm


def window_data(
    tokens, model: DeformationModel, cfg: AdaptConfig
) -> tuple[RandomWindowBatches, FixedWindowBatches, dict]:
    """The recording's training windows (random, masked, augmented; `eval_every` per pass)
    and held-out windows (fixed), split by time blocks; and the split's facts."""
    step = int(cfg.step)
    window = 2 * model.half_window * step + 1
    train, val, facts = split_sessions(
        [tokens], float(cfg.val_fraction), int(cfg.block_frames), min_frames=window
    )
    masking = MaskConfig()  # deformnet-train's (conf/data/sim.yaml masking)
    bank = WindowBank(train, model.half_window, step)
    train_set = RandomWindowBatches(
        bank, int(cfg.batch_size), int(cfg.eval_every), masking, int(cfg.seed),
        augment=cfg.augment, mirror_perm=mirror_perm(model.body, cfg.augment),
    )  # fmt: skip
    vbank = WindowBank(val, model.half_window, step)
    val_set = FixedWindowBatches.build(
        vbank, int(cfg.val_windows), int(cfg.batch_size), int(cfg.seed) + 1, masking
    )
    return train_set, val_set, facts


def starting_model(
    pretrained: DeformationModel | None, body: BodyModel
) -> tuple[DeformationModel, str]:
    """The model fine-tuning starts from, on the recording's ``body`` (its body model: the
    canonical frames are the recording's), and how it was made: "fine-tune" (a copy of
    ``pretrained``'s net when it has ``body``'s parts, or when it is part-agnostic,
    `DeformationModel.part_agnostic`: it identifies parts by their rest coordinates;
    `DeformationModel.for_body`) or "scratch"
    (``pretrained``'s architecture built for ``body``'s parts, starting from the interpolation
    prior: ``prior_residual``; with no pretrained net, the shipped net's architecture)."""
    if pretrained is not None and (
        tuple(pretrained.body.parts) == tuple(body.parts) or pretrained.part_agnostic
    ):
        return copy.deepcopy(pretrained).for_body(body), "fine-tune"
    if pretrained is None:  # the shipped net's architecture
        pretrained = load_default()
    arch = pretrained
    if arch.net_config is None:
        raise ValueError("deformation=self: the starting net has no net_config to rebuild it")
    ncfg = dict(arch.net_config, num_parts=body.num_parts, prior_residual=True)
    net = build_net(ncfg)
    return DeformationModel(net, body, arch.half_window, ncfg, arch.step, arch.steps, arch.up), (
        "scratch"
    )


def _forever(batches):
    """The batches of an iterable, passed over again and again (a random window sampler draws
    fresh windows on every pass)."""
    while True:
        yield from batches


def _to(batch: Mapping[str, Any], device: torch.device) -> dict:
    return {
        k: (_to(v, device) if isinstance(v, Mapping) else v.to(device, non_blocking=True))
        for k, v in batch.items()
    }


def evaluate(model: DeformationModel, batches, device: torch.device) -> dict[str, float]:
    """RMSE (mm) of the net and of the rigid, linear and offset (interp) baselines over
    held-out windows (the mid frame's measured parts)."""
    sums = summed_over(
        model, batches, lambda b: window_sums(model, _to(b, device), model.half_window)
    )
    total = sums["count"].sum().clamp_min(1.0)
    return {
        name: float((sums[key].sum() / total).sqrt())
        for name, key in (("net", "net"), ("rigid", "rigid"), ("linear", "linear"),
                          ("interp", "offset"))
    }  # fmt: skip


class AdamW:
    """AdamW (decoupled weight decay; the update of ``torch.optim.AdamW`` with its defaults),
    the learning rate given at each step. Not torch.optim's: its first use imports
    ``torch._dynamo``, 3-6 s on this shared 2-core machine, about the default tracking's time.

    groups: [(parameters, weight decay), ...]."""

    def __init__(self, groups, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.groups = [(list(ps), float(wd)) for ps, wd in groups]
        self.betas, self.eps, self.t = betas, float(eps), 0
        self.state = {
            id(p): (torch.zeros_like(p), torch.zeros_like(p)) for ps, _ in self.groups for p in ps
        }

    def zero_grad(self) -> None:
        for ps, _ in self.groups:
            for p in ps:
                p.grad = None

    @torch.no_grad()
    def step(self, lr: float) -> None:
        self.t += 1
        b1, b2 = self.betas
        c1, c2 = 1.0 - b1**self.t, 1.0 - b2**self.t
        for ps, wd in self.groups:
            for p in ps:
                if p.grad is None:
                    continue
                m, v = self.state[id(p)]
                p.mul_(1.0 - lr * wd)
                m.lerp_(p.grad, 1.0 - b1)
                v.mul_(b2).addcmul_(p.grad, p.grad, value=1.0 - b2)
                denom = (v.sqrt() / math.sqrt(c2)).add_(self.eps)
                p.addcdiv_(m, denom, value=-lr / c1)


def fine_tune(
    model: DeformationModel,
    train_batches,
    val_batches,
    cfg: AdaptConfig,
    device: torch.device,
    on_eval=None,
) -> dict:
    """Train ``model`` in place on ``train_batches`` (an iterable of window batches, passed
    over again as often as needed) and keep its best weights on ``val_batches``: AdamW, linear
    warm-up then cosine decay over ``cfg.max_steps`` (or ``cfg.max_time``, when that comes
    first); scored before the first step and every ``cfg.eval_every`` steps; stops at
    ``max_steps``, ``max_time`` or after ``patience`` scores that improve the best by less
    than ``min_improvement`` (relative). on_eval(step, scores): called after each
    score. Returns the facts: steps, evaluations, stop reason, best step and scores, history."""
    model.to(device).train()
    params = [p for p in model.parameters() if p.requires_grad]
    decay = [p for p in params if p.ndim >= 2]
    no_decay = [p for p in params if p.ndim < 2]
    opt = AdamW([(decay, float(cfg.weight_decay)), (no_decay, 0.0)])
    total = int(cfg.max_steps)
    warm = max(1, min(int(cfg.warmup_steps), total // 5))
    budget = cfg.max_time
    t0 = time.monotonic()

    def factor(step: int) -> float:
        if step < warm:
            return (step + 1) / warm
        p = (step - warm) / max(1, total - warm)
        if budget:
            p = max(p, (time.monotonic() - t0) / budget)
        return 0.02 + 0.98 * 0.5 * (1.0 + math.cos(math.pi * min(1.0, p)))

    scores = evaluate(model, val_batches, device)
    history = [{"step": 0, **scores}]
    if on_eval is not None:
        on_eval(0, scores)
    best = {"step": 0, **scores}
    best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    stale, step, reason = 0, 0, "max_steps"
    for batch in _forever(train_batches):
        b = _to(batch, device)
        pred_c, R, t = model.canonical(b["rigid"], b["deformed"], b["observed"])
        loss = masked_mse(pred_c, (b["target"] - t[:, None, :]) @ R, b["target_mask"])
        opt.zero_grad()
        loss.backward()
        opt.step(float(cfg.lr) * factor(step))
        step += 1
        out_of_time = budget is not None and time.monotonic() - t0 >= budget
        if step % int(cfg.eval_every) == 0 or step >= total or out_of_time:
            scores = evaluate(model, val_batches, device)
            history.append({"step": step, "loss": float(loss.detach()), **scores})
            if on_eval is not None:
                on_eval(step, scores)
            if scores["net"] < best["net"]:
                improved = scores["net"] < best["net"] * (1.0 - float(cfg.min_improvement))
                best = {"step": step, **scores}
                best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
                stale = 0 if improved else stale + 1
            else:
                stale += 1
            if stale >= int(cfg.patience):
                reason = "no improvement"
                break
        if out_of_time:
            reason = "max_time"
            break
        if step >= total:
            break
    model.load_state_dict(best_state)
    model.eval()
    return {
        "steps": step,
        "evaluations": len(history),
        "stopped": reason,
        "best_step": best["step"],
        "best": {k: v for k, v in best.items() if k != "step"},
        "seconds": round(time.monotonic() - t0, 2),
        "history": history,
    }


def _tensorboard(path: Path):
    """A SummaryWriter at ``path`` (imported here: tensorboard is optional and slow to load)."""
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(str(path))


def adapt_net(tokens, out: Path, adapt_cfg, progress: bool) -> tuple:
    """``deformation=self``: fine-tune the starting net (`starting_model`: the shipped one by
    default) on this recording's tokens (`fine_tune`, split by time blocks). Writes the adapted
    model ``out/deformation.ckpt`` and the fine-tuning's record ``out/adapt/metrics.json``
    (``adapt.tensorboard``: scalars in ``out/adapt/tb``); returns (model on the CPU, facts)."""
    cfg = AdaptConfig.from_any(adapt_cfg)
    device = select_device(cfg.accelerator)
    work = Path(out) / "adapt"
    work.mkdir(parents=True, exist_ok=True)
    pre = load_net(cfg.pretrained, "adapt.pretrained")  # None: from scratch
    body = tokens.body_model()
    model, how = starting_model(pre, body)
    if how == "scratch" and pre is not None:
        log.warning(
            "deformation=self: the starting net knows the parts %s, this recording has %s: "
            "training a net of its architecture from scratch",
            list(pre.body.parts),
            list(tokens.parts),
        )
    if model.up is not None:
        check_track_up(tokens.rigid, tokens.body_points, model.up, tokens.source or "recording")
    with torch_threads(cfg.threads):
        torch.manual_seed(int(cfg.seed))
        train, val, data_facts = window_data(tokens, model, cfg)
        step = int(cfg.step)
        model.steps = tuple(sorted({step, *(cfg.augment.steps or (step,))}))
        model.step = step
        writer = _tensorboard(work / "tb") if cfg.tensorboard else None
        bar = None
        if progress:
            from rich.progress import Progress  # (the console bar only when asked for)

            bar = Progress(transient=True)
            task = bar.add_task("fine-tuning (deformation=self)", total=int(cfg.max_steps))
            bar.start()

        def on_eval(s: int, scores: dict) -> None:
            if writer is not None:
                for k, v in scores.items():
                    writer.add_scalar(f"val/rmse_mm_{k}" if k != "net" else "val/rmse_mm", v, s)
            if bar is not None:
                bar.update(task, completed=s)
            log.debug("adapt step %d: %s", s, scores)

        try:
            facts = fine_tune(model, train, val, cfg, device, on_eval)
        finally:
            if bar is not None:
                bar.stop()
            if writer is not None:
                writer.close()
    model = model.cpu().eval()
    ckpt = Path(out) / "deformation.ckpt"
    model.save(ckpt)
    best = facts["best"]
    log.info(
        "deformation=self: %s, %d steps on %s (%s; best at step %d, %.1f s): held-out tokens "
        "%.2f mm (linear %.2f, interp %.2f, rigid %.2f)",
        how, facts["steps"], device.type, facts["stopped"], facts["best_step"], facts["seconds"],
        best["net"], best["linear"], best["interp"], best["rigid"],
    )  # fmt: skip
    write_text(
        work / "metrics.json",
        json.dumps({"start": how, "device": device.type, **facts, "data": data_facts}, indent=2)
        + "\n",
    )
    result = {
        "pretrained": cfg.pretrained if how == "fine-tune" else None,
        "start": how,
        "checkpoint": str(ckpt),
        "device": device.type,
        "steps": facts["steps"],
        "best_step": facts["best_step"],
        "stopped": facts["stopped"],
        "train_s": facts["seconds"],
        "val_rmse_mm": best["net"],
        "val_rmse_mm_rigid": best["rigid"],
        "val_rmse_mm_linear": best["linear"],
        "val_rmse_mm_interp": best["interp"],
        "data": data_facts,
    }
    return model, result
