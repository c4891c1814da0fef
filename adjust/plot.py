"""Figures of 3D tracks, scenes, errors and reprojections (matplotlib, Agg backend).

Every function returns a matplotlib Figure (`save` writes it atomically as PNG and closes it);
the labelled MP4 of the tracks is `adjust.tracks_video`, the report's training and event
figures `adjust.report_figures`. Shapes: T frames, K parts, C cameras; points in mm (global
frame), pixels with the origin at the top-left pixel centre. Skeletons: `skeleton_edges` (a
user's skeleton.csv, a SLEAP file's edges, else the minimum spanning tree). Used by
`adjust.apps.report` (the demo's report) and `adjust-plot` (`adjust.apps.plot`, a user's own
data). numpy and OpenCV in; no torch, no Lightning.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402

from deformnet.atomic import atomic_path  # noqa: E402

log = logging.getLogger(__name__)

#: reprojection figure styles: accepted / rejected / below-threshold detections, model points
STYLE = {
    "accepted": dict(marker="o", s=28, facecolors="tab:green", edgecolors="k", linewidths=0.5),
    "rejected": dict(marker="X", s=40, c="tab:red", linewidths=0.5),
    "low": dict(marker="o", s=22, facecolors="none", edgecolors="0.55", linewidths=0.8),
    "model": dict(marker="+", s=60, c="tab:blue", linewidths=1.4),
}


def save(fig, path: str | Path, dpi: int = 100) -> Path:
    """Write `fig` as a PNG atomically and close it; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)
    return path


def runs_of(mask: np.ndarray) -> list[tuple[int, int]]:
    """(T,) bool -> [(start, stop_exclusive), ...] of the True stretches."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(np.int8))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def spanning_edges(points: np.ndarray) -> list[tuple[int, int]]:
    """Skeleton edges for drawing: `adjust.io.skeleton.spanning_edges` (minimum spanning tree of
    the parts' median distances). points: (T, K, 3)."""
    from adjust.io.skeleton import spanning_edges as mst  # adjust.io imports torch: on demand

    return mst(np.asarray(points, dtype=np.float64))


def skeleton_edges(
    parts: Sequence[str],
    points: np.ndarray | None = None,
    skeleton=None,
    edges=None,
    detections=None,
) -> list[tuple[int, int]]:
    """Skeleton edges (index pairs into `parts`) for figures: `edges` (pairs of part names),
    else a user's `skeleton` file (``skeleton.csv`` with ``part_a,part_b``, or a SLEAP file),
    else the SLEAP files' edges in `detections` (a folder), else the minimum spanning tree of
    `points` (T, K, 3) (`adjust.io.skeleton.resolve_skeleton`)."""
    from adjust.io.skeleton import resolve_skeleton  # adjust.io imports torch: on demand

    return resolve_skeleton(parts, points, edges, skeleton, detections)[0]


def _time_axis(T: int, fps: float | None) -> tuple[np.ndarray, str]:
    if fps and np.isfinite(fps) and fps > 0:
        return np.arange(T) / float(fps), "time (s)"
    return np.arange(T, dtype=np.float64), "frame"


# ---------------------------------------------------------------------------------------------
# scene and rig
# ---------------------------------------------------------------------------------------------
def camera_axes(camera) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), view direction (3,), unit) of an `adjust.camera.Camera` in world mm:
    x_cam = R X + t, so the centre is -R^T t and the optical axis is R's third row."""
    R = np.asarray(camera.R, dtype=np.float64)
    return np.asarray(camera.center, dtype=np.float64), R[2] / np.linalg.norm(R[2])


