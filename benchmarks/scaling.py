"""Scaling of the rigid pose-track adjustment: wall time at T = 10,000 and 100,000 frames,
peak memory at 100,000 and 1,000,000 frames, and the deformable adjustment (adjust-track with
the learned net) at 10,000 frames.

Synthetic scene: the default mouse body model (8 parts), 3 ring cameras, a smooth trajectory
that keeps turning through 180 degrees, 2 px Gaussian detector noise, 20 % missing detections.
Default solver settings (grid constraint, two-Gaussian mixture, Cauchy kernel), fit
initialisation included in the time. Prints one line per size and a JSON summary as the last
line, also written to runs/benchmarks/scaling.json.

Memory: each size in its own process (so the peaks are separate). The synthetic detections are
made first; then the kernel's peak-RSS counter is reset (/proc/self/clear_refs; where that is
refused, a thread samples VmRSS every 5 ms) and `adjust_poses` runs: ``peak_rss_mb`` is the
process's peak resident set size during the adjustment (interpreter, torch, inputs, working
memory and the result), ``before_rss_mb`` the resident size just before it, ``inputs_mb`` the
detections and weights (float64), ``result_mb`` the arrays of the returned `AdjustmentResult`.

Deformable: a simulated 10,000-frame scene (adjust-simulate, default rig), `adjust-track` with
the learned net (``deformation=default``, the shipped net, or ``--checkpoint``) end to end
(loading, rigid, interp and net stages, outputs), timed against the rigid `adjust-track` on the
same scene: ``deformable_over_rigid_adjustment`` (the adjustment stages, target <= 3) and
``deformable_over_rigid_end_to_end``.

    .venv/bin/python benchmarks/scaling.py [--frames 10000 100000] [--threads 1]
        [--memory-frames 100000 1000000] [--deformable-frames 10000]
        [--checkpoint runs/.../best.ckpt]  (--deformable-frames 0 / --memory-frames 0: skip)
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch
from common import emit

from adjust.camera import CameraTensors
from adjust.lsq import SolverConfig, adjust_poses, synthetic
from adjust.lsq.geometry import pose_difference
from adjust.lsq.solver import TRACK_OUTPUTS
from deformnet.body import default_mouse
from deformnet.paths import CONF_DIR

log = logging.getLogger("benchmarks.scaling")


def run_one(T: int, threads: int, seed: int = 0) -> dict:
    body = torch.tensor(default_mouse().points)
    cams = CameraTensors.from_cameras(synthetic.ring_cameras(3))
    truth = synthetic.smooth_trajectory(T, seed=seed)
    xy, w, _ = synthetic.simulate(truth, body, cams, noise_px=2.0, drop=0.2, seed=seed)
    cfg = SolverConfig(num_threads=threads)
    t0, c0 = time.perf_counter(), time.process_time()
    res = adjust_poses(xy, w, cams, body, cfg, progress=False)
    seconds = time.perf_counter() - t0
    cpu = time.process_time() - c0
    d = pose_difference(torch.as_tensor(res.poses), truth)
    return {
        "frames": T,
        "seconds": round(seconds, 3),
        "cpu_seconds": round(cpu, 3),
        "iterations": res.iterations,
        "chunks": res.chunks,
        "converged": bool(res.converged),
        "rot_rmse_rad": float(d[:, :3].pow(2).sum(-1).mean().sqrt()),
        "trans_rmse_mm": float(d[:, 3:].pow(2).sum(-1).mean().sqrt()),
    }


def _status_kb(field: str) -> int:
    """A field of /proc/self/status in kB (VmRSS, VmHWM); -1 where there is none."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return -1


class PeakRSS:
    """Peak resident set size of this process over a `with` block (MB): the kernel's VmHWM after
    resetting it (/proc/self/clear_refs), or, where that is refused, VmRSS sampled every 5 ms."""

    def __enter__(self):
        self.method = "VmHWM"
        try:
            with open("/proc/self/clear_refs", "w") as fh:
                fh.write("5")
        except OSError:
            self.method = "sampled VmRSS"
        self.before_kb = _status_kb("VmRSS")
        self._peak = self.before_kb
        self._stop = threading.Event()
        self._thread = None
        if self.method != "VmHWM":
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.wait(0.005):
            self._peak = max(self._peak, _status_kb("VmRSS"))

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        hwm = _status_kb("VmHWM") if self.method == "VmHWM" else -1
        self.peak_kb = max(self._peak, hwm, _status_kb("VmRSS"))

    @property
    def peak_mb(self) -> float:
        return self.peak_kb / 1024.0

    @property
    def before_mb(self) -> float:
        return self.before_kb / 1024.0


