"""adjust.tracks_video.tracks_video: a labelled 3D video (MP4) of the tracks beside their 2D
reprojections (over the cameras' videos when given); skeletons for figures from a user's
skeleton.csv."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from adjust.camera import Camera
from adjust.io import read_points3d, write_points3d
from adjust.kinematics import align_tracks
from adjust.plot import skeleton_edges
from adjust.tracks_video import project_points, tracks_video

PARTS = ["nose", "head", "body", "tail"]
T = 12


def _cameras() -> list[Camera]:
    K = np.array([[400.0, 0, 160], [0, 400, 120], [0, 0, 1]])
    return [
        Camera("top", K, np.zeros(5), np.zeros(3), np.array([0, 0, 600.0]), (320, 240)),
        Camera("side", K, np.zeros(5), np.array([0.3, 0, 0]), np.array([0, 0, 650.0]), (320, 240)),
    ]


def _tracks(tmp_path):
    t = np.arange(T)[:, None]
    base = np.array([[30.0, 0, 0], [15, 0, 5], [0, 0, 5], [-30, 0, 0]])
    X = base[None] + np.concatenate([2 * t, np.sin(t), 0 * t], -1)[:, None]
    X[4, 0] = np.nan  # a part missing in one frame
    nan = np.full((T, len(PARTS)), np.nan)
    path = write_points3d(
        tmp_path / "points3d.csv", PARTS, X, nan, nan, nan, fnum=np.arange(T) + 100
    )
    return read_points3d(path)


def _videos(tmp_path, cams, frames: int = T + 100) -> dict:
    """One video per camera, grey frames 0 .. frames - 1 (the tracks' fnum are 100 ..)."""
    out = {}
    for cam in cams:
        path = tmp_path / f"{cam.name}_{frames}.mp4"
        w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30, cam.size)
        for f in range(frames):
            w.write(np.full((cam.size[1], cam.size[0], 3), 90 + f % 50, np.uint8))
        w.release()
        out[cam.name] = path
    return out


def _read(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    cap.release()
    return frames


def test_tracks_video_beside_reprojections(tmp_path):
    d = _tracks(tmp_path)
    cams = _cameras()
    skel = tmp_path / "skeleton.csv"
    skel.write_text("part_a,part_b\nnose,head\nhead,body\nbody,tail\n")
    path = tracks_video(
        tmp_path / "out" / "tracks3d.mp4",
        d,
        cams,
        fps=30,
        clip=(102, 110),
        videos=_videos(tmp_path, cams),
        video_first_frame=0,
        skeleton=skel,
        size=(640, 360),
    )
    frames = _read(path)
    assert len(frames) == 8 and frames[0].shape == (360, 640, 3)
    assert not np.array_equal(frames[0], frames[-1])  # the body moves, the labels change
    # the 3D view alone, every row, no calibration
    alone = _read(tracks_video(tmp_path / "alone.mp4", d, size=(320, 240)))
    assert len(alone) == T and alone[0].shape == (240, 320, 3)
    with pytest.raises(ValueError, match="clip=0:5: none of these frames"):
        tracks_video(tmp_path / "x.mp4", d, clip=(0, 5))
    short = _videos(tmp_path, cams, frames=105)
    with pytest.raises(ValueError, match="no frame 105"):
        tracks_video(tmp_path / "x.mp4", d, cams, clip=(103, 107), videos=short)
    assert not (tmp_path / "x.mp4").exists()


def test_aligned_tracks_reproject_where_the_world_points_do(tmp_path):
    d = _tracks(tmp_path)
    cam = _cameras()[1]
    a = align_tracks(d, {"x": ["tail", "nose"], "y": ["body", [0, 50, 5]]})
    # tracks_video moves aligned points back with M and center before reprojecting
    back = (a["points"] + a["center"]) @ a["M"]
    np.testing.assert_allclose(
        project_points(back, cam), project_points(d["points"], cam), atol=1e-9, equal_nan=True
    )


def test_skeleton_for_figures(tmp_path):
    d = _tracks(tmp_path)
    skel = tmp_path / "skeleton.csv"
    skel.write_text("part_a,part_b\nnose,head\nhead,tail\n")
    assert skeleton_edges(PARTS, d["points"], skeleton=skel) == [(0, 1), (1, 3)]
    assert skeleton_edges(PARTS, d["points"], edges=[["body", "tail"]]) == [(2, 3)]
    assert len(skeleton_edges(PARTS, d["points"])) == 3  # spanning tree
