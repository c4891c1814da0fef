"""Simulator throughput: frames per second of `deformnet.sim.simulate` (default config).

    .venv/bin/python benchmarks/simulate.py                  # 1,000,000 frames, best of 1
    .venv/bin/python benchmarks/simulate.py --frames 200000 --repeat 3

Requirement: 1,000,000 frames in under 60 s on a 2-core CPU. Prints a summary and, as its last
line, JSON {"frames_per_s": ..., "frames": ..., "seconds": ..., ...}, also written atomically to
runs/benchmarks/simulate.json (or --out).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import sys
import time
from pathlib import Path

from deformnet.atomic import write_text
from deformnet.sim import simulate

log = logging.getLogger("benchmarks.simulate")
ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=1, help="runs; the fastest counts")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "benchmarks" / "simulate.json")
    args = ap.parse_args(argv)
    if args.frames < 1 or args.repeat < 1:
        ap.error("--frames and --repeat must be >= 1")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    simulate(num_frames=1000, seed=args.seed)  # warm-up: imports, caches
    times = []
    for i in range(args.repeat):
        t0 = time.perf_counter()
        data = simulate(num_frames=args.frames, seed=args.seed + i)
        times.append(time.perf_counter() - t0)
        log.info("run %d: %d frames in %.2f s", i + 1, args.frames, times[-1])
        del data
    best = min(times)
    result = {
        "frames_per_s": args.frames / best,
        "frames": args.frames,
        "seconds": best,
        "seconds_all": times,
        "seconds_per_million": best * 1e6 / args.frames,
        "cpu_count": os.cpu_count(),
        "load_avg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "python": platform.python_version(),
    }
    write_text(args.out, json.dumps(result, indent=2) + "\n")
    print(
        f"simulate: {args.frames} frames in {best:.2f} s "
        f"({result['frames_per_s']:,.0f} frames/s; written to {args.out})"
    )
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
