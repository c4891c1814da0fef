"""`adjust-plot`: figures of a user's own tracks (the shared real hand data), overlays on video
frames (tiny synthetic videos written here with cv2.VideoWriter) and an MP4 clip."""

from __future__ import annotations

import cv2
import hydra
import numpy as np
import pytest

from adjust.io import InputError, load_calibration, read_points3d
from deformnet.paths import CONF_DIR, real_hand_dir

PNG = b"\x89PNG\r\n\x1a\n"


def _compose(name, overrides):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose(name, overrides=overrides)


def _frames(path) -> int:
    """The number of frames OpenCV reads from a video file."""
    cap = cv2.VideoCapture(str(path))
    n = 0
    while cap.read()[0]:
        n += 1
    cap.release()
    return n


def _is_png(path) -> bool:
    with open(path, "rb") as fh:
        return fh.read(8) == PNG


@pytest.fixture(scope="module")
def hand_tracks(tmp_path_factory):
    from adjust.apps.triangulate import run

    d = real_hand_dir()
    assert (d / "calibration.toml").is_file(), f"shared real hand data missing: {d}"
    out = tmp_path_factory.mktemp("hand")
    run(
        _compose(
            "triangulate",
            [
                f"input.calibration={d / 'calibration.toml'}",
                f"input.detections={d / 'trial_000'}",
                f"output.dir={out}",
            ],
        )
    )
    return d, out / "points3d.csv"


def test_real_hand_data_figures(hand_tracks, tmp_path):
    from adjust.apps.plot import run

    d, tracks = hand_tracks
    res = run(
        _compose(
            "plot",
            [
                f"tracks={tracks}",
                f"input.calibration={d / 'calibration.toml'}",
                f"input.detections={d / 'trial_000'}",
                "frames=[0,200]",
                f"output.dir={tmp_path}",
            ],
        )
    )
    names = set(res["files"])
    assert names == {
        "body3d",
        "confidence",
        "reprojection_error",
        "reprojection_frame0",
        "reprojection_frame200",
    }
    for path in res["files"].values():
        assert _is_png(path), path
    assert res["frames"] == 513 and len(res["parts"]) == 21
    assert (tmp_path / "summary.json").is_file()


def test_tracks_alone_need_no_calibration(hand_tracks, tmp_path):
    import pandas as pd

    from adjust.apps.plot import run

    _, tracks = hand_tracks
    short = tmp_path / "points3d.csv"  # the first 40 frames, 5 parts: the same figures
    df = pd.read_csv(tracks).iloc[:40]
    keep = [
        c
        for c in df.columns
        if c.split("_")[0] in ("wrist", "thumb1", "index1", "ring1", "little1") or c == "fnum"
    ]
    df[keep].to_csv(short, index=False)
    res = run(_compose("plot", [f"tracks={short}", "fps=100", f"output.dir={tmp_path}"]))
    assert set(res["files"]) == {"body3d", "confidence", "reprojection_error"}
    assert res["frames"] == 40 and len(res["parts"]) == 5


def test_bad_arguments_are_clear_errors(hand_tracks, tmp_path):
    from adjust.apps.plot import parse_clip, run

    d, tracks = hand_tracks
    with pytest.raises(ValueError, match="clip=START:STOP needs video=DIR"):
        run(_compose("plot", [f"tracks={tracks}", "clip=1:5", f"output.dir={tmp_path}"]))
    with pytest.raises(ValueError, match="needs input.calibration"):
        run(_compose("plot", [f"tracks={tracks}", f"video={tmp_path}", f"output.dir={tmp_path}"]))
    with pytest.raises(InputError, match="frame 9999 is not in the tracks"):
        run(_compose("plot", [f"tracks={tracks}", "frames=[9999]", f"output.dir={tmp_path}"]))
    with pytest.raises(ValueError, match="START:STOP"):
        parse_clip("10-20")
    with pytest.raises(ValueError, match="0 <= START < STOP"):
        parse_clip("20:10")
    assert parse_clip("3:7") == (3, 7)


