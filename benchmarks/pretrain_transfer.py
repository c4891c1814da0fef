"""Pretraining objectives judged on a mouse the nets were not trained on.

A net's validation RMSE is measured on the simulator it was trained on; what matters is how it
tracks another mouse. Each variant of `deformnet-train` (the default LSTM, the default
simulator, `--seconds` of CPU training, each `--seeds` value once: `seed=S`):

- ``body``: the masked-frame objective, windows in the body frame (the shipped net's recipe);
- ``heading``: the masked-frame objective in the heading frame (`up=[0,0,1]`);
(The forecasting term's variants were measured at commit 2e8c1a5 and deleted with the term.)

Each net then tracks the `sim=mouse_b` scenes of `benchmarks/domain_gap.py` (the second
simulated mouse: 1.2x Table 1, 100 fps, trot, spine bending, free head, rearing; scene seeds
``--scenes``, nothing trains on them) with `adjust-track deformation=CKPT`, and beside them
`adjust-track`'s default (``interp``, no net). Reported per variant: the val RMSE on its own
simulator, and per scene RMSE mm all / seen by >= 2 cameras / occluded (< 2), the fraction
within 5 mm and the uncertainty calibration (rms error / rms `_sigma`, seen / occluded); the
means over seeds and scenes, and each variant's mean RMSE (all, occluded) relative to
``body``'s.

    .venv/bin/python benchmarks/pretrain_transfer.py [--variants body,heading]
        [--seeds 0,1] [--seconds 240] [--scenes 92000,92010] [--frames 1500]

Prints a table; the last line is JSON, also written atomically to
runs/benchmarks/pretrain_transfer.json.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, start, subset  # noqa: E402
from domain_gap import ROOT, calibration, evaluate, make_scene  # noqa: E402
from tracking import run_track, train_net  # noqa: E402

log = logging.getLogger("benchmarks.pretrain_transfer")

HEADING = ["up=[0,0,1]"]
VARIANTS = {
    "body": [],
    "heading": HEADING,
}
COLUMNS = ("rmse_all", "rmse_seen2", "rmse_occluded", "within5", "calib_seen", "calib_occluded")


def _ints(ap: argparse.ArgumentParser, text: str, flag: str) -> list[int]:
    try:
        out = [int(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        ap.error(f"{flag}: comma-separated integers, got {text!r}")
    if not out:
        ap.error(f"{flag}: at least one value")
    return out


def track_scene(scene: Path, out: Path, overrides: list[str]) -> dict:
    tr = np.load(scene / "truth.npz")
    truth, nviews = tr["points"], tr["nviews"]
    parts = [str(p) for p in tr["parts"]]
    est, secs, _ = run_track(scene, out, ["threads=1", *overrides])
    return {
        **evaluate(est, truth, nviews),
        **calibration(out, est, truth, nviews, parts),
        "seconds": round(secs, 2),
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--seeds", default="0,1", help="deformnet-train seeds, one net each")
    ap.add_argument("--seconds", type=int, default=240, help="CPU training per net")
    ap.add_argument("--scenes", default="92000,92010", help="mouse_b scene seeds")
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "pretrain_transfer"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "pretrain_transfer.json"))
    ap.add_argument("--threads", type=int, default=1)
    args = start(ap, argv)
    logging.getLogger("lightning.pytorch").setLevel(logging.WARNING)
    t_start = time.perf_counter()
    variants = subset(ap, args.variants, VARIANTS, "--variants")
    seeds = _ints(ap, args.seeds, "--seeds")
    scene_seeds = _ints(ap, args.scenes, "--scenes")
    if args.seconds < 10:
        ap.error(f"--seconds: at least 10, got {args.seconds}")
    work = Path(args.work)
    scenes = {
        s: make_scene(work / f"scene_mouse_b_{args.frames}_{s}", args.frames, s)
        for s in scene_seeds
    }
    interp = {s: track_scene(sc, work / f"interp_{s}", []) for s, sc in scenes.items()}
    secs = f"00:00:{args.seconds // 60:02d}:{args.seconds % 60:02d}"
    runs: dict = {}
    for name in variants:
        for seed in seeds:
            key = f"{name}/{seed}"
            ov = [f"trainer.max_time={secs}", f"seed={seed}", *VARIANTS[name]]
            log.info("%s: deformnet-train %s", key, ov)
            ckpt, tsecs, metrics = train_net(work / "nets" / f"{name}_{seed}", ov)
            runs[key] = {
                "checkpoint": ckpt,
                "train_seconds": round(tsecs, 1),
                "val_rmse_mm": metrics.get("best/val_rmse_mm"),
                "scenes": {
                    str(s): track_scene(sc, work / f"{name}_{seed}_{s}", [f"deformation={ckpt}"])
                    for s, sc in scenes.items()
                },
            }
            log.info("%s: %s", key, {s: round(r["rmse_all"], 3)
                                     for s, r in runs[key]["scenes"].items()})  # fmt: skip
    table: dict = {}
    for name in variants:
        rs = [runs[f"{name}/{seed}"] for seed in seeds]
        row = {"val_rmse_mm": float(np.mean([r["val_rmse_mm"] for r in rs]))}
        for c in COLUMNS:
            row[c] = float(np.mean([r["scenes"][str(s)][c] for r in rs for s in scene_seeds]))
        row["rmse_all_per_net"] = [round(r["scenes"][str(s)]["rmse_all"], 3)
                                   for r in rs for s in scene_seeds]  # fmt: skip
        table[name] = row
    table["interp"] = {c: float(np.mean([interp[s][c] for s in scene_seeds])) for c in COLUMNS}
    if "body" in table:
        for name in variants:
            for c in ("rmse_all", "rmse_occluded"):
                table[name][f"{c}_vs_body"] = table[name][c] / table["body"][c]
    print(f"\npretraining objectives on another mouse: {len(seeds)} nets x {args.seconds} s "
          f"each, tracking mouse_b scenes {scene_seeds} ({args.frames} frames); means")  # fmt: skip
    head = ["val mm", "all", "seen2", "occl.", "<=5mm", "cal s", "cal o", "all/body"]
    print(f"{'variant':<18}" + "".join(f"{h:>9}" for h in head))
    for name, row in table.items():
        vals = [row.get("val_rmse_mm"), *(row[c] for c in COLUMNS), row.get("rmse_all_vs_body")]
        print(f"{name:<18}" + "".join(f"{'n/a':>9}" if v is None else f"{v:>9.3f}" for v in vals))
    summary = {
        "table": table,
        "runs": runs,
        "interp": interp,
        "setup": {"variants": {k: VARIANTS[k] for k in variants}, "seeds": seeds,
                  "seconds": args.seconds, "scenes": scene_seeds, "frames": args.frames},
        "total_seconds": round(time.perf_counter() - t_start, 1),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }  # fmt: skip
    return emit(summary, args.out)


if __name__ == "__main__":
    main()
