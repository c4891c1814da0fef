"""Axes from a calibration board (adjust.kinematics.board_frame): a synthetic board on a tilted
floor filmed by known cameras gives back the true floor frame (x along the first row, z up,
origin at corner 0) to a tight tolerance; too few cameras, corners on one line, a bent board and
a wrong square size are refused with one line; bad corner files name file and row; the frame
moves tracks (adjust.export.write_anipose) and works from adjust-export's config."""

from __future__ import annotations

from pathlib import Path

import hydra
import numpy as np
import pandas as pd
import pynwb
import pytest
import torch
from scipy.spatial.transform import Rotation

from adjust.apps.export import run as export_run
from adjust.camera import Camera, look_at_pose, project_points
from adjust.export import read_nwb_tracks, write_anipose, write_nwb
from adjust.io import InputError, read_points3d, save_calibration, write_points3d
from adjust.kinematics import (
    BoardConfig,
    BoardFrame,
    alignment_kwargs,
    apply_axes,
    board_corners,
    board_frame,
    board_frame_from_files,
    read_board_corners,
)
from deformnet.paths import CONF_DIR

ROWS, COLS, SQUARE = 5, 7, 30.0
BOARD = BoardConfig(detections="corners.csv", rows=ROWS, columns=COLS, square_mm=SQUARE)
# the board's pose in the calibration's world: a floor tilted by a few degrees, corner 0 away
# from the world origin
R_TRUE = Rotation.from_euler("zyx", [35.0, 6.0, -4.0], degrees=True).as_matrix()
T_TRUE = np.array([-60.0, 40.0, 15.0])
M_TRUE = R_TRUE.T  # rows: x along the first row, y along the first column, z the normal
CENTER_TRUE = R_TRUE.T @ T_TRUE


def _cameras(positions) -> list[Camera]:
    K = np.array([[1200.0, 0, 640], [0, 1200.0, 512], [0, 0, 1]])
    target = T_TRUE + R_TRUE @ np.array([COLS - 1, ROWS - 1, 0]) * SQUARE / 2
    cams = []
    for i, pos in enumerate(positions):
        R, t = look_at_pose(np.asarray(pos, float), target, up=(0, 1, 0), name=f"cam_{i}")
        cams.append(Camera.from_matrices(f"cam_{i}", K, R, t, size=(1280, 1024)))
    return cams


CAMS = _cameras([[400, -300, 700], [-450, -250, 650], [50, 500, 800]])


def _pixels(world: np.ndarray, cams, noise_px=0.0, drop=0.0, seed=0) -> np.ndarray:
    """(N, C, 2) pixels of world points (N, 3), with Gaussian noise and random drop-outs."""
    rng = np.random.default_rng(seed)
    X = torch.as_tensor(world)[:, None, :]
    out = []
    for c in cams:
        uv = project_points(
            X, torch.as_tensor(c.K), torch.as_tensor(c.R), torch.as_tensor(c.tvec)
        ).numpy()[:, 0]
        out.append(uv)
    xy = np.stack(out, 1) + rng.normal(0, noise_px, (len(world), len(cams), 2))
    xy[rng.random((len(world), len(cams))) < drop] = np.nan
    return xy


def _board_world(bend_mm=0.0, square=SQUARE) -> np.ndarray:
    m = board_corners(ROWS, COLS, square)
    m[:, 2] += bend_mm * (m[:, 0] > m[:, 0].mean())  # one half raised: a bent board
    return m @ R_TRUE.T + T_TRUE


def _angle_deg(A, B) -> float:
    return float(np.degrees(Rotation.from_matrix(A @ B.T).magnitude()))


def test_exact_corners_give_the_true_frame():
    f = board_frame(_pixels(_board_world(), CAMS), CAMS, BOARD)
    np.testing.assert_allclose(f.M, M_TRUE, atol=1e-9)
    np.testing.assert_allclose(f.center, CENTER_TRUE, atol=1e-6)
    assert f.corners == ROWS * COLS and f.plane_rms_mm < 1e-6 and f.fit_rms_mm < 1e-6
    assert f.square_mm_measured == pytest.approx(SQUARE, abs=1e-6)
    # the board's corner 0 goes to the origin, its first row along +x, the floor to z = 0
    Xb = apply_axes(_board_world(), f.M, f.center)
    np.testing.assert_allclose(Xb, board_corners(ROWS, COLS, SQUARE), atol=1e-6)


