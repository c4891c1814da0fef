"""Fitting a behavior classifier's head on fixed features: by full-batch L-BFGS
(`fit_head_lbfgs`, the linear-probe protocol), a forest by scikit-learn (`fit_head_forest`),
and the forest's self-training on a teacher's pseudo-labels (`self_train_forest`).
Shapes: N frames, D features, C classes."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch
from sklearn.ensemble import RandomForestClassifier
from torch import Tensor, nn

from deformnet.behavior.features import SessionBank, context_features
from deformnet.behavior.heads import EnsembleHead, ForestHead
from deformnet.behavior.sequence import sequence_signature, sequence_teacher
from deformnet.behavior.settings import PseudoLabelSettings
from deformnet.behavior.teachers import (
    co_training_pseudo_labels,
    linear_teacher_probs,
    pseudo_sample_weights,
)

__all__ = ["fit_head_lbfgs", "fit_head_forest", "self_train_forest", "teach_forest"]


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
    and pseudo-labelled frames, `pseudo_sample_weights`). The forest reads only
    the frame-feature columns (`BehaviorClassifier.frame_columns`). Returns {"trees", "nodes",
    "depth", "columns"}."""
    head = model.head
    if not isinstance(head, ForestHead):
        raise TypeError(f"fit_head_forest needs a ForestHead, got {type(head).__name__}")
    labels = torch.as_tensor(labels, dtype=torch.long)
    if features.dim() != 2 or features.shape[0] != labels.shape[0] or labels.numel() == 0:
        raise ValueError(f"features (N, D) and labels (N,), got {features.shape}, {labels.shape}")
    cols = model.frame_columns()
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


def self_train_forest(
    model, bank: SessionBank, lengths: Sequence[int], idx: np.ndarray, features: Tensor,
    settings: PseudoLabelSettings, probs: np.ndarray | Sequence[np.ndarray],
    all_features: Tensor | None = None,
    unlabelled: Sequence[Tensor] = (), balanced: bool = True,
) -> tuple[dict, Tensor]:  # fmt: skip
    """Self-training of a fitted forest head: a teacher's class probabilities ``probs``
    (len(bank) + M, C) of every training frame of ``bank`` (sessions of ``lengths`` frames) and
    of the M frames of ``unlabelled`` (the features (T_u, D) of sessions nobody labelled,
    `data.unlabelled_tracks`, after the training frames); the class-balanced pseudo-labels of
    the frames without a label (`class_balanced_pseudo_labels`) join the labelled frames ``idx``
    (their features ``features`` (N, D)) and the forest is fitted again on both, weighted per
    frame (`pseudo_sample_weights`, class-``balanced`` or not). ``all_features``: every training
    frame's features (len(bank), D), computed when not given. ``probs`` a list of two
    (`pseudo_labels.teacher=cotrain`: the frame features' teacher's, the embedding's):
    co-training (`co_training_pseudo_labels`, shares settings.keep and
    settings.embedding_keep). Returns facts (the pseudo-labelled frames in all, per class and
    from the unlabelled sessions, the refitted forest's; co-training: the frames dropped for a
    conflict) and every training frame's features."""
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
    keeps = [settings.keep, settings.embedding_keep][: len(views)]
    rows, pseudo, conflicts = co_training_pseudo_labels(  # one view: class-balanced alone
        views, [*lengths, *(len(u) for u in unlabelled)], labelled, keeps, settings.smooth
    )  # fmt: skip
    facts = {"teacher": settings.teacher, "frames": int(rows.size),
             "per_class": np.bincount(pseudo, minlength=C).tolist(),
             "unlabelled_frames": int((rows >= N).sum())}  # fmt: skip
    if len(views) > 1:
        facts["conflicts"] = conflicts
    if rows.size == 0:  # every frame is labelled: nothing to teach
        return facts, all_features
    y = np.concatenate([labels[idx], pseudo])
    sw = pseudo_sample_weights(y, len(idx), C, settings.labelled_weight, balanced)
    x = torch.cat([features, pool[torch.as_tensor(rows)]])
    facts["forest"] = fit_head_forest(model, x, torch.as_tensor(y), sample_weight=sw)
    return facts, all_features


def teach_forest(
    model, bank: SessionBank, lengths: Sequence[int], idx: np.ndarray, features: Tensor,
    unlabelled: Sequence, pseudo: PseudoLabelSettings, weights, mech: Mapping | None,
    scale_mode: str, out: Path,
) -> tuple[dict, Tensor]:  # fmt: skip
    """`pseudo_labels.teacher` (linear | cotrain, `PseudoLabelSettings`) teaches the fitted forest
    head: the teacher's probabilities of every training frame of ``bank`` (sessions of
    ``lengths`` frames; labelled frames ``idx`` with features ``features``) and of the
    ``unlabelled`` sessions' frames (`Session`s) where ``pseudo.unlabelled``, then
    `self_train_forest`. Returns (facts, every training frame's features)."""
    C = model.head.num_classes
    all_features = context_features(model, bank, torch.arange(len(bank)))
    ylab = bank.labels.numpy()[idx]
    ufeats = []  # the unlabelled sessions' features
    for u in unlabelled:
        ub = SessionBank([u], bank.n)
        ufeats.append(context_features(model, ub, torch.arange(len(ub))))
    taught = ufeats if pseudo.unlabelled else []  # pseudo-labelled too
    tfacts: dict = {}
    if pseudo.teacher == "cotrain":
        tprobs, tfacts = sequence_teacher(
            model, all_features, lengths, ufeats, idx, ylab, C, weights, pseudo,
            sequence_signature(model, mech, scale_mode), out,
        )  # fmt: skip
    else:  # linear
        frame = torch.cat([all_features, *taught])[:, model.frame_columns()].double().numpy()
        tprobs = linear_teacher_probs(frame, idx, ylab, C, weights, pseudo.bins)
    facts, all_features = self_train_forest(  # weights None: loss.class_weights=none
        model, bank, lengths, idx, features, pseudo, tprobs, all_features, taught,
        balanced=pseudo.balanced and weights is not None,
    )  # fmt: skip
    return facts | tfacts, all_features
