"""Robustness: defective inputs through every console script, as a user runs them.

A small simulated scene (default rig: 3 cameras; `adjust-simulate`, with ground truth) is
copied and spoilt in a fixed list of ways (detections, calibration, settings, outputs,
checkpoints), plus the shared real SLEAP mouse whose `side` camera has a wrong pose, and run
through adjust-triangulate and adjust-track; the other console scripts (adjust-simulate,
adjust-calibrate, adjust-events, adjust-export, adjust-plot, adjust-demo, deformnet-simulate,
deformnet-train, deformnet-classify) get their own defective inputs and settings (issue 46's
among them: tracks without rows, more than 255 parts, bouts mixing text and numbers, labelled
images, frame numbers beyond int64, unusable output folders, FIFOs and devices, absurd thread
counts and noise levels). Every case runs as a subprocess. Per case the table shows the exit
code, whether a traceback appeared, and the result: for adjust-triangulate and adjust-track
whether ``points3d.csv`` was written and whether it holds empty or absurd values (no finite
point at all; a coordinate beyond 10 m; RMSE against the ground truth, matched by ``fnum``,
above 25 mm or 3x the clean run's); for a case that must be refused, that it was; for one that
must work, that its output is there.

*Silent wrong result*: exit 0 with empty or absurd output, or exit 0 where the input must be
refused (a one-camera session, ``stochastic.sigma_det_px=1e-9``), or exit 0 without the output.
*Lost data*: a run killed (SIGKILL at a random moment), interrupted (Ctrl-C) or refused (a
second run into a busy ``output.dir``) after a complete earlier run, whose folder then holds
neither the earlier run whole nor the new one (a summary that does not describe the files
beside it, files of two runs, no summary); an interrupted run must exit 130, a refused one 2.
Targets: zero tracebacks, zero silent wrong results, zero lost data, no code run from a data
file, nothing in the working directory. Last line JSON (counts), also written to
runs/benchmarks/robustness.json.

    .venv/bin/python benchmarks/robustness.py [--jobs 2] [--frames 100] [--only 'NAME;...']
        [--groups inputs,scripts,lost,chunks]

``--groups``: ``inputs`` (the defective sessions through adjust-triangulate and adjust-track),
``scripts`` (the other console scripts), ``lost`` (killed, interrupted and concurrent runs),
``chunks`` (adjust-track on a 300-frame session in 128-frame chunks: NWB output, two of three
cameras out for a chunk, one camera throughout, a net mode, bad NWB settings, killed and
interrupted re-runs).
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import json
import logging
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from common import emit

from adjust.pixels import edit_map
from adjust.scene.defective import defective_tracks, tracks_file
from deformnet.paths import CONF_DIR, shared_dir

log = logging.getLogger("benchmarks.robustness")
BIN = Path(sys.executable).parent
APPS = ("adjust-triangulate", "adjust-track")
#: every console script (pyproject.toml's [project.scripts])
SCRIPTS = (
    "adjust-simulate",
    "adjust-triangulate",
    "adjust-track",
    "adjust-calibrate",
    "adjust-events",
    "adjust-export",
    "adjust-plot",
    "adjust-demo",
    "deformnet-simulate",
    "deformnet-train",
    "deformnet-classify",
)
GROUPS = ("inputs", "scripts", "lost", "chunks")
TRACK_FAST = ["progress=false", "solver.max_iterations=8"]
CAMERAS = ("top", "side", "front")  # the default rig's
ENV = {**os.environ, "HYDRA_FULL_ERROR": "0"}
#: the outputs of adjust-triangulate / adjust-track that must belong to one run
OUTPUT_NAMES = (
    "points3d.csv",
    "points3d.extra.csv",
    "summary.json",
    "accepted.npz",
    "tokens.npz",
    "tracks.nwb",
)


# --- the scene and its spoilt copies -------------------------------------------------------


def simulate(folder: Path, frames: int) -> Path:
    import hydra

    from adjust.apps.simulate import run

    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra.compose("scene", [f"output.dir={folder}", f"num_frames={frames}", "seed=5"])
    run(cfg)
    return folder


def _read(path: Path) -> list[list[str]]:
    return [ln.split(",") for ln in path.read_text().splitlines()]


def _write(path: Path, rows: list[list[str]]) -> None:
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")


def _rewrite(folder: Path, cam: str, edit: Callable[[list[list[str]]], list[list[str]]]) -> None:
    """Rewrite a camera's detections CSV as edit(rows) (its rows: 3 header rows, then frames)."""
    p = folder / "detections" / f"{cam}.csv"
    _write(p, edit(_read(p)))


def _no_detections(rows: list[list[str]], a: int = 0, b: int | None = None) -> list[list[str]]:
    """The rows with the detections of frames a..b-1 (default: every frame) empty (frame
    index kept)."""
    b = len(rows) - 3 if b is None else b
    blank = [[r[0]] + [""] * (len(r) - 1) for r in rows[3 + a : 3 + b]]
    return rows[: 3 + a] + blank + rows[3 + b :]


def _reversed_frames(rows: list[list[str]]) -> list[list[str]]:
    """The rows with the frames (index and detections) in reverse order."""
    return rows[:3] + rows[3:][::-1]


def _reversed_detections(rows: list[list[str]]) -> list[list[str]]:
    """The rows with the detections in reverse frame order, the frame index kept."""
    body = rows[3:]
    data = [r[1:] for r in body][::-1]
    return rows[:3] + [[r[0], *d] for r, d in zip(body, data)]


def _without_likelihood(rows: list[list[str]]) -> list[list[str]]:
    """The rows without their likelihood columns (named in the third header row)."""
    keep = [j for j, c in enumerate(rows[2]) if c != "likelihood"]
    return [[r[j] for j in keep] for r in rows]


def _cell(folder: Path, cam: str, row: int, col: int, value: str) -> None:
    """Set a data cell (row 0 = first frame, col 0 = first data column) of a camera's CSV."""
    p = folder / "detections" / f"{cam}.csv"
    rows = _read(p)
    rows[3 + row][1 + col] = value
    _write(p, rows)


def _column(folder: Path, cam: str, col: int, fn: Callable[[str], str]) -> None:
    p = folder / "detections" / f"{cam}.csv"
    rows = _read(p)
    for r in rows[3:]:
        r[1 + col] = fn(r[1 + col])
    _write(p, rows)


def _toml(folder: Path, old: str, new: str, count: int = 1) -> None:
    p = folder / "calibration.toml"
    text = p.read_text()
    assert old in text, old
    p.write_text(text.replace(old, new, count))


