"""`deformnet-classify`: fine-tune a behavior classifier on a (pretrained) deformation net's
encoder, or predict behavior labels with one (Hydra app over `run(cfg)`).

    deformnet-classify pretrained=runs/train/<run>/checkpoints/best.ckpt freeze=false \\
        label_fraction=0.1 data.train_tracks=[a/points3d.csv] data.train_labels=[a.csv] \\
        data.val_tracks=[...] data.val_labels=[...] data.test_tracks=[...] data.test_labels=[...]
    deformnet-classify pretrained=null net=transformer ...        # same architecture, scratch
    deformnet-classify mode=predict checkpoint=OUT/classifier.pt tracks=points3d.csv

Inputs: 3D tracks in the points3d CSV layout `adjust-track` writes (`{part}_x/_y/_z` columns,
`pose_rx..pose_tz`, `fnum`; read here by column name, without `adjust`), one file per session,
with labels per frame (`fnum,label` CSV) or as bouts (`start,stop,label` CSV, frame numbers,
stop inclusive). Sessions are split into train / val / test by session. Without pose columns
(e.g. `adjust-triangulate` output) the rigid pose of each frame is fitted to the points by
Kabsch; `data.interpolate=true` first fills gaps by linear interpolation in time.

Training writes into the output folder: `classifier.pt` (what `mode=predict` loads),
`report.json` (per-class precision / recall / F1, macro-F1, bout counts and mean durations, raw
and smoothed), `confusion.png`, `ethogram.png`, `config.yaml`. Prediction writes
`predictions.csv` (fnum, label, label_raw, p_<class>...) and `bouts.csv` (start, stop, label,
mean_probability).

Here: the window bank, the context features, the head's L-BFGS fit, building and loading the
classifier, and the app. Tracks and labels: `deformnet.behavior_labels`; metrics and figures:
`deformnet.behavior_report`; the modules: `deformnet.heads`, `deformnet.classify_lit`.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor, nn

from deformnet.apprun import run_app
from deformnet.atomic import finite_or_none, write_text
from deformnet.behavior_labels import (
    Session,
    body_scale,
    bouts,
    check_fps,
    read_labels,
    read_tracks,
    resample_session,
    same_fps,
    smooth,
    subsample_labels,
    to_track_frames,
)
from deformnet.behavior_report import (
    bout_stats,
    confusion_figure,
    ethogram_figure,
    evaluate,
    save_figure,
)
from deformnet.confutil import to_plain
from deformnet.deformation import check_track_up
from deformnet.lockbox import calibration_mechanisms, mechanism_table
from deformnet.paths import CONF_DIR, output_dir
from deformnet.quiet import quiet_lightning
from deformnet.sequence import feature_signature

log = logging.getLogger(__name__)

__all__ = [
    "SessionBank",
    "context_features",
    "fit_head_lbfgs",
    "fit_head_forest",
    "load_classifier",
    "predict_probs",
    "predict_session",
    "feature_range",
    "unfamiliar_share",
    "set_body_scales",
    "read_session",
    "run",
    "main",
]

CHECKPOINT_KIND = "mousetrack-behavior-classifier"


# --------------------------------------------------------------------------------------------
# windows
# --------------------------------------------------------------------------------------------
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


class _Frames(torch.utils.data.Dataset):
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


class _FeatureBank:
    """Classifier features (N, out_dim) of some frames of a bank, computed once (frozen
    encoder)."""

    def __init__(self, model, bank: SessionBank, idx: np.ndarray, features: Tensor | None = None):
        self.features = context_features(model, bank, idx) if features is None else features
        self.labels = bank.labels[torch.as_tensor(idx, dtype=torch.long)]

    def __len__(self) -> int:
        return len(self.labels)

    def batch(self, idx: Tensor) -> dict:
        return {"features": self.features[idx], "label": self.labels[idx]}


def fit_head_lbfgs(
    model,
    features: Tensor,
    labels: Tensor,
    class_weights: Sequence[float] | None = None,
    l2: float = 1.0,
    max_iter: int = 200,
) -> dict:
    """Fit the classifier's head alone on fixed features by full-batch L-BFGS (the linear-probe
    protocol: deterministic, to convergence): minimise the class-weighted sum over the frames
    of the cross-entropy plus 0.5 l2 |W|^2 over the head's weight matrices (for a linear head,
    multinomial logistic regression with C = 1 / l2).

    features (N, out_dim) as `model.features` gives them (standardised inside
    `model.classify`), labels (N,) class indices. An `EnsembleHead`'s members are fitted each
    on its own (from their own initialisations). Returns {"loss" (the members' mean),
    "iterations" (their sum)}."""
    from deformnet.heads import EnsembleHead

    labels = torch.as_tensor(labels, dtype=torch.long)
    if features.dim() != 2 or features.shape[0] != labels.shape[0] or labels.numel() == 0:
        raise ValueError(f"features (N, D) and labels (N,), got {features.shape}, {labels.shape}")
    head = model.head
    was_training = head.training
    head.train(False)  # dropout off: a deterministic objective
    dtype = next(head.parameters()).dtype
    x = ((features.detach() - model.feature_mean) / model.feature_std).to(dtype)
    if class_weights is None:
        sw = torch.ones(labels.shape, dtype=dtype)
    else:
        sw = torch.as_tensor(class_weights, dtype=dtype)[labels]
    members = list(head.members) if isinstance(head, EnsembleHead) else [head]
    facts = [_lbfgs(m, x, labels, sw, l2, max_iter) for m in members]
    head.train(was_training)
    return {
        "loss": float(np.mean([f[0] for f in facts])) / max(float(sw.sum()), 1e-12),
        "iterations": int(sum(f[1] for f in facts)),
    }


def _lbfgs(head: nn.Module, x: Tensor, labels: Tensor, sw: Tensor, l2: float, max_iter: int):
    """One head fitted by L-BFGS (see `fit_head_lbfgs`); (objective, iterations)."""
    params = [p for p in head.parameters() if p.requires_grad]
    mats = [p for p in params if p.dim() >= 2]
    opt = torch.optim.LBFGS(
        params,
        lr=1.0,
        max_iter=int(max_iter),
        history_size=50,
        line_search_fn="strong_wolfe",
        tolerance_grad=1e-6,
        tolerance_change=1e-9,
    )

    def closure():
        opt.zero_grad()
        ce = nn.functional.cross_entropy(head(x), labels, reduction="none")
        loss = (ce * sw).sum() + 0.5 * float(l2) * sum((m**2).sum() for m in mats)
        loss.backward()
        return loss

    with torch.enable_grad():
        opt.step(closure)
        loss = float(closure().detach())
    return loss, int(opt.state[opt._params[0]].get("n_iter", 0))


def fit_head_forest(
    model,
    features: Tensor,
    labels: Tensor,
    class_weights: Sequence[float] | None = None,
    sample_weight: np.ndarray | None = None,
) -> dict:
    """Fit the classifier's `ForestHead` (scikit-learn's RandomForestClassifier with the head's
    settings, class-weighted) on fixed features (N, out_dim) as `model.features` gives them
    (standardised as `model.classify` does; trees do not care) and labels (N,); or, with
    ``sample_weight`` (N,), weighted per frame instead of per class (self-training's labelled
    and pseudo-labelled frames, `deformnet.pseudo.pseudo_sample_weights`). With
    ``head.inputs == "frame"`` the forest reads only the frame-feature columns
    (`BehaviorClassifier.frame_columns`). Returns {"trees", "nodes", "depth", "columns"}."""
    from sklearn.ensemble import RandomForestClassifier

    from deformnet.heads import ForestHead

    head = model.head
    if not isinstance(head, ForestHead):
        raise TypeError(f"fit_head_forest needs a ForestHead, got {type(head).__name__}")
    labels = torch.as_tensor(labels, dtype=torch.long)
    if features.dim() != 2 or features.shape[0] != labels.shape[0] or labels.numel() == 0:
        raise ValueError(f"features (N, D) and labels (N,), got {features.shape}, {labels.shape}")
    if head.inputs == "frame":
        cols = model.frame_columns()
    else:
        cols = torch.arange(features.shape[1])
    x = ((features.detach() - model.feature_mean) / model.feature_std)[:, cols]
    y = labels.numpy()
    present = np.unique(y)
    weights = None
    if class_weights is not None and sample_weight is None:
        weights = {int(c): float(class_weights[int(c)]) for c in present}
    if sample_weight is not None and np.shape(sample_weight) != y.shape:
        raise ValueError(f"sample_weight must be ({y.size},), got {np.shape(sample_weight)}")
    forest = RandomForestClassifier(
        n_estimators=head.trees,
        min_samples_leaf=head.min_samples_leaf,
        max_features=head.max_features,
        class_weight=weights,
        random_state=head.seed,
        n_jobs=1,
    )
    forest.fit(x.double().numpy(), y, sample_weight=sample_weight)
    head.set_forest(forest, cols.numpy(), forest.classes_)
    return {
        "trees": head.trees,
        "nodes": int(head.feature.numel()),
        "depth": int(head.depth),
        "columns": int(cols.numel()),
    }


PSEUDO_TEACHERS = ("none", "linear", "cotrain")
SEQUENCE_DEFAULTS = {  # pseudo_labels.sequence (conf/classify.yaml documents them)
    "encoder": None, "steps": 1000, "channels": 128, "dilations": [1, 2, 4, 8, 16, 32, 64],
    "mask_ratio": 0.75, "longest_span": 60, "crop": 256, "batch": 32, "lr": 1e-3,
    "target": "frame", "context": [15, 33], "seed": 0,
}  # fmt: skip


def _number(block: str, key: str, v, kind):
    try:
        if isinstance(v, bool) or (kind is int and float(v) != int(float(v))):
            raise ValueError
        return kind(v)
    except (TypeError, ValueError):
        what = "an integer" if kind is int else "a number"
        raise ValueError(f"{block}.{key} must be {what}, got {v!r}") from None


def _sequence_settings(block) -> dict:
    """`pseudo_labels.sequence` checked (ValueError naming the setting)."""
    sq = {**SEQUENCE_DEFAULTS, **(dict(to_plain(block)) if block else {})}
    unknown = sorted(set(sq) - set(SEQUENCE_DEFAULTS))
    if unknown:
        moved = " (bins is pseudo_labels.bins)" if "bins" in unknown else ""
        raise ValueError(f"pseudo_labels.sequence: unknown settings {unknown} (known: "
                         f"{sorted(SEQUENCE_DEFAULTS)}){moved}")  # fmt: skip
    b = "pseudo_labels.sequence"
    out = {"encoder": None if sq["encoder"] in (None, "") else str(sq["encoder"])}
    for key, kind, low in (("steps", int, 0), ("channels", int, 1), ("longest_span", int, 4),
                           ("crop", int, 16), ("batch", int, 1),
                           ("seed", int, None), ("lr", float, None),
                           ("mask_ratio", float, None)):  # fmt: skip
        out[key] = _number(b, key, sq[key], kind)
        if low is not None and out[key] < low:
            raise ValueError(f"{b}.{key} must be >= {low}, got {out[key]}")
    if out["lr"] <= 0:
        raise ValueError(f"{b}.lr must be > 0, got {out['lr']}")
    if not 0.0 < out["mask_ratio"] < 1.0:
        raise ValueError(f"{b}.mask_ratio must be in (0, 1), got {out['mask_ratio']}")
    if str(sq["target"]) not in ("frame", "all"):
        raise ValueError(f"{b}.target must be 'frame' or 'all', got '{sq['target']}'")
    out["target"] = str(sq["target"])
    for key in ("dilations", "context"):
        v = sq[key]
        if not isinstance(v, (list, tuple)):
            raise ValueError(f"{b}.{key} must be a list of integers, got {v!r}")
        out[key] = [_number(b, key, x, int) for x in v]
    if not out["dilations"] or min(out["dilations"]) < 1:
        raise ValueError(f"{b}.dilations must be a non-empty list of integers >= 1, got "
                         f"{out['dilations']}")  # fmt: skip
    if any(c < 3 or c % 2 == 0 for c in out["context"]):
        raise ValueError(f"{b}.context must be odd frame counts >= 3, got {out['context']}")
    if out["encoder"] is None and out["steps"] == 0:
        log.warning("%s.steps=0: the sequence encoder is not pretrained (its random weights "
                    "teach: a control, not a classifier to use)", b)  # fmt: skip
    return out


def pseudo_settings(cfg: DictConfig, forest: bool) -> dict | None:
    """`pseudo_labels` checked before any data is read: None (teacher none) or {"teacher",
    "keep", "smooth", "labelled_weight", "bins", "unlabelled"} (teacher=cotrain: and
    "sequence", its sequence encoder's settings, and "embedding_keep")."""
    pl = dict(to_plain(cfg.get("pseudo_labels")) or {})
    teacher = str(pl.get("teacher", "none"))
    if teacher not in PSEUDO_TEACHERS:
        raise ValueError(f"pseudo_labels.teacher must be one of {PSEUDO_TEACHERS}, got "
                         f"'{teacher}'")  # fmt: skip
    if teacher == "none":
        return None
    if not forest:
        raise ValueError(f"pseudo_labels.teacher={teacher} self-trains the forest head: set "
                         "head=forest freeze=true (or pseudo_labels.teacher=none)")  # fmt: skip
    out: dict = {"teacher": teacher}
    for key, default, kind in (("keep", 0.3, float), ("smooth", 9, int),
                               ("labelled_weight", 5.0, float), ("bins", 4, int)):  # fmt: skip
        out[key] = _number("pseudo_labels", key, pl.get(key, default), kind)
    out["unlabelled"] = pl.get("unlabelled", True)
    if not isinstance(out["unlabelled"], bool):
        raise ValueError(f"pseudo_labels.unlabelled must be true or false, got "
                         f"{out['unlabelled']!r}")  # fmt: skip
    if out["bins"] < 2:
        raise ValueError(f"pseudo_labels.bins must be an integer >= 2, got {out['bins']}")
    if not 0.0 < out["keep"] <= 1.0:
        raise ValueError(f"pseudo_labels.keep must be in (0, 1], got {out['keep']}")
    if out["smooth"] < 1:
        raise ValueError(f"pseudo_labels.smooth must be an integer >= 1, got {out['smooth']}")
    if out["labelled_weight"] <= 0:
        raise ValueError(f"pseudo_labels.labelled_weight must be > 0, got "
                         f"{out['labelled_weight']}")  # fmt: skip
    if teacher == "cotrain":
        out["sequence"] = _sequence_settings(pl.get("sequence"))
        out["embedding_keep"] = _number(
            "pseudo_labels", "embedding_keep", pl.get("embedding_keep", 0.5), float
        )
        if not 0.0 < out["embedding_keep"] <= 1.0:
            raise ValueError(f"pseudo_labels.embedding_keep must be in (0, 1], got "
                             f"{out['embedding_keep']}")  # fmt: skip
    return out


def frame_feature_columns(model) -> Tensor:
    """Indices (F,) of the frame features among a frame's own encoder output (the first
    `model.encoder.out_dim` of its context features; `BehaviorClassifier.frame_columns`)."""
    cols = model.frame_columns()
    return cols[cols < model.encoder.out_dim]


def sequence_signature(model, mech: Mapping | None, scale_mode: str) -> dict:
    """What a sequence encoder pretrained on this classifier's per-frame features must match
    (`deformnet.sequence.feature_signature`)."""
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
    settings: dict,
    signature: Mapping,
    out: Path,
    bins: int = 4,
    teach_unlabelled: bool = True,
) -> tuple[list[np.ndarray], dict]:
    """`pseudo_labels.teacher=cotrain`: the behavior-scale sequence encoder
    (`deformnet.sequence`), pretrained by masked-span reconstruction on the training sessions'
    per-frame features (each frame's own encoder output: the first `encoder.out_dim` columns of
    ``train_features`` (N, out_dim), every training frame, sessions of ``lengths`` frames) and
    the ``unlabelled`` sessions' (their features, (T_u, out_dim) each), or loaded
    (``settings["encoder"]``, checked against ``signature``, `sequence_signature`); it is saved
    to out/sequence_encoder.pt. Two teachers fitted on the labelled frames ``idx`` (labels
    ``labels`` (L,), ``num_classes`` C, class weights (C,) or None), one per view: the binned
    frame features (with context; `linear_teacher_probs`, ``bins`` per feature) and the
    encoder's embedding (`embedding_teacher_probs`). Returns their probabilities (N + M, C) of
    every training frame, then every unlabelled session's (M frames in all; M = 0 without
    ``teach_unlabelled``: then only the pretraining reads them), as a list of two, and facts."""
    from deformnet.atomic import atomic_path
    from deformnet.sequence import (
        SequenceEncoder,
        embedding_teacher_probs,
        embeddings,
        export_sequence_encoder,
        linear_teacher_probs,
        load_sequence_encoder,
        pretrain_sequences,
    )

    D = model.encoder.out_dim
    per_frame = train_features[:, :D].float()
    bounds = np.cumsum([0, *lengths])
    train_seqs = [per_frame[a:b] for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    facts: dict = {}
    if settings["encoder"]:  # the signature holds the feature count (out_dim)
        seq = load_sequence_encoder(settings["encoder"], signature)
        facts["encoder"] = str(settings["encoder"])
        log.info("sequence encoder from %s", settings["encoder"])
    else:
        torch.manual_seed(int(settings["seed"]))
        target = frame_feature_columns(model) if settings["target"] == "frame" else None
        seq = SequenceEncoder(D, settings["channels"], settings["dilations"], target)
        seqs = train_seqs + [u[:, :D].float() for u in unlabelled]
        log.info("sequence pretraining: %d steps on %d sessions (%d unlabelled), %d frames",
                 settings["steps"], len(seqs), len(unlabelled),
                 sum(len(s) for s in seqs))  # fmt: skip
        facts["pretraining"] = pretrain_sequences(
            seq, seqs, settings["steps"], settings["mask_ratio"], settings["longest_span"],
            settings["crop"], settings["batch"], settings["lr"], settings["seed"],
        )  # fmt: skip
        log.info("sequence pretraining: %s", facts["pretraining"])
        path = out / "sequence_encoder.pt"
        with atomic_path(path) as tmp:
            torch.save(export_sequence_encoder(seq, signature, facts["pretraining"]), tmp)
        facts["encoder"] = str(path)
    taught = list(unlabelled) if teach_unlabelled else []  # the frames to label, after training's
    emb = embeddings(seq, train_seqs + [u[:, :D].float() for u in taught], settings["context"])
    frame = torch.cat([train_features, *taught])[:, model.frame_columns()].double().numpy()
    emb = emb.double().numpy()
    return [
        linear_teacher_probs(frame, idx, labels, num_classes, class_weights, bins),
        embedding_teacher_probs(emb, idx, labels, num_classes, class_weights),
    ], facts  # fmt: skip


def self_train_forest(
    model, bank: SessionBank, lengths: Sequence[int], idx: np.ndarray, features: Tensor,
    settings: dict, probs: np.ndarray | Sequence[np.ndarray], all_features: Tensor | None = None,
    unlabelled: Sequence[Tensor] = (),
) -> tuple[dict, Tensor]:  # fmt: skip
    """Self-training of a fitted forest head: a teacher's class probabilities ``probs``
    (len(bank) + M, C) of every training frame of ``bank`` (sessions of ``lengths`` frames) and
    of the M frames of ``unlabelled`` (the features (T_u, D) of sessions nobody labelled,
    `data.unlabelled_tracks`, after the training frames); the class-balanced pseudo-labels of
    the frames without a label (`deformnet.pseudo.class_balanced_pseudo_labels`) join the
    labelled frames ``idx`` (their features ``features`` (N, D)) and the forest is fitted again
    on both, weighted per frame (`pseudo_sample_weights`). ``all_features``: every training
    frame's features (len(bank), D), computed when not given. ``probs`` a list of two
    (`pseudo_labels.teacher=cotrain`: the frame features' teacher's, the embedding's):
    co-training (`deformnet.pseudo.co_training_pseudo_labels`, shares settings["keep"] and
    settings["embedding_keep"]). Returns facts (the pseudo-labelled frames in all, per class and
    from the unlabelled sessions, the refitted forest's; co-training: the frames dropped for a
    conflict) and every training frame's features."""
    from deformnet.pseudo import co_training_pseudo_labels, pseudo_sample_weights

    if all_features is None:
        all_features = context_features(model, bank, torch.arange(len(bank)))
    pool = torch.cat([all_features, *unlabelled]) if len(unlabelled) else all_features
    labels = bank.labels.numpy()
    views = [probs] if isinstance(probs, np.ndarray) else list(probs)
    N, C = len(labels), views[0].shape[1]
    for p in views:
        if p.shape != (len(pool), C):
            raise ValueError(f"probs must be ({len(pool)}, {C}), got {p.shape}")
    labelled = np.r_[labels >= 0, np.zeros(len(pool) - N, bool)]
    keeps = [settings["keep"], settings.get("embedding_keep")][: len(views)]
    rows, pseudo, conflicts = co_training_pseudo_labels(  # one view: class-balanced alone
        views, [*lengths, *(len(u) for u in unlabelled)], labelled, keeps, settings["smooth"]
    )  # fmt: skip
    facts = {"teacher": settings["teacher"], "frames": int(rows.size),
             "per_class": np.bincount(pseudo, minlength=C).tolist(),
             "unlabelled_frames": int((rows >= N).sum())}  # fmt: skip
    if len(views) > 1:
        facts["conflicts"] = conflicts
    if rows.size == 0:  # every frame is labelled: nothing to teach
        return facts, all_features
    y = np.concatenate([labels[idx], pseudo])
    sw = pseudo_sample_weights(y, len(idx), C, settings["labelled_weight"])
    x = torch.cat([features, pool[torch.as_tensor(rows)]])
    facts["forest"] = fit_head_forest(model, x, torch.as_tensor(y), sample_weight=sw)
    return facts, all_features


def _loader(bank, idx: np.ndarray, batch_size: int, samples: int | None, seed: int):
    ds = _Frames(bank, idx)
    sampler = None
    if samples:
        gen = torch.Generator().manual_seed(int(seed))
        sampler = torch.utils.data.RandomSampler(
            ds, replacement=True, num_samples=int(samples), generator=gen
        )
    return torch.utils.data.DataLoader(
        ds, batch_size=int(batch_size), sampler=sampler, shuffle=False, collate_fn=ds.collate
    )


# --------------------------------------------------------------------------------------------
# model building, checkpoint
# --------------------------------------------------------------------------------------------
def _build(
    net_cfg: dict,
    body,
    half_window: int,
    head_cfg: dict,
    frame_features: bool,
    C: int,
    context: dict | None = None,
    up=None,
    mechanisms: dict | None = None,
    measurements: bool = False,
    heights_up=None,
    source: str = "",
):
    """The classifier a config or a checkpoint describes (``source``: the checkpoint file, for
    errors); its net and head are built from allow-lists with plain arguments only
    (`deformnet.deformation.build_net`, `deformnet.heads.build_head`)."""
    from deformnet.deformation import build_net
    from deformnet.heads import BehaviorClassifier, MechanismFeatures, WindowEncoder, build_head

    mech = None
    if mechanisms:
        parts = [body.parts.index(p) for p in mechanisms["parts"]]
        mech = MechanismFeatures(
            mechanisms["positions"], parts, mechanisms["names"], float(mechanisms["scale"])
        )
    enc = WindowEncoder(
        build_net(net_cfg, source), np.asarray(body.points), half_window, frame_features, up, mech,
        measurements, heights_up,
    )  # fmt: skip
    ctx = dict(context or {})
    frames = [int(f) for f in (ctx.get("frames") or [])]
    halves = bool(ctx.get("halves", False))
    dim = BehaviorClassifier.feature_dim(enc.out_dim, frames, halves)
    return BehaviorClassifier(
        enc, build_head(head_cfg, dim, C, source), frames, int(ctx.get("stride", 1) or 1), halves
    )


def export_classifier(model, meta: dict) -> dict:
    return {
        "kind": CHECKPOINT_KIND,
        **meta,
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
    }


def load_classifier(path: str | os.PathLike):
    """(model in eval mode, metadata) from a `classifier.pt` written by training. Read as data
    (`deformnet.checkpoint.load_checkpoint`, weights only); its net and head are built from
    the allow-lists of this project's classes with plain arguments (`_build`); anything else
    is a ValueError naming the file."""
    from deformnet.body import BodyModel
    from deformnet.checkpoint import load_checkpoint

    blob = load_checkpoint(path, "classifier checkpoint")
    if not isinstance(blob, dict) or blob.get("kind") != CHECKPOINT_KIND:
        raise ValueError(f"{path} is not a behavior classifier (write it with deformnet-classify)")
    try:
        b = blob["body"]
        body = BodyModel.from_mapping(b["parts"], b.get("aliases"), b.get("name", "body"))
        model = _build(
            blob["net_config"],
            body,
            int(blob["half_window"]),
            blob["head"],
            bool(blob["frame_features"]),
            len(blob["classes"]),
            blob.get("context"),
            blob.get("up"),
            blob.get("mechanisms"),
            bool(blob.get("measurements", False)),
            blob.get("heights_up"),
            os.fspath(path),
        )
        model.load_state_dict(blob["state_dict"])
    except (KeyError, TypeError, AttributeError, RuntimeError, IndexError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(
            f"{path}: the classifier checkpoint does not fit this version of deformnet-classify "
            f"(written by an older or newer one?): {first[:200]}"
        ) from None
    return model.eval(), {**{k: v for k, v in blob.items() if k != "state_dict"}, "body": body}


@torch.no_grad()
def predict_probs(model, bank: SessionBank, batch_size: int = 512) -> np.ndarray:
    """Class probabilities (N, C) for every frame of the bank, in order."""
    return _features_probs(model, bank, batch_size)[1]


@torch.no_grad()
def _features_probs(model, bank: SessionBank, batch_size: int = 512) -> tuple[Tensor, np.ndarray]:
    """Every bank frame's classifier features (N, D) and class probabilities (N, C)."""
    feats = context_features(model, bank, torch.arange(len(bank)), batch_size)
    return feats, torch.softmax(model.classify(feats), -1).numpy()


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


def predict_session(
    model,
    session: Session,
    smoothing: dict,
    rng: Mapping | None = None,
    rates: tuple[float, float] | None = None,
    antialias: bool = True,
) -> dict:
    """{"probs" (T, C), "raw" (T,), "labels" (T,) smoothed (= raw without smoothing),
    "unfamiliar" (T,) each frame's `unfamiliar_share` given the training range `rng`, else
    None}. rates: (the session's frame rate, the classifier's) in Hz, when they differ: the
    session is labelled resampled to the classifier's rate (`resample_session`: its windows,
    speeds and smoothing in the time the classifier learnt them), the results taken back to
    the session's own frames (`to_track_frames`: probabilities interpolated, the smoothed
    labels and unfamiliar shares of the nearest resampled frame); to a lower rate low-passed
    first unless `antialias` is false."""
    if rates is not None:
        fps, rate = rates
        low = resample_session(session, fps, rate, antialias)
        res = predict_session(model, low, smoothing, rng)
        back = functools.partial(to_track_frames, fnum=session.fnum, fps=fps, rate=rate)
        probs = back(res["probs"], kind="linear")
        return {
            "probs": probs,
            "raw": probs.argmax(-1),
            "labels": back(res["labels"]),
            "unfamiliar": None if res["unfamiliar"] is None else back(res["unfamiliar"]),
        }
    feats, probs = _features_probs(model, SessionBank([session], model.half_window))
    raw = probs.argmax(-1)
    lab = smooth(probs, int(smoothing.get("median") or 0), int(smoothing.get("min_bout") or 0))
    unfamiliar = None if rng is None else unfamiliar_share(feats, rng)
    return {"probs": probs, "raw": raw, "labels": lab, "unfamiliar": unfamiliar}


def frame_rates(fps, meta: Mapping, name: str) -> tuple[float, float] | None:
    """The rates `predict_session` resamples a track `name` recorded at `fps` (Hz, or None:
    unknown) between, for a classifier whose meta stores its training rate ("fps", None
    where unknown): (fps, the classifier's) where both are known and differ, else None
    (logged: the track taken to be at the classifier's rate, or not resampled)."""
    fps = check_fps(fps, "fps")
    rate = check_fps(meta.get("fps"), "the classifier's fps")
    if fps is None:
        if rate is None:
            log.info("%s: no fps= given, and the classifier knows no frame rate", name)
        else:  # the data cannot tell: another animal moves 0.7-1.8x the mm per frame
            log.warning(
                "%s: no fps= given: the track is taken to be at the classifier's frame rate, "
                "%g Hz; at another rate its windows and speeds mean other times than the "
                "classifier learnt (give fps=, the track's rate, to have it resampled)",
                name,
                rate,
            )
        return None
    if rate is None:
        log.warning(
            "%s: the classifier does not know the frame rate it was trained at (trained "
            "without fps=): the track (%g Hz) is labelled frame by frame as it is; if the rates "
            "differ its windows and speeds mean other times than the classifier learnt",
            name,
            fps,
        )
        return None
    if same_fps(fps, rate):
        return None
    log.info("%s: %g Hz, labelled resampled to the classifier's %g Hz", name, fps, rate)
    return fps, rate


# --------------------------------------------------------------------------------------------
# the app
# --------------------------------------------------------------------------------------------
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


def _sessions(cfg: DictConfig, split: str, body, classes: Sequence[str]) -> list[Session]:
    """The sessions of a split (train, val, test; or unlabelled: data.unlabelled_tracks, no
    labels files, every frame's label -1) as the config reads them (`data.*_tracks` and
    `data.*_labels`)."""
    d = cfg.data
    unl = split == "unlabelled"
    interp = bool(d.get("interpolate", False))
    tracks = [str(p) for p in (d.get(f"{split}_tracks") or [])]
    labels = [str(p) for p in (d.get(f"{split}_labels") or [])]
    if split == "train" and cfg.get("tracks") and not tracks:  # tracks=[...] labels=[...]
        tracks, labels = _path_list(cfg.get("tracks")), _path_list(cfg.get("labels"))
        if len(tracks) != len(labels):
            raise ValueError(f"tracks= has {len(tracks)} files but labels= {len(labels)} (one "
                             "labels file per session)")  # fmt: skip
    if unl:
        labels = [None] * len(tracks)
    if len(tracks) != len(labels):
        raise ValueError(
            f"data.{split}_tracks has {len(tracks)} files but data.{split}_labels {len(labels)}"
        )
    rates = to_plain(d.get(f"{split}_fps"))
    fps = check_fps(cfg.get("fps"), "fps")
    if rates is not None:
        if not isinstance(rates, list) or len(rates) != len(tracks):
            raise ValueError(
                f"data.{split}_fps must list one frame rate per session of data.{split}_tracks "
                f"({len(tracks)}), got {rates!r}"
            )
        if fps is None:
            raise ValueError(
                f"data.{split}_fps gives each session's frame rate: set fps= too, the rate the "
                "classifier reads them at"
            )
        rates = [check_fps(r, f"data.{split}_fps[{i}]") for i, r in enumerate(rates)]
    out = []
    for i, (tp, lp) in enumerate(zip(tracks, labels)):
        tr = read_tracks(tp, body, interpolate=interp)
        if lp is None:
            lab = np.full(len(tr["fnum"]), -1, dtype=np.int64)
        else:
            rate = fps if rates is None else rates[i]  # BORIS events in seconds
            lab = read_labels(lp, tr["fnum"], classes, tracks=tp, fps=rate)
        parts = (tr["rigid"], tr["deformed"], tr["observed"], tr["fnum"])
        s = Session(tp, *parts, lab, pose=tr["pose"])
        if rates is not None and not same_fps(rates[i], fps):
            log.info("%s: %g Hz, read resampled to %g Hz (fps)", tp, rates[i], fps)
            s = resample_session(s, rates[i], fps, bool(cfg.get("antialias", True)))
        out.append(s)
    return out


def _path_list(value) -> list[str]:
    """A path or a list of paths (``tracks=a.csv``, ``tracks=[a.csv,b.csv]``) as a list."""
    value = to_plain(value)
    if value is None:
        return []
    return [str(p) for p in value] if isinstance(value, list) else [str(value)]


def mechanism_setup(cfg: DictConfig, body) -> dict | None:
    """The lock-box context (`deformnet.heads.MechanismFeatures`) from the config's
    ``mechanisms`` block: {"names", "positions" (M x [x, y, z] mm), "parts" (the body model's
    names), "scale", "source"}, or None when neither ``mechanisms.positions`` ({name: [x, y,
    z]}, or ``sim``: the simulator's lock box) nor ``mechanisms.calibration`` (a
    calibration.toml with a [metadata.mechanisms] table, as `adjust-simulate` writes and
    `adjust-events` reads) is set. Errors name the file, mechanism or part."""
    m = cfg.get("mechanisms") or {}
    pos, calib = to_plain(m.get("positions")), m.get("calibration")
    if pos is None and not calib:
        return None
    if pos is not None and calib:
        raise ValueError("set mechanisms.positions or mechanisms.calibration, not both")
    if calib:
        try:
            pos = calibration_mechanisms(str(calib))
        except ValueError as exc:
            raise ValueError(f"mechanisms.calibration: {exc}") from None
        source = f"{calib} [metadata.mechanisms]"
    elif pos == "sim":
        from deformnet.sim import MECHANISMS, SimConfig
        from deformnet.sim.scene import build_scene

        scene = build_scene(SimConfig.from_config(cfg.get("sim")), body)
        pos = dict(zip(MECHANISMS, scene.mech_pos.tolist()))
        source = "the simulator's lock box (sim.lockbox)"
    else:
        source = "mechanisms.positions"
    table = mechanism_table(pos, source)
    names, xyz = list(table), list(table.values())
    parts = []
    for q in list(to_plain(m.get("parts")) or []):
        r = body.resolve(str(q))
        if r is None:
            raise ValueError(
                f"mechanisms.parts: unknown body part '{q}' (the body model's: {list(body.parts)})"
            )
        parts.append(r)
    if not parts:
        raise ValueError("mechanisms.parts: name at least one body part (e.g. nose_tip)")
    scale = float(m.get("scale", 50.0))
    if not scale > 0:
        raise ValueError(f"mechanisms.scale must be > 0 mm, got {scale}")
    return {"names": names, "positions": xyz, "parts": parts, "scale": scale, "source": source}


def classifier_from_config(cfg: DictConfig, net_cfg: dict, body, half_window: int, C: int, up):
    """The classifier the config describes (its head, frame features, lock-box context,
    measurements and temporal context) on an encoder config (`_encoder_config`'s), untrained;
    (model, its `mechanism_setup` or None). A forest head that reads only frame features needs
    some (ValueError)."""
    head_cfg = dict(to_plain(cfg.head))
    ff = bool(cfg.get("frame_features", True))
    mech = mechanism_setup(cfg, body)
    meas = bool(cfg.get("measurements", False))
    heights_up = to_plain(cfg.get("heights_up"))
    if heights_up is not None and not meas:
        raise ValueError("heights_up is the up of the measurements' part heights: set "
                         "measurements=true too (or leave heights_up unset)")  # fmt: skip
    frame_only = head_cfg.get("name") == "forest" and head_cfg.get("inputs", "frame") == "frame"
    if frame_only and not (ff or mech or meas):
        raise ValueError(
            "head.inputs=frame needs frame_features=true or lock-box context (mechanisms.*) or "
            "measurements=true, or head.inputs=all"
        )
    context = dict(to_plain(cfg.get("context")) or {})
    model = _build(net_cfg, body, half_window, head_cfg, ff, C, context, up, mech, meas, heights_up)
    return model, mech


def _encoder_config(cfg: DictConfig, classes):
    """(net config, body, half_window, pretrained-net state or None, world up or None: the
    canonical frame the encoder reads, `deformnet.tokens.canonicalize`)."""
    from deformnet.body import BodyModel
    from deformnet.deformation import DeformationModel, frame_up
    from deformnet.train import net_config

    if cfg.get("pretrained"):
        dm = DeformationModel.from_checkpoint(str(cfg.pretrained))
        log.info(
            "encoder: %s from %s", dm.net_config.get("_target_"), cfg.pretrained
        )  # fmt: skip
        up = frame_up(to_plain(cfg.get("up")), dm, str(cfg.pretrained))
        return dict(dm.net_config), dm.body, dm.half_window, dm.net.state_dict(), up

    body = BodyModel.from_config(cfg.body)
    _, ncfg = net_config(cfg, body.num_parts)
    return ncfg, body, int(cfg.half_window), None, frame_up(to_plain(cfg.get("up")))


def _train(cfg: DictConfig, out: Path) -> dict:
    import lightning as L

    from deformnet.atomic import write_text
    from deformnet.classify_lit import ClassifyLit

    classes = [str(c) for c in cfg.classes]
    C = len(classes)
    net_cfg, body, hw, state, up = _encoder_config(cfg, classes)
    body = body.with_aliases(to_plain(cfg.get("aliases")))  # kept in classifier.pt
    head_cfg = dict(to_plain(cfg.head))
    forest = head_cfg.get("name") == "forest"
    if forest and not bool(cfg.freeze):  # before any data is read
        raise ValueError(
            "head=forest is fitted by scikit-learn on a frozen encoder's features: set freeze=true"
        )
    pseudo = pseudo_settings(cfg, forest)
    scale_mode = str(cfg.get("body_scale", "none"))  # settings checked before any data is read
    if scale_mode not in BODY_SCALE_MODES:
        raise ValueError(f"body_scale must be one of {BODY_SCALE_MODES}, got '{scale_mode}'")
    unf = _unfamiliar_settings(cfg)
    fps = check_fps(cfg.get("fps"), "fps")  # the training sessions' rate (None: unknown)
    model, mech = classifier_from_config(cfg, net_cfg, body, hw, C, up)
    ff, meas = model.encoder.frame_features, model.encoder.measurements
    if mech is not None:
        log.info("lock-box context: %s from %s (parts %s)", mech["names"], mech["source"],
                 mech["parts"])  # fmt: skip
    if state is not None:
        model.encoder.net.load_state_dict(state)
    span = model.half_window  # the encoder's half window plus the context's

    train = _sessions(cfg, "train", body, classes)
    val = _sessions(cfg, "val", body, classes)
    test = _sessions(cfg, "test", body, classes)
    # more recordings without labels: the teachers label their frames too (the forest learns
    # from them), and the cotrain teacher's sequence pretraining reads them
    unlabelled = _sessions(cfg, "unlabelled", body, classes)
    if unlabelled and pseudo is None:
        log.warning("data.unlabelled_tracks: %d sessions not used (only "
                    "pseudo_labels.teacher=linear|cotrain learns from them)",
                    len(unlabelled))  # fmt: skip
        unlabelled = []
    elif (
        unlabelled
        and not pseudo["unlabelled"]
        and (pseudo["teacher"] == "linear" or pseudo["sequence"]["encoder"])
    ):
        log.warning("data.unlabelled_tracks: %d sessions not used (pseudo_labels.unlabelled="
                    "false, and no sequence pretraining reads them)", len(unlabelled))  # fmt: skip
        unlabelled = []
    hup = model.encoder.heights_up if meas else None
    for s in (*train, *val, *test, *unlabelled):  # a heading-frame encoder or the heights: the
        check_track_up(s.rigid, body.points, model.encoder.heights_up, s.name)  # tracks' up
    set_body_scales((*train, *val, *test, *unlabelled), scale_mode, body)
    if not train:
        raise ValueError("no training sessions: set data.train_tracks / data.train_labels")
    frac, seg = float(cfg.label_fraction), int(cfg.get("label_segment", 1))
    subsample_labels(train, frac, seg, int(cfg.label_seed))
    subsample_labels(val, frac, seg, int(cfg.label_seed) + 1)
    bank = SessionBank(train, span)
    idx = np.flatnonzero(bank.labels.numpy() >= 0)
    if idx.size == 0:
        raise ValueError("the training sessions have no labelled frames")
    counts = np.bincount(bank.labels.numpy()[idx], minlength=C)
    weights = None
    if str(cfg.loss.class_weights) == "balanced":
        weights = np.where(counts > 0, counts.sum() / np.maximum(C * counts, 1), 0.0)
    elif str(cfg.loss.class_weights) != "none":
        raise ValueError(f"loss.class_weights must be 'balanced' or 'none', got {cfg.loss}")
    log.info("labelled training frames: %d (%s)", idx.size, dict(zip(classes, counts.tolist())))
    # the head's inputs standardised by the labelled training frames' features (at the start)
    train_features = context_features(model, bank, idx)
    if idx.size >= 2:
        model.set_standardization(train_features)

    d = cfg.data
    bs = int(d.batch_size)
    train_dl = _loader(bank, idx, bs, int(d.steps_per_epoch) * bs, int(cfg.seed))
    val_dl = None
    if val:
        vbank = SessionBank(val, span)
        vidx = np.flatnonzero(vbank.labels.numpy() >= 0)
        vmax = d.get("val_frames")
        if vmax and vidx.size > int(vmax):
            vidx = vidx[np.linspace(0, vidx.size - 1, int(vmax)).round().astype(int)]
        if vidx.size:
            val_dl = _loader(vbank, vidx, 512, None, 0)

    lit = ClassifyLit(
        model,
        classes,
        class_weights=None if weights is None else weights.tolist(),
        freeze=bool(cfg.freeze),
        lr=float(cfg.optim.lr),
        encoder_lr=float(cfg.optim.encoder_lr),
        weight_decay=float(cfg.optim.weight_decay),
        token_dropout=float(d.get("token_dropout", 0.0)),
    )
    logger: Any = False
    lcfg = to_plain(cfg.get("logger")) or {}
    if lcfg.get("_target_"):
        logger = hydra.utils.instantiate(lcfg)

    def fit(train_loader, val_loader, **changes) -> Any:
        tcfg = {**dict(to_plain(cfg.trainer)), **changes}
        if val_loader is None:
            tcfg["limit_val_batches"] = 0
            tcfg["num_sanity_val_steps"] = 0
        trainer = L.Trainer(
            **tcfg,
            logger=logger,
            enable_progress_bar=str(cfg.get("progress_bar", "none")) != "none",
            enable_checkpointing=False,
            default_root_dir=str(out),
        )
        trainer.fit(lit, train_dataloaders=train_loader, val_dataloaders=val_loader)
        return trainer

    # A frozen encoder's features are computed once (no token dropout) and the head is fitted
    # on them: a forest by scikit-learn, another head by full-batch L-BFGS to convergence (the
    # linear-probe protocol); a pretrained encoder that is fine-tuned gets such a probe first,
    # then trains with the encoder.
    solver = "forest" if forest else "lbfgs"
    probe = state is not None
    steps = 0
    trainer = None
    probe_facts: dict = {}
    all_features = None  # every training frame's features (the forest's self-training)
    if bool(cfg.freeze) or probe:
        fbank = _FeatureBank(model, bank, idx, train_features)
        fv = None if val_dl is None else _FeatureBank(model, vbank, vidx)
        lit.head_only = True
        if forest:
            probe_facts = fit_head_forest(model, fbank.features, fbank.labels, weights)
            if pseudo is not None:
                lengths = [len(s) for s in train]
                tfacts: dict = {}
                all_features = context_features(model, bank, torch.arange(len(bank)))
                ylab = bank.labels.numpy()[idx]
                ufeats: list = []  # the unlabelled sessions' features
                for u in unlabelled:
                    ub = SessionBank([u], span)
                    ufeats.append(context_features(model, ub, torch.arange(len(ub))))
                taught = ufeats if pseudo["unlabelled"] else []  # pseudo-labelled too
                if pseudo["teacher"] == "cotrain":
                    tprobs, tfacts = sequence_teacher(
                        model, all_features, lengths, ufeats, idx, ylab, C, weights,
                        pseudo["sequence"], sequence_signature(model, mech, scale_mode),
                        out, pseudo["bins"], len(taught) > 0,
                    )  # fmt: skip
                else:  # linear
                    from deformnet.sequence import linear_teacher_probs

                    frame = torch.cat([all_features, *taught])[:, model.frame_columns()]
                    frame = frame.double().numpy()
                    tprobs = linear_teacher_probs(frame, idx, ylab, C, weights,
                                                  pseudo["bins"])  # fmt: skip
                probe_facts["pseudo_labels"], all_features = self_train_forest(
                    model, bank, lengths, idx, fbank.features, pseudo, tprobs, all_features,
                    taught,
                )  # fmt: skip
                probe_facts["pseudo_labels"] |= tfacts
                pl = probe_facts["pseudo_labels"]
                log.info("self-training: %d pseudo-labelled frames (%s)", pl["frames"],
                         dict(zip(classes, pl["per_class"])))  # fmt: skip
        else:
            probe_facts = fit_head_lbfgs(
                model,
                fbank.features,
                fbank.labels,
                weights,
                float(cfg.get("head_l2", 1.0)),
                int(cfg.get("head_max_iter", 200)),
            )
        if fv is not None:  # the probe's validation score: the state to beat
            with torch.no_grad():
                pv = model.classify(fv.features).argmax(-1).numpy()
            from deformnet.classify_lit import macro_f1

            score, per = macro_f1(fv.labels.numpy(), pv, C)
            probe_facts["val_macro_f1"] = score
            lit.best_score = score
            lit.best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
            if logger:
                logger.log_metrics(
                    {"val/macro_f1": score}
                    | ({"train/loss": probe_facts["loss"]} if "loss" in probe_facts else {})
                    | {f"val/f1/{c}": float(f) for c, f in zip(classes, per) if np.isfinite(f)},
                    step=0,
                )
        log.info("head fitted by %s (%s)", "scikit-learn" if forest else "L-BFGS", probe_facts)
        if not bool(cfg.freeze):
            lit.head_only = False
            trainer = fit(train_dl, val_dl)
    else:
        trainer = fit(train_dl, val_dl)
    steps += int(trainer.global_step) if trainer is not None else 0
    if lit.best_state is not None:
        model.load_state_dict(lit.best_state)
    model.eval()
    # what the training data look like to the trained classifier: each feature's range over
    # every training frame (labelled or not), for telling a recording unlike them (predict)
    if all_features is None:
        all_features = context_features(model, bank, torch.arange(len(bank)))
    rng = feature_range(all_features)

    smoothing = dict(to_plain(cfg.smoothing) or {})
    meta = {
        "net_config": net_cfg,
        "body": body.to_mapping(),
        "half_window": hw,
        "up": None if up is None else list(up),
        "head": head_cfg,
        "frame_features": ff,
        "context": {
            "frames": list(model.context_frames),
            "stride": model.stride,
            "halves": model.halves,
        },  # fmt: skip
        "mechanisms": mech,
        "measurements": meas,
        "heights_up": None if hup is None else list(hup),
        "classes": classes,
        "smoothing": smoothing,
        "pretrained": str(cfg.pretrained) if cfg.get("pretrained") else None,
        "freeze": bool(cfg.freeze),
        "label_fraction": frac,
        "feature_range": rng,
        "body_scale": scale_mode,
        "fps": fps,
        "pseudo_labels": pseudo,  # how the forest head was taught (None: labelled frames only)
    }
    ckpt = out / "classifier.pt"
    from deformnet.atomic import atomic_path

    with atomic_path(ckpt) as tmp:
        torch.save(export_classifier(model, meta), tmp)

    # --- reports on the test sessions (else validation, else training) -----------------------
    eval_name, eval_sessions = (
        ("test", test) if test else (("val", val) if val else ("train", train))
    )  # noqa: E501
    bout_fps = fps or 30.0  # bout durations (frame rate unknown: 30 fps assumed)
    yt, yr, ys, unfamiliar = [], [], [], []
    first = None
    for s in eval_sessions:
        pr = predict_session(model, s, smoothing, rng)
        unfamiliar.append(pr["unfamiliar"] > unf["frame_share"])
        yt.append(s.labels)
        yr.append(pr["raw"])
        ys.append(pr["labels"])
        if first is None:
            first = {"true": s.labels, "predicted": pr["raw"], "smoothed": pr["labels"]}
    yt, yr, ys = np.concatenate(yt), np.concatenate(yr), np.concatenate(ys)
    raw = evaluate(yt, yr, classes)
    smoothed = evaluate(yt, ys, classes)
    report = {
        "split": eval_name,
        "sessions": [s.name for s in eval_sessions],
        "raw": raw,
        "smoothed": smoothed,
        "smoothing": smoothing,
        "bouts": {
            "true": bout_stats(yt, classes, bout_fps),
            "predicted": bout_stats(yr, classes, bout_fps),
            "smoothed": bout_stats(ys, classes, bout_fps),
        },
        "fps": fps,
        "labelled_training_frames": int(idx.size),
        "body_scales": None
        if scale_mode == "none"
        else {s.name: round(float(s.scale), 4) for s in (*train, *val, *test)},
        "unfamiliar_frames": float(np.concatenate(unfamiliar).mean()),
        "training_steps": steps,
        "head_solver": solver,
        "mechanisms": None if mech is None else {k: mech[k] for k in ("names", "parts", "source")},
        "probe": probe_facts or None,
        "best_val_macro_f1": lit.best_score if lit.best_state is not None else None,
        "checkpoint": str(ckpt),
    }
    cm_fig = confusion_figure(
        raw["confusion"], classes, f"{eval_name}: macro-F1 {raw['macro_f1']:.3f}"
    )  # noqa: E501
    eth_fig = ethogram_figure(first, classes, bout_fps)
    if logger and hasattr(logger, "experiment") and hasattr(logger.experiment, "add_figure"):
        logger.experiment.add_figure(f"{eval_name}/confusion", cm_fig, global_step=steps)
        logger.experiment.add_figure(f"{eval_name}/ethogram", eth_fig, global_step=steps)
        logger.experiment.flush()
    save_figure(cm_fig, out / "confusion.png")
    save_figure(eth_fig, out / "ethogram.png")
    write_text(out / "report.json", json.dumps(finite_or_none(report), indent=2) + "\n")
    log.info(
        "%s macro-F1 %.3f (smoothed %.3f); classifier %s",
        eval_name,
        raw["macro_f1"],
        smoothed["macro_f1"],
        ckpt,
    )
    return {
        "output_dir": str(out),
        "checkpoint": str(ckpt),
        "report": report,
        "metrics": {}
        if trainer is None
        else {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1},
    }


def _predict_mechanisms(cfg: DictConfig, model, meta: dict) -> None:
    """mode=predict: the mechanisms' positions in this recording's frame. The classifier's own
    (its training rig's) unless ``mechanisms.positions`` / ``mechanisms.calibration`` give
    this session's (the same mechanisms by name; a moved lock box); its parts and scale stay
    the classifier's."""
    trained = meta.get("mechanisms")
    here = mechanism_setup(cfg, meta["body"])
    if here is None:
        if trained:
            log.info("lock-box context: the classifier's mechanism positions (%s)",
                     trained.get("source"))  # fmt: skip
        return
    if not trained:
        raise ValueError(
            f"{cfg.checkpoint} was trained without lock-box context: unset mechanisms.positions "
            "/ mechanisms.calibration"
        )
    pos = dict(zip(here["names"], here["positions"]))
    missing = [n for n in trained["names"] if n not in pos]
    if missing:
        raise ValueError(f"{here['source']}: no position for mechanism(s) {missing} "
                         f"(the classifier's: {trained['names']})")  # fmt: skip
    xyz = [pos[n] for n in trained["names"]]  # in the classifier's order
    model.encoder.mechanisms.positions.copy_(torch.tensor(xyz, dtype=torch.float32))
    meta["mechanisms"] = {**trained, "positions": xyz, "source": here["source"]}
    log.info("lock-box context: mechanism positions from %s", here["source"])


def _unfamiliar_settings(cfg: DictConfig) -> dict:
    """``unfamiliar.frame_share`` and ``unfamiliar.warn_share``, checked (ValueError)."""
    u = cfg.get("unfamiliar") or {}
    out = {k: float(u.get(k, d)) for k, d in (("frame_share", 0.05), ("warn_share", 0.1))}
    for k, v in out.items():
        if not 0.0 <= v < 1.0:
            raise ValueError(f"unfamiliar.{k} must be in [0, 1), got {v}")
    return out


def read_session(
    path: str, model, meta: Mapping, interpolate: bool = False, aliases: Mapping | None = None
) -> Session:
    """A track for a trained classifier (`load_classifier`'s model and meta) to label: read in
    its body model's parts (its file's names through the model's aliases and `aliases`),
    checked against the world's up its encoder assumes (its heading frame's, else the
    heights'; or none), unlabelled, with its body scale if the classifier divides it out
    (``body_scale``, as it was trained)."""
    tr = read_tracks(path, meta["body"].with_aliases(aliases), interpolate=interpolate)
    check_track_up(tr["rigid"], meta["body"].points, model.encoder.heights_up, path)
    T = len(tr["fnum"])
    parts = (tr["rigid"], tr["deformed"], tr["observed"], tr["fnum"])
    s = Session(path, *parts, np.full(T, -1), pose=tr["pose"])
    set_body_scales([s], meta.get("body_scale") or "none", meta["body"])
    return s


def _predict(cfg: DictConfig, out: Path) -> dict:
    from deformnet.atomic import atomic_path

    if isinstance(to_plain(cfg.get("tracks")), list) or cfg.get("labels"):
        raise ValueError("mode=predict labels one track: tracks=points3d.csv (no labels=)")
    if not cfg.get("checkpoint") or not cfg.get("tracks"):
        raise ValueError("mode=predict needs checkpoint=CLASSIFIER.pt and tracks=points3d.csv")
    model, meta = load_classifier(str(cfg.checkpoint))
    classes = list(meta["classes"])
    unf = _unfamiliar_settings(cfg)
    _predict_mechanisms(cfg, model, meta)
    rates = frame_rates(cfg.get("fps"), meta, str(cfg.tracks))  # before the track is read
    antialias = bool(cfg.get("antialias", True))
    s = read_session(
        str(cfg.tracks), model, meta, bool(cfg.data.get("interpolate")),
        to_plain(cfg.get("aliases")),
    )  # fmt: skip
    T = len(s.fnum)
    smoothing = dict(to_plain(cfg.smoothing) or {}) or dict(meta.get("smoothing") or {})
    rng = meta.get("feature_range")
    pr = predict_session(model, s, smoothing, rng, rates, antialias)
    fnum = s.fnum
    names = np.asarray(classes, dtype=object)
    df = pd.DataFrame(
        {"fnum": fnum, "label": names[pr["labels"]], "label_raw": names[pr["raw"]]}
        | {f"p_{c}": pr["probs"][:, i] for i, c in enumerate(classes)}
    )
    warning, share = None, None
    if rng is None:
        log.info("%s stores no training feature range (an older classifier): the recording is "
                 "not compared with the training data", cfg.checkpoint)  # fmt: skip
    else:
        df["unfamiliar"] = pr["unfamiliar"]
        share = float(np.mean(pr["unfamiliar"] > unf["frame_share"]))
        if share > unf["warn_share"]:
            warning = (
                f"{cfg.tracks}: {100 * share:.0f}% of the frames are unlike the classifier's "
                f"training data (more than {100 * unf['frame_share']:g}% of their features "
                "outside the training range; column 'unfamiliar'): its labels there are not to "
                "be trusted (another animal, rig or tracker?). Label some of this recording's "
                "frames and train on them too; a forest head (head=forest freeze=true "
                "measurements=true) with body_scale=session transfers best"
            )
            log.warning("%s", warning)
    pred_path, bouts_path = out / "predictions.csv", out / "bouts.csv"
    with atomic_path(pred_path) as tmp:
        df.to_csv(tmp, index=False)
    rows = [
        {
            "start": int(fnum[a]),
            "stop": int(fnum[b]),
            "label": classes[c],
            "mean_probability": float(pr["probs"][a : b + 1, c].mean()),
        }
        for a, b, c in bouts(pr["labels"])
    ]
    with atomic_path(bouts_path) as tmp:
        pd.DataFrame(rows, columns=["start", "stop", "label", "mean_probability"]).to_csv(
            tmp, index=False
        )
    log.info("%d frames, %d bouts -> %s, %s", T, len(rows), pred_path, bouts_path)
    summary = {
        "output_dir": str(out),
        "predictions": str(pred_path),
        "bouts": str(bouts_path),
        "frames": T,
        "num_bouts": len(rows),
        "unfamiliar_frames": share,
        "body_scale": s.scale,
        "pose": s.pose,
        "fps": check_fps(cfg.get("fps"), "fps"),
        "classifier_fps": meta.get("fps"),
        "resampled": rates is not None,
        "antialiased": antialias and rates is not None and rates[1] < rates[0],
        "warning": warning,
    }
    write_text(out / "summary.json", json.dumps(finite_or_none(summary), indent=2) + "\n")
    return summary


def run(cfg: DictConfig) -> dict:
    """mode=train: fine-tune and report (returns output_dir, checkpoint, report, metrics);
    mode=predict: label a track (returns the written files)."""
    import lightning as L

    from deformnet.atomic import write_text
    from deformnet.threads import set_torch_threads

    set_torch_threads(cfg.get("threads"))
    mode = str(cfg.get("mode", "train"))
    if mode not in ("train", "predict"):
        raise ValueError(f"mode must be 'train' or 'predict', got '{mode}'")
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    out = output_dir(cfg)
    write_text(out / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
    return _train(cfg, out) if mode == "train" else _predict(cfg, out)


def _quiet_run(cfg: DictConfig) -> dict:
    with quiet_lightning():  # no Lightning tips or deprecations on the console
        return run(cfg)


@hydra.main(config_path=str(CONF_DIR), config_name="classify", version_base=None)
def main(cfg: DictConfig) -> None:
    # one error handler (deformnet.apprun): bad input or config (one line naming the file or
    # row), an unusable or busy output.dir: exit 2; Ctrl-C: exit 130
    run_app(_quiet_run, cfg)


if __name__ == "__main__":
    main()
