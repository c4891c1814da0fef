"""`adjust-plot`: figures of a user's own 3D tracks (no truth needed).

    adjust-plot tracks=OUT/points3d.csv output.dir=OUT/plots
    adjust-plot tracks=OUT/points3d.csv input.calibration=calibration.toml \\
        input.detections=DIR frames=[100,250]
    adjust-plot tracks=... input.calibration=... video=VIDEOS frames=[100] clip=100:400

Writes into ``output.dir``:

- ``body3d.png``: the tracked body over time in 3D;
- ``confidence.png``: per part over time, the cameras used (``{part}_ncams``) and the 3D
  standard error (``{part}_sigma``, when the file has it);
- ``reprojection_error.png``: the reprojection error per part over time (``{part}_error``, or
  recomputed from the calibration and detections), per camera when both are given;
- with ``input.calibration`` and ``input.detections``: ``reprojection_frame<F>.png`` per chosen
  frame (the parts reprojected over each camera's accepted / rejected / below-threshold
  detections; ``input.pattern``, ``input.individual``, ``input.likelihood_threshold`` choose
  and read the detection files as in adjust-track);
- with ``video=DIR`` (one video per camera, the camera's name in the file name) and
  ``input.calibration``: ``video_frame<F>.png`` per chosen frame, the cameras' frames side by
  side with the reprojected parts drawn on them (OpenCV), and with ``clip=START:STOP`` (frame
  numbers, stop exclusive) ``clip_<START>_<STOP>.mp4``;
- ``summary.json``: the inputs and the files written.

`frames` are the tracks' frame numbers (``fnum``); default: three evenly spaced frames.
`run(cfg) -> dict` is the plain function behind the Hydra app.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from adjust import plot
from adjust.apps.common import finite_or_none, run_or_exit
from adjust.camera import CameraTensors, project_cameras
from adjust.io import InputError, load_calibration, load_scene, read_points3d
from adjust.settings import load_kwargs, required
from adjust.tracks_video import tracks_video
from deformnet.atomic import atomic_path, write_text
from deformnet.confutil import to_plain
from deformnet.paths import CONF_DIR, output_dir

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".wmv")
#: BGR colours of the overlay
COLORS = {"model": (255, 128, 0), "accepted": (0, 200, 0), "rejected": (0, 0, 255)}


def match_videos(folder: str | Path, cameras) -> dict[str, Path]:
    """camera name -> its video in `folder` (the file name contains the camera's name; the
    longest matching name wins). A camera without a video is skipped (logged); no video for
    any camera, or one camera matching several files, is an InputError."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"video folder not found: {folder}")
    files = sorted(f for f in folder.iterdir() if f.suffix.lower() in VIDEO_SUFFIXES)
    names = [c.name for c in cameras]
    found: dict[str, list[Path]] = {n: [] for n in names}
    for f in files:
        hits = [n for n in names if n in f.stem]
        if hits:
            found[max(hits, key=len)].append(f)
    out = {}
    for n, fs in found.items():
        if len(fs) > 1:
            raise InputError(
                f"{folder}: camera '{n}' matches several videos {[f.name for f in fs]}"
            )
        if fs:
            out[n] = fs[0]
        else:
            log.warning("%s: no video for camera '%s' (its name is in no file name)", folder, n)
    if not out:
        raise InputError(
            f"{folder}: no video ({', '.join(VIDEO_SUFFIXES)}) whose name contains a camera name "
            f"{names}"
        )
    return out


def parse_clip(clip) -> tuple[int, int] | None:
    """'START:STOP' (frame numbers, stop exclusive) -> (start, stop); None -> None."""
    if clip is None or str(clip) in ("", "None", "null"):
        return None
    text = str(clip)
    try:
        a, b = (int(v) for v in text.split(":"))
    except ValueError:
        raise ValueError(
            f"clip={text!r}: expected START:STOP frame numbers, e.g. clip=100:400"
        ) from None
    if not 0 <= a < b:
        raise ValueError(f"clip={text!r}: need 0 <= START < STOP")
    return a, b