def _trim_heap() -> None:
    """Hand freed heap memory back to the OS (glibc), so "before" is what is really held."""
    import ctypes
    import gc

    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        pass


def memory_one(T: int, threads: int, dtype: str = "float32", seed: int = 0) -> dict:
    """Peak memory of the rigid adjustment of T frames, in this process (see module doc): the
    detections stored as ``dtype``, the result arrays adjust-track keeps (`TRACK_OUTPUTS`)."""

    body = torch.tensor(default_mouse().points)
    cams = CameraTensors.from_cameras(synthetic.ring_cameras(3))
    truth = synthetic.smooth_trajectory(T, seed=seed)
    xy, w, _ = synthetic.simulate(truth, body, cams, noise_px=2.0, drop=0.2, seed=seed)
    xy, w = xy.numpy().astype(dtype), w.numpy().astype(dtype)
    del truth, _
    _trim_heap()
    cfg = SolverConfig(num_threads=threads)
    t0 = time.perf_counter()
    with PeakRSS() as mem:
        res = adjust_poses(xy, w, cams, body, cfg, progress=False, outputs=TRACK_OUTPUTS)
    seconds = time.perf_counter() - t0
    result_mb = sum(v.nbytes for v in vars(res).values() if isinstance(v, np.ndarray)) / 2**20
    return {
        "frames": T,
        "peak_rss_mb": round(mem.peak_mb, 1),
        "before_rss_mb": round(mem.before_mb, 1),
        "inputs_mb": round((np.asarray(xy).nbytes + np.asarray(w).nbytes) / 2**20, 1),
        "result_mb": round(result_mb, 1),
        "kb_per_frame": round((mem.peak_mb - mem.before_mb) * 1024 / T, 3),
        "seconds": round(seconds, 2),
        "method": mem.method,
        "input_dtype": dtype,
        "chunks": res.chunks,
    }


