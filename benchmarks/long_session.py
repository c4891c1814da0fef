"""Long sessions end to end: peak memory and wall time of `adjust-track` (``body=auto``, the
default ``deformation=interp``) at 100,000, 300,000 and 1,000,000 frames, 12 parts, 3 cameras
(issue 46: <= 2 GB at 1M frames).

Synthetic session (`write_session`): a 12-part rigid body (the default mouse's 8 parts and 4
more) moving along `adjust.lsq.synthetic.smooth_trajectory`, each part off its rigid place by a
smooth random offset (~2 mm), seen by 3 ring cameras with 2 px Gaussian noise, 20 % of the
detections missing (likelihood 0.05, empty x and y), the others with likelihoods 0.6-1; written
as one DeepLabCut CSV per camera (``%.3f`` px) with an anipose calibration.toml, in blocks (the
generator's memory is bounded too). Sessions are cached under ``--work``.

Each run is `adjust.pipeline.run` on the session in its own process (``--child``): the peak
resident set size is the kernel's VmHWM of that process at its end (interpreter, torch, the
whole run: reading, the sample, every chunk, the outputs), ``before_rss_mb`` its size before
the run. ``--chunk-frames 0`` runs the session whole (the recipe without chunks, for the
comparison at sizes it can hold). ``--nwb`` writes the NWB file too (``output.nwb=true``,
block by block in a chunked run). ``--profile`` samples the resident size every 0.1 s and
reports the largest per log message (where the memory goes).

    flock /tmp/mousetrack-cpu.lock .venv/bin/python benchmarks/long_session.py \
        [--frames 100000 300000 1000000] [--chunk-frames 50000] [--work runs/benchmarks/long]
        [--out runs/benchmarks/long_session.json] [--profile] [--nwb]

Prints one line per size and the JSON summary as the last line (also written to ``--out``).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from common import emit
from hydra import compose, initialize_config_dir
from scipy.signal import lfilter

from adjust.apps.common import finite_or_none
from adjust.camera import CameraTensors, project_cameras
from adjust.io import save_calibration
from adjust.lsq import synthetic
from adjust.pipeline import run as run_track
from deformnet.atomic import write_text
from deformnet.body import default_mouse
from deformnet.paths import CONF_DIR
from deformnet.so3 import transform_points

log = logging.getLogger("benchmarks.long_session")

ROOT = Path(__file__).resolve().parents[1]
#: the four parts added to the default mouse's eight (mm, body frame)
EXTRA_PARTS = {
    "neck": (0.0, 12.0, 12.0),
    "back": (0.0, -5.0, 16.0),
    "tail_mid": (0.0, -55.0, -8.0),
    "belly": (0.0, 0.0, -6.0),
}
TARGET_MB_1M = 2048.0
BLOCK = 100_000


def body_points() -> tuple[list[str], np.ndarray]:
    """The 12 parts and their points (K, 3) mm."""
    mouse = default_mouse()
    parts = [*mouse.parts, *EXTRA_PARTS]
    return parts, np.concatenate([np.asarray(mouse.points), np.array(list(EXTRA_PARTS.values()))])


def write_session(folder: Path, frames: int, seed: int = 0, block: int = BLOCK) -> Path:
    """A synthetic session of `frames` frames in `folder` (see the module doc):
    calibration.toml and detections/cam{i}.csv; written in blocks of `block` frames."""
    parts, B = body_points()
    cams_list = synthetic.ring_cameras(3)
    cams = CameraTensors.from_cameras(cams_list)
    trajectory = synthetic.smooth_trajectory(frames, seed=seed)  # (T, 6): 48 bytes a frame
    det_dir = folder / "detections"
    det_dir.mkdir(parents=True, exist_ok=True)
    save_calibration(folder / "calibration.toml", cams_list)
    rng = np.random.default_rng(seed)
    K = len(parts)
    offset = np.zeros((K, 3))
    cols = pd.MultiIndex.from_product(
        [["DLC_synthetic"], parts, ["x", "y", "likelihood"]],
        names=["scorer", "bodyparts", "coords"],
    )
    files = [det_dir / f"{c.name}.csv" for c in cams_list]
    for f in files:
        f.unlink(missing_ok=True)
    for a in range(0, frames, block):
        b = min(frames, a + block)
        n = b - a
        poses = trajectory[a:b]
        # smooth per-part offsets: an AR(1) walk (0.995 per frame, stationary sd ~2 mm)
        steps = rng.normal(0.0, 2.0 * np.sqrt(1 - 0.995**2), (n, K, 3))
        offs, _ = lfilter([1.0], [1.0, -0.995], steps, axis=0, zi=0.995 * offset[None])
        offset = offs[-1]
        X = transform_points(poses, torch.as_tensor(B)) + torch.as_tensor(offs)
        xy = project_cameras(X, cams).numpy()  # (n, K, C, 2)
        xy = xy + rng.normal(0.0, 2.0, xy.shape)
        gone = rng.random(xy.shape[:-1]) < 0.2
        lik = np.where(gone, 0.05, rng.uniform(0.6, 1.0, gone.shape))
        xy[gone] = np.nan
        for c, f in enumerate(files):
            data = np.concatenate([xy[:, :, c], lik[:, :, c, None]], -1).reshape(n, K * 3)
            df = pd.DataFrame(data, index=pd.RangeIndex(a, b), columns=cols)
            with open(f, "a", newline="", encoding="utf-8") as fh:
                df.to_csv(fh, header=a == 0, float_format="%.3f")
    return folder


def ensure_session(work: Path, frames: int, seed: int = 0) -> Path:
    folder = work / f"session_{frames}"
    done = folder / ".complete"
    if not done.exists():
        shutil.rmtree(folder, ignore_errors=True)
        t0 = time.perf_counter()
        write_session(folder, frames, seed)
        done.write_text("ok\n")
        log.info("wrote the %d-frame session in %.0f s", frames, time.perf_counter() - t0)
    return folder


def _status_kb(field: str) -> int:
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return -1


class _Profile(logging.Handler):
    """The largest resident size (sampled every 0.1 s) between consecutive log messages."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.rows: list[dict] = []
        self.peak = 0
        self.t0 = time.perf_counter()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._sample, daemon=True)
        self.thread.start()

    def _sample(self) -> None:
        while not self.stop.wait(0.1):
            self.peak = max(self.peak, _status_kb("VmRSS"))

    def emit(self, record: logging.LogRecord) -> None:
        self.peak = max(self.peak, _status_kb("VmRSS"))
        self.rows.append(
            {
                "t_s": round(time.perf_counter() - self.t0, 1),
                "peak_rss_mb_before": round(self.peak / 1024, 1),
                "message": record.getMessage()[:120],
            }
        )
        self.peak = _status_kb("VmRSS")


