"""Behavior classifier heads and the classifier (plain `nn.Module`s, no Lightning).

Heads map (B, D) -> (B, num_classes) logits: `LinearHead`, `MLPHead` (conf/head/*.yaml), an
`EnsembleHead` of several (``head.ensemble``), or `ForestHead` (a random forest fitted by
scikit-learn on a frozen encoder's frame features, evaluated in torch; for few labels).
`BehaviorClassifier` = encoder (`deformnet.behavior.encoder.WindowEncoder`) + temporal context
(the mean and std of the encoder outputs of the surrounding frames, `context_frames`) +
standardisation + head.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from deformnet.behavior.encoder import WindowEncoder
from deformnet.behavior.settings import HeadSettings
from deformnet.checkpoint import plain_kwargs

__all__ = [
    "LinearHead", "MLPHead", "EnsembleHead", "ForestHead", "HEADS", "build_head",
    "context_offsets", "BehaviorClassifier",
]  # fmt: skip


class LinearHead(nn.Module):
    """Logits = W LayerNorm(x) + b (``norm``; else W x + b: inputs the classifier has
    standardised already).  x (B, in_dim) -> (B, num_classes)."""

    def __init__(
        self, in_dim: int, num_classes: int, dropout: float = 0.0, norm: bool = True
    ) -> None:
        super().__init__()
        mods: list[nn.Module] = [nn.LayerNorm(in_dim)] if norm else []
        self.net = nn.Sequential(*mods, nn.Dropout(dropout), nn.Linear(in_dim, num_classes))

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)


class MLPHead(nn.Module):
    """LayerNorm, then `layers` x (Linear(hidden), GELU, Dropout), then Linear(num_classes)."""

    def __init__(
        self,
        in_dim: int,
        num_classes: int,
        hidden: int = 128,
        layers: int = 1,
        dropout: float = 0.1,
    ) -> None:
        super().__init__()
        mods: list[nn.Module] = [nn.LayerNorm(in_dim)]
        d = in_dim
        for _ in range(max(1, int(layers))):
            mods += [nn.Linear(d, hidden), nn.GELU(), nn.Dropout(dropout)]
            d = hidden
        mods.append(nn.Linear(d, num_classes))
        self.net = nn.Sequential(*mods)

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)


class EnsembleHead(nn.Module):
    """Several heads of one kind (independently initialised), their class probabilities
    averaged: logits = log(mean_i softmax(head_i(x))) (so softmax gives the mean probabilities
    and cross-entropy trains the ensemble's prediction). With few labels one head's fit
    depends on its initialisation by several macro-F1 points; the mean of a few does not
    (a deep ensemble). `fit_head_lbfgs` fits each member on its own.
    x (B, in_dim) -> (B, num_classes)."""

    def __init__(self, members: Sequence[nn.Module]) -> None:
        super().__init__()
        if len(members) < 1:
            raise ValueError("an ensemble head needs at least one member")
        self.members = nn.ModuleList(members)

    def forward(self, x: Tensor) -> Tensor:
        logp = torch.stack([m(x).log_softmax(-1) for m in self.members])  # (M, B, C)
        return torch.logsumexp(logp, 0) - math.log(len(self.members))


class ForestHead(nn.Module):
    """A random forest as a head: fitted by scikit-learn (`deformnet.behavior.fit.fit_head_forest`,
    on a frozen encoder's features), stored as flat tensors (weights-only checkpoints, no
    pickled estimator) and evaluated here in torch. logits = log(mean over the trees of the
    class fractions of the leaf each tree sends x to) (softmax gives the forest's
    `predict_proba`). Not trainable by gradient.

    trees, min_samples_leaf, max_features: the forest's settings; seed: its random_state. It
    reads the classifier's frame-feature columns (the pose, the offsets, the mechanism
    distances, the measurements and their temporal context; set by `fit_head_forest`).
    x (B, in_dim) -> (B, num_classes).
    """

    def __init__(
        self,
        in_dim: int,
        num_classes: int,
        trees: int = 200,
        min_samples_leaf: int = 2,
        max_features: str | float | int = "sqrt",
        seed: int = 0,
    ) -> None:
        super().__init__()
        if int(trees) < 1 or int(min_samples_leaf) < 1:
            raise ValueError(f"head.trees and head.min_samples_leaf must be >= 1, got {trees}, "
                             f"{min_samples_leaf}")  # fmt: skip
        self.in_dim, self.num_classes = int(in_dim), int(num_classes)
        self.trees, self.min_samples_leaf = int(trees), int(min_samples_leaf)
        self.max_features, self.seed = max_features, int(seed)
        for name, dtype in (("columns", torch.long), ("roots", torch.long),
                            ("feature", torch.long), ("left", torch.long),
                            ("right", torch.long), ("threshold", torch.float64)):  # fmt: skip
            self.register_buffer(name, torch.zeros(0, dtype=dtype))
        self.register_buffer("value", torch.zeros(0, self.num_classes))
        self.register_buffer("depth", torch.zeros((), dtype=torch.long))

    @property
    def fitted(self) -> bool:
        return self.roots.numel() > 0

    def set_forest(self, forest, columns: Sequence[int], class_index: Sequence[int]) -> None:
        """Store a fitted scikit-learn forest (its estimators_' tree_ arrays) that reads the
        input columns ``columns`` and whose classes_ are the head's classes ``class_index``."""
        cols = torch.as_tensor(np.asarray(columns), dtype=torch.long)
        if cols.numel() < 1 or int(cols.max()) >= self.in_dim or int(cols.min()) < 0:
            raise ValueError(f"columns must index the head's {self.in_dim} inputs")
        cidx = np.asarray(class_index, dtype=np.int64)
        feat, thr, left, right, val, roots = [], [], [], [], [], []
        off, depth = 0, 0
        for est in forest.estimators_:
            t = est.tree_
            n = int(t.node_count)
            leaf = t.children_left < 0
            ids = np.arange(n)
            roots.append(off)
            feat.append(np.where(leaf, 0, t.feature))
            thr.append(np.where(leaf, np.inf, t.threshold))
            # a leaf points at itself: every tree walks `depth` steps and stays at its leaf
            left.append(off + np.where(leaf, ids, t.children_left))
            right.append(off + np.where(leaf, ids, t.children_right))
            v = np.zeros((n, self.num_classes))
            frac = t.value[:, 0, :]
            v[:, cidx] = frac / np.maximum(frac.sum(-1, keepdims=True), 1e-300)
            val.append(v)
            off += n
            depth = max(depth, int(t.max_depth))
        self.columns = cols
        self.roots = torch.as_tensor(np.asarray(roots), dtype=torch.long)
        self.feature = torch.as_tensor(np.concatenate(feat), dtype=torch.long)
        self.threshold = torch.as_tensor(np.concatenate(thr), dtype=torch.float64)
        self.left = torch.as_tensor(np.concatenate(left), dtype=torch.long)
        self.right = torch.as_tensor(np.concatenate(right), dtype=torch.long)
        self.value = torch.as_tensor(np.concatenate(val), dtype=torch.float32)
        self.depth = torch.tensor(depth, dtype=torch.long)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # the forest's size is known only once fitted: take the stored tensors' shapes
        for name, buf in self.named_buffers(recurse=False):
            key = prefix + name
            if key in state_dict and state_dict[key].shape != buf.shape:
                setattr(self, name, torch.empty_like(state_dict[key], dtype=buf.dtype))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def forward(self, x: Tensor) -> Tensor:
        if x.dim() != 2 or x.shape[1] != self.in_dim:
            raise ValueError(f"x must be (B, {self.in_dim}), got {tuple(x.shape)}")
        if not self.fitted:
            raise RuntimeError("ForestHead is not fitted (deformnet.behavior.fit.fit_head_forest)")
        x = x[:, self.columns].double()  # scikit-learn's thresholds are float64
        node = self.roots.expand(x.shape[0], -1)  # (B, trees)
        for _ in range(int(self.depth)):
            go_left = torch.gather(x, 1, self.feature[node]) <= self.threshold[node]
            node = torch.where(go_left, self.left[node], self.right[node])
        p = self.value[node].mean(1)  # (B, C)
        return torch.log(p.clamp_min(1e-12))


#: the heads a config or a checkpoint may name (its ``name``): `build_head` builds only these
HEADS = {"linear": LinearHead, "mlp": MLPHead, "forest": ForestHead}


def build_head(
    config: Mapping[str, Any], in_dim: int, num_classes: int, source: str = ""
) -> nn.Module:
    """A head from a plain config {"name": linear|mlp|forest (the allow-list `HEADS`),
    "ensemble": members (default 1), ...constructor arguments (plain values only,
    `deformnet.checkpoint.plain_kwargs`)}; ensemble > 1: an `EnsembleHead` of that many.
    ValueError (naming ``source``, the checkpoint file, when given) for another name, a nested
    config or a non-plain value."""
    where = f"{source}: head" if source else "head"
    cfg = plain_kwargs(config, where)
    try:  # the head's own keys (typed); the others are its constructor's arguments
        s = HeadSettings(**{k: cfg.pop(k) for k in ("name", "ensemble") if k in cfg})
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}" if source else str(exc)) from None
    if s.name not in HEADS:
        raise ValueError(f"{where}.name must be one of {sorted(HEADS)}, got '{s.name[:200]}'")
    if s.name == "forest" and s.ensemble != 1:
        raise ValueError(f"{where}.ensemble must be 1 for a forest (it is an ensemble: head.trees)")
    try:
        heads = [HEADS[s.name](int(in_dim), int(num_classes), **cfg) for _ in range(s.ensemble)]
    except TypeError as exc:
        raise ValueError(f"{where}: cannot build the {s.name} head: {exc}") from None
    return heads[0] if s.ensemble == 1 else EnsembleHead(heads)


