"""Behavior-scale masked pretraining, and the teacher it makes for few-label behavior heads
(`pseudo_labels.teacher=cotrain`).

Each frame of a session is the classifier's per-frame feature vector (the frozen deformation
encoder's output, the pose, the per-part offsets, the lock-box mechanism distances, the
SimBA-style measurements), and a temporal convolutional net (`SequenceEncoder`: residual
dilated convolutions) reads a session's sequence of them with spans of frames hidden and learns
to reconstruct the hidden frames' frame features (`pretrain_sequences`; "task programming",
Sun et al., CVPR 2021). No labels: it learns from every training frame and from more
recordings of the same animals (`deformnet-classify data.unlabelled_tracks=`). Its per-frame
outputs with their mean and standard deviation over centred spans (`embeddings`) are a frame's
embedding; a logistic regression on it is the second teacher of co-training
(`sequence_teacher`, `deformnet.behavior.teachers`).

Shapes: T frames of a session, D per-frame features, N frames of several sessions concatenated
in order, C classes. Importable without Lightning.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from deformnet.atomic import atomic_path
from deformnet.behavior.settings import PseudoLabelSettings
from deformnet.behavior.teachers import embedding_teacher_probs, linear_teacher_probs
from deformnet.checkpoint import load_checkpoint

log = logging.getLogger(__name__)

__all__ = ["SequenceEncoder", "span_mask", "pretrain_sequences", "pooled", "embeddings",
           "feature_signature", "export_sequence_encoder", "load_sequence_encoder",
           "sequence_signature", "sequence_teacher"]  # fmt: skip

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


def frame_feature_columns(model) -> Tensor:
    """Indices (F,) of the frame features among a frame's own encoder output (the first
    `model.encoder.out_dim` of its context features; `BehaviorClassifier.frame_columns`)."""
    cols = model.frame_columns()
    return cols[cols < model.encoder.out_dim]


def sequence_signature(model, mech: Mapping | None, scale_mode: str) -> dict:
    """What a sequence encoder pretrained on this classifier's per-frame features must match
    (`feature_signature`)."""
    enc = model.encoder
    return feature_signature(enc, {
        "mechanisms": None if mech is None else mech["names"],
        "measurements": bool(enc.measurements), "frame_features": bool(enc.frame_features),
        "body_scale": scale_mode, "out_dim": enc.out_dim,
    })  # fmt: skip


def sequence_teacher(
    model,
    train_features: Tensor,
    lengths: Sequence[int],
    unlabelled: Sequence[Tensor],
    idx: np.ndarray,
    labels: np.ndarray,
    num_classes: int,
    class_weights,
    pseudo: PseudoLabelSettings,
    signature: Mapping,
    out: Path,
) -> tuple[list[np.ndarray], dict]:
    """`pseudo_labels.teacher=cotrain`: the behavior-scale sequence encoder
    pretrained by masked-span reconstruction on the training sessions'
    per-frame features (each frame's own encoder output: the first `encoder.out_dim` columns of
    ``train_features`` (N, out_dim), every training frame, sessions of ``lengths`` frames) and
    the ``unlabelled`` sessions' (their features, (T_u, out_dim) each), or loaded
    (``pseudo.sequence.encoder``, checked against ``signature``, `sequence_signature`); it is saved
    to out/sequence_encoder.pt. Two teachers fitted on the labelled frames ``idx`` (labels
    ``labels`` (L,), ``num_classes`` C, class weights (C,) or None), one per view: the binned
    frame features (with context; `linear_teacher_probs`, ``pseudo.bins`` per feature) and the
    encoder's embedding (`embedding_teacher_probs`). Returns their probabilities (N + M, C) of
    every training frame, then every unlabelled session's (M frames in all; M = 0 without
    ``pseudo.unlabelled``: then only the pretraining reads them), as a list of two, and facts."""
    settings, D = pseudo.sequence, model.encoder.out_dim
    per_frame = train_features[:, :D].float()
    bounds = np.cumsum([0, *lengths])
    train_seqs = [per_frame[a:b] for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    facts: dict = {}
    if settings.encoder:  # the signature holds the feature count (out_dim)
        seq = load_sequence_encoder(settings.encoder, signature)
        facts["encoder"] = str(settings.encoder)
        log.info("sequence encoder from %s", settings.encoder)
    else:
        if not settings.steps:
            log.warning("pseudo_labels.sequence.steps=0: the sequence encoder is not "
                        "pretrained (its random weights teach: a control, not a classifier "
                        "to use)")  # fmt: skip
        torch.manual_seed(int(settings.seed))
        target = frame_feature_columns(model) if settings.target == "frame" else None
        seq = SequenceEncoder(D, settings.channels, settings.dilations, target)
        seqs = train_seqs + [u[:, :D].float() for u in unlabelled]
        log.info("sequence pretraining: %d steps on %d sessions (%d unlabelled), %d frames",
                 settings.steps, len(seqs), len(unlabelled),
                 sum(len(s) for s in seqs))  # fmt: skip
        facts["pretraining"] = pretrain_sequences(
            seq, seqs, settings.steps, settings.mask_ratio, settings.longest_span,
            settings.crop, settings.batch, settings.lr, settings.seed,
        )  # fmt: skip
        log.info("sequence pretraining: %s", facts["pretraining"])
        path = out / "sequence_encoder.pt"
        with atomic_path(path) as tmp:
            torch.save(export_sequence_encoder(seq, signature, facts["pretraining"]), tmp)
        facts["encoder"] = str(path)
    taught = list(unlabelled) if pseudo.unlabelled else []  # the frames to label, after training's
    emb = embeddings(seq, train_seqs + [u[:, :D].float() for u in taught], settings.context)
    frame = torch.cat([train_features, *taught])[:, model.frame_columns()].double().numpy()
    emb = emb.double().numpy()
    return [
        linear_teacher_probs(frame, idx, labels, num_classes, class_weights, pseudo.bins),
        embedding_teacher_probs(emb, idx, labels, num_classes, class_weights),
    ], facts  # fmt: skip
