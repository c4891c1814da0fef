"""A deformation net against interpolation on a recording's own held-out parts.

No Lightning: `adjust-track` uses it to decide, part by part, whether a net it did not train on
this recording (``deformation=default`` or a checkpoint) predicts this recording's hidden parts
better than the interpolation it would otherwise use (``deform.require_better``: against
`offset_baseline`, the rigid model plus interpolated offsets, as ``deformation=interp``);
`DeformLit`'s validation sums the same errors (`window_sums`), and `adjust.net_gate`'s
comparison with interp's kriging adds them up and reports them as this module does
(`summed_over`, `rmse_by_part`).

The windows are the training-like masked windows of `deformnet.windows` over the recording's
tokens (`deformnet.sessions.SessionTokens`): the mid frame's measured parts are the targets,
hidden from both predictors, and gaps are hidden around them as occlusions hide them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch
from torch import Tensor

from deformnet.tokens import linear_baseline, offset_baseline
from deformnet.windows import FixedWindowBatches, MaskConfig, WindowBank

__all__ = [
    "window_sums",
    "heldout_errors",
    "evaluating",
    "summed_over",
    "rmse_by_part",
    "MIN_TARGETS",
    "WINDOWS",
]

MIN_TARGETS = 50  # a part with fewer held-out targets is not judged (too few to tell)
WINDOWS = 2048  # masked windows a recording's held-out check draws (`heldout_errors`, the gate)


def window_sums(model, batch: Mapping[str, Tensor], mid: int) -> dict[str, Tensor]:
    """Per-part sums over a batch of windows: squared 3D errors (mm^2) of the net, the rigid
    mid point, `linear_baseline` and `offset_baseline`, and the number of targets.

    model: a `DeformationModel` (global windows -> mid-frame positions); batch: rigid,
    deformed (B, W, K, 3), observed (B, W, K), target (B, K, 3), target_mask (B, K);
    mid: the mid frame's index in the window. Returns {"net", "rigid", "linear", "offset",
    "count"}, each (K,) float64."""
    rigid, deformed, observed = batch["rigid"], batch["deformed"], batch["observed"]
    target, mask = batch["target"], batch["target_mask"]
    if rigid.ndim != 4 or target.shape != (rigid.shape[0], rigid.shape[2], 3):
        raise ValueError(
            f"window_sums: rigid (B, W, K, 3) and target (B, K, 3), got {tuple(rigid.shape)} "
            f"and {tuple(target.shape)}"
        )
    m = mask.to(rigid.dtype)

    def sums(pred: Tensor) -> Tensor:
        return (((pred - target) ** 2).sum(-1) * m).sum(0).double()

    pred = model(rigid, deformed, observed)
    return {
        "net": sums(pred),
        "rigid": sums(rigid[:, mid]),
        "linear": sums(linear_baseline(rigid, deformed, observed, mid)),
        "offset": sums(offset_baseline(rigid, deformed, observed, mid)),
        "count": m.sum(0).double(),
    }


@contextmanager
def evaluating(model: torch.nn.Module) -> Iterator[torch.nn.Module]:
    """`model` in eval mode without gradients inside the block; its training flag restored
    after (an exception included)."""
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            yield model
    finally:
        model.train(was_training)


def summed_over(
    model: torch.nn.Module,
    batches: Iterable[Mapping[str, Tensor]],
    sums: Callable[[Mapping[str, Tensor]], Mapping[str, Tensor]],
) -> dict[str, Tensor]:
    """Each key's per-part sums (K,) added up over `batches` in order, `sums(batch)` run with
    `model` `evaluating` (e.g. `window_sums` of the batch)."""
    total: dict[str, Tensor] = {}
    with evaluating(model):
        for batch in batches:
            for k, v in sums(batch).items():
                total[k] = total[k] + v if k in total else v
    return total


def rmse_by_part(sums: Mapping[str, Tensor], count: Tensor) -> dict[str, tuple[list[float], float]]:
    """Root mean squared errors from per-part sums of squared errors: sums {name: (K,)},
    count (K,) targets per part -> {name: (per part [K] (NaN where a part has no target),
    over all parts (NaN without any target))}."""
    n = float(count.sum())
    out: dict[str, tuple[list[float], float]] = {}
    for k, x in sums.items():
        r = (x / count.clamp_min(1.0)).sqrt()
        part = [float(v) if c > 0 else float("nan") for v, c in zip(r, count)]
        out[k] = (part, float(np.sqrt(float(x.sum()) / n)) if n > 0 else float("nan"))
    return out


def heldout_errors(
    model,
    tokens,
    windows: int = WINDOWS,
    batch_size: int = 256,
    seed: int = 0,
    step: int | None = None,
    masking: Any = None,
) -> dict:
    """RMSE (mm) of `model`, of offset interpolation (`offset_baseline`) and of linear
    interpolation on `windows` evenly spaced masked windows of a recording's tokens, per part
    and over all.

    tokens: a `deformnet.sessions.SessionTokens` (its parts must be the model's); step: frames
    between tokens (None: the model's); masking: a `deformnet.windows.MaskConfig` or mapping
    (None: the training default). Returns {"parts", "net_mm", "interp_mm", "linear_mm",
    "rigid_mm", "targets" (lists per part; NaN where a part has no target), "net_all_mm",
    "interp_all_mm", "linear_all_mm", "windows"}. ValueError if the recording is shorter
    than one window."""
    parts = tuple(tokens.parts)
    if parts != tuple(model.body.parts):
        raise ValueError(
            f"heldout_errors: the tokens' parts {list(parts)} are not the net's "
            f"{list(model.body.parts)}"
        )
    step = int(model.step if step is None else step)
    bank = WindowBank([tokens.to_sequence()], model.half_window, step)
    data = FixedWindowBatches.build(
        bank, int(windows), int(batch_size), int(seed), MaskConfig.from_any(masking)
    )
    total = summed_over(
        model, data.batches, lambda batch: window_sums(model, batch, model.half_window)
    )
    count = total.pop("count")
    rmse = rmse_by_part(total, count)
    return {
        "parts": list(parts),
        "net_mm": rmse["net"][0],
        "interp_mm": rmse["offset"][0],
        "linear_mm": rmse["linear"][0],
        "rigid_mm": rmse["rigid"][0],
        "targets": [int(c) for c in count],
        "net_all_mm": rmse["net"][1],
        "interp_all_mm": rmse["offset"][1],
        "linear_all_mm": rmse["linear"][1],
        "windows": sum(int(b["rigid"].shape[0]) for b in data.batches),
    }
