"""Robustness: defective inputs through adjust-triangulate and adjust-track, as a user runs them.

A small simulated scene (default rig: 3 cameras; `adjust-simulate`, with ground truth) is
copied and spoilt in a fixed list of ways (detections, calibration, settings, outputs,
checkpoints), plus the shared real SLEAP mouse whose `side` camera has a wrong pose. Every case
runs through the console scripts as subprocesses; per case and app the table shows the exit
code, whether a traceback appeared, whether ``points3d.csv`` was written, whether it holds
empty or absurd values (no finite point at all; a coordinate beyond 10 m; RMSE against the
ground truth, matched by ``fnum``, above 25 mm or 3x the clean run's), and whether a hidden
temporary file was left. A *silent wrong result* is exit 0 with empty or absurd output.
Target: zero silent wrong results, zero tracebacks. Last line JSON (counts), also written to
runs/benchmarks/robustness.json.

    .venv/bin/python benchmarks/robustness.py [--jobs 2] [--frames 100] [--only NAME,...]
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from common import emit

from deformnet.paths import CONF_DIR, shared_dir

log = logging.getLogger("benchmarks.robustness")
BIN = Path(sys.executable).parent
APPS = ("adjust-triangulate", "adjust-track")
TRACK_FAST = ["progress=false", "solver.max_iterations=8"]
CAMERAS = ("top", "side", "front")  # the default rig's


# --- the scene and its spoilt copies -------------------------------------------------------


def simulate(folder: Path, frames: int) -> Path:
    import hydra

    from adjust.scene_cli import run

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


def _no_detections(rows: list[list[str]]) -> list[list[str]]:
    """The rows with every frame's detections empty (frame index kept)."""
    return rows[:3] + [[r[0]] + [""] * (len(r) - 1) for r in rows[3:]]


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


def _reverse_rows(folder: Path, cam: str) -> None:
    p = folder / "detections" / f"{cam}.csv"
    rows = _read(p)
    body = rows[3:]
    data = [r[1:] for r in body][::-1]
    _write(p, rows[:3] + [[r[0], *d] for r, d in zip(body, data)])


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


def cases(base: Path) -> list[tuple[str, Callable[[Path], list[str]], tuple[str, ...]]]:
    """(name, spoil(folder) -> extra overrides, apps). The folder is a fresh copy of `base`."""
    both = APPS
    track = ("adjust-track",)
    tri = ("adjust-triangulate",)
    out = []

    def case(name, apps=both):
        """A case whose function spoils the folder and returns its overrides (None: none)."""

        def deco(fn):
            out.append((name, lambda f: fn(f) or [], apps))
            return fn

        return deco

    def setting(name, override=None, apps=both):
        """A case that only gives an override (`name` itself by default)."""
        out.append((name, lambda f: [override or name], apps))

    @case("clean")
    def _(f):
        pass

    @case("one cell x=1e200")
    def _(f):
        _cell(f, "top", 10, 0, "1e200")

    @case("one part at 1e160 in every camera")
    def _(f):
        for cam in CAMERAS:
            _column(f, cam, 0, lambda v: "1e160" if v else v)
            _column(f, cam, 1, lambda v: "1e160" if v else v)

    @case("inf cell")
    def _(f):
        _cell(f, "side", 5, 3, "inf")

    @case("likelihood 50 on some detections")
    def _(f):
        _likelihoods(f, lambda v: 50.0 if v < 0.7 else v)

    @case("negative likelihood")
    def _(f):
        _cell(f, "front", 3, 2, "-0.5")

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

    @case("non-numeric cell")
    def _(f):
        _cell(f, "side", 7, 1, "abc")

    @case("header rows only")
    def _(f):
        for cam in CAMERAS:
            _rewrite(f, cam, lambda rows: rows[:3])

    @case("one file truncated (fewer frames)")
    def _(f):
        _rewrite(f, "side", lambda rows: rows[:-30])

    @case("one file's frame numbers offset by 1000")
    def _(f):
        _renumber(f, "front", lambda i: i + 1000)

    @case("duplicate frame number")
    def _(f):
        p = f / "detections" / "top.csv"
        rows = _read(p)
        rows[5][0] = rows[4][0]
        _write(p, rows)

    @case("one camera's rows reversed")
    def _(f):
        _reverse_rows(f, "side")

    @case("one camera's rows in reverse order, frame index too")
    def _(f):
        _rewrite(f, "side", lambda rows: rows[:3] + rows[3:][::-1])

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

    @case("all detections of one camera empty")
    def _(f):
        _rewrite(f, "front", _no_detections)

    @case("every detection empty")
    def _(f):
        for cam in CAMERAS:
            _rewrite(f, cam, _no_detections)

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

    @case("fisheye calibration")
    def _(f):
        _toml(f, 'name = "top"', 'name = "top"\nfisheye = true')

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

    return out


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