def _frame_label(value) -> int | str:
    """A frame number (int) or a labelled image's name (str, e.g. ``img001``, without its
    suffix, for file names)."""
    if isinstance(value, int | np.integer):
        return int(value)
    return Path(str(value)).stem or str(value)


def _rows(fnum: np.ndarray, frames, T: int) -> list[tuple[int | str, int]]:
    """[(frame number or labelled image, row)] for the chosen frames (fnum values; default:
    3 evenly spaced rows)."""
    fn = np.asarray(fnum)
    if not frames:
        rows = np.unique(np.linspace(0, T - 1, min(3, T)).round().astype(int))
        return [(_frame_label(fn[r]), int(r)) for r in rows]
    out = []
    for f in frames:
        hit = np.flatnonzero(fn.astype(str) == str(f))
        if not hit.size:
            raise InputError(f"frames: frame {f} is not in the tracks (fnum {fn[0]}..{fn[-1]})")
        out.append((_frame_label(fn[hit[0]]), int(hit[0])))
    return out


def _project(points: np.ndarray, cameras) -> np.ndarray:
    """(T, K, 3) mm -> (T, K, C, 2) px (NaN where a point is missing)."""
    import torch

    X = torch.as_tensor(np.nan_to_num(points, nan=0.0))
    uv = project_cameras(X, CameraTensors.from_cameras(list(cameras))).numpy()
    uv[~np.isfinite(points).all(-1)] = np.nan
    return uv


def _read_frame(cap, index: int):
    import cv2

    cap.set(cv2.CAP_PROP_POS_FRAMES, int(index))
    ok, img = cap.read()
    return img if ok else None


def draw_overlay(img, uv: np.ndarray, parts, codes: np.ndarray | None, det: np.ndarray | None):
    """Draw one camera's reprojected parts (blue +, labelled) and its detections (accepted
    green dot, rejected red X) on a BGR image in place. uv, det: (K, 2) px; codes: (K,)."""
    import cv2

    def pt(p):
        return int(round(float(p[0]))), int(round(float(p[1])))

    for k, name in enumerate(parts):
        if det is not None and codes is not None and np.isfinite(det[k]).all():
            if codes[k] == 1:
                cv2.circle(img, pt(det[k]), 5, COLORS["accepted"], -1, cv2.LINE_AA)
            elif codes[k] == 2:
                cv2.drawMarker(img, pt(det[k]), COLORS["rejected"], cv2.MARKER_TILTED_CROSS, 10, 2)
            if np.isfinite(uv[k]).all():
                cv2.line(img, pt(det[k]), pt(uv[k]), (90, 90, 90), 1, cv2.LINE_AA)
        if np.isfinite(uv[k]).all():
            cv2.drawMarker(img, pt(uv[k]), COLORS["model"], cv2.MARKER_CROSS, 12, 2)
            cv2.putText(
                img,
                str(name),
                (pt(uv[k])[0] + 6, pt(uv[k])[1] - 6),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.35,
                COLORS["model"],
                1,
                cv2.LINE_AA,
            )
    return img