def _cams(folder: Path):
    from adjust.io import load_calibration

    return load_calibration(folder / "calibration.toml")


def _save(folder: Path, cams) -> None:
    from adjust.io import save_calibration

    save_calibration(folder / "calibration.toml", cams)


def _replace_camera(folder: Path, index: int, **fields) -> None:
    """Change fields (K, dist, ...) of the calibration's camera `index`."""
    import dataclasses

    cams = _cams(folder)
    cams[index] = dataclasses.replace(cams[index], **fields)
    _save(folder, cams)


def _likelihoods(folder: Path, fn: Callable[[float], float], cams=CAMERAS):
    for cam in cams:
        p = folder / "detections" / f"{cam}.csv"
        rows = _read(p)
        for r in rows[3:]:
            for j in range(3, len(r), 3):
                if r[j] != "":
                    r[j] = repr(fn(float(r[j])))
        _write(p, rows)


def _rotate_camera(folder: Path, name: str, degrees: float) -> None:
    import dataclasses

    cams = _cams(folder)
    i = [c.name for c in cams].index(name)
    a = np.radians(degrees)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    from adjust.camera import Camera

    c = cams[i]
    new = Camera.from_matrices(name, c.K, Rz @ c.R, Rz @ c.tvec, c.dist, c.size)
    cams[i] = dataclasses.replace(new, extra=c.extra)
    _save(folder, cams)


def _flip_camera(folder: Path, name: str) -> None:
    from adjust.camera import Camera

    cams = _cams(folder)
    i = [c.name for c in cams].index(name)
    c = cams[i]
    flip = np.diag([-1.0, 1.0, -1.0])
    cams[i] = Camera.from_matrices(name, c.K, flip @ c.R, flip @ c.tvec, c.dist, c.size)
    _save(folder, cams)


def _in_metres(folder: Path, declared: bool) -> None:
    """The calibration's translations in metres, with ``[metadata] units = "m"`` or none."""
    import re

    p = folder / "calibration.toml"
    text = re.sub(
        r"translation = \[([^\]]*)\]",
        lambda m: "translation = " + repr([float(v) / 1000 for v in m.group(1).split(",")]),
        p.read_text(),
    )
    if declared:
        text = text.replace("[metadata]\n", '[metadata]\nunits = "m"\n', 1)
        if 'units = "m"' not in text:
            text += '\n[metadata]\nunits = "m"\n'
    p.write_text(text)


def _turn_camera(folder: Path, name: str, degrees: float) -> None:
    """Camera `name` turned (a pan) by `degrees` from the session's middle frame on: its
    detections from there are the turned camera's; its calibration stays (a bumped camera)."""
    from scipy.spatial.transform import Rotation

    from adjust.io import read_dlc, write_dlc_csv
    from adjust.moves import unrotate

    cam = next(c for c in _cams(folder) if c.name == name)
    p = folder / "detections" / f"{name}.csv"
    t = read_dlc(p)
    xy, half = t.xy.copy(), len(t.xy) // 2
    turn = Rotation.from_rotvec(np.radians(degrees) * np.array([0.0, 1.0, 0.0])).as_matrix()
    xy[half:] = unrotate(t.xy[half:], cam, turn)
    write_dlc_csv(p, t.parts, xy, t.likelihood)


def _double_rate(rows: list[list[str]]) -> list[list[str]]:
    """A detection file's rows as a camera at twice the rate films them: each frame twice,
    numbered 2 f and 2 f + 1."""
    body = [[str(2 * int(r[0]) + k), *r[1:]] for r in rows[3:] for k in (0, 1)]
    return rows[:3] + body


def _sides_swapped(rows: list[list[str]]) -> list[list[str]]:
    """A detection file's rows with its left/right parts named the other way round (the
    bodyparts header row's names exchanged: ``left_x`` <-> ``right_x``)."""
    swap = {"left": "right", "right": "left"}
    head = [
        "_".join(swap.get(w, w) for w in c.split("_")) if i else c for i, c in enumerate(rows[1])
    ]
    return [rows[0], head, *rows[2:]]


def _pixels(fn: Callable[[np.ndarray], np.ndarray]) -> Callable[[list[list[str]]], list[list[str]]]:
    """A rows edit: every detection's (x, y) px as ``fn`` maps it (a detection with an empty
    cell left as it is)."""

    def edit(rows: list[list[str]]) -> list[list[str]]:
        xs = [j for j, c in enumerate(rows[2]) if c == "x"]
        out = [list(r) for r in rows]
        for r in out[3:]:
            for j in xs:
                if j + 1 < len(r) and r[j].strip() and r[j + 1].strip():
                    xy = fn(np.array([float(r[j]), float(r[j + 1])]))
                    r[j], r[j + 1] = repr(float(xy[0])), repr(float(xy[1]))
        return out

    return edit


def _edited_video(f: Path, cam: str, how: str) -> None:
    """Camera `cam`'s detections as made on its video flipped or turned `how` (`adjust.pixels`:
    the inverse of the check's map x = A u + d, u = A^T (x - d))."""
    A, d = (np.array(v) for v in edit_map(how, next(c for c in _cams(f) if c.name == cam).size))
    _rewrite(f, cam, _pixels(lambda xy: (xy - d) @ (A if A.ndim == 2 else np.diag(A))))


def _undistorted_video(f: Path, cam: str, k1: float = -1.0) -> None:
    """Every camera given a lens of barrel distortion `k1` (the calibration's, and the detections
    distorted as it shows them), except camera `cam`'s detections: as on its video undistorted
    before the pose estimator (cv2.undistort), the calibration keeping the lens
    (`adjust.lens`)."""
    import dataclasses

    import torch

    from adjust.distortion import distort_points

    cams = [dataclasses.replace(c, dist=np.array([k1, 0.0, 0.0, 0.0, 0.0])) for c in _cams(f)]
    _save(f, cams)
    for c in cams:
        if c.name != cam:
            K, d = torch.as_tensor(c.K), torch.as_tensor(c.dist)
            lens = _pixels(lambda xy, K=K, d=d: distort_points(torch.as_tensor(xy), K, d).numpy())
            _rewrite(f, c.name, lens)


def _renumber(folder: Path, cam: str, fn: Callable[[int], int]) -> None:
    p = folder / "detections" / f"{cam}.csv"
    rows = _read(p)
    for r in rows[3:]:
        r[0] = str(fn(int(r[0])))
    _write(p, rows)


