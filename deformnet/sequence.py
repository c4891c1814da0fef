"""Behavior-scale masked pretraining, and the teacher it makes for few-label behavior heads.

The deformation net's windows (33 frames, in the body frame) are too short and too local to
need the behavior, and with about 1% of the frames labelled its features are worth no more to
a head than a random net's (`benchmarks/behavior_probe.py`). Here the pretraining is at the
behavior's own scale: each frame of a session is the classifier's per-frame feature vector (the
frozen deformation encoder's output, the pose, the per-part offsets, the lock-box mechanism
distances, the SimBA-style measurements; `deformnet.heads.BehaviorClassifier` without temporal
context), and a temporal convolutional net (`SequenceEncoder`: residual dilated convolutions)
reads a session's sequence of them with spans of frames hidden and learns to reconstruct the
hidden frames' frame features (`pretrain_sequences`; the hand-made features labs read, as in
"task programming", Sun et al., CVPR 2021). No labels: it learns from every training frame and
from more recordings of the same animals (`deformnet-classify data.unlabelled_tracks=`).

Its per-frame outputs with their mean and standard deviation over centred spans (`embeddings`)
are a frame's embedding. With few labels it is a teacher (`linear_teacher_probs`): a
class-weighted logistic regression on the embedding beside the binned frame features (`binned`:
one-hot quantile bins, so that a linear model can threshold a feature as a tree does) labels
the unlabelled training frames, and the forest head learns from the labelled and the
confidently pseudo-labelled ones (`deformnet.pseudo`; `deformnet-classify
pseudo_labels.teacher=sequence`). At test time the classifier is the forest on the frame
features; what the encoder adds is in the labels it was fitted on. The same regression on the
binned frame features alone is `pseudo_labels.teacher=linear`; over 16 simulated test sessions
at 1% labels it teaches nearly as well (README, Behavior: "Which teacher").

Shapes: T frames of a session, D per-frame features, N frames of several sessions concatenated
in order, C classes. Importable without Lightning.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from deformnet.checkpoint import load_checkpoint

log = logging.getLogger(__name__)

CLAMP = 8.0  # standardised per-frame features are clipped to +-CLAMP


class _Block(nn.Module):
    def __init__(self, channels: int, dilation: int) -> None:
        super().__init__()
        self.conv = nn.Conv1d(channels, channels, 3, padding=dilation, dilation=dilation)
        self.norm = nn.GroupNorm(1, channels)
        self.mix = nn.Conv1d(channels, channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        return x + self.mix(nn.functional.gelu(self.norm(self.conv(x))))


class SequenceEncoder(nn.Module):
    """A session's per-frame features -> per-frame embeddings and reconstructions.

    dim: D features per frame; ``target``: the columns (of D) that `forward` reconstructs
    (default all). The inputs are standardised by `mean` / `std` (D,) (`set_standardization`,
    from the pretraining frames) and clipped to +-CLAMP. Receptive field: 1 + 2 sum(dilations)
    frames.

    embed(x (B, T, D)) -> (B, T, channels); forward(x (B, T, D), mask (B, T), 1 = hidden: those
    frames' features are zeroed and flagged) -> (B, T, len(target)).
    """

    def __init__(
        self,
        dim: int,
        channels: int = 128,
        dilations: Sequence[int] = (1, 2, 4, 8, 16, 32, 64),
        target: Sequence[int] | None = None,
    ) -> None:
        super().__init__()
        dil = [int(d) for d in dilations]
        if int(dim) < 1 or int(channels) < 1 or not dil or min(dil) < 1:
            raise ValueError(f"SequenceEncoder: dim and channels must be >= 1 and dilations "
                             f"integers >= 1 (some), got {dim}, {channels}, {dil}")  # fmt: skip
        tgt = list(range(int(dim))) if target is None else [int(c) for c in target]
        if not tgt or min(tgt) < 0 or max(tgt) >= int(dim):
            raise ValueError(f"SequenceEncoder: target columns must index the {dim} features")
        self.dim, self.channels, self.dilations = int(dim), int(channels), tuple(dil)
        self.register_buffer("target", torch.as_tensor(tgt, dtype=torch.long))
        self.register_buffer("mean", torch.zeros(self.dim))
        self.register_buffer("std", torch.ones(self.dim))
        self.inp = nn.Conv1d(self.dim + 1, self.channels, 1)
        self.blocks = nn.Sequential(*[_Block(self.channels, d) for d in dil])
        self.out = nn.Conv1d(self.channels, len(tgt), 1)

    @property
    def receptive_field(self) -> int:
        return 1 + 2 * sum(self.dilations)

    def config(self) -> dict:
        return {"dim": self.dim, "channels": self.channels, "dilations": list(self.dilations),
                "target": self.target.tolist()}  # fmt: skip

    @torch.no_grad()
    def set_standardization(self, frames: Tensor) -> None:
        """Standardise the inputs by these frames' (N >= 2, D) mean and std (a nearly constant
        feature, e.g. an absent mechanism's distance, is centred, not scaled)."""
        if frames.dim() != 2 or frames.shape[1] != self.dim or frames.shape[0] < 2:
            raise ValueError(f"frames must be (N >= 2, {self.dim}), got {tuple(frames.shape)}")
        f = frames.double()
        sd = f.std(0)
        self.mean.copy_(f.mean(0).to(self.mean))
        self.std.copy_(torch.where(sd > 1e-3, sd, torch.ones_like(sd)).to(self.std))

    def normalize(self, x: Tensor) -> Tensor:
        """(..., D) features -> standardised, clipped (the net's inputs and targets)."""
        return ((x - self.mean) / self.std).clamp(-CLAMP, CLAMP)

    def _check(self, x: Tensor) -> None:
        if x.dim() != 3 or x.shape[-1] != self.dim:
            raise ValueError(f"x must be (B, T, {self.dim}), got {tuple(x.shape)}")

    def _hidden(self, z: Tensor, mask: Tensor) -> Tensor:
        """Standardised inputs z (B, T, D), mask (B, T) -> (B, channels, T)."""
        h = torch.cat([z * (1 - mask[..., None]), mask[..., None]], -1).transpose(1, 2)
        return self.blocks(self.inp(h))

    def embed(self, x: Tensor) -> Tensor:
        self._check(x)
        z = self.normalize(x)
        return self._hidden(z, z.new_zeros(z.shape[:2])).transpose(1, 2)

    def forward(self, x: Tensor, mask: Tensor) -> Tensor:
        self._check(x)
        if mask.shape != x.shape[:2]:
            raise ValueError(f"mask must be {tuple(x.shape[:2])}, got {tuple(mask.shape)}")
        z = self.normalize(x)
        return self.out(self._hidden(z, mask.to(z))).transpose(1, 2)


def span_mask(
    batch: int, length: int, ratio: float, gen: torch.Generator, longest: int = 23
) -> Tensor:
    """(batch, length) masks, 1 on random spans of 4..``longest`` frames (clipped to half the
    length) until at least ``ratio`` (0 < ratio < 1) of each row's frames are."""
    if not 0.0 < float(ratio) < 1.0 or int(length) < 8:
        raise ValueError(f"span_mask: ratio must be in (0, 1) and length >= 8, got {ratio}, "
                         f"{length}")  # fmt: skip
    longest = max(4, min(int(longest), int(length) // 2))
    m = torch.zeros(int(batch), int(length))
    for b in range(int(batch)):
        while m[b].mean() < ratio:
            n = int(torch.randint(4, longest + 1, (1,), generator=gen))
            s = int(torch.randint(0, int(length) - n + 1, (1,), generator=gen))
            m[b, s : s + n] = 1
    return m


def pretrain_sequences(
    model: SequenceEncoder,
    sessions: Sequence[Tensor],
    steps: int,
    ratio: float = 0.75,
    longest: int = 60,
    crop: int = 256,
    batch: int = 32,
    lr: float = 1e-3,
    seed: int = 0,
) -> dict:
    """Masked-span reconstruction on random crops of sessions, each (T_i, D) (not
    standardised): ``model``'s standardisation is set from all their frames, then ``steps``
    AdamW steps (lr, weight decay 1e-4) on batches of ``batch`` crops of ``crop`` frames (at
    most the longest session's; a session is drawn in proportion to the crops it holds, sessions
    shorter than the crop not at all), ``ratio`` of each crop hidden in spans of 4..``longest``
    frames (`span_mask`); the loss is the MSE of the hidden frames' standardised target columns.
    Deterministic for a seed (and thread count). Returns {"steps", "loss" (mean of the last 100
    steps), "seconds", "sessions", "frames", "crop"}."""
    xs = [torch.as_tensor(s, dtype=torch.float32) for s in sessions]
    if not xs or any(x.dim() != 2 or x.shape[1] != model.dim for x in xs):
        raise ValueError(f"sessions must be a non-empty list of (T_i, {model.dim}) arrays, got "
                         f"{[tuple(x.shape) for x in xs]}")  # fmt: skip
    if any(not torch.isfinite(x).all() for x in xs):
        raise ValueError("pretrain_sequences: the sessions' features must be finite")
    if int(steps) < 0 or int(batch) < 1 or float(lr) <= 0:
        raise ValueError(f"steps must be >= 0, batch >= 1 and lr > 0, got {steps}, {batch}, {lr}")
    lengths = np.array([len(x) for x in xs])
    crop = min(int(crop), int(lengths.max()))
    if crop < 16:
        raise ValueError(f"the sessions are too short for sequence pretraining: the longest has "
                         f"{lengths.max()} frames (at least 16 needed)")  # fmt: skip
    model.set_standardization(torch.cat(xs))
    room = np.maximum(lengths - crop + 1, 0).astype(np.float64)
    probs = torch.as_tensor(room / room.sum())
    gen = torch.Generator().manual_seed(int(seed))
    opt = torch.optim.AdamW(model.parameters(), float(lr), weight_decay=1e-4)
    model.train()
    t0, losses = time.perf_counter(), []
    for step in range(int(steps)):
        si = torch.multinomial(probs, int(batch), replacement=True, generator=gen).tolist()
        crops = []
        for i in si:
            s = int(torch.randint(0, int(room[i]), (1,), generator=gen))
            crops.append(xs[i][s : s + crop])
        x = torch.stack(crops)
        m = span_mask(int(batch), crop, ratio, gen, longest)
        target = model.normalize(x)[..., model.target]
        loss = (((model(x, m) - target) ** 2).mean(-1) * m).sum() / m.sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        if (step + 1) % 200 == 0:
            log.info("sequence pretraining step %d: masked reconstruction %.4f", step + 1,
                     np.mean(losses[-100:]))  # fmt: skip
    model.eval()
    return {
        "steps": len(losses),
        "loss": float(np.mean(losses[-100:])) if losses else None,
        "seconds": round(time.perf_counter() - t0, 1),
        "sessions": len(xs),
        "frames": int(lengths.sum()),
        "crop": crop,
    }


def pooled(z: Tensor, spans: Sequence[int], eps: float = 0.0) -> Tensor:
    """Per-frame outputs z (S, E, T) -> (S, T, (1 + 2 len(spans)) E): each frame's output with
    its mean and standard deviation over the centred spans (odd frames; edges averaged over the
    frames there are; ``eps`` under the square root keeps a gradient through it finite)."""
    if z.dim() != 3:
        raise ValueError(f"z must be (S, E, T), got {tuple(z.shape)}")
    out = [z]
    for span in spans:
        if int(span) < 1 or int(span) % 2 == 0:
            raise ValueError(f"context spans must be odd and >= 1, got {span}")
        p = int(span) // 2
        mu = nn.functional.avg_pool1d(z, int(span), 1, p, count_include_pad=False)
        sq = nn.functional.avg_pool1d(z**2, int(span), 1, p, count_include_pad=False)
        out += [mu, (sq - mu**2).clamp_min(float(eps)).sqrt()]
    return torch.cat(out, 1).transpose(1, 2)


@torch.no_grad()
def embeddings(model: SequenceEncoder, sessions: Sequence[Tensor], spans: Sequence[int]) -> Tensor:
    """Each frame's embedding (sum T_i, (1 + 2 len(spans)) channels): the net's output for the
    whole session (T_i, D) with its mean and standard deviation over centred ``spans``."""
    mode = model.training
    model.eval()
    try:
        out = [
            pooled(model.embed(torch.as_tensor(x, dtype=torch.float32)[None]).transpose(1, 2),
                   spans)[0]
            for x in sessions
        ]  # fmt: skip
    finally:
        model.train(mode)
    return torch.cat(out) if out else torch.zeros(0, model.channels * (1 + 2 * len(spans)))


def standardised(x: np.ndarray) -> np.ndarray:
    """Columns of x (N, F) standardised by their own mean and std (a (nearly) constant one, std
    <= 1e-6, is zero)."""
    mu, sd = x.mean(0), x.std(0)
    keep = sd > 1e-6
    return np.where(keep, (x - mu) / np.where(keep, sd, 1.0), 0.0)


def quantile_binner(x: np.ndarray, bins: int = 4):
    """A function that puts features (M, F) beside their one-hot quantile bins: (M, B + F), B
    the bins in all (``bins`` per feature, fewer where a feature has fewer distinct values; none
    for a feature constant over x); the edges from x (N, F). A linear model on them can
    threshold a feature, as a forest's split does."""
    import warnings

    from sklearn.preprocessing import KBinsDiscretizer

    if int(bins) < 2:
        raise ValueError(f"bins must be >= 2, got {bins}")
    x = np.asarray(x)
    if x.ndim != 2:
        raise ValueError(f"x must be (N, F), got {x.shape}")
    F = x.shape[1]
    varies = np.ptp(x, axis=0) > 1e-6 if len(x) else np.zeros(F, bool)
    kb = None
    if varies.any():  # else nothing to bin (a constant feature, e.g. an absent mechanism's)
        with warnings.catch_warnings():  # a feature with few distinct values gets fewer bins
            warnings.filterwarnings("ignore", "Bins whose width are too small", UserWarning)
            kb = KBinsDiscretizer(int(bins), encode="onehot-dense", strategy="quantile")
            kb.fit(x[:, varies])

    def transform(y: np.ndarray) -> np.ndarray:
        y = np.asarray(y)
        if y.ndim != 2 or y.shape[1] != F:
            raise ValueError(f"features must be (M, {F}), got {y.shape}")
        if kb is None:
            return y.copy()
        return np.hstack([kb.transform(y[:, varies]).astype(y.dtype), y])

    return transform


def binned(x: np.ndarray, bins: int = 4) -> np.ndarray:
    """Features x (N, F) beside their one-hot quantile bins, the edges from x
    (`quantile_binner`): (N, B + F)."""
    return quantile_binner(x, bins)(x)


def linear_teacher_probs(
    frame: np.ndarray,
    idx: np.ndarray,
    labels: np.ndarray,
    num_classes: int,
    class_weights: Sequence[float] | None = None,
    bins: int = 4,
    embedding: np.ndarray | None = None,
) -> np.ndarray:
    """A teacher's class probabilities (N, C) of every frame: a logistic regression (C=1,
    scikit-learn) on the standardised frame features ``frame`` (N, F) with their one-hot
    quantile bins (`binned`), beside the standardised ``embedding`` (N, E) when given (both
    standardised over all N frames, labelled or not), fitted on the labelled rows ``idx`` (L,)
    with ``labels`` (L,), class-weighted by ``class_weights`` (C,) (None: unweighted). A class
    no labelled frame has gets probability 0. `deformnet-classify pseudo_labels.teacher=linear`
    (no embedding) and ``sequence`` (the sequence encoder's, `embeddings`)."""
    frame = np.asarray(frame, np.float64)
    if frame.ndim != 2:
        raise ValueError(f"frame must be (N, F), got {frame.shape}")
    parts = [binned(standardised(frame), bins)]
    if embedding is not None:
        embedding = np.asarray(embedding, np.float64)
        if embedding.ndim != 2 or len(embedding) != len(frame):
            raise ValueError(f"embedding must be ({len(frame)}, E), got {embedding.shape}")
        parts.append(standardised(embedding))
    return _logistic_probs(np.hstack(parts), idx, labels, num_classes, class_weights)


def embedding_teacher_probs(
    embedding: np.ndarray,
    idx: np.ndarray,
    labels: np.ndarray,
    num_classes: int,
    class_weights: Sequence[float] | None = None,
) -> np.ndarray:
    """The class probabilities (N, C) of every frame of a teacher that reads only the
    standardised ``embedding`` (N, E) (the sequence encoder's, `embeddings`): the logistic
    regression of `linear_teacher_probs`, fitted on the labelled rows ``idx`` (L,) with
    ``labels`` (L,). The second view of `deformnet-classify pseudo_labels.teacher=cotrain`."""
    embedding = np.asarray(embedding, np.float64)
    if embedding.ndim != 2:
        raise ValueError(f"embedding must be (N, E), got {embedding.shape}")
    return _logistic_probs(standardised(embedding), idx, labels, num_classes, class_weights)


def _logistic_probs(x, idx, labels, num_classes, class_weights) -> np.ndarray:
    """The class-weighted logistic regression (C=1) on features x (N, D) fitted on the rows
    idx: every row's probabilities (N, C), 0 for a class no labelled row has."""
    from sklearn.linear_model import LogisticRegression

    idx, y = np.asarray(idx, np.int64), np.asarray(labels, np.int64)
    if idx.shape != y.shape or idx.size == 0:
        raise ValueError(f"idx and labels must be (L,) with L >= 1, got {idx.shape}, {y.shape}")
    present = np.unique(y)
    cw = None if class_weights is None else {int(c): float(class_weights[int(c)]) for c in present}
    P = np.zeros((len(x), int(num_classes)))
    if present.size == 1:  # one class labelled: it is every frame's
        P[:, present[0]] = 1.0
        return P
    lr = LogisticRegression(C=1.0, max_iter=3000, class_weight=cw)
    lr.fit(x[idx], y)
    P[:, lr.classes_] = lr.predict_proba(x)
    return P


def feature_signature(encoder: nn.Module, extra: Mapping) -> dict:
    """What a sequence encoder's inputs are, to tell a reused one from a mismatched one: a
    digest of the frozen deformation encoder's weights and ``extra`` (the frame features'
    settings: mechanisms, measurements, body scale...)."""
    h = hashlib.sha1()
    for k, v in sorted(encoder.state_dict().items()):
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return {"encoder_sha1": h.hexdigest(), **{k: extra[k] for k in sorted(extra)}}


def export_sequence_encoder(model: SequenceEncoder, signature: Mapping, facts: Mapping) -> dict:
    """The object `deformnet-classify` saves as sequence_encoder.pt (`load_sequence_encoder`)."""
    return {"kind": "mousetrack.sequence_encoder", "config": model.config(),
            "state_dict": model.state_dict(), "signature": dict(signature),
            "facts": dict(facts)}  # fmt: skip


def load_sequence_encoder(path: str, signature: Mapping | None = None) -> SequenceEncoder:
    """A saved sequence encoder (`export_sequence_encoder`); with ``signature``, checked to read
    the same per-frame features (else a ValueError naming the file and what differs). Read as
    data (`deformnet.checkpoint.load_checkpoint`, weights only): a missing, truncated or
    corrupt file, or one holding pickled objects, is a ValueError naming it."""
    obj = load_checkpoint(path, "sequence encoder")
    if not isinstance(obj, dict) or obj.get("kind") != "mousetrack.sequence_encoder":
        raise ValueError(f"{path}: not a sequence encoder deformnet-classify wrote "
                         "(sequence_encoder.pt)")  # fmt: skip
    if signature is not None:
        saved = obj.get("signature") if isinstance(obj.get("signature"), dict) else {}
        diff = sorted(k for k in set(saved) | set(signature) if saved.get(k) != signature.get(k))
        if diff:
            raise ValueError(
                f"{path}: this sequence encoder was pretrained on other per-frame features than "
                f"this classifier's (they differ in {', '.join(diff)}): pretrain it again "
                "(pseudo_labels.sequence.encoder=null)"
            )
    try:
        cfg = obj["config"]
        model = SequenceEncoder(cfg["dim"], cfg["channels"], cfg["dilations"], cfg["target"])
        model.load_state_dict(obj["state_dict"])
    except (KeyError, TypeError, AttributeError, RuntimeError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(
            f"{path}: a sequence encoder this version cannot read ({first[:200]})"
        ) from None
    model.eval()
    return model
