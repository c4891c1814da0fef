"""Imputation benchmark: how well do the deformation nets fill gaps in a body part's track?

Trains both nets (LSTM, transformer) with the default CPU config (`deformnet-train` defaults,
~5 min each on a 2-core machine) and evaluates them on held-out simulated sequences (seeds no
training run uses, the simulator's own missing data switched off so the truth is known
everywhere): in each window, a gap of 1, 5 or 15 frames centred on the mid frame hides every
part's deformed position (the mid frame and its neighbours), and 30% of the other tokens are
missing at random. Metric: RMSE (mm, 3D point distance) of the mid frame's deformed positions over
all parts, for the nets and two baselines on the same windows: rigid (predict X̄) and linear
interpolation between the nearest observed frames in the window.

    .venv/bin/python benchmarks/imputation.py                       # train + evaluate
    .venv/bin/python benchmarks/imputation.py --checkpoint lstm=runs/.../best.ckpt \\
        --checkpoint transformer=runs/.../best.ckpt                 # evaluate only
    .venv/bin/python benchmarks/imputation.py -o trainer.max_time=00:00:02:00   # overrides

Prints a table and, as its last line, JSON {"lstm": {"gap1": rmse, "gap5": ..., "gap15": ...},
"transformer": {...}, "rigid": {...}, "linear": {...}}, also written atomically to
runs/benchmarks/imputation.json (details beside it in imputation_details.json).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import torch

from deformnet.atomic import write_text
from deformnet.paths import CONF_DIR

log = logging.getLogger("benchmarks.imputation")

NETS = ("lstm", "transformer")
GAPS = (1, 5, 15)
TEST_SEED = 90_000  # held out: training uses seed + i and seed + 10_000 + i


def compose(overrides: list[str]):
    import hydra

    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose("train", overrides=overrides)


def train(net: str, out_root: Path, overrides: list[str]) -> tuple[str, dict]:
    """Train one net with the default config (plus overrides); returns (best checkpoint, result)."""
    from deformnet.train import run

    cfg = compose([f"net={net}", f"output.dir={out_root / net}", "progress_bar=none", *overrides])
    t0 = time.monotonic()
    result = run(cfg)
    result["train_seconds"] = time.monotonic() - t0
    ckpt = result["best_checkpoint"] or result["last_checkpoint"]
    if not ckpt:
        raise RuntimeError(f"training {net} wrote no checkpoint")
    return ckpt, result


@torch.no_grad()
def evaluate(
    model,
    windows: int,
    sequences: int,
    num_frames: int,
    dropout: float,
    seed: int,
    overrides: list[str],
) -> dict[str, dict[str, float]]:
    """RMSE (mm) of the model and the rigid / linear baselines for every gap in GAPS."""
    from omegaconf import OmegaConf

    from deformnet.data import FixedWindowBatches, WindowBank, simulate_sequences
    from deformnet.tokens import linear_baseline

    cfg = compose(overrides)
    sim = OmegaConf.to_container(cfg.sim, resolve=True)
    sim["missing"] = dict(sim.get("missing") or {}, dropout=0.0, occlusion_rate=0.0)
    seqs = simulate_sequences(sim, model.body, num_frames, [seed + i for i in range(sequences)])
    n = model.half_window
    bank = WindowBank(seqs, n)
    out: dict[str, dict[str, float]] = {"model": {}, "rigid": {}, "linear": {}}
    for gap in GAPS:
        data = FixedWindowBatches.build(
            bank, windows, 512, seed=seed + gap, gap=gap, dropout=dropout
        )
        se = {k: torch.zeros((), dtype=torch.float64) for k in out}
        count = 0
        for b in data.batches:
            rigid, deformed, observed, target = (
                b["rigid"],
                b["deformed"],
                b["observed"],
                b["target"],
            )
            preds = {
                "model": model(rigid, deformed, observed),
                "rigid": rigid[:, n],
                "linear": linear_baseline(rigid, deformed, observed, n),
            }
            for k, p in preds.items():
                se[k] += ((p - target) ** 2).sum(-1).sum().double()
            count += target.shape[0] * target.shape[1]
        for k in out:
            out[k][f"gap{gap}"] = float((se[k] / count).sqrt())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--checkpoint",
        action="append",
        default=[],
        metavar="NET=PATH",
        help="evaluate this checkpoint instead of training NET",
    )
    ap.add_argument(
        "-o",
        "--override",
        action="append",
        default=[],
        help="Hydra override for training (e.g. trainer.max_time=00:00:02:00)",
    )
    ap.add_argument("--out", default="runs/benchmarks/imputation.json")
    ap.add_argument("--train-dir", default="runs/benchmarks/imputation")
    ap.add_argument("--windows", type=int, default=4000, help="evaluation windows per gap")
    ap.add_argument("--sequences", type=int, default=4, help="held-out sequences")
    ap.add_argument("--frames", type=int, default=3000, help="frames per held-out sequence")
    ap.add_argument("--dropout", type=float, default=0.3)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    torch.set_num_threads(args.threads)

    from deformnet.deformation import DeformationModel

    given = dict(c.split("=", 1) for c in args.checkpoint)
    unknown = set(given) - set(NETS)
    if unknown:
        ap.error(f"unknown nets {sorted(unknown)}; use {', '.join(NETS)}")
    details: dict = {
        "nets": {},
        "dropout": args.dropout,
        "windows": args.windows,
        "sequences": args.sequences,
        "frames": args.frames,
        "gaps": list(GAPS),
    }
    results: dict[str, dict[str, float]] = {}
    baselines = None
    for net in NETS:
        if net in given:
            ckpt, info = given[net], {}
        else:
            log.info(
                "training %s (default CPU config%s)",
                net,
                f", overrides {args.override}" if args.override else "",
            )
            ckpt, info = train(net, Path(args.train_dir), args.override)
        model = DeformationModel.from_checkpoint(ckpt).eval()
        t0 = time.monotonic()
        ev = evaluate(
            model, args.windows, args.sequences, args.frames, args.dropout, TEST_SEED, args.override
        )
        results[net] = ev["model"]
        baselines = baselines or {"rigid": ev["rigid"], "linear": ev["linear"]}
        details["nets"][net] = {
            "checkpoint": str(ckpt),
            "half_window": model.half_window,
            "train_seconds": info.get("train_seconds"),
            "val_metrics": info.get("metrics"),
            "eval_seconds": time.monotonic() - t0,
        }
    results.update(baselines or {})

    # table
    cols = [*NETS, "rigid", "linear"]
    lines = [
        "",
        "imputation RMSE (mm), mid frame, all parts; 30% other tokens missing",
        f"{'gap':>6} "
        + " ".join(f"{c:>12}" for c in cols)
        + " "
        + " ".join(f"{c + '/rigid':>18} {c + '/linear':>19}" for c in NETS),
    ]
    for gap in GAPS:
        key = f"gap{gap}"
        row = f"{gap:>6} " + " ".join(f"{results[c][key]:>12.3f}" for c in cols)
        for c in NETS:
            row += f" {results[c][key] / results['rigid'][key]:>18.2f}"
            row += f" {results[c][key] / results['linear'][key]:>19.2f}"
        lines.append(row)
    ok = all(
        results[c][f"gap{g}"] <= 0.5 * results["rigid"][f"gap{g}"] for c in NETS for g in GAPS
    ) and all(
        results[c][f"gap{g}"] <= 0.5 * results["linear"][f"gap{g}"] for c in NETS for g in (5, 15)
    )
    lines.append(
        f"target (nets <= 0.5x rigid at every gap, <= 0.5x linear at 5 and 15): "
        f"{'met' if ok else 'NOT met'}"
    )
    print("\n".join(lines), flush=True)

    out = Path(args.out)
    write_text(out, json.dumps(results) + "\n")
    details["results"] = results
    details["target_met"] = ok
    write_text(out.with_name(out.stem + "_details.json"), json.dumps(details, indent=2) + "\n")
    print(json.dumps(results), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
