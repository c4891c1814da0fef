"""A behavior classifier's features: every frame of some sessions as a window centre
(`SessionBank`), their context features (`context_features`: the encoder run once per frame a
context needs), the training frames' feature range and the share of a frame's features outside
it (`feature_range`, `unfamiliar_share`), the sessions' body scales (`set_body_scales`).
Shapes: N frames, D features."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from deformnet.behavior.tracks import Session, body_scale

log = logging.getLogger(__name__)

__all__ = ["SessionBank", "Frames", "context_features", "feature_range",
           "unfamiliar_share", "BODY_SCALE_MODES",
           "set_body_scales"]  # fmt: skip


class SessionBank:
    """All frames of some sessions as window centres: each session is padded with its first /
    last frame n times (padding marked unobserved), so every frame has a full window."""

    def __init__(self, sessions: Sequence[Session], half_window: int) -> None:
        n = self.n = int(half_window)
        rig, dfm, obs, mids, lab, scl = [], [], [], [], [], []
        off = 0
        scaled = {s.scale is not None for s in sessions}
        if len(scaled) > 1:
            raise ValueError("sessions with and without a body scale cannot share a bank")
        for s in sessions:
            T = len(s)
            pad = ((n, n), (0, 0), (0, 0))
            rig.append(np.pad(s.rigid, pad, mode="edge"))
            dfm.append(np.pad(s.deformed, pad, mode="edge"))
            obs.append(np.pad(s.observed, ((n, n), (0, 0)), constant_values=False))
            mids.append(off + n + np.arange(T))
            lab.append(s.labels)
            scl.append(np.full(T + 2 * n, 1.0 if s.scale is None else s.scale, np.float32))
            off += T + 2 * n
        self.rigid = torch.from_numpy(np.concatenate(rig).astype(np.float32))
        self.deformed = torch.from_numpy(np.concatenate(dfm).astype(np.float32))
        self.observed = torch.from_numpy(np.concatenate(obs))
        self.mids = torch.from_numpy(np.concatenate(mids).astype(np.int64))
        self.labels = torch.from_numpy(np.concatenate(lab).astype(np.int64))
        #: each bank frame's session body scale (the classifier divides it out), or None
        self.scale = torch.from_numpy(np.concatenate(scl)) if scaled == {True} else None

    def __len__(self) -> int:
        return len(self.mids)

    def batch(self, idx: Tensor) -> dict:
        frames = self.mids[idx][:, None] + torch.arange(-self.n, self.n + 1)
        out = {
            "rigid": self.rigid[frames],
            "deformed": self.deformed[frames],
            "observed": self.observed[frames],
            "label": self.labels[idx],
        }
        if self.scale is not None:
            out["scale"] = self.scale[self.mids[idx]]
        return out


class Frames(torch.utils.data.Dataset):
    def __init__(self, bank: SessionBank, idx: np.ndarray) -> None:
        self.bank, self.idx = bank, torch.as_tensor(idx, dtype=torch.long)

    def __len__(self) -> int:
        return len(self.idx)

    def __getitem__(self, i: int) -> int:
        return int(self.idx[i])

    def collate(self, items: list[int]) -> dict:
        return self.bank.batch(torch.as_tensor(items, dtype=torch.long))


@torch.no_grad()
def context_features(model, bank: SessionBank, idx, batch_size: int = 512) -> Tensor:
    """The classifier's (not standardised) features (N, out_dim) of the bank frames ``idx``
    (N,), the encoder run once per distinct frame that a context needs (in eval mode; the
    model's train / eval modes are restored)."""
    modes = {m: m.training for m in model.modules()}
    try:
        model.eval()
        return _context_features(model, bank, idx, batch_size)
    finally:
        for m, mode in modes.items():
            m.training = mode


def _encode(model, bank: SessionBank, positions: Tensor, batch_size: int) -> Tensor:
    """The encoder's outputs (P, encoder.out_dim) of the windows centred at ``positions`` (P,)
    in the bank's arrays."""
    enc = model.encoder
    if bank.n != model.half_window:
        raise ValueError(f"bank half window {bank.n} != the classifier's {model.half_window}")
    steps = torch.arange(-enc.half_window, enc.half_window + 1)
    feats = []
    for chunk in positions.split(int(batch_size)):
        fr = chunk[:, None] + steps
        scale = None if bank.scale is None else bank.scale[chunk]
        feats.append(enc(bank.rigid[fr], bank.deformed[fr], bank.observed[fr], scale))
    return torch.cat(feats) if feats else torch.zeros(0, enc.out_dim)


def _context_features(model, bank: SessionBank, idx, batch_size: int) -> Tensor:
    idx = torch.as_tensor(idx, dtype=torch.long)
    offsets = torch.as_tensor(model.offsets)
    pos = bank.mids[idx][:, None] + offsets  # (N, O) positions in the bank's arrays
    uniq, inverse = torch.unique(pos, return_inverse=True)
    F = _encode(model, bank, uniq, batch_size)
    out = [
        model.pool(F[inv])
        for inv in inverse.split(max(1, int(batch_size) * 8 // max(len(model.offsets), 1)))
    ]
    return torch.cat(out) if out else torch.zeros(0, model.out_dim)


#: the training frames' range of each classifier feature that a recording's frames are compared
#: with (`feature_range`): its RANGE_QUANTILE and 1 - RANGE_QUANTILE quantiles, widened on each
#: side by RANGE_MARGIN sqrt(RANGE_FRAMES / N) of their distance for N training frames (few
#: frames give a narrow range: another session of the same animal would fall outside it)
RANGE_QUANTILE = 0.001
RANGE_MARGIN = 0.1
RANGE_FRAMES = 3000


def feature_range(features: Tensor, q: float = RANGE_QUANTILE, margin: float | None = None) -> dict:
    """The range of the training frames' classifier features (N, D) (`context_features`):
    {"low", "high" (D,) float32: the q and 1 - q quantiles, each moved out by ``margin`` times
    their distance (default RANGE_MARGIN sqrt(RANGE_FRAMES / N)); "quantile", "margin",
    "frames": N}; stored in classifier.pt so that `unfamiliar_share` can tell a recording
    unlike the training data."""
    if features.dim() != 2 or features.shape[0] < 2:
        raise ValueError(f"features must be (N >= 2, D), got {tuple(features.shape)}")
    if not 0.0 <= float(q) < 0.5:
        raise ValueError(f"the range quantile must be in [0, 0.5), got {q}")
    n = int(features.shape[0])
    m = RANGE_MARGIN * math.sqrt(RANGE_FRAMES / n) if margin is None else float(margin)
    if not m >= 0:
        raise ValueError(f"the range margin must be >= 0, got {margin}")
    x = features.detach().double().numpy()
    low, high = np.quantile(x, float(q), axis=0), np.quantile(x, 1.0 - float(q), axis=0)
    span = high - low
    return {
        "low": torch.from_numpy(low - m * span).float(),
        "high": torch.from_numpy(high + m * span).float(),
        "quantile": float(q),
        "margin": m,
        "frames": n,
    }


def unfamiliar_share(features: Tensor, rng: Mapping) -> np.ndarray:
    """Per frame, the share of its classifier features (N, D) outside the training frames'
    range (`feature_range`) -> (N,) in [0, 1]. About 2 RANGE_QUANTILE on frames like the
    training data; frames of another animal, another rig or wrong tracks have far more."""
    low, high = torch.as_tensor(rng["low"]), torch.as_tensor(rng["high"])
    if features.dim() != 2 or features.shape[1] != low.shape[0]:
        raise ValueError(
            f"features must be (N, {low.shape[0]}) like the training range, got "
            f"{tuple(features.shape)}"
        )
    f = features.to(low.dtype)
    return ((f < low) | (f > high)).double().mean(-1).numpy()


BODY_SCALE_MODES = ("session", "none")


def set_body_scales(sessions: Sequence[Session], mode: str, body) -> None:
    """``body_scale``: "session" sets each session's `scale` to its `body_scale` against the
    classifier's body model (which it divides out; a session it cannot be measured on is a
    ValueError naming it), "none" to None (in place)."""
    mode = str(mode)
    if mode not in BODY_SCALE_MODES:
        raise ValueError(f"body_scale must be one of {BODY_SCALE_MODES}, got '{mode}'")
    for s in sessions:
        s.scale = None
        if mode == "session":
            s.scale = body_scale(body, s.rigid, s.deformed, s.observed, s.name)
            log.info("%s: body scale %.3f (the animal's size / the body model's)", s.name, s.scale)