def _box_edges(corners: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    lo, hi = corners.min(0), corners.max(0)
    xs, ys, zs = (lo[0], hi[0]), (lo[1], hi[1]), (lo[2], hi[2])
    v = np.array([[x, y, z] for x in xs for y in ys for z in zs])
    edges = []
    for i in range(8):
        for j in range(i + 1, 8):
            if np.count_nonzero(v[i] != v[j]) == 1:
                edges.append((v[i], v[j]))
    return edges


def scene_figure(
    cameras: Sequence,
    track_xy: np.ndarray | None = None,
    arena_size: Sequence[float] | None = None,
    lockbox_corners: np.ndarray | None = None,
    mechanisms: Mapping[str, Sequence[float]] | None = None,
    title: str = "",
):
    """The rig and the arena, three panels: the rig's plan view (camera centres and view
    directions, the arena), a 3D view, and the arena (lock box, mechanisms, the mouse's track
    on the plane, coloured by time).

    cameras: `adjust.camera.Camera` list; track_xy: (T, 2) mm (e.g. the body's translation);
    arena_size: (2,) mm, the arena [0, sx] x [0, sy]; lockbox_corners: (M, 3) mm."""
    fig = plt.figure(figsize=(16, 5.4))
    ax = fig.add_subplot(1, 3, 1)
    ax3 = fig.add_subplot(1, 3, 2, projection="3d")
    axa = fig.add_subplot(1, 3, 3)
    colors = plt.get_cmap("tab10")
    centres = np.array([camera_axes(c)[0] for c in cameras]) if cameras else np.zeros((0, 3))
    has_arena = arena_size is not None and np.all(np.isfinite(np.asarray(arena_size, float)))
    sx, sy = (float(arena_size[0]), float(arena_size[1])) if has_arena else (300.0, 300.0)
    mid = np.array([sx / 2, sy / 2, 0.0])
    for a in (ax, axa):
        a.add_patch(plt.Rectangle((0, 0), sx, sy, fill=False, ec="k", lw=1.5, label="arena"))
    ax3.plot([0, sx, sx, 0, 0], [0, 0, sy, sy, 0], [0] * 5, "k-", lw=1)
    if lockbox_corners is not None and np.size(lockbox_corners):
        c = np.asarray(lockbox_corners, dtype=np.float64).reshape(-1, 3)
        lo, hi = c.min(0), c.max(0)
        for a in (ax, axa):
            a.add_patch(
                plt.Rectangle(
                    (lo[0], lo[1]),
                    hi[0] - lo[0],
                    hi[1] - lo[1],
                    fc="0.85",
                    ec="0.3",
                    label="lock box",
                )
            )
        for e0, e1 in _box_edges(c):
            ax3.plot(*np.stack([e0, e1]).T, color="0.4", lw=1)
    for name, p in (mechanisms or {}).items():
        p = np.asarray(p, dtype=np.float64)
        axa.plot(p[0], p[1], "s", color="tab:orange", ms=7)
        axa.annotate(
            str(name), p[:2], textcoords="offset points", xytext=(0, -13), fontsize=8, ha="center"
        )
        ax3.scatter(*p, color="tab:orange", marker="s", s=20)
    if track_xy is not None and len(track_xy):
        xy = np.asarray(track_xy, dtype=np.float64)
        t = np.linspace(0, 1, len(xy))
        sc = axa.scatter(xy[:, 0], xy[:, 1], c=t, cmap="viridis", s=3)
        ax3.scatter(xy[:, 0], xy[:, 1], np.zeros(len(xy)), c=t, cmap="viridis", s=1)
        cb = fig.colorbar(sc, ax=axa, fraction=0.046, pad=0.02, ticks=[0, 1])
        cb.ax.set_yticklabels(["start", "end"])
    for i, cam in enumerate(cameras):
        centre, view = camera_axes(cam)
        col = colors(i % 10)
        reach = 0.8 * float(np.linalg.norm(centre - mid))
        ax.plot(centre[0], centre[1], "^", color=col, ms=10, label=f"camera {cam.name}")
        if np.linalg.norm(view[:2]) > 1e-6:
            ax.annotate(
                "",
                centre[:2] + view[:2] * reach,
                centre[:2],
                arrowprops=dict(arrowstyle="->", color=col, lw=1.5),
            )
        ax.annotate(cam.name, centre[:2], textcoords="offset points", xytext=(6, 6), fontsize=8)
        ax3.scatter(*centre, color=col, marker="^", s=50)
        ax3.quiver(*centre, *(view * reach), color=col, arrow_length_ratio=0.08)
        ax3.text(*centre, f" {cam.name}", fontsize=8)
    allxy = np.concatenate([centres[:, :2], [[0.0, 0.0], [sx, sy]]])
    pad = 0.08 * float(np.ptp(allxy, axis=0).max())
    ax.set_xlim(allxy[:, 0].min() - pad, allxy[:, 0].max() + pad)
    ax.set_ylim(allxy[:, 1].min() - pad, allxy[:, 1].max() + pad)
    axa.set_xlim(-0.03 * sx, 1.03 * sx)
    axa.set_ylim(-0.03 * sy, 1.03 * sy)
    for a, ttl in (
        (ax, "rig, plan view (arrow: view direction)"),
        (axa, "arena: lock box, mechanisms, the mouse's track"),
    ):
        a.set_aspect("equal")
        a.set_xlabel("x (mm)")
        a.set_ylabel("y (mm)")
        a.set_title(ttl, fontsize=10)
    ax.legend(fontsize=7, loc="best")
    ax3.set_xlabel("x (mm)")
    ax3.set_ylabel("y (mm)")
    ax3.set_zlabel("z (mm)")
    ax3.set_title("rig and arena in 3D", fontsize=10)
    _equal_3d(ax3, np.concatenate([centres, [[0, 0, 0], [sx, sy, 0]]]))
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def _equal_3d(ax, pts: np.ndarray) -> None:
    pts = np.asarray(pts, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(-1)]
    if not len(pts):
        return
    mid = (pts.max(0) + pts.min(0)) / 2
    r = max(float(np.ptp(pts, axis=0).max()) / 2, 1.0)
    ax.set_xlim(mid[0] - r, mid[0] + r)
    ax.set_ylim(mid[1] - r, mid[1] + r)
    ax.set_zlim(max(mid[2] - r, min(0.0, pts[:, 2].min())), mid[2] + r)


# ---------------------------------------------------------------------------------------------
# tracks
# ---------------------------------------------------------------------------------------------
def body3d_figure(
    points: np.ndarray,
    parts: Sequence[str],
    snapshots: int = 6,
    fps: float | None = None,
    title: str = "tracked body over time",
    edges: Sequence[tuple[int, int]] | None = None,
):
    """A 3D plot of the tracked body over time: every part's trajectory (thin, coloured by
    time) and the skeleton at `snapshots` evenly spaced frames (with their times).

    points: (T, K, 3) mm, NaN where missing; edges: skeleton (part index pairs), default the
    minimum spanning tree of the median distances."""
    pts = np.asarray(points, dtype=np.float64)
    T, K = pts.shape[:2]
    if edges is None:
        edges = spanning_edges(pts) if K > 1 else []
    fig = plt.figure(figsize=(11, 8))
    ax = fig.add_subplot(projection="3d")
    cmap = plt.get_cmap("viridis")
    for k in range(K):
        ax.plot(*pts[:, k].T, lw=0.4, alpha=0.35, color=plt.get_cmap("tab20")(k % 20))
    tsec, unit = _time_axis(T, fps)
    frames = np.unique(np.linspace(0, T - 1, max(1, snapshots)).round().astype(int))
    for f in frames:
        col = cmap(f / max(T - 1, 1))
        p = pts[f]
        ax.scatter(*p.T, color=col, s=14, depthshade=False)
        for a, b in edges:
            ax.plot(*np.stack([p[a], p[b]]).T, color=col, lw=1.6)
        ok = np.isfinite(p).all(-1)
        if ok.any():
            top = p[ok][np.argmax(p[ok, 2])]
            label = f"{tsec[f]:.1f} s" if unit.startswith("time") else f"frame {f}"
            ax.text(*top, label, fontsize=7, color=col)
    for k, name in enumerate(parts):
        ax.plot([], [], color=plt.get_cmap("tab20")(k % 20), label=str(name))
    ax.legend(fontsize=6, loc="upper left", ncol=2 if K > 12 else 1)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    _equal_3d(ax, pts.reshape(-1, 3))
    ax.set_title(f"{title} (skeletons: {len(frames)} frames, colour = time)")
    fig.tight_layout()
    return fig


def _part_grid(K: int, height: float = 1.3):
    cols = 2 if K > 6 else 1
    rows = int(np.ceil(K / cols))
    fig, axes = plt.subplots(
        rows, cols, figsize=(13, max(3.0, height * rows + 1)), sharex=True, squeeze=False
    )
    return fig, axes.T.ravel() if cols > 1 else axes.ravel(), rows, cols


def _finish_grid(fig, axes, K: int, xlabel: str, title: str) -> None:
    for ax in axes[K:]:
        ax.set_visible(False)
    for ax in axes[:K]:
        ax.tick_params(labelsize=7)
    for ax in axes[:K]:
        ax.set_xlabel("")
    visible = [ax for ax in axes[:K]]
    if visible:
        visible[-1].set_xlabel(xlabel)
        if len(axes) > 1:
            axes[min(K - 1, int(np.ceil(K / 2)) - 1)].set_xlabel(xlabel)
    fig.suptitle(title)
    # fixed margins: tight_layout over many panels costs seconds
    fig.subplots_adjust(left=0.07, right=0.94, top=0.93, bottom=0.07, hspace=0.3, wspace=0.28)


def error_figure(
    errors: Mapping[str, np.ndarray],
    parts: Sequence[str],
    occluded: np.ndarray,
    fps: float | None = None,
    title: str = "3D error against truth per part (shaded: seen by fewer than 2 cameras)",
):
    """Per-part 3D error over time for several methods, occluded stretches shaded.

    errors: method -> (T, K) mm (NaN where no estimate); occluded: (T, K) bool."""
    occ = np.asarray(occluded, bool)
    T, K = occ.shape
    t, unit = _time_axis(T, fps)
    dt = t[1] - t[0] if T > 1 else 1.0
    fig, axes, _, _ = _part_grid(K)
    colors = plt.get_cmap("tab10")
    for k, ax in enumerate(axes[:K]):
        for a, b in runs_of(occ[:, k]):
            ax.axvspan(t[a] - dt / 2, t[b - 1] + dt / 2, color="0.88", lw=0)
        for i, (name, e) in enumerate(errors.items()):
            ax.plot(t, np.asarray(e)[:, k], lw=0.7, color=colors(i % 10), label=name)
        ax.set_ylabel(f"{parts[k]}\nmm", fontsize=7)
        finite = np.concatenate([np.asarray(e)[:, k] for e in errors.values()])
        finite = finite[np.isfinite(finite)]
        if finite.size:
            ax.set_ylim(0, max(1.0, float(np.percentile(finite, 99.5)) * 1.1))
    axes[0].legend(fontsize=7, ncol=len(errors), loc="upper right")
    _finish_grid(fig, axes, K, unit, title)
    return fig


def confidence_figure(
    ncams: np.ndarray,
    sigma: np.ndarray | None,
    parts: Sequence[str],
    fps: float | None = None,
    title: str = "confidence per part: cameras used (_ncams) and 3D standard error (_sigma)",
):
    """Per part over time: the number of cameras whose detection was used (``_ncams``, shaded
    where 0: the part comes from the model alone) and, when given, the 3D standard error
    ``_sigma`` (mm). ncams, sigma: (T, K)."""
    nc = np.asarray(ncams, dtype=np.float64)
    T, K = nc.shape
    t, unit = _time_axis(T, fps)
    dt = t[1] - t[0] if T > 1 else 1.0
    fig, axes, _, _ = _part_grid(K)
    top = max(1.0, float(np.nanmax(nc)) if np.isfinite(nc).any() else 1.0)
    for k, ax in enumerate(axes[:K]):
        for a, b in runs_of(nc[:, k] == 0):
            ax.axvspan(t[a] - dt / 2, t[b - 1] + dt / 2, color="mistyrose", lw=0)
        ax.step(t, nc[:, k], where="mid", color="tab:blue", lw=0.8)
        ax.set_ylim(-0.2, top + 0.3)
        ax.set_ylabel(f"{parts[k]}\ncams", fontsize=7, color="tab:blue")
        if sigma is not None:
            s = np.asarray(sigma, dtype=np.float64)[:, k]
            ax2 = ax.twinx()
            ax2.plot(t, s, color="tab:red", lw=0.7)
            ax2.tick_params(labelsize=7, colors="tab:red")
            if np.isfinite(s).any():
                ax2.set_ylim(0, max(0.5, float(np.nanpercentile(s, 99.5)) * 1.1))
            ax2.set_ylabel("sigma mm", fontsize=6, color="tab:red")
    _finish_grid(fig, axes, K, unit, title)
    return fig


def reprojection_error_figure(
    error: np.ndarray,
    parts: Sequence[str],
    per_camera: Mapping[str, np.ndarray] | None = None,
    fps: float | None = None,
):
    """Reprojection error (px): per part over time (``_error``, the mean over the cameras
    used), and the distribution per camera when `per_camera` (camera -> (T, K) px) is given."""
    err = np.asarray(error, dtype=np.float64)
    T, K = err.shape
    t, unit = _time_axis(T, fps)
    ncol = 2 if per_camera else 1
    fig, axes = plt.subplots(1, ncol, figsize=(13, 4.8), squeeze=False)
    ax = axes[0, 0]
    cmap = plt.get_cmap("tab20")
    for k in range(K):
        ax.plot(t, err[:, k], lw=0.5, color=cmap(k % 20), label=str(parts[k]))
    med = np.nanmedian(err, axis=1) if np.isfinite(err).any() else np.full(T, np.nan)
    ax.plot(t, med, "k-", lw=1.2, label="median over parts")
    ax.set_xlabel(unit)
    ax.set_ylabel("reprojection error (px)")
    if np.isfinite(err).any():
        ax.set_ylim(0, max(1.0, float(np.nanpercentile(err, 99.5)) * 1.1))
    ax.set_title("reprojection error per part (mean over the cameras used)")
    ax.legend(fontsize=6, ncol=3 if K > 8 else 1, loc="upper right")
    if per_camera:
        ax = axes[0, 1]
        data, names = [], []
        for name, e in per_camera.items():
            v = np.asarray(e, dtype=np.float64).ravel()
            data.append(v[np.isfinite(v)])
            names.append(str(name))
        ax.boxplot(data, showfliers=False)
        ax.set_xticks(range(1, len(names) + 1), names, rotation=30, ha="right")
        med = [np.median(d) if d.size else np.nan for d in data]
        for i, m in enumerate(med):
            if np.isfinite(m):
                ax.text(i + 1, m, f" {m:.2f}", fontsize=7, va="bottom")
        ax.set_ylabel("px")
        ax.set_title("per camera (used detections; box: quartiles, whiskers 1.5 IQR)")
    fig.tight_layout()
    return fig


# ---------------------------------------------------------------------------------------------
# reprojections over the detections
# ---------------------------------------------------------------------------------------------
def classify_detections(
    xy: np.ndarray, likelihood: np.ndarray, threshold: float, uv: np.ndarray, ncams: np.ndarray
) -> np.ndarray:
    """Which detections the track rests on: codes 0 missing (no detection at or above the
    likelihood threshold), 1 accepted, 2 rejected; (..., K, C), batched over leading dims.

    xy: (..., K, C, 2) detections (NaN where absent or below the threshold); likelihood:
    (..., K, C); uv: (..., K, C, 2) the tracked points reprojected; ncams: (..., K) cameras used
    (the points3d ``_ncams`` column; NaN: all present), or (..., K, C) bool: exactly which
    detections the track used (adjust-track's ``accepted.npz``, `load_accepted`). With counts
    only, the ``ncams`` detections nearest the reprojection count as accepted (the tracker's
    gate drops the detections far from it), any others as rejected."""
    xy, uv = np.asarray(xy, dtype=np.float64), np.asarray(uv, dtype=np.float64)
    lik = np.asarray(likelihood, dtype=np.float64)
    present = np.isfinite(xy).all(-1) & (lik >= threshold)
    if np.asarray(ncams).dtype == bool and np.shape(ncams) == present.shape:
        # exact: adjust-track's accepted.npz says which detections it used
        return np.where(present, np.where(np.asarray(ncams), 1, 2), 0).astype(np.int64)
    d = np.linalg.norm(xy - uv, axis=-1)
    d = np.where(present & np.isfinite(d), d, np.inf)
    rank = np.argsort(np.argsort(d, axis=-1, kind="stable"), axis=-1, kind="stable")
    nc = np.asarray(ncams, dtype=np.float64)
    n = np.where(np.isfinite(nc), nc, present.sum(-1))[..., None]
    return np.where(present, np.where(rank < n, 1, 2), 0).astype(np.int64)


def load_accepted(tracks_path, parts: Sequence[str], cameras: Sequence) -> np.ndarray | None:
    """(T, K, C) bool: which detections adjust-track used, from ``accepted.npz`` beside its
    ``points3d.csv`` (parts and cameras reordered by name), or None when there is none."""
    from pathlib import Path

    f = Path(tracks_path).parent / "accepted.npz"
    if not f.is_file():
        return None
    with np.load(f, allow_pickle=False) as z:
        acc, fp, fc = z["accepted"], [str(p) for p in z["parts"]], [str(c) for c in z["cameras"]]
    names = [getattr(c, "name", c) for c in cameras]
    if not (set(parts) <= set(fp) and set(names) <= set(fc)):
        return None
    return acc[:, [fp.index(p) for p in parts]][:, :, [fc.index(c) for c in names]]


def reprojection_figure(
    frame_label: str,
    cameras: Sequence,
    xy: np.ndarray,
    likelihood: np.ndarray,
    threshold: float,
    uv: np.ndarray,
    ncams: np.ndarray,
    parts: Sequence[str],
    raw_xy: np.ndarray | None = None,
    images: Sequence[np.ndarray | None] | None = None,
):
    """One frame, one panel per camera: the tracked parts reprojected (blue +, joined to each
    detection by a thin line) over the camera's detections: accepted (green dot), rejected by
    the tracker (red X) and below the likelihood threshold (grey ring, when `raw_xy` holds the
    raw positions). Parts no camera detected show the reprojection alone, labelled.

    xy: (K, C, 2) accepted-threshold detections (NaN = none); likelihood: (K, C); uv: (K, C, 2);
    ncams: (K,); raw_xy: (K, C, 2) the files' positions regardless of likelihood; images:
    optional background frame per camera (H, W, 3) uint8 RGB."""
    C = len(cameras)
    code = classify_detections(xy, likelihood, threshold, uv, ncams)
    cols = min(C, 3)
    rows = int(np.ceil(C / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.4 * rows), squeeze=False)
    axes = axes.ravel()
    for c, cam in enumerate(cameras):
        ax = axes[c]
        w, h = (int(cam.size[0]), int(cam.size[1])) if cam.size else (0, 0)
        if images is not None and images[c] is not None:
            ax.imshow(images[c])
            h, w = images[c].shape[:2]
        if w and h:
            ax.add_patch(plt.Rectangle((-0.5, -0.5), w, h, fill=False, ec="0.5", lw=0.8))
        det = xy[:, c]
        for k in range(len(parts)):
            if np.isfinite(det[k]).all() and np.isfinite(uv[k, c]).all():
                ax.plot(*np.stack([det[k], uv[k, c]]).T, color="0.3", lw=0.6)
        for key, val in (("accepted", 1), ("rejected", 2)):
            m = code[:, c] == val
            if m.any():
                ax.scatter(det[m, 0], det[m, 1], label=key, **STYLE[key])
        if raw_xy is not None:
            low = ~np.isfinite(det).all(-1) & np.isfinite(raw_xy[:, c]).all(-1)
            if low.any():
                ax.scatter(
                    raw_xy[low, c, 0], raw_xy[low, c, 1], label="below threshold", **STYLE["low"]
                )
        ok = np.isfinite(uv[:, c]).all(-1)
        ax.scatter(uv[ok, c, 0], uv[ok, c, 1], label="tracked (reprojected)", **STYLE["model"])
        for k in np.flatnonzero(ok & (code[:, c] == 0)):
            ax.annotate(
                str(parts[k]),
                uv[k, c],
                fontsize=6,
                color="tab:blue",
                textcoords="offset points",
                xytext=(4, 4),
            )
        pts = np.concatenate([uv[ok, c], det[np.isfinite(det).all(-1)]])
        if len(pts):
            lo, hi = pts.min(0), pts.max(0)
            pad = max(20.0, 0.15 * float((hi - lo).max()))
            ax.set_xlim(lo[0] - pad, hi[0] + pad)
            ax.set_ylim(hi[1] + pad, lo[1] - pad)  # image rows grow downwards
        elif w and h:
            ax.set_xlim(-0.5, w - 0.5)
            ax.set_ylim(h - 0.5, -0.5)
        ax.set_aspect("equal")
        n_acc, n_rej = int((code[:, c] == 1).sum()), int((code[:, c] == 2).sum())
        ax.set_title(
            f"{cam.name}: {n_acc} accepted, {n_rej} rejected, "
            f"{int((code[:, c] == 0).sum())} missing",
            fontsize=9,
        )
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6, loc="lower right")
    for ax in axes[C:]:
        ax.set_visible(False)
    fig.suptitle(f"{frame_label}: tracked parts reprojected over each camera's detections (px)")
    fig.tight_layout()
    return fig