#: ``--nwb``: the NWB file too (issue 46: written block by block in a chunked run)
NWB = ["output.nwb=true", "output.fps=100", "output.session_start_time=2026-01-01T00:00:00"]


def child(session: Path, out: Path, chunk_frames: int, profile: bool, nwb: bool = False) -> dict:
    """One adjust-track run in this process: its JSON row."""
    torch.set_num_threads(1)
    overrides = [
        f"input.calibration={session / 'calibration.toml'}",
        f"input.detections={session / 'detections'}",
        f"output.dir={out}",
        "body=auto",
        "progress=false",
        f"chunk_frames={chunk_frames}",
        *(NWB if nwb else []),
    ]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose("track", overrides)
    prof = _Profile() if profile else None
    if prof is not None:
        logging.getLogger().addHandler(prof)
        logging.getLogger().setLevel(logging.INFO)
    before = _status_kb("VmRSS")
    t0 = time.perf_counter()
    summary = run_track(cfg)
    seconds = time.perf_counter() - t0
    row = {
        "frames": int(summary["num_frames"]),
        "chunk_frames": chunk_frames,
        "nwb": nwb,
        "chunks": len((summary.get("chunked") or {}).get("chunks", [])) or 1,
        "peak_rss_mb": round(_status_kb("VmHWM") / 1024, 1),
        "before_rss_mb": round(before / 1024, 1),
        "seconds": round(seconds, 1),
        "time_s": summary["time_s"],
        "iterations": summary.get("iterations"),
        "converged": summary.get("converged"),
        "health": summary["health"]["status"],
        "completeness": summary.get("completeness"),
        "reprojection_median_px": summary["reprojection_error_px"]["median"],
        "sigma_det_px": (summary.get("stochastic") or {}).get("sigma_det_px"),
    }
    if prof is not None:
        prof.stop.set()
        row["profile"] = prof.rows
    return row


def measure(session: Path, out: Path, chunk_frames: int, profile: bool, nwb: bool = False) -> dict:
    cmd = [sys.executable, __file__, "--child", str(session), "--child-out", str(out)]
    cmd += ["--chunk-frames", str(chunk_frames)] + (["--profile"] if profile else [])
    cmd += ["--nwb"] if nwb else []
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), *sys.path]))
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"run {session} failed:\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[100000, 300000, 1000000])
    ap.add_argument("--chunk-frames", type=int, default=50000, help="0: the session whole")
    ap.add_argument("--work", type=Path, default=ROOT / "runs" / "benchmarks" / "long")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "benchmarks" / "long_session.json")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--nwb", action="store_true", help="write the NWB file too (output.nwb)")
    ap.add_argument("--keep-outputs", action="store_true")
    ap.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--child-out", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.child is not None:
        row = child(args.child, args.child_out, args.chunk_frames, args.profile, args.nwb)
        print(json.dumps(row))
        return {}
    rows = []
    for T in args.frames:
        session = ensure_session(args.work, T)
        out = args.work / f"out_{T}_{args.chunk_frames}"
        row = measure(session, out, args.chunk_frames, args.profile, args.nwb)
        if not args.keep_outputs:
            shutil.rmtree(out, ignore_errors=True)
        log.info(
            "T=%d chunk_frames=%d: peak %.0f MB, %.0f s (%d chunks), reprojection median %.2f px",
            row["frames"],
            args.chunk_frames,
            row["peak_rss_mb"],
            row["seconds"],
            row["chunks"],
            row["reprojection_median_px"] or float("nan"),
        )
        rows.append(row)
        _result(rows, argv, args.out, final=False)  # each size as it ends (a long run may stop)
    return _result(rows, argv, args.out, final=True)


def _result(rows: list[dict], argv, out: Path, final: bool) -> dict:
    result = {
        "benchmark": "long_session",
        "command": " ".join(["benchmarks/long_session.py", *(argv or sys.argv[1:])]),
        "parts": 12,
        "cameras": 3,
        "body": "auto",
        "deformation": "interp",
        "target_peak_mb_at_1m": TARGET_MB_1M,
        "runs": rows,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "complete": final,
    }
    if final:
        emit(result, out)
    else:
        write_text(out, json.dumps(finite_or_none(result)) + "\n")
    return result


if __name__ == "__main__":
    main()