def test_noisy_partial_corners_give_the_frame_within_tolerance():
    """0.3 px noise, a fifth of the corners missing per camera: within 0.1 degree, 0.2 mm."""
    xy = _pixels(_board_world(), CAMS, noise_px=0.3, drop=0.2, seed=4)
    f = board_frame(xy, CAMS, BOARD)
    assert _angle_deg(f.M, M_TRUE) < 0.1
    np.testing.assert_allclose(f.M.T @ f.center, T_TRUE, atol=0.2)  # corner 0 in the world
    assert f.plane_rms_mm < 0.3 and f.fit_rms_mm < 0.5
    assert f.square_mm_measured == pytest.approx(SQUARE, abs=0.1)
    assert np.allclose(f.M @ f.M.T, np.eye(3)) and np.linalg.det(f.M) == pytest.approx(1.0)


def test_z_points_to_the_cameras_side():
    """The same board filmed from below (cameras under a glass floor): z still points to the
    cameras unless cameras_below says they are below; x stays along the first row."""
    below = _cameras([[400, -300, -700], [-450, -250, -650], [50, 500, -800]])
    xy = _pixels(_board_world(), below)
    up = board_frame(xy, below, BOARD)
    np.testing.assert_allclose(up.M[0], M_TRUE[0], atol=1e-9)
    np.testing.assert_allclose(up.M[2], -M_TRUE[2], atol=1e-9)
    flipped = board_frame(xy, below, BoardConfig(**{**BOARD.__dict__, "cameras_below": True}))
    np.testing.assert_allclose(flipped.M, M_TRUE, atol=1e-9)


@pytest.mark.parametrize(
    "case, match",
    [
        ("one_camera", "1 camera\\(s\\) see >= 4 corners"),
        ("one_row", "lie on one line"),
        ("bent", "not planar"),
        ("wrong_square", "off a 5 x 7 board of 25.0 mm squares"),
    ],
)
def test_refusals(case, match):
    board, world = BOARD, _board_world()
    xy = _pixels(world, CAMS)
    if case == "one_camera":
        xy[3:, 1:] = np.nan  # cameras 1, 2 see 3 corners each
    elif case == "one_row":
        xy[COLS:] = np.nan  # only the first row anywhere
    elif case == "bent":
        xy = _pixels(_board_world(bend_mm=8.0), CAMS)
    else:
        board = BoardConfig(detections="c.csv", rows=ROWS, columns=COLS, square_mm=25.0)
    with pytest.raises(InputError, match=match) as exc:
        board_frame(xy, CAMS, board)
    assert "\n" not in str(exc.value)


def _write_corners(path: Path, xy: np.ndarray, cams) -> Path:
    rows = [
        {"camera": c.name, "corner": k, "x": xy[k, i, 0], "y": xy[k, i, 1]}
        for i, c in enumerate(cams)
        for k in range(len(xy))
        if np.isfinite(xy[k, i]).all()
    ]
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


def test_read_board_corners_and_its_errors(tmp_path):
    xy = _pixels(_board_world(), CAMS, drop=0.3, seed=1)
    path = _write_corners(tmp_path / "corners.csv", xy, CAMS)
    got = read_board_corners(path, [c.name for c in CAMS], ROWS * COLS)
    np.testing.assert_allclose(got, xy, equal_nan=True)
    bad = {
        "camera,corner,x\ncam_0,0,1\n": "missing column",
        "camera,corner,x,y\ncam_9,0,1,2\n": "camera 'cam_9' at row 0 is not in the calibration",
        "camera,corner,x,y\ncam_0,35,1,2\n": "corner 35 at row 0 is not a corner",
        "camera,corner,x,y\ncam_0,1,1,2\ncam_0,1,3,4\n": "corner 1 is given twice",
        "camera,corner,x,y\ncam_0,1,a,2\n": "non-numeric",
    }
    for text, match in bad.items():
        p = tmp_path / "bad.csv"
        p.write_text(text)
        with pytest.raises(InputError, match=match) as exc:
            read_board_corners(p, [c.name for c in CAMS], ROWS * COLS)
        assert str(p) in str(exc.value)


def _tracks(tmp_path: Path, M0=None, c0=None) -> tuple[Path, np.ndarray]:
    """Tracks of two parts walking on the board (world frame, or already aligned by M0, c0)."""
    rng = np.random.default_rng(2)
    T = 20
    onboard = rng.uniform(0, 150, (T, 2, 3)) * [1, 1, 0.2]
    world = onboard @ R_TRUE.T + T_TRUE
    pts = world if M0 is None else apply_axes(world, M0, c0)
    path = write_points3d(
        tmp_path / "points3d.csv",
        ["nose", "tail"],
        pts,
        np.zeros((T, 2)),
        np.full((T, 2), 3),
        np.ones((T, 2)),
        M=M0,
        center=c0,
    )
    return path, onboard