class _Payload:
    def __reduce__(self):
        return (os.system, ("touch /tmp/mousetrack-robustness-pwned",))


def _payload_checkpoint(folder: Path) -> Path:
    import torch

    p = folder / "shared.ckpt"
    torch.save({"deformation_model": {"x": _Payload()}}, p)
    return p


def cases(base: Path) -> list[tuple[str, Callable[[Path], list[str]], tuple[str, ...], str]]:
    """(name, spoil(folder) -> extra overrides, apps, expect). The folder is a fresh copy of
    `base`; expect: "judge" (exit 0 must come with sound tracks; a refusal is fine) or "error"
    (the input must be refused: exit 0 is a silent wrong result)."""
    both = APPS
    track = ("adjust-track",)
    tri = ("adjust-triangulate",)
    out = []

    def case(name, apps=both, expect="judge"):
        """A case whose function spoils the folder and returns its overrides (None: none)."""

        def deco(fn):
            out.append((name, lambda f: fn(f) or [], apps, expect))
            return fn

        return deco

    def setting(name, override=None, apps=both, expect="judge"):
        """A case that only gives an override (`name` itself by default)."""
        out.append((name, lambda f: [override or name], apps, expect))

    def cell(name, cam, row, col, value):
        """A case that only writes `value` into one cell of a camera's detections (`_cell`)."""
        out.append((name, lambda f: _cell(f, cam, row, col, value) or [], both, "judge"))

    def rewrite(name, cams, edit, expect="judge"):
        """A case that only rewrites the rows of each of `cams`' detection files (`_rewrite`)."""

        def spoil(f):
            for cam in cams:
                _rewrite(f, cam, edit)
            return []

        out.append((name, spoil, both, expect))

    @case("clean")
    def _(f):
        pass

    cell("one cell x=1e200", "top", 10, 0, "1e200")

    @case("one part at 1e160 in every camera")
    def _(f):
        for cam in CAMERAS:
            _column(f, cam, 0, lambda v: "1e160" if v else v)
            _column(f, cam, 1, lambda v: "1e160" if v else v)

    cell("inf cell", "side", 5, 3, "inf")

    @case("likelihood 50 on some detections")
    def _(f):
        _likelihoods(f, lambda v: 50.0 if v < 0.7 else v)

    cell("negative likelihood", "front", 3, 2, "-0.5")

    @case("all likelihoods 0")
    def _(f):
        _likelihoods(f, lambda v: 0.0)

    setting("likelihood_threshold=2", "input.likelihood_threshold=2")
    setting("likelihood_threshold=abc", "input.likelihood_threshold=abc")

    @case("empty detections folder")
    def _(f):
        for p in (f / "detections").iterdir():
            p.unlink()

    @case("a camera's file missing")
    def _(f):
        (f / "detections" / "front.csv").unlink()

    @case("stray file in the folder")
    def _(f):
        (f / "detections" / "notes.csv").write_text("a,b\n1,2\n")

    @case("truncated row")
    def _(f):
        p = f / "detections" / "top.csv"
        rows = _read(p)
        rows[20] = rows[20][:7]
        _write(p, rows)

    cell("non-numeric cell", "side", 7, 1, "abc")
    rewrite("header rows only", CAMERAS, lambda rows: rows[:3])
    rewrite("one file truncated (fewer frames)", ("side",), lambda rows: rows[:-30])

    @case("one file's frame numbers offset by 1000")
    def _(f):
        _renumber(f, "front", lambda i: i + 1000)

    @case("one camera 4 frames out of step (its video started early)")
    def _(f):
        _renumber(f, "front", lambda i: i + 4)

    rewrite("one camera at twice the others' frame rate", ("front",), _double_rate)
    rewrite("one camera's left and right named the other way round", ("side",), _sides_swapped)

    @case("one camera's video flipped left to right")
    def _(f):
        _edited_video(f, "front", "left to right")

    @case("one camera's video turned a quarter turn clockwise")
    def _(f):
        _edited_video(f, "front", "a quarter turn clockwise")

    rewrite("one camera's x and y columns swapped", ("side",), _pixels(lambda xy: xy[::-1]))

    @case("one camera's video undistorted, the calibration keeping its lens")
    def _(f):
        _undistorted_video(f, "front")

    @case("one camera turned 1 deg mid-session (bumped)")
    def _(f):
        _turn_camera(f, "front", 1.0)

    @case("calibration in metres, no units", expect="error")
    def _(f):
        _in_metres(f, declared=False)

    @case("calibration in metres, units = m")
    def _(f):
        _in_metres(f, declared=True)

    @case("duplicate frame number")
    def _(f):
        p = f / "detections" / "top.csv"
        rows = _read(p)
        rows[5][0] = rows[4][0]
        _write(p, rows)

    rewrite("one camera's rows reversed", ("side",), _reversed_detections)

    rewrite("one camera's rows in reverse order, frame index too", ("side",), _reversed_frames)

    @case("two camera files swapped")
    def _(f):
        d = f / "detections"
        (d / "side.csv").rename(d / "tmp.csv")
        (d / "front.csv").rename(d / "side.csv")
        (d / "tmp.csv").rename(d / "front.csv")

    @case("binary garbage as a detection file")
    def _(f):
        (f / "detections" / "top.csv").write_bytes(bytes(range(256)) * 16)

    @case("unknown part name (body=mouse)", track)
    def _(f):
        p = f / "detections" / "top.csv"
        rows = _read(p)
        rows[1] = [c.replace("nose_tip", "whisker") for c in rows[1]]
        _write(p, rows)

    rewrite("all detections of one camera empty", ("front",), _no_detections)
    rewrite("every detection empty", CAMERAS, _no_detections)

    @case("CRLF line endings and a BOM")
    def _(f):
        p = f / "detections" / "top.csv"
        p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes().replace(b"\n", b"\r\n"))

    @case("focal length 0")
    def _(f):
        K = _cams(f)[0].K.copy()
        K[0, 0] = K[1, 1] = 0.0
        _replace_camera(f, 0, K=K)

    @case("negative focal length")
    def _(f):
        K = _cams(f)[1].K.copy()
        K[0, 0] = -K[0, 0]
        _replace_camera(f, 1, K=K)

    @case("K third row not [0, 0, 1]")
    def _(f):
        K = _cams(f)[2].K.copy()
        K[2] = [0.0, 0.001, 1.0]
        _replace_camera(f, 2, K=K)

    @case("distortion k1 = 1e6")
    def _(f):
        _replace_camera(f, 0, dist=np.array([1e6, 0, 0, 0, 0.0]))

    @case("all cameras at one pose")
    def _(f):
        import dataclasses

        cams = _cams(f)
        cams = [dataclasses.replace(c, rvec=cams[0].rvec, tvec=cams[0].tvec) for c in cams]
        _save(f, cams)

    @case("a camera with the scene behind it")
    def _(f):
        _flip_camera(f, "front")

    @case("one camera's pose off by 8 degrees")
    def _(f):
        _rotate_camera(f, "side", 8.0)

    @case("binary calibration file")
    def _(f):
        (f / "calibration.toml").write_bytes(bytes(range(256)) * 8)

    @case("a directory as the calibration")
    def _(f):
        return [f"input.calibration={f / 'detections'}"]

    @case("calibration file missing")
    def _(f):
        (f / "calibration.toml").unlink()

    @case("calibration lacks a camera")
    def _(f):
        _save(f, _cams(f)[:2])

    @case("calibration has a camera without a file")
    def _(f):
        import dataclasses

        cams = _cams(f)
        extra = dataclasses.replace(cams[0], name="back", tvec=cams[0].tvec + 100.0)
        _save(f, [*cams, extra])

    @case("fisheye flag with 5 distortion coefficients")
    def _(f):
        _toml(f, 'name = "top"', 'name = "top"\nfisheye = true')

    @case("fisheye flag on a pinhole camera (4 coefficients)")
    def _(f):
        _replace_camera(f, 0, fisheye=True)

    @case("calibration is not TOML")
    def _(f):
        (f / "calibration.toml").write_text("this is [not toml\n")

    for name in (
        "solver.max_iterations=abc",
        "solver.max_iterations=2.5",
        "solver.max_iterations=-3",
        "solver.chunk_size=abc",
        "threads=abc",
    ):
        setting(name, apps=track)
    setting("triangulate.min_views=abc", apps=tri)
    setting("input.camera_check=bogus")
    setting("input.exclude_cameras=[nope]")
    setting("input.exclude_cameras=[side] (by hand)", "input.exclude_cameras=[side]")

    @case("output.dir is a file")
    def _(f):
        (f / "afile").write_text("x")
        return [f"output.dir={f / 'afile'}"]

    @case("output.dir not writable")
    def _(f):
        return ["output.dir=/proc/mousetrack/out"]

    setting("deformation=/etc/passwd", apps=track)

    @case("deformation checkpoint with a pickle payload", track)
    def _(f):
        return [f"deformation={_payload_checkpoint(f)}"]

    # --- issue 46 ---------------------------------------------------------------------------
    rewrite("only one camera has detections", ("side", "front"), _no_detections, "error")

    @case("one camera's likelihoods all below the threshold")
    def _(f):
        _likelihoods(f, lambda v: 0.1, cams=("front",))

    @case("empty likelihood cells (x, y given) in one camera")
    def _(f):
        _column(f, "top", 2, lambda v: "")
        _column(f, "top", 5, lambda v: "")

    rewrite("no likelihood column in one camera", ("side",), _without_likelihood)

    @case("frame number beyond int64", expect="error")
    def _(f):
        _renumber(f, "top", lambda i: i if i < 50 else i + 10**23)

    @case("a FIFO as the calibration", expect="error")
    def _(f):
        os.mkfifo(f / "fifo.toml")
        return [f"input.calibration={f / 'fifo.toml'}"]

    setting("/dev/zero as the calibration", "input.calibration=/dev/zero", expect="error")
    for name in (
        "stochastic.sigma_det_px=1e-9",
        "stochastic.sigma_det_px=-2",
        "solver.sigma_det_px=0",
        "threads=100000",
        "threads=0",
        "deform.threads=-1",
    ):
        setting(name, apps=track, expect="error")
    return out


