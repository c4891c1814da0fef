"""The DISK-style imputation peer: a transformer that fills the gaps of triangulated 3D
keypoints from the other keypoints and the frames around them, with no body model and no
cameras (after DISK, "Deep Imputation of SKeleton data", Rose et al.; our implementation).

DISK trains on segments of the lab's own 3D data that have no missing keypoint, hiding
keypoints over random gaps and learning to put them back; here:

- ``fit_disk(train, ...)``: train (N, T, K, 3) mm sequences, NaN = missing; windows of
  ``window`` frames, each centred on the mean of its present points and divided by ``scale``
  mm; every keypoint hidden over a random gap (probability ``gap_prob``, length 1..window) on
  top of what is already missing; the loss (mean squared error) on the hidden points that were
  present. With complete training data (e.g. a simulator's) that is DISK's protocol; with the
  scene's own incomplete points it learns from whatever is there (DISK itself needs complete
  segments, and an occluded recording may have none).
- ``impute(model, points)``: points (T, K, 3) with NaN -> every point: the present ones as they
  are, the missing ones the average of the overlapping windows' predictions (stride half a
  window, triangular weights).

Token per frame: the K x 3 coordinates (0 where missing) and the K presence flags; a linear
embedding, sinusoidal positions, a transformer encoder, a linear read-out of K x 3.
"""

from __future__ import annotations

import math
import time
import warnings

import numpy as np
import torch
from torch import nn

WINDOW = 60  # frames a window spans (`fit_disk`'s default)


class DiskImputer(nn.Module):
    """(B, W, K, 3) points normalised (centred on the window's present points, divided by
    `scale` mm), (B, W, K) presence -> (B, W, K, 3)."""

    def __init__(
        self,
        parts: int,
        window: int,
        scale: float,
        dim: int = 128,
        layers: int = 4,
        heads: int = 4,
    ):
        super().__init__()
        self.parts, self.window, self.scale = int(parts), int(window), float(scale)
        self.embed = nn.Linear(4 * self.parts, dim)
        from deformnet.nets import sinusoidal_encoding

        pe = sinusoidal_encoding(self.window, dim)
        self.register_buffer("pos", pe)
        layer = nn.TransformerEncoderLayer(dim, heads, 4 * dim, dropout=0.0, batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, layers)
        self.out = nn.Linear(dim, 3 * self.parts)

    def forward(self, x: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        B, W, K, _ = x.shape
        x = torch.where(present[..., None], x, torch.zeros_like(x))
        tok = torch.cat((x.reshape(B, W, 3 * K), present.to(x.dtype)), -1)
        h = self.encoder(self.embed(tok) + self.pos[:W])
        return self.out(h).reshape(B, W, K, 3)


def _normalise(win: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(..., W, K, 3) with NaN -> normalised windows and their centres (..., 3)."""
    with warnings.catch_warnings():  # a window with no present point: centre 0
        warnings.simplefilter("ignore", RuntimeWarning)
        c = np.nan_to_num(np.nanmean(win.reshape(*win.shape[:-3], -1, 3), axis=-2))
    return (win - c[..., None, None, :]) / scale, c


def fit_disk(
    train: np.ndarray,
    seconds: float = 180.0,
    window: int = WINDOW,
    scale: float = 50.0,
    gap_prob: float = 0.5,
    batch: int = 32,
    seed: int = 0,
) -> tuple[DiskImputer, dict]:
    """Train on (N, T, K, 3) sequences (NaN = missing) for `seconds`; (model, facts)."""
    train = np.asarray(train, dtype=np.float64)
    if train.ndim != 4 or train.shape[-1] != 3 or train.shape[1] < window:
        raise ValueError(f"train must be (N, T >= {window}, K, 3), got {train.shape}")
    N, T, K, _ = train.shape
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    model = DiskImputer(K, window, scale)
    opt = torch.optim.Adam(model.parameters(), lr=3e-4)
    t0, steps, losses = time.perf_counter(), 0, []
    while time.perf_counter() - t0 < seconds:
        n = rng.integers(0, N, batch)
        s = rng.integers(0, T - window + 1, batch)
        win = np.stack([train[i, j : j + window] for i, j in zip(n, s, strict=True)])
        present = np.isfinite(win).all(-1)
        hide = np.zeros_like(present)
        for b in range(batch):
            for k in range(K):
                if rng.random() < gap_prob:
                    g = int(rng.integers(1, window + 1))
                    a = int(rng.integers(0, window - g + 1))
                    hide[b, a : a + g, k] = True
        target = present & hide
        if not target.any():
            continue
        seen = present & ~hide
        x, c = _normalise(np.where(seen[..., None], win, np.nan), scale)
        y = (np.nan_to_num(win) - c[:, None, None, :]) / scale  # the target, centred alike
        pred = model(torch.tensor(np.nan_to_num(x), dtype=torch.float32), torch.tensor(seen))
        m = torch.tensor(target)
        loss = ((pred - torch.tensor(y, dtype=torch.float32)) ** 2).sum(-1)[m].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        steps += 1
        losses.append(float(loss.detach()))
    rmse = scale * math.sqrt(np.mean(losses[-50:])) if losses else float("nan")
    facts = {"steps": steps, "seconds": round(time.perf_counter() - t0, 1),
             "train_rmse_mm_last50": rmse, "window": window, "scale": scale}  # fmt: skip
    return model.eval(), facts


@torch.no_grad()
def impute(model: DiskImputer, points: np.ndarray) -> np.ndarray:
    """points (T, K, 3) mm, NaN = missing -> (T, K, 3): present points kept, missing filled."""
    points = np.asarray(points, dtype=np.float64)
    scale = model.scale
    T, K, _ = points.shape
    W = model.window
    if T < W:
        raise ValueError(f"{T} frames < the imputer's window {W}")
    starts = list(range(0, T - W + 1, W // 2))
    if starts[-1] != T - W:
        starts.append(T - W)
    acc = np.zeros((T, K, 3))
    wsum = np.zeros((T, 1, 1))
    tri = 1.0 - np.abs(np.linspace(-1, 1, W + 2)[1:-1])  # triangular weights, > 0
    for s in starts:
        win = points[s : s + W]
        present = np.isfinite(win).all(-1)
        x, c = _normalise(win, scale)
        pred = (
            model(
                torch.tensor(np.nan_to_num(x)[None], dtype=torch.float32),
                torch.tensor(present[None]),
            )[0]
            .double()
            .numpy()
        )
        acc[s : s + W] += tri[:, None, None] * (pred * scale + c)
        wsum[s : s + W] += tri[:, None, None]
    filled = acc / wsum
    return np.where(np.isfinite(points).all(-1, keepdims=True), points, filled)