@pytest.mark.parametrize("aligned", [False, True])
def test_board_aligns_tracks_through_the_config(tmp_path, aligned):
    """`alignment_kwargs` of an ``axes.board`` node, then write_anipose: the points are in the
    board's frame (also for tracks already aligned otherwise) and the axes columns hold the
    board's M, center."""
    calib = save_calibration(tmp_path / "calibration.toml", CAMS)
    corners = _write_corners(tmp_path / "corners.csv", _pixels(_board_world(), CAMS), CAMS)
    M0 = Rotation.from_euler("z", 50, degrees=True).as_matrix() if aligned else None
    c0 = np.array([5.0, -7.0, 2.0]) if aligned else None
    tracks, onboard = _tracks(tmp_path, M0, c0)
    node = {"x": None, "y": None, "z": None, "origin": None}
    node["board"] = {"detections": str(corners), "rows": ROWS, "columns": COLS, "square_mm": SQUARE}
    kw = alignment_kwargs(node, calib)
    assert isinstance(kw["axes"], BoardFrame)
    out = write_anipose(tmp_path / "aligned.csv", tracks, **kw)
    d = read_points3d(out)
    np.testing.assert_allclose(d["points"], onboard, atol=1e-5)
    np.testing.assert_allclose(d["M"], M_TRUE, atol=1e-9)
    np.testing.assert_allclose(d["center"], CENTER_TRUE, atol=1e-5)


def test_alignment_settings_refused(tmp_path):
    node = {"x": ["a", "b"], "board": {"detections": "c.csv", "rows": 3, "columns": 4}}
    with pytest.raises(ValueError, match="not both"):
        alignment_kwargs({**node, "board": {**node["board"], "square_mm": 20}}, None)
    with pytest.raises(ValueError, match="square_mm"):
        alignment_kwargs({"board": node["board"]}, None)
    with pytest.raises(ValueError, match="rows"):
        alignment_kwargs({"board": {"detections": "c.csv", "rows": 1, "columns": 4}}, None)
    with pytest.raises(InputError, match="needs calibration="):
        alignment_kwargs({"board": {**node["board"], "square_mm": 20}}, None)
    assert alignment_kwargs({"board": {"detections": None, "rows": None}}, None) == {}


def test_board_aligns_an_nwb_export(tmp_path):
    """write_nwb with a board's frame: the points are in the board's frame, the fit is in the
    file's notes, and the stored cameras still project the board's corners to their pixels."""
    calib = save_calibration(tmp_path / "calibration.toml", CAMS)
    xy = _pixels(_board_world(), CAMS)
    corners = _write_corners(tmp_path / "corners.csv", xy, CAMS)
    tracks, onboard = _tracks(tmp_path)
    board = BoardConfig(detections=str(corners), rows=ROWS, columns=COLS, square_mm=SQUARE)
    frame = board_frame_from_files(board, calib)
    path = write_nwb(
        tmp_path / "t.nwb",
        tracks,
        calibration=calib,
        fps=30.0,
        session_start_time="2026-03-01T09:30:00+00:00",
        axes=frame,
    )
    d = read_nwb_tracks(path)
    np.testing.assert_allclose(d["points"], onboard, atol=1e-5)
    model = torch.as_tensor(board_corners(ROWS, COLS, SQUARE))
    for i, c in enumerate(CAMS):
        cam = d["cameras"][c.name]
        uv = project_points(
            model, *(torch.as_tensor(cam[k], dtype=torch.float64) for k in ("K", "R", "t"))
        )
        np.testing.assert_allclose(uv.numpy(), xy[:, i], atol=1e-4)
    with pynwb.NWBHDF5IO(str(path), "r") as io:
        notes = io.read().notes
    assert "plane_rms_mm" in notes and "square_mm_measured" in notes


def test_adjust_export_takes_a_board(tmp_path):
    """adjust-export anipose with axes.board.* (Hydra's compose API, as the console script):
    the output is in the board's frame; a board without calibration is refused."""
    calib = save_calibration(tmp_path / "calibration.toml", CAMS)
    corners = _write_corners(tmp_path / "corners.csv", _pixels(_board_world(), CAMS), CAMS)
    tracks, onboard = _tracks(tmp_path)
    board = [
        f"axes.board.detections={corners}",
        f"axes.board.rows={ROWS}",
        f"axes.board.columns={COLS}",
        f"axes.board.square_mm={SQUARE}",
    ]
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra.compose(
            "export", ["format=anipose", f"tracks={tracks}", f"calibration={calib}", *board]
        )
        bare = hydra.compose("export", ["format=anipose", f"tracks={tracks}", *board])
    res = export_run(cfg)
    d = read_points3d(res["output"])
    np.testing.assert_allclose(d["points"], onboard, atol=1e-5)
    np.testing.assert_allclose(d["M"], M_TRUE, atol=1e-9)
    with pytest.raises(InputError, match="axes.board needs calibration="):
        export_run(bare)