# --- the other console scripts -----------------------------------------------------------------


@dataclass
class Job:
    """One subprocess run. expect: "judge" (adjust-triangulate / adjust-track: the tracks in
    `out` judged), "error" (must be refused: exit 2), "ok" (must work: exit 0 and `check()`);
    mode: "run"; "session" (args: calibration, detections, overrides: `run_case`); for lost
    data "kill" / "sigint" / "busy" (after a clean run into `out`)."""

    name: str
    app: str
    args: list[str]
    expect: str = "judge"
    out: Path | None = None
    truth: dict | None = None
    check: Callable[[], bool] | None = None
    mode: str = "run"
    again: list[str] = field(default_factory=list)  # lost data: the second run's overrides


def _calibrate_inputs(base: Path, folder: Path, points: int = 10, plane: bool = False) -> None:
    """Known 3D points and their images in each camera of `base`'s calibration (name,x,y,z and
    one name,u,v CSV per camera)."""
    import torch

    from adjust.camera import CameraTensors, project_cameras

    cams = _cams(base)
    rng = np.random.default_rng(points)
    X = rng.uniform(-150, 150, (points, 3)) + np.array([0.0, 0.0, 40.0])
    if plane:
        X[:, 2] = 0.0
    uv = project_cameras(torch.as_tensor(X), CameraTensors.from_cameras(cams, torch.float64))
    uv = uv.numpy()  # (N, C, 2)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "points3d.csv").write_text(
        "name,x,y,z\n" + "".join(f"q{i},{a},{b},{c}\n" for i, (a, b, c) in enumerate(X.tolist()))
    )
    (folder / "2d").mkdir(exist_ok=True)
    for c, cam in enumerate(cams):
        (folder / "2d" / f"{cam.name}.csv").write_text(
            "name,u,v\n" + "".join(f"q{i},{u},{v}\n" for i, (u, v) in enumerate(uv[:, c].tolist()))
        )


