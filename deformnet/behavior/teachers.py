"""The teachers of few-label behavior heads, and class-balanced pseudo-labels (self-training).

With about 1% of the frames labelled, a classifier fitted on them (the teacher) labels the
other training frames; the frames it is most sure of join the labelled ones and the forest head
(the student) is fitted on both (`deformnet.behavior.fit.self_train_forest`). A few-label
teacher's confidence is not comparable across classes (it is surest of the easy, frequent
ones), so every class keeps its own most confident share of the frames the teacher gives it
(class-balanced self-training, Zou et al., ECCV 2018). Behaviors come in bouts, so the teacher's
probabilities are first averaged over a few neighbouring frames of the same session.

Teachers (`pseudo_labels.teacher`, `deformnet.behavior.settings.PseudoLabelSettings`):
``linear``, a logistic regression on the binned frame features (`linear_teacher_probs`);
``cotrain``, that and one on a pretrained sequence encoder's embedding
(`embedding_teacher_probs`, `deformnet.behavior.sequence`), their confident frames pooled
(`co_training_pseudo_labels`).
Shapes: N frames (the sessions' frames concatenated in order), C classes.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np
from sklearn.linear_model import LogisticRegression
from sklearn.preprocessing import KBinsDiscretizer

__all__ = [
    "class_balanced_pseudo_labels", "pseudo_sample_weights", "co_training_pseudo_labels",
    "binned", "linear_teacher_probs", "embedding_teacher_probs",
]  # fmt: skip


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
                          labelled_weight: float, balanced: bool = True) -> np.ndarray:  # fmt: skip
    """Sample weights (M,) of a student's training rows: ``labels`` (M,) of the labelled rows
    (the first ``labelled``) and the pseudo-labelled ones after them; each class weighted
    total / (C count) over both if ``balanced`` (`loss.class_weights=balanced`), else 1 (the
    teacher's class frequencies kept), a labelled row ``labelled_weight`` times more."""
    y = np.asarray(labels, dtype=np.int64)
    if not 0 <= int(labelled) <= y.size:
        raise ValueError(f"labelled must be in [0, {y.size}], got {labelled}")
    if float(labelled_weight) <= 0:
        raise ValueError(f"pseudo_labels.labelled_weight must be > 0, got {labelled_weight}")
    counts = np.bincount(y, minlength=num_classes)
    w = (counts.sum() / np.maximum(num_classes * counts, 1))[y] if balanced else np.ones(y.size)
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
) -> np.ndarray:
    """A teacher's class probabilities (N, C) of every frame: a logistic regression (C=1,
    scikit-learn) on the frame features ``frame`` (N, F), standardised over all N frames, with
    their one-hot quantile bins (`binned`), fitted on the labelled rows ``idx`` (L,) with
    ``labels`` (L,), class-weighted by ``class_weights`` (C,) (None: unweighted). A class no
    labelled frame has gets probability 0 (`pseudo_labels.teacher=linear`)."""
    frame = np.asarray(frame, np.float64)
    if frame.ndim != 2:
        raise ValueError(f"frame must be (N, F), got {frame.shape}")
    x = binned(standardised(frame), bins)
    return _logistic_probs(x, idx, labels, num_classes, class_weights)


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
