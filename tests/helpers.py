"""Shared test helpers (pytest puts this folder on sys.path)."""

from __future__ import annotations

import numpy as np
import torch

from adjust.camera import CameraTensors, project_cameras
from adjust.io import Detections
from deformnet.body import default_mouse
from deformnet.deformation import DeformationModel, build_net


def tiny_lstm_config(num_parts: int) -> dict:
    """Net config of a tiny LSTM deformation net (window W = 5)."""
    return {
        "_target_": "deformnet.nets.LSTMPredictor",
        "num_parts": num_parts,
        "half_window": 2,
        "hidden": 8,
        "layers": 1,
        "embed": 8,
    }


def tiny_deformation_model(seed: int = 0, up=None) -> DeformationModel:
    """An untrained tiny LSTM DeformationModel of the default mouse (predicts the rigid model);
    up: the world up of its heading frame (None: the body frame)."""
    torch.manual_seed(seed)
    body = default_mouse()
    config = tiny_lstm_config(body.num_parts)
    return DeformationModel(build_net(config), body, 2, config, up=up)


def quiet_trainer(max_steps: int, **kwargs):
    """A Lightning trainer on the CPU for `max_steps` steps, without logger, checkpoints,
    progress bar or model summary (kwargs: further `lightning.Trainer` arguments)."""
    import lightning as L

    return L.Trainer(
        max_steps=max_steps,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
        **kwargs,
    )


def write_bout_labels(path, labels, classes, first: int = 0):
    """A per-frame label array (T,) (class indices) as the `start,stop,label` bouts CSV
    `deformnet-classify` reads, frame numbers from `first`; returns the path."""
    import pandas as pd

    from deformnet.behavior.labels import bouts

    rows = [
        {"start": a + first, "stop": b + first, "label": classes[c]} for a, b, c in bouts(labels)
    ]
    pd.DataFrame(rows, columns=["start", "stop", "label"]).to_csv(path, index=False)
    return path


def track_session(scene, out, overrides) -> dict:
    """`adjust-track` (its `run` through the compose API) on a session folder `scene` into
    `out`, without a progress bar; returns its summary."""
    from adjust.apps.track import run
    from deformnet.confutil import compose

    return run(
        compose(
            "track",
            [f"input.session={scene}", f"output.dir={out}", "progress=false", *overrides],
        )
    )


#: the recipe these tests were written for (before the default became the forest head with the
#: linear teacher): pinned unless a test sets the key itself
OLD_RECIPE = ("net=lstm", "head=mlp", "freeze=false", "measurements=false",
              "pseudo_labels.teacher=none", "context.frames=[15,33]")  # fmt: skip


def pinned(overrides) -> list[str]:
    """``overrides`` with `OLD_RECIPE`'s settings it does not set itself in front."""
    keys = {o.split("=")[0].lstrip("+~") for o in overrides}
    return [o for o in OLD_RECIPE if o.split("=")[0] not in keys] + list(overrides)


def wandering_path(t: np.ndarray, K: int = 8) -> np.ndarray:
    """(len(t), K, 3) mm at times t (frames): K parts at fixed offsets about a centre that
    wanders smoothly through the default rig's arena (period 300 frames)."""
    rng = np.random.default_rng(0)
    w = 2 * np.pi / 300
    centre = np.stack(
        [150 + 80 * np.cos(w * t), 150 + 70 * np.sin(2 * w * t), 30 + 15 * np.sin(3 * w * t)], -1
    )
    return centre[:, None] + rng.normal(0, 20, (K, 3))


def projected_detections(cams, X, noise: float, rng: np.random.Generator):
    """`adjust.io.Detections` of points X (T, K, 3) mm seen by every camera of `cams`, with
    Gaussian pixel noise of sd `noise` drawn from `rng`: parts p0.., likelihood 1, files
    <camera>.csv, frames 0..T-1."""
    ct = CameraTensors.from_cameras(cams, dtype=torch.float64)
    xy = project_cameras(torch.as_tensor(X), ct).numpy()
    xy = xy + rng.normal(0, noise, xy.shape)
    T, K, C = xy.shape[:3]
    return Detections(
        tuple(c.name for c in cams),
        tuple(f"p{k}" for k in range(K)),
        xy,
        np.ones((T, K, C)),
        tuple(f"{c.name}.csv" for c in cams),
        0.5,
        np.arange(T),
    )


def own_clock_detections(cams, T: int, c: int, times: np.ndarray, noise: float = 0.5):
    """`projected_detections` of `wandering_path` at frames 0..T-1, camera c's rows g = 0,
    1, ... showing the times `times` (frames) instead: a camera with its own clock or frame
    rate, its file numbered in its own frames. Rows: the union of the files' frames."""
    rng = np.random.default_rng(1)
    base = projected_detections(cams, wandering_path(np.arange(T, dtype=np.float64)), noise, rng)
    own = projected_detections(cams, wandering_path(np.asarray(times, float)), noise, rng)
    n = max(T, len(times))
    xy = np.full((n, base.num_parts, len(cams), 2), np.nan)
    lik = np.zeros((n, base.num_parts, len(cams)))
    xy[:T], lik[:T] = base.xy, base.likelihood
    xy[:, :, c], lik[:, :, c] = np.nan, 0.0
    xy[: len(times), :, c], lik[: len(times), :, c] = own.xy[:, :, c], 1.0
    return Detections(base.cameras, base.parts, xy, lik, base.files, 0.5, np.arange(n))