def script_jobs(work: Path, base: Path) -> list[Job]:
    """Defective inputs and settings of the console scripts other than adjust-triangulate and
    adjust-track (and their issue-46 cases that need no session copy)."""
    jobs: list[Job] = []
    d = work / "scripts"
    d.mkdir()
    (d / "afile").write_text("x")
    tracks = tracks_file(
        d / "tracks.csv", 8, T=60, names=list(np.load(base / "truth.npz")["parts"]), seed=8
    )
    bad = defective_tracks(d, tracks, T=30)
    empty, big, labelled, huge, bouts = (
        bad[k] for k in ("empty", "big", "labelled", "huge", "bouts")
    )
    ckpt = _payload_checkpoint(d)
    nwb = ["fps=100", "session_start_time=2026-01-01T00:00:00", "subject.subject_id=m1",
           "subject.species=Mus musculus", "subject.sex=F", "subject.age=P90D"]  # fmt: skip
    mech = "mechanisms={lever: [0.0, 0.0, 0.0]}"
    o = d / "out"

    def job(name, app, args, expect="error", check=None):
        jobs.append(Job(name, app, [str(a) for a in args], expect, check=check))

    def works(name, app, args, *outputs):
        """A job that must work (exit 0) and write each of `outputs`."""
        job(name, app, args, "ok", lambda: all(Path(p).is_file() for p in outputs))

    # adjust-simulate
    works(
        "simulate: a small scene",
        "adjust-simulate",
        [f"output.dir={o}/sim", "num_frames=20"],
        o / "sim" / "calibration.toml",
        o / "sim" / "detections" / "top.csv",
    )
    job("simulate: num_frames=-5", "adjust-simulate", [f"output.dir={o}/sim2", "num_frames=-5"])
    job("simulate: output.dir is a file", "adjust-simulate", [f"output.dir={d}/afile"])
    # adjust-calibrate
    _calibrate_inputs(base, d / "cal")
    _calibrate_inputs(base, d / "plane", plane=True)
    cal = [f"input.points3d={d}/cal/points3d.csv", f"input.points2d={d}/cal/2d",
           "input.size=[1280,1024]"]  # fmt: skip
    works(
        "calibrate: known points",
        "adjust-calibrate",
        [*cal, f"output.dir={o}/cal"],
        o / "cal" / "calibration.toml",
    )
    job("calibrate: points in one plane", "adjust-calibrate",
        [f"input.points3d={d}/plane/points3d.csv", f"input.points2d={d}/plane/2d",
         "input.size=[1280,1024]", f"output.dir={o}/cal2"])  # fmt: skip
    job("calibrate: /dev/zero as the 3D points", "adjust-calibrate",
        ["input.points3d=/dev/zero", f"input.points2d={d}/cal/2d", "input.size=[1280,1024]",
         f"output.dir={o}/cal3"])  # fmt: skip
    # adjust-events
    works(
        "events: tracks",
        "adjust-events",
        [f"tracks={tracks}", mech, f"output.dir={o}/ev"],
        o / "ev" / "events.csv",
    )
    ev = f"output.dir={o}/ev2"
    job("events: tracks without rows", "adjust-events", [f"tracks={empty}", mech, ev])
    job("events: labelled images", "adjust-events", [f"tracks={labelled}", "parts=[p0]", mech, ev])
    job("events: frame number beyond int64", "adjust-events", [f"tracks={huge}", mech, ev])
    job("events: no mechanisms", "adjust-events", [f"tracks={tracks}", ev])
    job("events: /dev/zero as tracks", "adjust-events", ["tracks=/dev/zero", mech, ev])
    job("events: inferred.below=2", "adjust-events", [f"tracks={tracks}", mech, "inferred.below=2",
        ev])  # fmt: skip
    # adjust-export
    works(
        "export: nwb",
        "adjust-export",
        ["nwb", f"tracks={tracks}", *nwb, f"output={o}/t.nwb"],
        o / "t.nwb",
    )
    works(
        "export: more than 255 parts (nwb)",
        "adjust-export",
        ["nwb", f"tracks={big}", *nwb, f"output={o}/big.nwb"],
        o / "big.nwb",
    )
    works(
        "export: bouts mixing text and numbers",
        "adjust-export",
        ["nwb", f"tracks={tracks}", *nwb, f"bouts={bouts}", f"output={o}/b.nwb"],
        o / "b.nwb",
    )
    job("export: tracks without rows", "adjust-export", ["anipose", f"tracks={empty}",
        f"output={o}/e.csv"])  # fmt: skip
    job("export: frame number beyond int64", "adjust-export", ["nwb", f"tracks={huge}", *nwb,
        f"output={o}/h.nwb"])  # fmt: skip
    job("export: unknown format", "adjust-export", ["xlsx", f"tracks={tracks}"])
    job("export: no fps", "adjust-export", ["nwb", f"tracks={tracks}", f"output={o}/n.nwb"])
    job("export: /dev/zero as tracks", "adjust-export", ["anipose", "tracks=/dev/zero",
        f"output={o}/z.csv"])  # fmt: skip
    job(
        "export: output in an unwritable place",
        "adjust-export",
        ["anipose", f"tracks={tracks}", "output=/proc/mousetrack/x.csv"],
    )
    # adjust-plot
    works(
        "plot: tracks",
        "adjust-plot",
        [f"tracks={tracks}", f"output.dir={o}/pl"],
        o / "pl" / "body3d.png",
    )
    works(
        "plot: labelled images",
        "adjust-plot",
        [f"tracks={labelled}", f"output.dir={o}/pl2"],
        o / "pl2" / "body3d.png",
    )
    job("plot: tracks without rows", "adjust-plot", [f"tracks={empty}", f"output.dir={o}/pl3"])
    job("plot: frame number beyond int64", "adjust-plot", [f"tracks={huge}",
        f"output.dir={o}/pl4"])  # fmt: skip
    job("plot: output.dir is a file", "adjust-plot", [f"tracks={tracks}", f"output.dir={d}/afile"])
    # adjust-demo (its failures only: a demo run takes minutes)
    job("demo: threads=100000", "adjust-demo", [f"output.dir={o}/demo", "threads=100000"])
    job("demo: output.dir is a file", "adjust-demo", [f"output.dir={d}/afile"])
    # deformnet-simulate
    works(
        "deformnet-simulate: a short run",
        "deformnet-simulate",
        [f"output.dir={o}/dsim", "num_frames=50"],
        o / "dsim" / "sim.npz",
    )
    job(
        "deformnet-simulate: num_frames=abc",
        "deformnet-simulate",
        [f"output.dir={o}/dsim2", "num_frames=abc"],
    )
    job(
        "deformnet-simulate: output.dir unusable",
        "deformnet-simulate",
        ["output.dir=/proc/mousetrack/x"],
    )
    # deformnet-train
    job("train: output.dir unusable", "deformnet-train", ["output.dir=/proc/mousetrack/x"])
    job("train: output.dir is a file", "deformnet-train", [f"output.dir={d}/afile/x"])
    job(
        "train: pretrained with a pickle payload",
        "deformnet-train",
        [f"pretrained={ckpt}", f"output.dir={o}/tr"],
    )
    job("train: pretrained=/dev/zero", "deformnet-train", ["pretrained=/dev/zero",
        f"output.dir={o}/tr2"])  # fmt: skip
    job("train: threads=100000", "deformnet-train", ["threads=100000", f"output.dir={o}/tr3"])
    # deformnet-classify
    job("classify: output.dir is a file", "deformnet-classify", [f"output.dir={d}/afile/x"])
    job("classify: output.dir unusable", "deformnet-classify", ["output.dir=/proc/mousetrack/x"])
    job("classify: mode=bogus", "deformnet-classify", ["mode=bogus", f"output.dir={o}/cl"])
    job(
        "classify: predict with a pickle payload",
        "deformnet-classify",
        ["mode=predict", f"checkpoint={ckpt}", f"tracks={tracks}", f"output.dir={o}/cl2"],
    )
    job("classify: threads=100000", "deformnet-classify", ["threads=100000",
        f"output.dir={o}/cl3"])  # fmt: skip
    return jobs


