"""`make demo`: the main job end to end on the embedded default (simulated data).

Runs the console scripts one after another, exactly as a user would, into
``runs/demo/<time>/``:

1. ``deformnet-simulate``   a deformable mouse in the lock-box arena (sim.npz + figure)
2. ``adjust-simulate``      a 3-camera scene folder: calibration.toml, detections/<cam>.csv, truth
3. ``adjust-triangulate``   the DLT baseline -> points3d.csv
4. ``deformnet-train``      a short training run of the LSTM deformation net (checkpoint)
5. ``adjust-track``         the rigid and the deformable pose-track adjustment -> points3d.csv
6. a table of completeness and 3D error against the simulated truth (also ``summary.json``).

``python -m deformnet.demo --train-minutes 2 --frames 1500`` sets the sizes.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import subprocess
import sys
import time
from pathlib import Path

log = logging.getLogger("demo")


def _script(name: str) -> str:
    """Path of a console script installed beside this interpreter (or on PATH)."""
    local = Path(sys.executable).parent / name
    if local.exists():
        return str(local)
    found = shutil.which(name)
    if found is None:
        raise FileNotFoundError(f"console script '{name}' not found: is mousetrack installed?")
    return found


def _step(title: str, args: list[str]) -> float:
    log.info("== %s: %s", title, " ".join(args))
    t0 = time.perf_counter()
    subprocess.run([_script(args[0]), *args[1:]], check=True)
    return time.perf_counter() - t0


def _evaluate(scene: Path, outputs: dict[str, Path]) -> dict:
    import numpy as np

    from adjust.io import read_points3d
    from adjust.metrics import point_errors

    truth = np.load(scene / "truth.npz")
    parts = [str(p) for p in truth["parts"]]
    rows = {}
    for method, folder in outputs.items():
        res = read_points3d(folder / "points3d.csv")
        order = [res["parts"].index(p) for p in parts]
        est = res["points"][:, order]
        rows[method] = point_errors(est, truth["points"], truth["nviews"], part_names=parts)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--frames", type=int, default=1500, help="frames in the tracked scene")
    ap.add_argument("--train-minutes", type=float, default=2.0, help="LSTM training time")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", type=Path, default=None, help="default: runs/demo/<time>")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")

    out = args.out or Path("runs") / "demo" / time.strftime("%Y-%m-%d_%H-%M-%S")
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    scene = out / "scene"
    minutes = max(0.1, float(args.train_minutes))
    max_time = f"00:00:{int(minutes):02d}:{int(round((minutes % 1) * 60)):02d}"
    seconds = {}
    seconds["simulate"] = _step(
        "simulate",
        [
            "deformnet-simulate",
            "num_frames=9000",
            f"seed={args.seed}",
            f"output.dir={out / 'simulate'}",
        ],
    )
    seconds["scene"] = _step(
        "scene",
        [
            "adjust-simulate",
            f"num_frames={args.frames}",
            f"seed={args.seed}",
            f"output.dir={scene}",
        ],
    )
    common = [
        f"input.calibration={scene / 'calibration.toml'}",
        f"input.detections={scene / 'detections'}",
    ]
    seconds["dlt"] = _step(
        "triangulate (DLT baseline)",
        ["adjust-triangulate", *common, "body=mouse", f"output.dir={out / 'dlt'}"],
    )
    seconds["train"] = _step(
        "train the LSTM deformation net",
        [
            "deformnet-train",
            "net=lstm",
            f"trainer.max_time={max_time}",
            "logger.save_dir=" + str(out / "tb"),
            f"output.dir={out / 'train'}",
        ],
    )
    ckpt = out / "train" / "checkpoints" / "best.ckpt"
    if not ckpt.exists():
        ckpt = out / "train" / "checkpoints" / "last.ckpt"
    seconds["rigid"] = _step(
        "track (rigid adjustment)", ["adjust-track", *common, f"output.dir={out / 'rigid'}"]
    )
    seconds["deformable"] = _step(
        "track (deformable adjustment)",
        ["adjust-track", *common, f"deformation={ckpt}", f"output.dir={out / 'deformable'}"],
    )
    rows = _evaluate(scene, {m: out / m for m in ("dlt", "rigid", "deformable")})

    header = (
        f"{'method':<11}{'complete':>9}{'rmse all':>10}{'rmse seen':>10}{'rmse occl':>10}"
        f"{'<=5mm':>8}{'seconds':>9}"
    )
    lines = [header, "-" * len(header)]
    for m, r in rows.items():
        lines.append(
            f"{m:<11}{r['completeness']:>9.3f}{r['rmse_all']:>10.2f}{r['rmse_seen']:>10.2f}"
            f"{r['rmse_occluded']:>10.2f}{r['within5_all']:>8.3f}{seconds[m]:>9.1f}"
        )
    table = "\n".join(lines)
    print(f"\nmousetrack demo: {args.frames} frames, 3 cameras; 3D error (mm) against truth\n")
    print(table)
    print(f"\nAll outputs: {out}")
    print(f"TensorBoard: tensorboard --logdir {out / 'tb'}")
    from deformnet.atomic import write_text

    summary = {m: {k: v for k, v in r.items() if k != "per_part"} for m, r in rows.items()}
    write_text(
        out / "summary.json", json.dumps({"seconds": seconds, "methods": summary}, indent=2) + "\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
