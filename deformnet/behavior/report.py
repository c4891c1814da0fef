"""Behavior classification reports: per-class metrics (scikit-learn), bout statistics, the
confusion-matrix and ethogram figures (matplotlib, written atomically), and a trained
classifier's report on its evaluation sessions (`write_report`: report.json and the figures)."""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib
import numpy as np
from sklearn.metrics import confusion_matrix, f1_score, precision_recall_fscore_support

from deformnet.atomic import atomic_path, finite_or_none, write_text
from deformnet.behavior.labels import bouts
from deformnet.behavior.tracks import Session

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 (after the backend is chosen)
from matplotlib.colors import ListedColormap  # noqa: E402

log = logging.getLogger(__name__)

__all__ = ["macro_f1", "bout_stats", "evaluate", "confusion_figure", "ethogram_figure",
           "save_figure", "write_report"]  # fmt: skip


def macro_f1(y_true: np.ndarray, y_pred: np.ndarray, num_classes: int) -> tuple[float, np.ndarray]:
    """Macro-F1 over the classes present in y_true or y_pred, and per-class F1 (num_classes,)
    (NaN for classes present in neither)."""
    present = np.union1d(np.unique(y_true), np.unique(y_pred)).astype(int)
    per = np.full(num_classes, np.nan)
    if len(y_true) == 0:
        return float("nan"), per
    f = f1_score(y_true, y_pred, labels=present, average=None, zero_division=0)
    per[present] = f
    return float(np.mean(f)), per


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


def confusion_figure(confusion: Sequence[Sequence[int]], classes: Sequence[str], title: str = ""):
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
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def write_report(
    out: Path,
    split: str,
    sessions: Sequence[Session],
    predictions: Sequence[Mapping],
    classes: Sequence[str],
    fps: float | None,
    facts: Mapping,
    logger=None,
    step: int = 0,
) -> dict:
    """A trained classifier's report on its evaluation sessions of ``split`` (their labels (T,)
    against `deformnet.behavior.model.predict_session`'s ``predictions``, raw and smoothed):
    report.json (per-class metrics, macro-F1, bout counts and mean durations at ``fps``, 30
    when unknown, and ``facts``), confusion.png and ethogram.png (the first session) in
    ``out``, also to a TensorBoard ``logger``; returns the report."""
    bout_fps = fps or 30.0
    yt = np.concatenate([s.labels for s in sessions])
    yr = np.concatenate([p["raw"] for p in predictions])
    ys = np.concatenate([p["labels"] for p in predictions])
    raw, smoothed = evaluate(yt, yr, classes), evaluate(yt, ys, classes)
    report = {
        "split": split,
        "sessions": [s.name for s in sessions],
        "raw": raw,
        "smoothed": smoothed,
        "bouts": {k: bout_stats(y, classes, bout_fps)
                  for k, y in (("true", yt), ("predicted", yr), ("smoothed", ys))},
        "fps": fps,
        **facts,
    }  # fmt: skip
    first = {"true": sessions[0].labels, "predicted": predictions[0]["raw"],
             "smoothed": predictions[0]["labels"]}  # fmt: skip
    figures = {
        "confusion": confusion_figure(raw["confusion"], classes,
                                      f"{split}: macro-F1 {raw['macro_f1']:.3f}"),
        "ethogram": ethogram_figure(first, classes, bout_fps),
    }  # fmt: skip
    if logger and hasattr(logger, "experiment") and hasattr(logger.experiment, "add_figure"):
        for name, fig in figures.items():
            logger.experiment.add_figure(f"{split}/{name}", fig, global_step=step)
        logger.experiment.flush()
    for name, fig in figures.items():
        save_figure(fig, out / f"{name}.png")
    write_text(out / "report.json", json.dumps(finite_or_none(report), indent=2) + "\n")
    log.info("%s macro-F1 %.3f (smoothed %.3f)", split, raw["macro_f1"], smoothed["macro_f1"])
    return report
