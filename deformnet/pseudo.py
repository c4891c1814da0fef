"""Class-balanced pseudo-labels for few-label behavior classification (self-training).

With about 1% of the frames labelled, a classifier fitted on them (the teacher) labels the
other training frames; the frames it is most sure of join the labelled ones and a classifier
(the student) is fitted on both. A few-label teacher's confidence is not comparable across
classes (it is surest of the easy, frequent ones), so a global confidence threshold keeps the
easy classes only: here every class keeps its own most confident share of the frames the
teacher gives it (class-balanced self-training, Zou et al., ECCV 2018). Behaviors come in bouts,
so the teacher's probabilities are first averaged over a few neighbouring frames of the same
session. `deformnet-classify pseudo_labels.teacher=self` (head=forest): the forest is its own
teacher. Shapes: N frames (the sessions' frames concatenated in order), C classes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def class_balanced_pseudo_labels(
    probs: np.ndarray,
    lengths: Sequence[int],
    labelled: np.ndarray,
    keep: float = 0.3,
    smooth: int = 9,
) -> tuple[np.ndarray, np.ndarray]:
    """Pseudo-labels of the unlabelled frames.

    probs (N, C): the teacher's class probabilities of every frame of the sessions, whose
    lengths (frames) sum to N, in order; labelled (N,) bool: the frames that have a label (never
    pseudo-labelled). The probabilities are averaged over centred spans of ``smooth`` frames
    within each session (1: not at all); each frame gets its most probable class, and of the
    frames given a class the most confident ``keep`` share (0 < keep <= 1) is kept, ties
    included, the labelled frames among them dropped. Returns the kept rows (M,) (ascending)
    and their labels (M,)."""
    from scipy.ndimage import uniform_filter1d

    P = np.asarray(probs, dtype=np.float64)
    lab = np.asarray(labelled, dtype=bool)
    n = [int(v) for v in lengths]
    if P.ndim != 2 or P.shape[1] < 1:
        raise ValueError(f"probs must be (N, C), got {P.shape}")
    if lab.shape != (P.shape[0],):
        raise ValueError(f"labelled must be ({P.shape[0]},), got {lab.shape}")
    if any(v < 0 for v in n) or sum(n) != P.shape[0]:
        raise ValueError(f"session lengths {n} must be >= 0 and sum to {P.shape[0]} frames")
    if not 0.0 < float(keep) <= 1.0:
        raise ValueError(f"pseudo_labels.keep must be in (0, 1], got {keep}")
    if int(smooth) != smooth or int(smooth) < 1:
        raise ValueError(f"pseudo_labels.smooth must be an integer >= 1 (frames), got {smooth}")
    if int(smooth) > 1:
        bounds = np.cumsum([0, *n])
        P = np.concatenate(
            [
                uniform_filter1d(P[a:b], int(smooth), axis=0, mode="nearest")
                for a, b in zip(bounds[:-1], bounds[1:])
                if b > a
            ]
        ) if P.shape[0] else P  # fmt: skip
    pred, conf = P.argmax(1), P.max(1)
    kept = np.zeros(P.shape[0], dtype=bool)
    for c in range(P.shape[1]):  # the share among every frame given c, then the unlabelled
        rows = np.flatnonzero(pred == c)
        if rows.size:
            kept[rows[conf[rows] >= np.quantile(conf[rows], 1.0 - float(keep))]] = True
    rows = np.flatnonzero(kept & ~lab)
    return rows, pred[rows]


def pseudo_sample_weights(labels: np.ndarray, labelled: int, num_classes: int,
                          labelled_weight: float) -> np.ndarray:  # fmt: skip
    """Sample weights (M,) of a student's training rows: ``labels`` (M,) of the labelled rows
    (the first ``labelled``) and the pseudo-labelled ones after them; each class weighted
    total / (C count) over both (balanced), a labelled row ``labelled_weight`` times more."""
    y = np.asarray(labels, dtype=np.int64)
    if not 0 <= int(labelled) <= y.size:
        raise ValueError(f"labelled must be in [0, {y.size}], got {labelled}")
    if float(labelled_weight) <= 0:
        raise ValueError(f"pseudo_labels.labelled_weight must be > 0, got {labelled_weight}")
    counts = np.bincount(y, minlength=num_classes)
    w = (counts.sum() / np.maximum(num_classes * counts, 1))[y]
    w[: int(labelled)] *= float(labelled_weight)
    return w


def co_training_pseudo_labels(
    probs: Sequence[np.ndarray],
    lengths: Sequence[int],
    labelled: np.ndarray,
    keep: Sequence[float],
    smooth: int = 9,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Pseudo-labels from teachers that read different views of the frames (co-training, Blum
    and Mitchell 1998): each view's class-balanced pseudo-labels
    (`class_balanced_pseudo_labels`, its own ``keep`` share), pooled. A frame one view is sure of
    and the others are not is labelled by that view, so a view adds the frames the others find
    hard; a frame two views are sure of with different classes is dropped. probs: V arrays
    (N, C), one per view; lengths, labelled (N,) and smooth as there; keep: V shares. Returns
    the kept rows (M,) (ascending), their labels (M,) and the number of frames dropped for a
    conflict."""
    views = [np.asarray(p, dtype=np.float64) for p in probs]
    keeps = [float(k) for k in keep]
    if not views or len(keeps) != len(views):
        raise ValueError(f"co-training needs one keep share per view: {len(views)} views, "
                         f"{len(keeps)} shares")  # fmt: skip
    if len({p.shape for p in views}) != 1:
        raise ValueError(f"the views' probabilities must have one shape, got "
                         f"{[p.shape for p in views]}")  # fmt: skip
    label = np.full(views[0].shape[0], -1, dtype=np.int64)
    conflict = np.zeros(views[0].shape[0], dtype=bool)
    for P, k in zip(views, keeps):
        rows, y = class_balanced_pseudo_labels(P, lengths, labelled, k, smooth)
        conflict[rows[(label[rows] >= 0) & (label[rows] != y)]] = True
        label[rows] = np.where(label[rows] >= 0, label[rows], y)
    label[conflict] = -1
    rows = np.flatnonzero(label >= 0)
    return rows, label[rows], int(conflict.sum())
