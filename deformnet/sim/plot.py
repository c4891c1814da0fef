"""Figure of a simulation: the body model in three views and the track on the arena plane."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from deformnet.atomic import atomic_path
from deformnet.sim.dataset import SimData

_COLORS = ("#4c72b0", "#dd8452", "#55a868", "#c44e52", "#8172b3", "#937860", "#da8bc3", "#8c8c8c")
_EDGES = (
    ("nose_tip", "left_ear"),
    ("nose_tip", "right_ear"),
    ("left_ear", "right_ear"),
    ("left_front_paw", "right_front_paw"),
    ("left_hind_paw", "right_hind_paw"),
    ("left_front_paw", "left_hind_paw"),
    ("right_front_paw", "right_hind_paw"),
    ("nose_tip", "tail_root"),
)


def _side_color(name: str) -> str:
    if name.startswith("left"):
        return "tab:blue"
    if name.startswith("right"):
        return "tab:red"
    return "black"


def track_xy(data: SimData) -> np.ndarray:
    """(T, 2) body track on the plane: the rigid hind paws' midpoint (rearing pitches the body
    about it, so it stays put), else the pose translation."""
    try:
        i, j = data.part_index("left_hind_paw"), data.part_index("right_hind_paw")
    except KeyError:
        return data.poses[:, 3:5]
    return 0.5 * (data.rigid[:, i, :2] + data.rigid[:, j, :2])


def _snapshots(ax, data: SimData, count: int = 8) -> None:
    """A few deformed mice (top view) along the track: head triangle, spine, paws."""
    parts = data.parts
    need = ("nose_tip", "left_ear", "right_ear", "tail_root")
    if not all(p in parts for p in need):
        return
    nose, le, re, tail = (parts.index(p) for p in need)
    paws = [i for i, p in enumerate(parts) if p.endswith("_paw")]
    for t in np.linspace(0, data.num_frames - 1, count + 2)[1:-1].astype(int):
        X = data.deformed[t]
        tri = X[[nose, le, re, nose], :2]
        ax.fill(tri[:, 0], tri[:, 1], color="0.2", alpha=0.8, zorder=4)
        neck = 0.5 * (X[le, :2] + X[re, :2])
        ax.plot([neck[0], X[tail, 0]], [neck[1], X[tail, 1]], color="0.2", lw=2, zorder=4)
        for i in paws:
            ax.scatter(X[i, 0], X[i, 1], s=10, color=_side_color(parts[i]), zorder=5)


def plot_sim(path: str | os.PathLike, data: SimData, max_points: int = 40000) -> Path:
    """Write a PNG (atomically): model mouse in top / side / front view (left parts blue, right
    parts red, names written) and the body track on the plane coloured by behavior, with the
    lock box, its mechanisms and the arena walls."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(15, 10.5))
    gs = fig.add_gridspec(2, 3, height_ratios=[1.0, 1.9])
    model, parts = data.model, data.parts
    views = (
        ("top view (X right, Y forward)", 0, 1),
        ("side view from the right (Y forward, Z up)", 1, 2),
        ("front view, facing the mouse (X right, Z up)", 0, 2),
    )
    for col, (title, a, b) in enumerate(views):
        ax = fig.add_subplot(gs[0, col])
        for p, q in _EDGES:
            if p in parts and q in parts:
                i, j = parts.index(p), parts.index(q)
                ax.plot(model[[i, j], a], model[[i, j], b], color="0.7", lw=1, zorder=1)
        labels: dict[tuple[float, float], list[str]] = {}
        for name, pt in zip(parts, model):
            ax.scatter(pt[a], pt[b], color=_side_color(name), s=30, zorder=2)
            labels.setdefault((round(pt[a], 3), round(pt[b], 3)), []).append(name)
        flipped = col == 2
        for (u, v), names in labels.items():  # parts that coincide in this view share a label
            color = _side_color(names[0]) if len(names) == 1 else "0.3"
            # write left parts' names on their outer side (right parts likewise)
            outward = names[0].startswith("left") and a == 0
            outward_r = names[0].startswith("right") and a == 0
            to_left = (outward and not flipped) or (outward_r and flipped)
            ax.annotate(
                " / ".join(names),
                (u, v),
                fontsize=7,
                xytext=(-3, 3) if to_left else (3, 3),
                textcoords="offset points",
                color=color,
                ha="right" if to_left else "left",
            )
        if col == 2:  # looking at the mouse from the front: its left appears on the right
            ax.invert_xaxis()
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("XYZ"[a] + " [mm]")
        ax.set_ylabel("XYZ"[b] + " [mm]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    fig.axes[0].text(
        0.02, 0.02, "blue = left, red = right", transform=fig.axes[0].transAxes, fontsize=8
    )

    ax = fig.add_subplot(gs[1, :])
    W, H = data.arena_size
    ax.add_patch(plt.Rectangle((0, 0), W, H, fill=False, lw=2, color="k"))
    T = data.num_frames
    step = max(1, T // max_points)
    xy = track_xy(data)[::step]
    lab = data.labels[::step]
    ax.plot(xy[:, 0], xy[:, 1], color="0.85", lw=0.5, zorder=1)
    for b, name in enumerate(data.behaviors):
        sel = lab == b
        if sel.any():
            ax.scatter(
                xy[sel, 0],
                xy[sel, 1],
                s=3,
                color=_COLORS[b % len(_COLORS)],
                label=f"{name} ({np.mean(data.labels == b):.0%})",
                zorder=2,
            )
    c = data.lockbox_corners
    x0, y0 = c[:, 0].min(), c[:, 1].min()
    ax.add_patch(
        plt.Rectangle(
            (x0, y0), c[:, 0].max() - x0, c[:, 1].max() - y0, color="0.4", alpha=0.6, zorder=3
        )
    )
    ax.text(x0 + 3, c[:, 1].max() - 8, "lock box", fontsize=9, color="w", zorder=4)
    for name, p in zip(*data.mechanisms):
        ax.scatter(p[0], p[1], marker="*", s=160, color="gold", edgecolor="k", zorder=5)
        ax.annotate(
            name,
            (p[0], p[1]),
            xytext=(0, -14),
            textcoords="offset points",
            ha="center",
            fontsize=8,
            zorder=5,
        )
    _snapshots(ax, data)
    ax.scatter(*track_xy(data)[0], marker="o", s=60, facecolor="none", edgecolor="k", zorder=5)
    ax.set_xlim(-10, W + 10)
    ax.set_ylim(-10, H + 10)
    ax.set_aspect("equal")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_title(
        f"body track: {T} frames, {T / data.fps:.0f} s at {data.fps:g} fps, "
        f"seed {data.seed} (circle = start)",
        fontsize=10,
    )
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8, markerscale=4)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    return Path(path)