def context_offsets(frames: Sequence[int], stride: int = 1) -> tuple[int, ...]:
    """Frame offsets (O,) whose encoder features the temporal context pools: multiples of
    ``stride`` within +-(max(frames) - 1) / 2 (0 included). No frames: (0,)."""
    frames = [int(f) for f in frames]
    stride = int(stride)
    if stride < 1:
        raise ValueError(f"context.stride must be >= 1, got {stride}")
    bad = [f for f in frames if f < 3 or f % 2 == 0]
    if bad:
        raise ValueError(f"context.frames must be odd and >= 3, got {bad}")
    if not frames:
        return (0,)
    c = (max(frames) - 1) // 2 // stride * stride
    return tuple(range(-c, c + 1, stride))


class BehaviorClassifier(nn.Module):
    """encoder (`WindowEncoder`) + temporal context + head -> logits (B, C).

    Without context (``context_frames`` empty) a frame's features are its window's encoder
    output (B, D). With context, e.g. (15, 33), they are that output plus the mean and the
    standard deviation of the encoder outputs of the frames around it, over centred spans of
    each length (every ``stride``-th frame): the behavior of a frame shows in how its window
    changes over the next second, as the SimBA-style rolling features of hand-made
    measurements do (D (1 + 2 len(context_frames)) values). The head sees them standardised by
    `feature_mean` / `feature_std` (set from the training frames, `set_standardization`).

    forward(rigid, deformed (B, W + 2 span, K, 3), observed (B, W + 2 span, K), scale (B,) or
    None) with W the encoder's window and span = `span` (0 without context); scale: each
    window's body scale (`WindowEncoder`).
    """

    def __init__(
        self,
        encoder: WindowEncoder,
        head: nn.Module,
        context_frames: Sequence[int] = (),
        stride: int = 1,
    ) -> None:
        super().__init__()
        self.encoder = encoder
        self.head = head
        self.context_frames = tuple(int(f) for f in context_frames)
        self.stride = int(stride)
        self.offsets = context_offsets(self.context_frames, self.stride)
        self.span = max(self.offsets)
        self.window = encoder.window + 2 * self.span
        self.half_window = encoder.half_window + self.span
        self.out_dim = self.feature_dim(encoder.out_dim, self.context_frames)
        self.register_buffer("feature_mean", torch.zeros(self.out_dim))
        self.register_buffer("feature_std", torch.ones(self.out_dim))

    def frame_columns(self) -> Tensor:
        """Indices (F,) of the frame features (the pose, the offsets, the observed flags, the
        mechanism distances, the measurements: see `WindowEncoder`) and of their context
        statistics among the classifier's features."""
        enc = self.encoder
        if not enc.frame_features and enc.mechanisms is None and not enc.measurements:
            raise ValueError("the classifier has no frame features (frame_features=false)")
        i = torch.arange(self.out_dim)
        return i[(i % enc.out_dim) >= 2 * enc.net.encode_dim]

    @staticmethod
    def feature_dim(encoder_dim: int, context_frames: Sequence[int]) -> int:
        return int(encoder_dim) * (1 + 2 * len(tuple(context_frames)))

    def pool(self, per_frame: Tensor) -> Tensor:
        """(B, O, D) encoder outputs at `offsets` -> (B, out_dim) context features."""
        if per_frame.dim() != 3 or per_frame.shape[1] != len(self.offsets):
            raise ValueError(
                f"per_frame must be (B, {len(self.offsets)}, D), got {tuple(per_frame.shape)}"
            )
        off = torch.as_tensor(self.offsets)
        out = [per_frame[:, self.offsets.index(0)]]
        for f in self.context_frames:
            near = off.abs() <= (f - 1) // 2
            sel = per_frame[:, near.nonzero().flatten()]
            out += [sel.mean(1), sel.std(1, unbiased=False)]
        return torch.cat(out, -1)

    def features(
        self, rigid: Tensor, deformed: Tensor, observed: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        """Context features (B, out_dim) of the batch's mid frames (not standardised)."""
        if rigid.dim() != 4 or rigid.shape[1] != self.window:
            raise ValueError(
                f"rigid must be (B, {self.window}, K, 3) (encoder window {self.encoder.window} "
                f"+ 2 x context span {self.span}), got {tuple(rigid.shape)}"
            )
        if not self.span:
            return self.encoder(rigid, deformed, observed, scale)
        B, W = rigid.shape[0], self.encoder.window
        starts = [self.span + o for o in self.offsets]  # sub-window centred at mid + o

        def unfold(x: Tensor) -> Tensor:
            return torch.stack([x[:, s : s + W] for s in starts], 1).flatten(0, 1)

        if scale is not None:  # every sub-window is the same session's
            if scale.shape != rigid.shape[:1]:
                raise ValueError(f"scale must be ({B},), got {tuple(scale.shape)}")
            scale = scale[:, None].expand(B, len(starts)).flatten()
        f = self.encoder(unfold(rigid), unfold(deformed), unfold(observed), scale)
        return self.pool(f.reshape(B, len(self.offsets), -1))

    @torch.no_grad()
    def set_standardization(self, features: Tensor) -> None:
        """Standardise the head's inputs by these (N, out_dim) features' mean and std."""
        if features.dim() != 2 or features.shape[1] != self.out_dim or features.shape[0] < 2:
            raise ValueError(f"features must be (N >= 2, {self.out_dim}), got {features.shape}")
        self.feature_mean.copy_(features.mean(0))
        std = features.std(0)
        # a (nearly) constant feature is centred, not scaled: a later change must not explode
        self.feature_std.copy_(torch.where(std > 1e-3, std, torch.ones_like(std)))

    def classify(self, features: Tensor) -> Tensor:
        """Logits (B, C) from context features (B, out_dim)."""
        return self.head((features - self.feature_mean) / self.feature_std)

    def forward(
        self, rigid: Tensor, deformed: Tensor, observed: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        return self.classify(self.features(rigid, deformed, observed, scale))
