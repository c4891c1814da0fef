"""Behavior classification on the deformation nets' encoders (plain `nn.Module`s, no Lightning).

The deformation nets (`deformnet.nets.LSTMPredictor`, `TransformerPredictor`) are pretrained to
predict a window's masked mid frame; their encoder (everything before the per-part output layer)
summarises the window around a frame. `WindowEncoder` runs that encoder on global windows:

    WindowEncoder(net, body_points, half_window)(rigid, deformed, observed) -> (B, D)

    rigid, deformed (B, W, K, 3) global mm, observed (B, W, K) bool; W = 2 half_window + 1;
    optional scale (B,): each window's animal size relative to the rigid model (`normalize_size`).

It canonicalises the window (the mid frame's rigid-model coordinates, `deformnet.tokens`), runs
the net's encoder (the LSTM's mid-frame output and embedding plus its time-average; the
transformer's normalised mid-frame output plus its time-average), and appends what the
canonical frame removes but behavior depends on ("frame features"): the mid pose (rotation
matrix, translation / pos_scale: height, pitch and place in the arena) and the mid frame's own
deformation offsets (the net masks them when predicting them; here they are inputs). With a
lock box's mechanism positions (`MechanismFeatures`) it also appends where the mouse is
relative to each mechanism: the distance of chosen parts (snout, front paws) to each one.
Given each window's body scale (the session's, `deformnet.behavior_labels.body_scale`), the
points are shrunk to the model's size about the rigid model's centroid before the encoder, the
offsets and the measurements see them (`normalize_size`: a larger or smaller animal looks like
the one the classifier was trained on); the mechanism distances stay those of the real points.

Heads map (B, D) -> (B, num_classes) logits: `LinearHead`, `MLPHead` (conf/head/*.yaml), an
`EnsembleHead` of several (``head.ensemble``), or `ForestHead` (a random forest fitted by
scikit-learn on a frozen encoder's features, evaluated in torch; for few labels).
`BehaviorClassifier` = encoder + temporal context (the mean and std of the encoder outputs of
the surrounding frames, `context_frames`) + standardisation + head.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from deformnet.checkpoint import plain_kwargs
from deformnet.nets import LSTMPredictor, TransformerPredictor
from deformnet.so3 import kabsch
from deformnet.windows import window_summary

__all__ = [
    "MechanismFeatures",
    "normalize_size",
    "pose_measurements",
    "WindowEncoder",
    "LinearHead",
    "MLPHead",
    "EnsembleHead",
    "ForestHead",
    "BehaviorClassifier",
    "build_head",
    "context_offsets",
]


def normalize_size(rigid: Tensor, points: Tensor, scale: Tensor) -> Tensor:
    """Points (..., K, 3) brought to the rigid model's size: c + (p - c) / scale, about the
    posed rigid model's centroid c = rigid (..., K, 3).mean(-2), scale (...,) > 0 the animal's
    size relative to the model (`deformnet.behavior_labels.body_scale`). Pose and place are
    kept; the parts' positions relative to the body (offsets, part distances, heights above
    the centroid) are divided by the scale."""
    if rigid.shape != points.shape or rigid.dim() < 2 or rigid.shape[-1] != 3:
        raise ValueError(
            f"rigid / points must be (..., K, 3) alike, got {tuple(rigid.shape)} / "
            f"{tuple(points.shape)}"
        )
    if tuple(scale.shape) != tuple(rigid.shape[:-2]):
        raise ValueError(f"scale must be {tuple(rigid.shape[:-2])}, got {tuple(scale.shape)}")
    c = rigid.mean(-2, keepdim=True)
    return c + (points - c) / scale.to(points.dtype)[..., None, None]


class MechanismFeatures(nn.Module):
    """Where the mouse is relative to a lock box's mechanisms, as frame features: the distance
    of each chosen part to each mechanism and, per mechanism, the nearest of those parts
    (SimBA's ROI distances), divided by ``scale`` mm.

    positions (M, 3) the mechanisms' global positions (mm, the tracks' frame); parts (P,) the
    chosen parts' indices in the body model's part order; names: the mechanisms' names (M,).
    points (B, K, 3) global mm -> (B, M (P + 1)): [part p, mechanism m] at p M + m, then the
    per-mechanism minimum over the parts.
    """

    def __init__(
        self,
        positions: Sequence[Sequence[float]],
        parts: Sequence[int],
        names: Sequence[str] | None = None,
        scale: float = 50.0,
    ) -> None:
        super().__init__()
        pos = np.asarray(positions, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[0] < 1 or pos.shape[1] != 3 or not np.isfinite(pos).all():
            raise ValueError(f"mechanism positions must be (M >= 1, 3) finite mm, got {pos!r}")
        parts = [int(k) for k in parts]
        if not parts or min(parts) < 0:
            raise ValueError(f"mechanism parts must be >= 1 part indices, got {parts}")
        if not float(scale) > 0:
            raise ValueError(f"mechanism scale must be > 0 mm, got {scale}")
        self.names = tuple(str(n) for n in (names or [f"m{i}" for i in range(len(pos))]))
        if len(self.names) != len(pos):
            raise ValueError(f"{len(self.names)} mechanism names for {len(pos)} positions")
        self.scale = float(scale)
        self.register_buffer("positions", torch.tensor(pos, dtype=torch.float32))
        self.register_buffer("parts", torch.tensor(parts, dtype=torch.long))
        self.out_dim = len(pos) * (len(parts) + 1)

    def forward(self, points: Tensor) -> Tensor:
        if points.dim() != 3 or points.shape[-1] != 3:
            raise ValueError(f"points must be (B, K, 3), got {tuple(points.shape)}")
        if int(self.parts.max()) >= points.shape[1]:
            raise ValueError(f"part index {int(self.parts.max())} >= {points.shape[1]} parts")
        p = points[:, self.parts]  # (B, P, 3)
        d = torch.linalg.vector_norm(p[:, :, None] - self.positions.to(p.dtype), dim=-1)
        d = d / self.scale  # (B, P, M)
        return torch.cat((d.flatten(1), d.amin(1)), -1)


def pose_measurements(
    points: Tensor, before: Tensor, scale: float = 50.0, up: Tensor | None = None
) -> Tensor:
    """Hand-made measurements of a frame, as SimBA computes them: every pairwise distance
    between the parts (upper triangle, row-major), each part's speed (its displacement since
    the frame before) and, given the world's unit ``up`` (3,), each part's height along it, all
    divided by ``scale`` mm. Without ``up`` rotation- and translation-invariant.

    points, before (B, K, 3) global mm -> (B, K (K - 1) / 2 + K (+ K with up))."""
    if points.dim() != 3 or points.shape[-1] != 3 or before.shape != points.shape:
        raise ValueError(
            f"points and before must be (B, K, 3) alike, got {tuple(points.shape)}, "
            f"{tuple(before.shape)}"
        )
    if up is not None and tuple(up.shape) != (3,):
        raise ValueError(f"up must be (3,), got {tuple(up.shape)}")
    K = points.shape[1]
    iu = torch.triu_indices(K, K, 1, device=points.device)
    dist = torch.linalg.vector_norm(points[:, iu[0]] - points[:, iu[1]], dim=-1)
    speed = torch.linalg.vector_norm(points - before, dim=-1)
    out = [dist, speed] + ([] if up is None else [points @ up.to(points.dtype)])
    return torch.cat(out, -1) / float(scale)


class WindowEncoder(nn.Module):
    """The encoder of a deformation net, as a window -> feature-vector map (see module doc).

    net: an `LSTMPredictor` or `TransformerPredictor` (its `head`, the per-part output layer, is
    not used); body_points (K, 3) the rigid body model (mm); frame_features: append the mid pose
    and the mid frame's offsets (12 + 4 K values; always the body frame's pose and offsets);
    up: the world's up (3,) when the net was trained in the heading frame, else None;
    mechanisms: a `MechanismFeatures` appended after the frame features (from the mid frame's
    points: observed parts where seen, the rigid model's elsewhere), or None; measurements:
    append hand-made measurements of the mid frame's points (SimBA-style: every pairwise part
    distance, each part's speed since the frame before and, given the world's up, each part's
    height along it: `pose_measurements`); heights_up: that up (3,) for an encoder without one
    (a body-frame net), None: the encoder's ``up`` (none: no heights); a heights_up that
    differs from the encoder's up is a ValueError.
    """

    def __init__(
        self,
        net: nn.Module,
        body_points: Tensor,
        half_window: int,
        frame_features: bool = True,
        up: Sequence[float] | None = None,
        mechanisms: MechanismFeatures | None = None,
        measurements: bool = False,
        heights_up: Sequence[float] | None = None,
    ) -> None:
        super().__init__()
        from deformnet.deformation import check_up

        if not isinstance(net, (LSTMPredictor, TransformerPredictor)):
            raise TypeError(
                f"WindowEncoder needs an LSTMPredictor or TransformerPredictor, got "
                f"{type(net).__name__}"
            )
        if int(half_window) != net.half_window:
            raise ValueError(f"half_window {half_window} != the net's {net.half_window}")
        self.net = net
        self.half_window = net.half_window
        self.window = net.window
        self.num_parts = net.num_parts
        self.frame_features = bool(frame_features)
        self.up = check_up(up)
        self.register_buffer("body_points", torch.tensor(np.array(body_points, dtype=np.float32)))
        self.mechanisms = mechanisms
        self.measurements = bool(measurements)
        if self.measurements and self.half_window < 1:
            raise ValueError("measurements need a window of at least 3 frames (half_window >= 1)")
        hup = check_up(heights_up)
        if hup is not None and self.up is not None and not np.allclose(hup, self.up):
            raise ValueError(
                f"heights_up {list(hup)} differs from the encoder's up {list(self.up)} (the "
                "heading-frame net's; leave heights_up unset)"
            )
        #: the world's up the measurements' part heights are taken along (None: no heights)
        self.heights_up = hup if hup is not None else self.up
        K = self.num_parts
        if mechanisms is not None and int(mechanisms.parts.max()) >= self.num_parts:
            raise ValueError(f"mechanism part index {int(mechanisms.parts.max())} >= the net's "
                             f"{self.num_parts} parts")  # fmt: skip
        self.out_dim = (
            2 * net.encode_dim
            + (12 + 4 * self.num_parts if self.frame_features else 0)
            + (0 if mechanisms is None else mechanisms.out_dim)
            + (
                (K * (K - 1) // 2 + K + (0 if self.heights_up is None else K))
                if self.measurements
                else 0
            )
        )

    def _check(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> None:
        want = (self.window, self.num_parts, 3)
        if rigid.dim() != 4 or tuple(rigid.shape[1:]) != want:
            raise ValueError(f"rigid must have shape (B, {want}), got {tuple(rigid.shape)}")
        if deformed.shape != rigid.shape or tuple(observed.shape) != tuple(rigid.shape[:-1]):
            raise ValueError(
                f"deformed {tuple(deformed.shape)} / observed {tuple(observed.shape)} do not fit "
                f"rigid {tuple(rigid.shape)}"
            )

    def encoder_parameters(self) -> list[nn.Parameter]:
        """The net's parameters this encoder uses (the unused per-part output layer excluded)."""
        return [p for n, p in self.net.named_parameters() if not n.startswith("head.")]

    def forward(
        self, rigid: Tensor, deformed: Tensor, observed: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        self._check(rigid, deformed, observed)
        observed = observed.bool()
        raw = deformed  # the real points: the mechanism distances
        if scale is not None:
            if scale.shape != rigid.shape[:1]:
                raise ValueError(f"scale must be ({rigid.shape[0]},), got {tuple(scale.shape)}")
            deformed = normalize_size(rigid, deformed, scale[:, None].expand(rigid.shape[:2]))
        up = None if self.up is None else rigid.new_tensor(self.up)
        summary, (rigid_c, deformed_c, R, t) = window_summary(
            self.net, self.body_points, rigid, deformed, observed, up
        )
        mid, net, B = self.half_window, self.net, summary.shape[0]

        def seen(i: int, pts: Tensor = deformed) -> Tensor:
            """Frame i's points (B, K, 3): pts where observed, else the rigid model's."""
            return torch.where(observed[:, i, :, None], pts[:, i], rigid[:, i])

        out = [summary]
        if self.frame_features:
            obs_mid = observed[:, mid]
            if up is None:
                off = deformed_c[:, mid] - rigid_c[:, mid]
            else:  # the frame features are the body frame's, whatever frame the net reads
                R, t = kabsch(rigid[:, mid], self.body_points.to(rigid.dtype))
                off = (seen(mid) - rigid[:, mid]) @ R
            off = torch.where(obs_mid[..., None], off / net.offset_scale, torch.zeros_like(off))
            out += [
                R.reshape(B, 9),
                t / (10.0 * net.pos_scale),
                off.reshape(B, -1),
                obs_mid.to(off.dtype),
            ]
        if self.mechanisms is not None:
            out.append(self.mechanisms(seen(mid, raw)))
        if self.measurements:
            hup = None if self.heights_up is None else rigid.new_tensor(self.heights_up)
            out.append(pose_measurements(seen(mid), seen(mid - 1), up=hup))
        return torch.cat(out, -1)


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
    """A random forest as a head: fitted by scikit-learn (`deformnet.classify.fit_head_forest`,
    on a frozen encoder's features), stored as flat tensors (weights-only checkpoints, no
    pickled estimator) and evaluated here in torch. logits = log(mean over the trees of the
    class fractions of the leaf each tree sends x to) (softmax gives the forest's
    `predict_proba`). Not trainable by gradient.

    trees, min_samples_leaf, max_features: the forest's settings; inputs: "frame" (only the
    classifier's frame-feature columns: the pose, the offsets and their temporal context, set
    by `fit_head_forest`) or "all" (every feature); seed: the forest's random_state.
    x (B, in_dim) -> (B, num_classes).
    """

    INPUTS = ("frame", "all")

    def __init__(
        self,
        in_dim: int,
        num_classes: int,
        trees: int = 200,
        min_samples_leaf: int = 2,
        max_features: str | float | int = "sqrt",
        inputs: str = "frame",
        seed: int = 0,
    ) -> None:
        super().__init__()
        if inputs not in self.INPUTS:
            raise ValueError(f"head.inputs must be one of {self.INPUTS}, got '{inputs}'")
        if int(trees) < 1 or int(min_samples_leaf) < 1:
            raise ValueError(f"head.trees and head.min_samples_leaf must be >= 1, got {trees}, "
                             f"{min_samples_leaf}")  # fmt: skip
        self.in_dim, self.num_classes = int(in_dim), int(num_classes)
        self.trees, self.min_samples_leaf = int(trees), int(min_samples_leaf)
        self.max_features, self.inputs, self.seed = max_features, str(inputs), int(seed)
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
            raise RuntimeError("ForestHead is not fitted (deformnet.classify.fit_head_forest)")
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
    name = str(cfg.pop("name", "linear"))
    if name not in HEADS:
        raise ValueError(f"{where}.name must be one of {sorted(HEADS)}, got '{name[:200]}'")
    members = cfg.pop("ensemble", 1)
    if members is None or int(members) < 1:
        raise ValueError(f"{where}.ensemble must be an integer >= 1, got {members}")
    if name == "forest" and int(members) != 1:
        raise ValueError(f"{where}.ensemble must be 1 for a forest (it is an ensemble: head.trees)")
    try:
        if int(members) == 1:
            return HEADS[name](int(in_dim), int(num_classes), **cfg)
        return EnsembleHead(
            [HEADS[name](int(in_dim), int(num_classes), **cfg) for _ in range(int(members))]
        )
    except TypeError as exc:
        raise ValueError(f"{where}: cannot build the {name} head: {exc}") from None


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
    measurements do (D (1 + 2 len(context_frames)) values). With ``halves`` each span also
    gives the mean over its frames before and the mean over its frames after the frame (D (1 +
    4 len(context_frames)) values): where a movement goes and what came before it, e.g. a walk
    that ends at a mechanism, or how long a reach lasts. The head sees them standardised by
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
        halves: bool = False,
    ) -> None:
        super().__init__()
        self.encoder = encoder
        self.head = head
        self.context_frames = tuple(int(f) for f in context_frames)
        self.stride = int(stride)
        self.halves = bool(halves)
        self.offsets = context_offsets(self.context_frames, self.stride)
        self.span = max(self.offsets)
        self.window = encoder.window + 2 * self.span
        self.half_window = encoder.half_window + self.span
        self.out_dim = self.feature_dim(encoder.out_dim, self.context_frames, self.halves)
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
    def feature_dim(encoder_dim: int, context_frames: Sequence[int], halves: bool = False) -> int:
        return int(encoder_dim) * (1 + (4 if halves else 2) * len(tuple(context_frames)))

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
            if self.halves:
                for side in (near & (off < 0), near & (off > 0)):
                    out.append(per_frame[:, side.nonzero().flatten()].mean(1))
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
