"""Behavior classification reports: per-class metrics (scikit-learn), bout statistics, the
confusion-matrix and ethogram figures (matplotlib, written atomically)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from deformnet.behavior_labels import bouts

__all__ = [
    "bout_stats", "evaluate", "paired_difference", "confusion_figure", "ethogram_figure",
    "save_figure",
]  # fmt: skip


# --------------------------------------------------------------------------------------------
# reports
# --------------------------------------------------------------------------------------------
def bout_stats(labels: np.ndarray, classes: Sequence[str], fps: float) -> dict:
    """Per class: bout count and mean duration (frames and s)."""
    runs = bouts(labels)
    out = {}
    for c, name in enumerate(classes):
        d = np.array([b - a + 1 for a, b, lab in runs if lab == c])
        mean = float(d.mean()) if d.size else 0.0
        out[name] = {"bouts": int(d.size), "mean_frames": mean, "mean_s": mean / fps}
    return out


def evaluate(y_true: np.ndarray, y_pred: np.ndarray, classes: Sequence[str]) -> dict:
    """Per-class precision / recall / F1 / support, macro-F1 (over the classes present in the
    truth or the predictions), accuracy, and the confusion matrix (rows: truth) on the labelled
    frames (y_true >= 0). scikit-learn metrics."""
    from sklearn.metrics import confusion_matrix, precision_recall_fscore_support

    from deformnet.classify_lit import macro_f1

    m = np.asarray(y_true) >= 0
    yt, yp = np.asarray(y_true)[m], np.asarray(y_pred)[m]
    C = len(classes)
    p, r, f, s = precision_recall_fscore_support(
        yt, yp, labels=np.arange(C), average=None, zero_division=0
    )
    score, _ = macro_f1(yt, yp, C)
    return {
        "macro_f1": score,
        "accuracy": float(np.mean(yt == yp)) if yt.size else float("nan"),
        "frames": int(yt.size),
        "per_class": {
            name: {
                "precision": float(p[c]),
                "recall": float(r[c]),
                "f1": float(f[c]),
                "support": int(s[c]),
            }
            for c, name in enumerate(classes)
        },
        "confusion": confusion_matrix(yt, yp, labels=np.arange(C)).tolist(),
    }


def paired_difference(a: Sequence[float], b: Sequence[float], level: float = 0.95) -> dict:
    """Is method a better than method b? Their scores a, b (N,) paired by unit (a label draw, a
    test session: the same unit for both), N >= 2. Returns the mean difference a - b, its
    two-sided Student-t confidence interval at ``level`` ("ci", [low, high]), the units where a
    is ahead / behind ("wins", "losses"; ties are neither), and the two-sided Wilcoxon
    signed-rank p-value (scipy; 1.0 when every difference is 0). "better" is true when the
    interval lies above 0 and p < 1 - level: a difference the units' spread cannot explain."""
    from scipy import stats

    x, y = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if x.ndim != 1 or x.shape != y.shape or x.size < 2:
        raise ValueError(f"a and b must be (N >= 2,) paired scores, got {x.shape} and {y.shape}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("paired_difference: the scores must be finite")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    d = x - y
    mean, se = float(d.mean()), float(d.std(ddof=1) / np.sqrt(d.size))
    half = float(stats.t.ppf(0.5 + level / 2, d.size - 1)) * se
    p = 1.0 if not np.any(d != 0) else float(stats.wilcoxon(d).pvalue)
    low, high = mean - half, mean + half
    return {
        "mean": mean,
        "ci": [low, high],
        "units": int(d.size),
        "wins": int(np.sum(d > 0)),
        "losses": int(np.sum(d < 0)),
        "wilcoxon_p": p,
        "better": bool(low > 0 and p < 1.0 - level),
    }


def confusion_figure(confusion: Sequence[Sequence[int]], classes: Sequence[str], title: str = ""):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cm = np.asarray(confusion, dtype=np.float64)
    norm = cm / np.maximum(cm.sum(1, keepdims=True), 1)
    fig, ax = plt.subplots(figsize=(6, 5))
    im = ax.imshow(norm, cmap="Blues", vmin=0, vmax=1)
    C = len(classes)
    ax.set_xticks(range(C), classes, rotation=45, ha="right")
    ax.set_yticks(range(C), classes)
    for i in range(C):
        for j in range(C):
            if cm[i, j]:
                ax.text(j, i, int(cm[i, j]), ha="center", va="center", fontsize=7,
                        color="w" if norm[i, j] > 0.5 else "k")  # fmt: skip
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(title or "confusion (row-normalised colour, counts)")
    fig.colorbar(im, ax=ax)
    fig.tight_layout()
    return fig


def ethogram_figure(tracks: dict[str, np.ndarray], classes: Sequence[str], fps: float):
    """One row per named label track (e.g. true, predicted), time in s."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    names = list(tracks)
    T = max(len(v) for v in tracks.values())
    img = np.full((len(names), T), np.nan)
    for i, n in enumerate(names):
        v = np.asarray(tracks[n], dtype=np.float64)
        img[i, : len(v)] = np.where(v >= 0, v, np.nan)
    C = len(classes)
    cmap = ListedColormap(plt.get_cmap("tab10")(np.arange(C) % 10))
    fig, ax = plt.subplots(figsize=(12, 0.6 * len(names) + 1.6))
    ax.imshow(img, aspect="auto", interpolation="nearest", cmap=cmap, vmin=-0.5, vmax=C - 0.5,
              extent=(0, T / fps, len(names) - 0.5, -0.5))  # fmt: skip
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("time (s)")
    handles = [plt.Rectangle((0, 0), 1, 1, color=cmap(c)) for c in range(C)]
    ax.legend(handles, classes, ncol=min(C, 8), loc="upper center", bbox_to_anchor=(0.5, -0.35),
              fontsize=8, frameon=False)  # fmt: skip
    fig.tight_layout()
    return fig


def save_figure(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    from deformnet.atomic import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
