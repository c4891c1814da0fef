"""A labelled video of 3D tracks beside their 2D reprojections (`tracks_video`, MP4 through
OpenCV; `adjust-plot video=...`). matplotlib (Agg, through `adjust.plot`) draws the 3D view."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import matplotlib.pyplot as plt
import numpy as np

from adjust.plot import _equal_3d, skeleton_edges
from deformnet.atomic import atomic_path

log = logging.getLogger(__name__)

__all__ = ["project_points", "tracks_video"]


# ---------------------------------------------------------------------------------------------
# labelled 3D video
# ---------------------------------------------------------------------------------------------
def project_points(points: np.ndarray, camera) -> np.ndarray:
    """(..., 3) world mm -> (..., 2) px through one `adjust.camera.Camera` (pinhole + OpenCV
    distortion, cv2.projectPoints; a fisheye camera's, cv2.fisheye.projectPoints); NaN in, NaN
    out."""
    X = np.asarray(points, dtype=np.float64)
    flat = X.reshape(-1, 3)
    ok = np.isfinite(flat).all(-1)
    uv = np.full((len(flat), 2), np.nan)
    if ok.any():
        R = np.asarray(camera.R, dtype=np.float64)
        rvec, _ = cv2.Rodrigues(R)
        tvec = np.asarray(camera.tvec, np.float64)
        if camera.fisheye:
            p, _ = cv2.fisheye.projectPoints(
                flat[ok][:, None], rvec, tvec, camera.K, camera.dist[:4]
            )
        else:
            p, _ = cv2.projectPoints(flat[ok], rvec, tvec, camera.K, camera.dist)
        uv[ok] = p.reshape(-1, 2)
    return uv.reshape(X.shape[:-1] + (2,))


def _video_rows(fnum: np.ndarray, clip: tuple[int, int] | None) -> list[int]:
    """Rows of the tracks to draw: those whose frame number is in [start, stop), or all."""
    if clip is None:
        return list(range(len(fnum)))
    fn = np.asarray(fnum)
    if not np.issubdtype(fn.dtype, np.number):
        raise ValueError("clip=START:STOP needs numeric frame numbers (fnum)")
    rows = np.flatnonzero((fn >= clip[0]) & (fn < clip[1])).tolist()
    if not rows:
        raise ValueError(f"clip={clip[0]}:{clip[1]}: none of these frames is in the tracks")
    return rows


def tracks_video(
    path: str | Path,
    tracks: Mapping,
    cameras: Sequence | None = None,
    *,
    fps: float | None = None,
    clip: tuple[int, int] | None = None,
    videos: Mapping[str, str | Path] | None = None,
    video_first_frame: int = 0,
    edges: Sequence[tuple[int, int]] | None = None,
    skeleton=None,
    detections=None,
    trail: int = 10,
    size: tuple[int, int] = (1280, 720),
) -> Path:
    """A labelled video (MP4, OpenCV's ``mp4v``) of the tracks: the body in 3D (parts labelled,
    the skeleton, each part's last `trail` positions) beside each camera's view of it (the
    parts reprojected with the skeleton and labels, over the camera's video frame when `videos`
    has one, else over the image's outline). Written atomically; returns the path.

    tracks: `adjust.io.read_points3d`'s dict (``parts``, ``points`` (T, K, 3) mm, ``fnum``,
    ``M``, ``center``: points in an axes-aligned frame are moved back to the world frame to be
    reprojected); cameras: `adjust.camera.Camera` list (None: the 3D view alone); clip: (start,
    stop) frame numbers, stop exclusive (None: every row); videos: camera name -> video file,
    whose first frame is frame number `video_first_frame`; edges: the skeleton as part index
    pairs (as `body3d_figure` takes it), else from `skeleton` / `detections` (`skeleton_edges`);
    fps: the video's rate (default 30); size: (width, height) px.
    """
    parts = [str(p) for p in tracks["parts"]]
    X = np.asarray(tracks["points"], dtype=np.float64)
    fnum = np.asarray(tracks["fnum"])
    rows = _video_rows(fnum, clip)
    if edges is not None:
        pairs = [(int(a), int(b)) for a, b in edges]
    else:
        pairs = skeleton_edges(parts, X, skeleton, None, detections) if len(parts) > 1 else []
    cams = list(cameras or [])
    M = np.asarray(tracks.get("M", np.eye(3)), dtype=np.float64)
    c = np.asarray(tracks.get("center", np.zeros(3)), dtype=np.float64)
    uv = np.stack([project_points((X + c) @ M, cam) for cam in cams], 2) if cams else None
    w, h = (int(size[0]) // 2 * 2, int(size[1]) // 2 * 2)  # even: what MP4 encoders want
    rate = float(fps) if fps and np.isfinite(fps) and fps > 0 else 30.0

    fig = plt.figure(figsize=(w / 100, h / 100), dpi=100)
    n_views = len(cams)
    ax3 = fig.add_axes((0.0, 0.04, 0.47 if n_views else 1.0, 0.9), projection="3d")
    cols = int(np.ceil(np.sqrt(n_views))) if n_views else 0
    grid = int(np.ceil(n_views / cols)) if n_views else 0
    axes2d = []
    for i in range(n_views):
        r, col = divmod(i, cols)
        axes2d.append(
            fig.add_axes(
                (0.52 + col * 0.47 / cols, 0.06 + (grid - 1 - r) * 0.88 / grid,
                 0.45 / cols, 0.84 / grid)
            )
        )  # fmt: skip
    # tab20's strong colours first, then its pale ones (labels stay readable on white)
    colors = [plt.get_cmap("tab20")((2 * k) % 20 + (2 * k // 20) % 2) for k in range(len(parts))]
    sel = X[rows]
    _equal_3d(ax3, sel.reshape(-1, 3))
    ax3.set_xlabel("x (mm)", fontsize=7)
    ax3.set_ylabel("y (mm)", fontsize=7)
    ax3.set_zlabel("z (mm)", fontsize=7)
    ax3.tick_params(labelsize=6)
    p0 = sel[0]
    scat = ax3.scatter(p0[:, 0], p0[:, 1], p0[:, 2], c=colors, s=18, depthshade=False)
    bones3 = [ax3.plot([], [], [], color="0.3", lw=1.5)[0] for _ in pairs]
    trails3 = [
        ax3.plot([], [], [], color=colors[k], lw=0.6, alpha=0.6)[0] for k in range(len(parts))
    ]
    names3 = [ax3.text(0, 0, 0, p, fontsize=6, color=colors[k]) for k, p in enumerate(parts)]
    title = fig.text(0.01, 0.965, "", fontsize=10, weight="bold")

    caps, images, marks, bones2, names2 = {}, [], [], [], []
    for i, (ax, cam) in enumerate(zip(axes2d, cams)):
        cw, ch = (int(cam.size[0]), int(cam.size[1])) if cam.size and cam.size[0] else (0, 0)
        if videos and cam.name in videos:
            cap = cv2.VideoCapture(str(videos[cam.name]))
            if not cap.isOpened():
                raise ValueError(f"{videos[cam.name]}: cannot open the video (camera '{cam.name}')")
            caps[cam.name] = cap
        u = uv[:, :, i][rows]
        if not (cw and ch):
            fin = u[np.isfinite(u).all(-1)]
            cw, ch = (
                (int(fin[:, 0].max()) + 50, int(fin[:, 1].max()) + 50) if len(fin) else (640, 480)
            )
        images.append(
            ax.imshow(np.full((ch, cw, 3), 30, np.uint8), extent=(-0.5, cw - 0.5, ch - 0.5, -0.5))
        )
        marks.append(
            ax.scatter(np.zeros(len(parts)), np.zeros(len(parts)), c=colors, s=12, marker="+")
        )
        bones2.append([ax.plot([], [], color="w", lw=1.0, alpha=0.8)[0] for _ in pairs])
        names2.append([ax.text(0, 0, p, fontsize=5, color=colors[k]) for k, p in enumerate(parts)])
        ax.set_xlim(-0.5, cw - 0.5)
        ax.set_ylim(ch - 0.5, -0.5)
        ax.set_title(cam.name, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])

    def draw(row: int):
        p = X[row]
        ok = np.isfinite(p).all(-1)
        scat._offsets3d = (p[ok, 0], p[ok, 1], p[ok, 2])
        scat.set_color([colors[k] for k in np.flatnonzero(ok)])
        for line, (a, b) in zip(bones3, pairs):
            seg = p[[a, b]] if ok[a] and ok[b] else np.full((2, 3), np.nan)
            line.set_data_3d(seg[:, 0], seg[:, 1], seg[:, 2])
        lo = rows[max(0, rows.index(row) - trail)] if trail else row
        for k, line in enumerate(trails3):
            tr = X[lo : row + 1, k]
            line.set_data_3d(tr[:, 0], tr[:, 1], tr[:, 2])
            names3[k].set_visible(bool(ok[k]))
            if ok[k]:
                names3[k].set_position_3d(p[k])
        f = fnum[row]
        t = f"  {float(f) / rate:.2f} s" if np.issubdtype(fnum.dtype, np.number) else ""
        title.set_text(f"frame {f}{t}")
        for i, cam in enumerate(cams):
            q = uv[row, :, i]
            qok = np.isfinite(q).all(-1)
            if cam.name in caps:
                cap = caps[cam.name]
                cap.set(cv2.CAP_PROP_POS_FRAMES, int(f) - int(video_first_frame))
                good, img = cap.read()
                if not good:
                    raise ValueError(
                        f"{videos[cam.name]}: no frame {f} (camera '{cam.name}'; "
                        f"video_first_frame={video_first_frame})"
                    )
                images[i].set_data(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
            marks[i].set_offsets(np.where(qok[:, None], q, -1e6))
            for line, (a, b) in zip(bones2[i], pairs):
                seg = q[[a, b]] if qok[a] and qok[b] else np.full((2, 2), np.nan)
                line.set_data(seg[:, 0], seg[:, 1])
            for k, txt in enumerate(names2[i]):
                txt.set_visible(bool(qok[k]))
                if qok[k]:
                    txt.set_position((q[k, 0] + 4, q[k, 1] - 4))
        fig.canvas.draw()
        rgba = np.asarray(fig.canvas.buffer_rgba())
        return cv2.cvtColor(rgba[:h, :w], cv2.COLOR_RGBA2BGR)

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_path(path, suffix=".mp4") as tmp:
            writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), rate, (w, h))
            if not writer.isOpened():
                raise RuntimeError(f"OpenCV cannot write an MP4 ({path})")
            try:
                for row in rows:
                    writer.write(draw(row))
            finally:
                writer.release()
    finally:
        plt.close(fig)
        for cap in caps.values():
            cap.release()
    log.info("3D video of %d frames (%d views) -> %s", len(rows), n_views, path)
    return path