#: a long session's frames and chunk size for the chunked cases (three chunks)
LONG_FRAMES, CHUNK = 300, 128


def _summary(out: Path) -> dict:
    try:
        return json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        return {}


def _chunked_ok(out: Path, truth: dict, gap: tuple[int, int] | None = None) -> bool:
    """A chunked adjust-track run sound: summary.json says chunked, every frame outside `gap`
    finite and within 25 mm rms of the truth, every frame in [gap) empty, ``tracked`` 0 there
    and named in summary.json ``untracked``."""
    from adjust.io import read_points3d

    s = _summary(out)
    if not s.get("chunked") or not (out / "points3d.csv").is_file():
        return False
    d = read_points3d(out / "points3d.csv")
    fnum = np.asarray(d["fnum"]).astype(int)
    inside = np.zeros(len(fnum), bool) if gap is None else (fnum >= gap[0]) & (fnum < gap[1])
    P = d["points"]
    if not np.isfinite(P[~inside]).all() or np.isfinite(P[inside]).any():
        return False
    e = np.linalg.norm(P[~inside] - truth["points"][fnum[~inside]], axis=-1)
    if np.sqrt(np.mean(e**2)) > 25.0:
        return False
    if gap is None:
        return "untracked" not in s
    named = s.get("untracked", {}).get("ranges") == [[gap[0], gap[1] - 1]]
    return named and bool((d["extra"]["tracked"][inside] == 0).all())


def chunk_jobs(work: Path) -> list[Job]:
    """adjust-track on a session longer than ``chunk_frames`` (issue 46): chunks with NWB
    output, a chunk in which two of the three cameras are out, one camera for the whole
    session, a net mode, NWB output without a frame rate."""
    long = simulate(work / "long", LONG_FRAMES)
    truth = dict(np.load(long / "truth.npz"))
    gap = work / "long-gap"
    shutil.copytree(long, gap)
    for cam in CAMERAS[1:]:  # side and front out for the middle chunk
        _rewrite(gap, cam, lambda rows: _no_detections(rows, CHUNK, 2 * CHUNK))
    one = work / "long-one"
    shutil.copytree(long, one)
    for cam in CAMERAS[1:]:
        _rewrite(one, cam, _no_detections)
    nwb = ["output.nwb=true", "output.fps=100", "output.session_start_time=2026-01-01T00:00:00"]
    jobs = []

    def job(name, folder, extra, expect="ok", check=None):
        out = work / "chunks" / "".join(c if c.isalnum() else "-" for c in name)
        args = [f"input.session={folder}", f"output.dir={out}", f"chunk_frames={CHUNK}"]
        jobs.append(Job(f"chunked: {name}", "adjust-track", [*args, *TRACK_FAST, *extra],
                        expect, out=out, check=check and (lambda: check(out))))  # fmt: skip

    job("clean, NWB", long, nwb,
        check=lambda o: _chunked_ok(o, truth) and (o / "tracks.nwb").is_file())  # fmt: skip
    job("two cameras out for a chunk, NWB", gap, nwb,
        check=lambda o: _chunked_ok(o, truth, (CHUNK, 2 * CHUNK))
        and (o / "tracks.nwb").is_file())  # fmt: skip
    job("one camera in the whole session", one, [], "error")
    job("deformation=default", long, ["deformation=default"],
        check=lambda o: _chunked_ok(o, truth)
        and _summary(o)["deformation"].get("decided_on") == "sample")  # fmt: skip
    job("NWB without a frame rate", long, ["output.nwb=true", "output.fps=null"], "error")
    job("NWB with a bad start time", long, [*nwb, "output.session_start_time=soon"], "error")
    for mode, n in (("kill", 2), ("sigint", 1)):  # an earlier chunked run's folder kept whole
        for i in range(n):
            out = work / "chunks" / f"lost-{mode}-{i}"
            args = [f"input.session={long}", f"output.dir={out}", f"chunk_frames={CHUNK}"]
            jobs.append(Job(f"chunked: re-run {mode} {i}", "adjust-track",
                            [*args, *TRACK_FAST, *nwb], "lost", out=out, mode=mode,
                            again=["solver.max_iterations=5"]))  # fmt: skip
    return jobs


def lost_jobs(work: Path, base: Path) -> list[Job]:
    """Killed, interrupted and concurrent re-runs of adjust-triangulate and adjust-track into
    a folder holding a complete earlier run."""
    jobs = []
    session = [f"input.calibration={base / 'calibration.toml'}",
               f"input.detections={base / 'detections'}"]  # fmt: skip
    again = {"adjust-triangulate": ["input.likelihood_threshold=0.6"],
             "adjust-track": ["solver.max_iterations=5"]}  # fmt: skip
    for app in APPS:
        fast = TRACK_FAST if app == "adjust-track" else []
        for mode, n in (("kill", 3), ("sigint", 1), ("busy", 1)):
            for i in range(n):
                out = work / "lost" / f"{app}-{mode}-{i}"
                jobs.append(Job(f"re-run {mode}{' ' + str(i) if n > 1 else ''}", app,
                                [*session, f"output.dir={out}", *fast], "lost", out=out,
                                mode=mode, again=again[app]))  # fmt: skip
    return jobs


# --- running and judging ---------------------------------------------------------------------