def run_case(app: str, calib: Path, dets: Path, extra: list[str], out: Path, cwd: Path) -> dict:
    args = [f"input.calibration={calib}", f"input.detections={dets}", f"output.dir={out}"]
    if app == "adjust-track":
        args += TRACK_FAST
    args += extra  # later overrides win
    t0 = time.perf_counter()
    p = subprocess.run(
        [str(BIN / app), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "HYDRA_FULL_ERROR": "0"},
    )
    text = p.stdout + p.stderr
    errors = [ln for ln in text.splitlines() if "[ERROR]" in ln]
    return {
        "rc": p.returncode,
        "traceback": "Traceback" in text,
        "error": errors[-1].split(" - ", 1)[-1][:160] if errors else None,
        "warnings": sum("[WARNING]" in ln for ln in text.splitlines()),
        "time_s": round(time.perf_counter() - t0, 1),
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--only", default="", help="comma-separated case names (default: all)")
    ap.add_argument(
        "--out", default=str(CONF_DIR.parent / "runs" / "benchmarks" / "robustness.json")
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    work = Path(tempfile.mkdtemp(prefix="mousetrack-robustness-"))
    cwd = work / "cwd"
    cwd.mkdir()
    base = simulate(work / "base", args.frames)
    truth = dict(np.load(base / "truth.npz"))
    todo = []  # (case, app, calib, dets, extra, out, truth)
    for name, spoil, apps in cases(base):
        if args.only and name not in args.only.split(","):
            continue
        folder = work / f"case{len(todo):03d}"
        shutil.copytree(base, folder)
        extra = spoil(folder)
        for app in apps:
            out = folder / f"out-{app}"
            todo.append((name, app, folder / "calibration.toml", folder / "detections", extra,
                         out, truth))  # fmt: skip
    sleap = shared_dir() / "data" / "real-mouse-sleap-4cam"
    if not args.only or "real SLEAP mouse (side: wrong pose)" in args.only:
        for app in APPS:
            extra = ["input.pattern=*.analysis.h5", "input.likelihood_threshold=0"]
            extra += ["body=auto"] if app == "adjust-track" else []
            todo.append(("real SLEAP mouse (side: wrong pose)", app, sleap / "calibration.toml",
                         sleap, extra, work / f"sleap-{app}", None))  # fmt: skip
    marker = Path("/tmp/mousetrack-robustness-pwned")
    marker.unlink(missing_ok=True)

    def one(item):
        name, app, calib, dets, extra, out, tr = item
        return item, run_case(app, calib, dets, extra, out, cwd)

    with cf.ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        done = list(pool.map(one, todo))
    clean = {}
    for (name, app, *_, out, tr), _res in done:
        if name == "clean" and (out / "points3d.csv").is_file():
            clean[app] = _judge(out, tr, None)["rmse_mm"]
    rows = []
    for (name, app, *_, out, tr), res in done:
        j = _judge(out, tr, clean.get(app)) if out.is_dir() else {
            "written": False, "empty": None, "absurd": None, "rmse_mm": None, "temp_left": False
        }  # fmt: skip
        silent = res["rc"] == 0 and bool(j["empty"] or j["absurd"] or not j["written"])
        rows.append({"case": name, "app": app, **res, **j, "silent_wrong": silent})
    print(f"{'case':52s} {'app':18s} {'rc':>3s} {'tb':>3s} {'out':>4s} {'bad':>4s} "
          f"{'rmse':>7s}  error / note")  # fmt: skip
    for r in rows:
        bad = (
            "-"
            if not r["written"]
            else ("EMPT" if r["empty"] else ("ABS" if r["absurd"] else "ok"))
        )
        rmse = f"{r['rmse_mm']:.1f}" if r["rmse_mm"] is not None else "-"
        note = r["error"] or (f"{r['warnings']} warnings" if r["warnings"] else "")
        print(f"{r['case'][:52]:52s} {r['app']:18s} {r['rc']:3d} "
              f"{'YES' if r['traceback'] else 'no':>3s} {'yes' if r['written'] else 'no':>4s} "
              f"{bad:>4s} {rmse:>7s}  {note[:90]}")  # fmt: skip
    summary = {
        "benchmark": "robustness",
        "cases": len({r["case"] for r in rows}),
        "runs": len(rows),
        "exit_0": sum(r["rc"] == 0 for r in rows),
        "exit_2": sum(r["rc"] == 2 for r in rows),
        "other_exit": sum(r["rc"] not in (0, 2) for r in rows),
        "tracebacks": sum(r["traceback"] for r in rows),
        "silent_wrong_results": sum(r["silent_wrong"] for r in rows),
        "temp_files_left": sum(bool(r["temp_left"]) for r in rows),
        "cwd_written": bool(list(cwd.iterdir())),
        "payload_executed": marker.exists(),
        "clean_rmse_mm": clean,
        "silent_wrong": [f"{r['case']} / {r['app']}" for r in rows if r["silent_wrong"]],
        "with_traceback": [f"{r['case']} / {r['app']}" for r in rows if r["traceback"]],
        "target": "zero silent wrong results, zero tracebacks",
    }
    summary["passed"] = bool(
        summary["silent_wrong_results"] == 0
        and summary["tracebacks"] == 0
        and summary["other_exit"] == 0
        and not summary["payload_executed"]
        and not summary["cwd_written"]
    )
    shutil.rmtree(work, ignore_errors=True)
    return emit(summary, args.out)


if __name__ == "__main__":
    main()