@pytest.fixture(scope="module")
def scene_with_videos(tmp_path_factory):
    """A 12-frame simulated scene, its DLT tracks, one small grey video per camera."""
    from adjust.apps.simulate import run as simulate
    from adjust.apps.triangulate import run as triangulate

    root = tmp_path_factory.mktemp("video")
    simulate(_compose("scene", ["num_frames=12", "seed=3", f"output.dir={root / 'scene'}"]))
    calib = root / "scene" / "calibration.toml"
    triangulate(
        _compose(
            "triangulate",
            [
                f"input.calibration={calib}",
                "body=mouse",
                f"input.detections={root / 'scene' / 'detections'}",
                f"output.dir={root / 'dlt'}",
            ],
        )
    )
    videos = root / "videos"
    videos.mkdir()
    for cam in load_calibration(calib):
        w, h = cam.size
        vw = cv2.VideoWriter(
            str(videos / f"session1_{cam.name}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (w, h)
        )
        assert vw.isOpened()
        for _ in range(12):
            vw.write(np.full((h, w, 3), 40, np.uint8))
        vw.release()
    return calib, root / "dlt" / "points3d.csv", videos


def _plot_scene(scene, out, *overrides) -> dict:
    """adjust-plot's `run` on the scene's tracks and calibration, with `overrides`, into `out`."""
    from adjust.apps.plot import run  # (as in the tests here: the app imported where it runs)

    calib, tracks, _ = scene
    base = [f"tracks={tracks}", f"input.calibration={calib}"]
    return run(_compose("plot", [*base, *overrides, f"output.dir={out}"]))


def test_video_overlay_and_clip(scene_with_videos, tmp_path):
    from adjust.apps.plot import COLORS, _project

    calib, tracks, videos = scene_with_videos
    res = _plot_scene(scene_with_videos, tmp_path, f"video={videos}", "frames=[4]", "clip=2:9")
    png = tmp_path / "video_frame4.png"
    assert res["files"]["video_frame4"] == str(png) and _is_png(png)
    img = cv2.imread(str(png))
    cams = load_calibration(calib)
    # the cameras side by side at a common height (all the same size here)
    assert img.shape[:2] == (cams[0].size[1], sum(c.size[0] for c in cams))
    # a reprojected part is drawn in the model colour at its pixel (first camera's panel)
    tr = read_points3d(tracks)
    uv = _project(tr["points"], cams)[4, :, 0]
    k = int(np.flatnonzero(np.isfinite(uv).all(-1))[0])
    u, v = np.round(uv[k]).astype(int)
    patch = img[v - 1 : v + 2, u - 1 : u + 2].reshape(-1, 3).astype(int)
    assert np.abs(patch - np.array(COLORS["model"])).sum(-1).min() < 60  # (mp4 colours shift)
    assert img[5:15, -15:-5].mean() < 60  # the grey background elsewhere
    clip = tmp_path / "clip_2_9.mp4"
    assert _frames(clip) == 7


def test_missing_video_frame_is_a_clear_error(scene_with_videos, tmp_path):
    from adjust.apps.plot import match_videos

    calib, _, videos = scene_with_videos
    assert set(match_videos(videos, load_calibration(calib))) == {"top", "side", "front"}
    short = tmp_path / "short"
    short.mkdir()
    (short / "top.mp4").write_bytes((videos / "session1_top.mp4").read_bytes())
    with pytest.raises(InputError, match=r"no frame 11 \(camera 'top'\)"):
        _plot_scene(
            scene_with_videos,
            tmp_path / "o",
            f"video={short}",
            "frames=[11]",
            "video_first_frame=-5",
        )
    with pytest.raises(InputError, match="no video"):
        match_videos(tmp_path / "o", load_calibration(calib))


def test_accepted_are_the_ncams_nearest_detections():
    from adjust.plot import classify_detections

    uv = np.zeros((2, 4, 2))  # 2 parts, 4 cameras, reprojections at the origin
    xy = np.array([[[1, 0], [50, 0], [0, 2], [3, 0]], [[1, 0], [np.nan, np.nan], [9, 0], [2, 0]]])
    lik = np.array([[0.9, 0.9, 0.9, 0.1], [0.9, 0.0, 0.9, 0.9]])
    codes = classify_detections(xy, lik, 0.5, uv, np.array([2, np.nan]))
    # part 0: camera 3 below the threshold; of the other three the 2 nearest are accepted
    assert codes[0].tolist() == [1, 2, 1, 0]
    # part 1: ncams unknown -> every present detection accepted; camera 1 missing
    assert codes[1].tolist() == [1, 0, 1, 1]
    batched = classify_detections(xy[None], lik[None], 0.5, uv[None], np.array([[2, np.nan]]))
    assert (batched[0] == codes).all()


def test_input_pattern_chooses_the_detection_files(scene_with_videos, tmp_path):
    """input.pattern (as in adjust-track, and as the loader's error suggests): a folder with two
    files per camera is ambiguous without it, read with it."""
    import shutil

    from adjust.apps.plot import run

    calib, tracks, _ = scene_with_videos
    det = tmp_path / "detections"
    shutil.copytree(calib.parent / "detections", det)
    for f in sorted(det.iterdir()):
        shutil.copy(f, det / f"{f.stem}_filtered{f.suffix}")
    base = [f"tracks={tracks}", f"input.calibration={calib}", f"input.detections={det}"]
    with pytest.raises(InputError, match="set a pattern"):
        run(_compose("plot", [*base, f"output.dir={tmp_path / 'a'}"]))
    cfg = _compose(
        "plot", [*base, "input.pattern='*_filtered.csv'", f"output.dir={tmp_path / 'b'}"]
    )
    res = run(cfg)
    assert any(k.startswith("reprojection_frame") for k in res["files"])
    assert _is_png(res["files"]["reprojection_error"])


def test_video3d_writes_the_labelled_3d_video(scene_with_videos, tmp_path):
    """adjust-plot video3d=true: tracks3d.mp4, one frame per row of the clip."""
    res = _plot_scene(scene_with_videos, tmp_path, "video3d=true", "clip=1:6")
    assert res["files"]["video3d"] == str(tmp_path / "tracks3d.mp4")
    assert _frames(res["files"]["video3d"]) == 5