def _judge(out: Path, truth: dict | None, clean_rmse: float | None) -> dict:
    pts = out / "points3d.csv"
    r = {"written": pts.is_file(), "empty": None, "absurd": None, "rmse_mm": None}
    hidden = [p.name for p in out.iterdir() if p.name.startswith(".") and p.name != ".hydra"]
    r["temp_left"] = bool(hidden) if out.is_dir() else False
    if not r["written"]:
        return r
    from adjust.io import read_points3d

    d = read_points3d(pts)
    P = d["points"]
    finite = np.isfinite(P).all(-1)
    r["empty"] = not finite.any()
    absurd = bool(np.abs(P[finite]).max() > 1e4) if finite.any() else False
    if truth is not None and finite.any():
        fnum = np.asarray(d["fnum"]).astype(int)
        ok = (fnum >= 0) & (fnum < len(truth["points"]))
        X = truth["points"][fnum[ok]]
        e = np.linalg.norm(P[ok] - X, axis=-1)[finite[ok]]
        if e.size:
            r["rmse_mm"] = float(np.sqrt(np.mean(e**2)))
            limit = max(25.0, 3 * clean_rmse) if clean_rmse else 25.0
            absurd = absurd or r["rmse_mm"] > limit
    r["absurd"] = absurd
    return r


def _digests(out: Path) -> dict[str, str]:
    from deformnet.atomic import file_digest

    return {n: file_digest(out / n) for n in OUTPUT_NAMES if (out / n).is_file()}


def folder_state(out: Path, before: dict[str, str]) -> str:
    """After a killed / interrupted / refused re-run (and the recovery the next run does first):
    "old" (the earlier run whole), "new" (the new run whole: its summary's files all match),
    or "lost" (a mix, or no summary)."""
    from deformnet.outputs import recover_outputs

    recover_outputs(out)
    now = _digests(out)
    if now == before:
        return "old"
    if "summary.json" not in now:
        return "lost"
    if now["summary.json"] == before.get("summary.json"):
        return "lost"  # the earlier summary beside files it does not describe
    try:
        summary = json.loads((out / "summary.json").read_text())
        files = summary["outputs"]["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return "lost"
    for name, facts in files.items():
        if now.get(name) != facts.get("sha256"):
            return "lost"
    return "new"


def _run(app: str, args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / app), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=600, env=ENV)  # fmt: skip


def _result(p_rc: int, text: str, t0: float) -> dict:
    errors = [ln for ln in text.splitlines() if "[ERROR]" in ln]
    return {
        "rc": p_rc,
        "traceback": "Traceback" in text,
        "error": errors[-1].split(" - ", 1)[-1][:160] if errors else None,
        "errors": len(errors),
        "warnings": sum("[WARNING]" in ln for ln in text.splitlines()),
        "time_s": round(time.perf_counter() - t0, 1),
    }


def run_case(app: str, calib: Path, dets: Path, extra: list[str], out: Path, cwd: Path) -> dict:
    args = [f"input.calibration={calib}", f"input.detections={dets}", f"output.dir={out}"]
    if app == "adjust-track":
        args += TRACK_FAST
    args += extra  # later overrides win
    t0 = time.perf_counter()
    p = _run(app, args, cwd)
    return _result(p.returncode, p.stdout + p.stderr, t0)


def run_lost(job: Job, cwd: Path, rng: random.Random) -> dict:
    """A clean run into job.out, then the second one (job.again) killed, interrupted or
    refused; the folder judged (`folder_state`)."""
    t0 = time.perf_counter()
    first = _run(job.app, job.args, cwd)
    if first.returncode != 0:
        r = _result(first.returncode, first.stdout + first.stderr, t0)
        return {**r, "state": "first run failed"}
    clean_s = time.perf_counter() - t0
    before = _digests(job.out)
    second = [job.app, *job.args, *job.again]
    if job.mode == "busy":  # a run holds the folder (its lock) while the second one starts
        holder = subprocess.Popen(
            [sys.executable, "-c", "import sys, time\nfrom deformnet.outputs import hold_output\n"
             "hold_output(sys.argv[1]); print('held', flush=True); time.sleep(120)",
             str(job.out)], stdout=subprocess.PIPE, text=True)  # fmt: skip
        holder.stdout.readline()
        t1 = time.perf_counter()
        try:
            p = _run(job.app, [*job.args, *job.again], cwd)
        finally:
            holder.kill()
            holder.wait()
        r = _result(p.returncode, p.stdout + p.stderr, t1)
        r["expected_rc"] = 2
    else:
        t1 = time.perf_counter()
        pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT, "text": True}
        p = subprocess.Popen([str(BIN / second[0]), *second[1:]], cwd=cwd, env=ENV, **pipes)
        time.sleep(rng.uniform(0.3, 1.0) * clean_s)
        p.send_signal(signal.SIGKILL if job.mode == "kill" else signal.SIGINT)
        text = p.communicate(timeout=600)[0]
        r = _result(p.returncode, text, t1)
        r["expected_rc"] = (-9, 0) if job.mode == "kill" else (130, 0)  # 0: it had finished
    r["state"] = folder_state(job.out, before)
    return r