def measure_memory(T: int, threads: int, dtype: str = "float32") -> dict:
    """`memory_one` in a fresh process (its own peak), returning its JSON row."""
    cmd = [sys.executable, __file__, "--memory-child", str(T), "--threads", str(threads)]
    cmd += ["--memory-dtype", dtype]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(CONF_DIR.parent), *sys.path]))
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"memory run T={T} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_deformable(
    T: int, checkpoint: str | None, threads: int, work: Path, overrides: list[str] = ()
) -> dict:
    """Time adjust-track rigid, interp (the default) and deformable on a simulated T-frame
    scene (see module doc)."""
    import tracking  # benchmarks/tracking.py: scene, training and adjust-track helpers

    scene = tracking.ensure_scene(work / f"scene_{T}", T, tracking.SCENE_SEED)
    deformation = f"deformation={checkpoint}" if checkpoint else "deformation=default"
    extra = ([f"threads={threads}"] if threads else []) + list(overrides)
    truth = np.load(scene / "truth.npz")["points"]
    row: dict = {"frames": T, "checkpoint": str(checkpoint or "default (shipped)")}
    for name, overrides in (
        ("rigid", ["deformation=rigid"]),
        ("interp", ["deformation=interp"]),  # adjust-track's default
        ("deformable", [deformation]),
    ):
        points, seconds, summary = tracking.run_track(scene, work / name, overrides + extra)
        err = np.linalg.norm(points - truth, axis=-1)
        t = summary.get("time_s", {})
        row[name] = {
            "seconds": round(seconds, 2),
            "adjust_s": t.get("adjust_s"),  # the adjustments alone (rigid [+ interp + net])
            "stages_s": {
                k: t[k]
                for k in ("rigid_s", "interp_s", "heldout_check_s", "net_s", "measured_prior_s")
                if k in t
            },
            "iterations": summary.get("iterations"),
            "completeness": float(np.isfinite(points).all(-1).mean()),
            "rmse_mm": float(np.sqrt(np.nanmean(err**2))),
        }
        if name == "deformable":
            row[name]["net_passes"] = summary["deformation"].get("net_passes")
        log.info(
            "adjust-track %s, T=%d: %.1f s (adjustment %.1f s), rmse %.2f mm",
            name,
            T,
            seconds,
            t.get("adjust_s", float("nan")),
            row[name]["rmse_mm"],
        )
    r, d = row["rigid"], row["deformable"]
    row["deformable_over_rigid_adjustment"] = round(d["adjust_s"] / r["adjust_s"], 2)
    row["deformable_over_rigid_end_to_end"] = round(d["seconds"] / r["seconds"], 2)
    row["target_ratio"] = 3.0
    return row


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[10000, 100000])
    ap.add_argument("--threads", type=int, default=1, help="torch threads (0: torch default)")
    ap.add_argument("--out", default=str(CONF_DIR.parent / "runs" / "benchmarks" / "scaling.json"))
    ap.add_argument("--deformable-frames", type=int, default=10000, help="0: skip")
    ap.add_argument(
        "--memory-frames", type=int, nargs="+", default=[100000, 1000000], help="0: skip"
    )
    ap.add_argument(
        "--memory-dtype",
        default="float32",
        choices=["float32", "float64"],
        help="storage of the detections in the memory runs (the solver computes in float64)",
    )
    ap.add_argument("--memory-child", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument(
        "--checkpoint", default=None, help="deformation checkpoint (else: the shipped net)"
    )
    ap.add_argument("--work", default=str(CONF_DIR.parent / "runs" / "benchmarks" / "scaling"))
    ap.add_argument("-o", "--override", action="append", default=[],
                    help="an adjust-track setting of the --deformable-frames runs")  # fmt: skip
    args = ap.parse_args(argv)
    if args.memory_child is not None:  # one memory measurement, in its own process
        print(json.dumps(memory_one(args.memory_child, args.threads, args.memory_dtype)))
        return {}
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    memory = []
    for T in [t for t in args.memory_frames if t > 0]:
        row = measure_memory(T, args.threads, args.memory_dtype)
        memory.append(row)
        log.info(
            "T=%7d  peak RSS %.0f MB during the adjustment (%.0f MB before it; inputs %.0f MB, "
            "result %.0f MB; %.2f KB/frame), %.1f s",
            T,
            row["peak_rss_mb"],
            row["before_rss_mb"],
            row["inputs_mb"],
            row["result_mb"],
            row["kb_per_frame"],
            row["seconds"],
        )
    rows = []
    for T in args.frames:
        row = run_one(T, args.threads)
        rows.append(row)
        log.info(
            "T=%7d  %.2f s wall, %.2f s cpu  (%d iterations, %d chunks, "
            "rot rmse %.4f rad, trans rmse %.3f mm)",
            T,
            row["seconds"],
            row["cpu_seconds"],
            row["iterations"],
            row["chunks"],
            row["rot_rmse_rad"],
            row["trans_rmse_mm"],
        )
    secs = [r["seconds"] for r in rows]
    ratio = secs[-1] / secs[0] if len(secs) > 1 and secs[0] > 0 else None
    cpus = [r["cpu_seconds"] for r in rows]
    cpu_ratio = cpus[-1] / cpus[0] if len(cpus) > 1 and cpus[0] > 0 else None
    deformable = None
    if args.deformable_frames > 0:
        deformable = run_deformable(
            args.deformable_frames, args.checkpoint, args.threads, Path(args.work), args.override
        )
    summary = {
        "benchmark": "scaling",
        "parts": 8,
        "cameras": 3,
        "runs": rows,
        "ratio": round(ratio, 3) if ratio is not None else None,
        "cpu_ratio": round(cpu_ratio, 3) if cpu_ratio is not None else None,
        "frame_ratio": args.frames[-1] / args.frames[0] if len(args.frames) > 1 else 1,
        "targets": {"seconds_at_100k": 20.0, "ratio": 12.0},
        "deformable": deformable,
        "memory": memory,
        "memory_target_mb_at_1m": 1536,
        "threads": args.threads or torch.get_num_threads(),
        "cpu": platform.processor() or platform.machine(),
        "load_avg_1min": round(float(np.round(_loadavg(), 2)), 2),
    }
    return emit(summary, args.out)


def _loadavg() -> float:
    try:
        import os

        return os.getloadavg()[0]
    except OSError:  # pragma: no cover
        return float("nan")


if __name__ == "__main__":
    main()