def _tile(images: list, label: str):
    """Frames side by side at a common height, with a caption bar."""
    import cv2

    h = min(im.shape[0] for im in images)
    row = [cv2.resize(im, (int(round(im.shape[1] * h / im.shape[0])), h)) for im in images]
    out = np.concatenate(row, axis=1)
    cv2.putText(out, label, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
    return out


def run(cfg: DictConfig) -> dict:
    """Draw the figures; returns {"output_dir", "files": {name: path}, ...}."""

    tracks_path = required(cfg, "tracks", "plot")
    inp = cfg.get("input") or {}
    calib, det_dir = inp.get("calibration"), inp.get("detections")
    clip = parse_clip(cfg.get("clip"))
    video = cfg.get("video")
    if video and not calib:
        raise ValueError("video=DIR needs input.calibration=calibration.toml (to reproject)")
    if clip and not (video or cfg.get("video3d")):
        raise ValueError("clip=START:STOP needs video=DIR or video3d=true")
    if det_dir and not calib:
        raise ValueError("input.detections needs input.calibration=calibration.toml too")
    tr = read_points3d(tracks_path)  # a file without part columns is an error there
    parts = list(tr["parts"])
    points = tr["points"]
    T, K = points.shape[:2]
    chosen = _rows(tr["fnum"], to_plain(cfg.get("frames")) or [], T)
    fps = cfg.get("fps")
    fps = float(fps) if fps else None
    out = output_dir(cfg)
    files: dict[str, str] = {}

    def keep(name: str, fig) -> None:
        files[name] = str(plot.save(fig, out / f"{name}.png"))

    edges = plot.skeleton_edges(parts, points, cfg.get("skeleton"), detections=det_dir)
    title = Path(tracks_path).name
    keep("body3d", plot.body3d_figure(points, parts, fps=fps, title=title, edges=edges))
    sigma = None
    if all(f"{p}_sigma" in tr["extra"] for p in parts):
        sigma = np.stack([np.asarray(tr["extra"][f"{p}_sigma"], float) for p in parts], -1)
    keep("confidence", plot.confidence_figure(tr["ncams"], sigma, parts, fps=fps))

    cameras = load_calibration(str(calib)) if calib else None
    det = None
    per_camera = None
    error = tr["error"]
    if det_dir:
        # input.likelihood_threshold, input.pattern, input.individual: as in adjust-track
        _, det = load_scene(str(calib), str(det_dir), None, **load_kwargs(inp))
        missing = [p for p in parts if p not in det.parts]
        if missing:
            raise InputError(f"{det_dir}: the detection files have no part(s) {missing}")
        order = [list(det.parts).index(p) for p in parts]
        det_xy, det_lik = det.xy[:, order], det.likelihood[:, order]
        if len(det_xy) != T:
            raise InputError(
                f"{det_dir}: {len(det_xy)} frames of detections, {tracks_path}: {T} rows"
            )
        uv = _project(points, cameras)
        d = np.linalg.norm(det_xy - uv, axis=-1)  # (T, K, C)
        used_views = plot.load_accepted(tracks_path, parts, cameras)  # exact, when written
        if used_views is None or used_views.shape[0] != T:
            used_views = tr["ncams"]
        codes_all = plot.classify_detections(det_xy, det_lik, det.threshold, uv, used_views)
        used = np.where(codes_all == 1, d, np.nan)
        per_camera = {c.name: used[..., i] for i, c in enumerate(cameras)}
        if not np.isfinite(error).any():
            with np.errstate(invalid="ignore"):
                error = np.nanmean(np.where(np.isfinite(used), used, np.nan), axis=-1)
    keep("reprojection_error", plot.reprojection_error_figure(error, parts, per_camera, fps=fps))

    if det is not None:
        for f, r in chosen:
            keep(
                f"reprojection_frame{f}",
                plot.reprojection_figure(
                    f"frame {f}",
                    cameras,
                    det_xy[r],
                    det_lik[r],
                    det.threshold,
                    uv[r],
                    used_views[r],
                    parts,
                ),
            )

    if video:
        files.update(
            _videos(
                cfg,
                str(video),
                cameras,
                tr,
                parts,
                chosen,
                clip,
                out,
                det_xy if det is not None else None,
                codes_all if det is not None else None,
            )
        )
    if cfg.get("video3d"):  # the labelled 3D video beside each camera's reprojections
        files["video3d"] = str(
            tracks_video(
                out / "tracks3d.mp4",
                tr,
                cameras,
                fps=fps,
                clip=clip,
                videos=match_videos(str(video), cameras) if video else None,
                video_first_frame=int(cfg.get("video_first_frame") or 0),
                edges=edges,
            )
        )
    summary = {
        "tracks": str(tracks_path),
        "frames": T,
        "parts": parts,
        "calibration": str(calib) if calib else None,
        "detections": str(det_dir) if det_dir else None,
        "video": str(video) if video else None,
        "chosen_frames": [f for f, _ in chosen],
        "files": files,
    }
    write_text(out / "summary.json", json.dumps(finite_or_none(summary), indent=2) + "\n")
    log.info("%d figures -> %s", len(files), out)
    return {"output_dir": str(out), **summary}


def _videos(cfg, folder, cameras, tr, parts, chosen, clip, out, det_xy, codes) -> dict:
    """video_frame<F>.png per chosen frame and the optional MP4 clip."""
    import cv2

    videos = match_videos(folder, cameras)
    idx = [i for i, c in enumerate(cameras) if c.name in videos]
    caps = {cameras[i].name: cv2.VideoCapture(str(videos[cameras[i].name])) for i in idx}
    for name, cap in caps.items():
        if not cap.isOpened():
            raise InputError(f"{videos[name]}: cannot open the video (camera '{name}')")
    uv = _project(tr["points"], cameras)
    fn = np.asarray(tr["fnum"])
    offset = int(cfg.get("video_first_frame") or 0)
    files = {}

    def frame_image(f: int, r: int):
        imgs = []
        for i in idx:
            name = cameras[i].name
            img = _read_frame(caps[name], f - offset)
            if img is None:
                raise InputError(f"{videos[name]}: no frame {f} (camera '{name}')")
            draw_overlay(
                img,
                uv[r, :, i],
                parts,
                None if codes is None else codes[r, :, i],
                None if det_xy is None else det_xy[r, :, i],
            )
            imgs.append(img)
        return _tile(imgs, f"frame {f}")

    try:
        for f, r in chosen:
            path = out / f"video_frame{f}.png"
            ok, buf = cv2.imencode(".png", frame_image(f, r))
            if not ok:  # pragma: no cover - OpenCV encodes PNG
                raise RuntimeError(f"cannot encode {path}")
            with atomic_path(path) as tmp:
                Path(tmp).write_bytes(buf.tobytes())
            files[f"video_frame{f}"] = str(path)
        if clip:
            a, b = clip
            rows = (
                {int(v): i for i, v in enumerate(fn)} if np.issubdtype(fn.dtype, np.number) else {}
            )
            todo = [(f, rows[f]) for f in range(a, b) if f in rows]
            if not todo:
                raise InputError(f"clip={a}:{b}: none of these frames is in the tracks")
            fps = float(cfg.get("fps") or 0) or caps[cameras[idx[0]].name].get(cv2.CAP_PROP_FPS)
            fps = fps if fps and np.isfinite(fps) and fps > 0 else 30.0
            path = out / f"clip_{a}_{b}.mp4"
            with atomic_path(path) as tmp:
                first = frame_image(*todo[0])
                h, w = first.shape[:2]
                writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
                if not writer.isOpened():
                    raise RuntimeError(f"OpenCV cannot write an MP4 ({path})")
                try:
                    writer.write(first)
                    for f, r in todo[1:]:
                        writer.write(cv2.resize(frame_image(f, r), (w, h)))
                finally:
                    writer.release()
            files["clip"] = str(path)
            log.info("clip of %d frames -> %s", len(todo), path)
    finally:
        for cap in caps.values():
            cap.release()
    return files


@hydra.main(config_path=str(CONF_DIR), config_name="plot", version_base=None)
def _app(cfg: DictConfig) -> None:
    res = run_or_exit(run, cfg)
    print(f"{len(res['files'])} files written to {res['output_dir']}")


def main() -> None:
    _app()


if __name__ == "__main__":
    main()