def _note(r: dict) -> str:
    return r["error"] or (f"{r['warnings']} warnings" if r["warnings"] else "")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--only", default="", help="case names separated by ';' (default: all)")
    ap.add_argument("--groups", default=",".join(GROUPS), help=f"of {', '.join(GROUPS)}")
    ap.add_argument(
        "--out", default=str(CONF_DIR.parent / "runs" / "benchmarks" / "robustness.json")
    )
    args = ap.parse_args(argv)
    groups = [g.strip() for g in args.groups.split(",") if g.strip()]
    if set(groups) - set(GROUPS):
        ap.error(f"--groups: unknown {sorted(set(groups) - set(GROUPS))}")
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    t_start = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="mousetrack-robustness-"))
    cwd = work / "cwd"
    cwd.mkdir()
    base = simulate(work / "base", args.frames)
    truth = dict(np.load(base / "truth.npz"))
    only = [n for n in args.only.split(";") if n]
    todo: list[Job] = []
    if "inputs" in groups:
        for name, spoil, apps, expect in cases(base):
            if only and name not in only:
                continue
            folder = work / f"case{len(todo):03d}"
            shutil.copytree(base, folder)
            extra = spoil(folder)
            for app in apps:
                out = folder / f"out-{app}"
                calib, dets = folder / "calibration.toml", folder / "detections"
                given = [str(calib), str(dets), *extra]
                todo.append(Job(name, app, given, expect, out, truth, mode="session"))
        sleap = shared_dir() / "data" / "real-mouse-sleap-4cam"
        if not only or "real SLEAP mouse (side: wrong pose)" in only:
            for app in APPS:
                extra = ["input.pattern=*.analysis.h5", "input.likelihood_threshold=0"]
                extra += ["body=auto"] if app == "adjust-track" else []
                todo.append(Job("real SLEAP mouse (side: wrong pose)", app,
                                [str(sleap / "calibration.toml"), str(sleap), *extra], "judge",
                                work / f"sleap-{app}", mode="session"))  # fmt: skip
    if "scripts" in groups:
        todo += [j for j in script_jobs(work, base) if not only or j.name in only]
    if "lost" in groups:
        todo += [j for j in lost_jobs(work, base) if not only or j.name in only]
    if "chunks" in groups:
        todo += [j for j in chunk_jobs(work) if not only or j.name in only]
    marker = Path("/tmp/mousetrack-robustness-pwned")
    marker.unlink(missing_ok=True)
    rng = random.Random(46)
    seeds = {id(j): rng.random() for j in todo}

    def one(job: Job):
        if job.expect == "lost":
            return job, run_lost(job, cwd, random.Random(seeds[id(job)]))
        if job.mode == "session":  # a session folder through adjust-triangulate / -track
            calib, dets, *extra = job.args
            return job, run_case(job.app, Path(calib), Path(dets), extra, job.out, cwd)
        t0 = time.perf_counter()
        p = _run(job.app, job.args, cwd)
        return job, _result(p.returncode, p.stdout + p.stderr, t0)

    with cf.ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        done = list(pool.map(one, todo))
    clean = {}
    for job, _res in done:
        if job.name == "clean" and job.out and (job.out / "points3d.csv").is_file():
            clean[job.app] = _judge(job.out, job.truth, None)["rmse_mm"]
    rows = []
    for job, res in done:
        row = {"case": job.name, "app": job.app, "expect": job.expect, **res}
        row.update(written=None, empty=None, absurd=None, rmse_mm=None, temp_left=False)
        row["lost"] = False
        if job.expect == "judge":
            if job.out.is_dir():
                row.update(_judge(job.out, job.truth, clean.get(job.app)))
            bad = row["empty"] or row["absurd"] or not row["written"]
            row["silent_wrong"] = res["rc"] == 0 and bool(bad)
            verdict = "EMPTY" if row["empty"] else ("ABSURD" if row["absurd"] else "ok")
            row["result"] = verdict if row["written"] else "-"
        elif job.expect == "error":
            if job.mode == "session" and job.out.is_dir():
                row["temp_left"] = any(
                    p.name.startswith(".") and p.name != ".hydra" for p in job.out.iterdir()
                )
            row["silent_wrong"] = res["rc"] == 0
            row["result"] = "ACCEPTED" if res["rc"] == 0 else "refused"
        elif job.expect == "ok":
            good = res["rc"] == 0 and job.check()
            row["silent_wrong"] = res["rc"] == 0 and not good
            row["result"] = "ok" if good else ("NO OUTPUT" if res["rc"] == 0 else "REFUSED")
        else:  # lost data
            expected = res.get("expected_rc")
            ok_rc = res["rc"] in (expected if isinstance(expected, tuple) else (expected,))
            row["lost"] = res["state"] not in ("old", "new")
            row["silent_wrong"] = False
            row["result"] = res["state"] + ("" if ok_rc else f" (rc {res['rc']}, not {expected})")
            row["bad_exit"] = not ok_rc
        rows.append(row)
    print(f"{'case':48s} {'app':19s} {'rc':>3s} {'tb':>3s} {'result':>10s} {'rmse':>6s}  "
          "error / note")  # fmt: skip
    for r in rows:
        rmse = f"{r['rmse_mm']:.1f}" if r["rmse_mm"] is not None else "-"
        print(f"{r['case'][:48]:48s} {r['app']:19s} {r['rc']:3d} "
              f"{'YES' if r['traceback'] else 'no':>3s} {r['result'][:10]:>10s} {rmse:>6s}  "
              f"{_note(r)[:90]}")  # fmt: skip
    expected_exit = {"judge": (0, 2), "error": (2,), "ok": (0,)}
    summary = {
        "benchmark": "robustness",
        "groups": groups,
        "scripts": sorted({r["app"] for r in rows}),
        "cases": len({(r["case"], r["app"]) for r in rows}),
        "runs": len(rows),
        "exit_0": sum(r["rc"] == 0 for r in rows),
        "exit_2": sum(r["rc"] == 2 for r in rows),
        "tracebacks": sum(r["traceback"] for r in rows),
        "silent_wrong_results": sum(r["silent_wrong"] for r in rows),
        "lost_data": sum(r["lost"] for r in rows),
        "unexpected_exit": sum(
            (r["rc"] not in expected_exit[r["expect"]])
            if r["expect"] in expected_exit
            else bool(r.get("bad_exit"))
            for r in rows
        ),  # fmt: skip
        "multi_line_errors": sum(r["errors"] > 1 for r in rows),
        "temp_files_left": sum(bool(r["temp_left"]) for r in rows),
        "cwd_written": sorted(str(p.relative_to(cwd)) for p in [*cwd.glob("*"), *cwd.glob("*/*")])
        or False,
        "payload_executed": marker.exists(),
        "clean_rmse_mm": clean,
        "silent_wrong": [f"{r['case']} / {r['app']}" for r in rows if r["silent_wrong"]],
        "with_traceback": [f"{r['case']} / {r['app']}" for r in rows if r["traceback"]],
        "lost": [f"{r['case']} / {r['app']}: {r['result']}" for r in rows if r["lost"]],
        "unexpected": [
            f"{r['case']} / {r['app']}: rc {r['rc']}"
            for r in rows
            if (
                r["rc"] not in expected_exit[r["expect"]]
                if r["expect"] in expected_exit
                else r.get("bad_exit")
            )
        ],  # fmt: skip
        "minutes": round((time.perf_counter() - t_start) / 60, 1),
        "target": "0 tracebacks, 0 silent wrong results, 0 lost data, no payload run, cwd clean",
    }
    summary["passed"] = bool(
        summary["silent_wrong_results"] == 0
        and summary["tracebacks"] == 0
        and summary["lost_data"] == 0
        and summary["unexpected_exit"] == 0
        and not summary["payload_executed"]
        and not summary["cwd_written"]
    )
    print(f"tracebacks {summary['tracebacks']}, silent wrong results "
          f"{summary['silent_wrong_results']}, lost data {summary['lost_data']}; "
          f"{summary['runs']} runs of {len(summary['scripts'])} console scripts, "
          f"{summary['minutes']} min")  # fmt: skip
    shutil.rmtree(work, ignore_errors=True)
    return emit(summary, args.out)


if __name__ == "__main__":
    main()
