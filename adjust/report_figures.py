"""Figures of the demo's report beyond the tracks (`adjust.apps.report`): training curves
(`curves_figure`), the lock-box events (`events_figure`) and the key figure (`key_figure`: one
part through an occlusion, the methods against the truth). matplotlib, Agg backend (through
`adjust.plot`)."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence

import matplotlib.pyplot as plt
import matplotlib.ticker
import numpy as np

from adjust.plot import _time_axis, runs_of

log = logging.getLogger(__name__)

__all__ = ["curves_figure", "events_figure", "key_figure"]


# ---------------------------------------------------------------------------------------------
# training curves, events
# ---------------------------------------------------------------------------------------------
def curves_figure(curves: Mapping[str, Mapping[str, tuple[Sequence[float], Sequence[float]]]]):
    """Validation curves of several runs: curves[run][tag] = (steps, values). Panels: the
    nets' val/rmse_mm (with the rigid and linear baselines they log, dashed) against step and
    against wall time when a ``_wall`` entry holds (seconds since start, values)."""
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.6))
    colors = plt.get_cmap("tab10")
    for i, (name, tags) in enumerate(curves.items()):
        col = colors(i % 10)
        if "val/rmse_mm" in tags:
            s, v = tags["val/rmse_mm"]
            axes[0].plot(s, v, "-o", ms=3, color=col, label=f"{name} val/rmse_mm")
        if "_wall" in tags:
            s, v = tags["_wall"]
            axes[1].plot(np.asarray(s) / 60.0, v, "-o", ms=3, color=col, label=name)
    first = next(iter(curves.values()), {})
    for tag, style in (("val/rmse_mm_rigid", ":"), ("val/rmse_mm_linear", "--")):
        if tag in first:
            s, v = first[tag]
            if len(v):
                for ax in axes:
                    ax.axhline(
                        float(v[-1]),
                        color="0.4",
                        ls=style,
                        lw=1,
                        label=tag.split("_")[-1] + " baseline",
                    )
    axes[0].set_xlabel("training step")
    axes[1].set_xlabel("wall time (min)")
    for ax in axes:
        ax.set_ylabel("validation RMSE of hidden parts (mm)")
        ax.legend(fontsize=8)
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.grid(alpha=0.3, which="both")
    fig.suptitle("deformation nets: validation curves (from the TensorBoard event files)")
    fig.tight_layout()
    return fig


def events_figure(
    events: Mapping[str, Sequence[Mapping]], mechanisms: Sequence[str], T: int, fps: float | None
):
    """Event timelines: one row per (source, mechanism); events: source (e.g. tracked, truth)
    -> list of {start, stop, mechanism, inferred} (frame indices)."""
    rows = [(src, m) for m in mechanisms for src in events]
    fig, ax = plt.subplots(figsize=(12, 0.35 * len(rows) + 1.5))
    scale = float(fps) if fps and np.isfinite(fps) and fps > 0 else 1.0
    colors = plt.get_cmap("tab10")
    srcs = list(events)
    for r, (src, m) in enumerate(rows):
        for e in events[src]:
            if e["mechanism"] != m:
                continue
            a, b = e["start"] / scale, (e["stop"] + 1) / scale
            col = colors(srcs.index(src) % 10)
            ax.barh(r, b - a, left=a, color=col, alpha=0.45 if e.get("inferred") else 0.9)
    ax.set_yticks(range(len(rows)), [f"{m} ({src})" for src, m in rows], fontsize=8)
    ax.set_xlim(0, T / scale)
    ax.invert_yaxis()
    ax.set_xlabel("time (s)" if scale != 1.0 else "frame")
    ax.set_title("lock-box contacts per mechanism (pale: inferred, the part mostly unseen)")
    fig.tight_layout()
    return fig


def key_figure(
    truth: np.ndarray,
    tracks: Mapping[str, np.ndarray],
    part: str,
    occluded: np.ndarray,
    fps: float | None = None,
    window: tuple[int, int] | None = None,
):
    """One part's x, y, z over time: the truth, the DLT triangulation (empty where fewer than
    2 cameras saw it) and the tracked estimates, occluded stretches shaded.

    truth: (T, 3) mm; tracks: method -> (T, 3) mm (NaN = none); occluded: (T,) bool;
    window: (start, stop) frames to show (default: all)."""
    T = len(truth)
    a, b = window or (0, T)
    t, unit = _time_axis(T, fps)
    dt = t[1] - t[0] if T > 1 else 1.0
    fig, axes = plt.subplots(3, 1, figsize=(12, 6.5), sharex=True)
    colors = plt.get_cmap("tab10")
    occ = np.asarray(occluded, bool)
    for i, ax in enumerate(axes):
        for s, e in runs_of(occ[a:b]):
            ax.axvspan(t[a + s] - dt / 2, t[a + e - 1] + dt / 2, color="0.88", lw=0)
        ax.plot(t[a:b], truth[a:b, i], color="k", lw=2.2, alpha=0.35, label="truth")
        for j, (name, x) in enumerate(tracks.items()):
            x = np.asarray(x, dtype=np.float64)
            if name == "dlt":
                ax.plot(t[a:b], x[a:b, i], ".", ms=3, color=colors(j % 10), label=name)
            else:
                ax.plot(t[a:b], x[a:b, i], lw=1.0, color=colors(j % 10), label=name)
        ax.set_ylabel(f"{'xyz'[i]} (mm)")
        ax.tick_params(labelsize=8)
    axes[0].legend(fontsize=8, ncol=len(tracks) + 1, loc="upper right")
    axes[-1].set_xlabel(unit)
    axes[0].set_title(
        f"{part}: complete 3D track from incomplete detections (grey: seen by fewer than 2 "
        "cameras, where triangulation has nothing)",
        fontsize=10,
    )
    fig.subplots_adjust(left=0.07, right=0.98, top=0.93, bottom=0.08, hspace=0.12)
    return fig
