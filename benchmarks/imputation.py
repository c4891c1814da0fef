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

``--real``: the same question on a real mouse's motion (``shared/data/real-mouse-motion-3d``,
the paper's 8 parts, in the floor's frame, `real_tokens`): tokens from the real 3D truth with
a rigid body fit (the default mouse's model, one scale fitted on frames 0-2399, moved by each
frame's least-squares rigid fit to the truth; the deformed position is the truth itself, so
every part-frame is measured). Evaluated on the held-out third (frames 2400-3599, which no
net may train on): in each window, a gap of 1, 5, 15 or 45 frames centred on the mid frame
hides every part, and 30% of the other tokens are missing at random (`gap_batches`); a
window sees a gap wider than itself at a wider token step (`gap_step`: the smallest of the
net's trained steps and ``--steps``, by default 1, 2, 3 as ``adapt.augment.steps``, that
leaves context on both sides; the tracker's ``deform.far_steps``), every method on the same
windows. Methods:
the shipped net (``deformnet.pretrained.load_default``, evaluate-only, through
`DeformationModel`), linear interpolation (`deformnet.tokens.linear_baseline`), interp's
kriging (`adjust.net_gate.kriged_mid`, what ``deformation=interp`` predicts, with the
offset covariance estimated from the held-out third's own tokens as interp estimates it from
its session), a DISK-style transformer (`peers.disk`, trained on frames 0-2399 only, windows
of the net's length at the same token steps) and the rigid model. Target: the net <= 0.7x
linear interpolation at gaps 15 and 45.

    .venv/bin/python benchmarks/imputation.py --real [--disk-seconds 300] [--windows 4000]

Prints the table; the last line is JSON, also written to runs/benchmarks/imputation_real.json.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch

from deformnet.atomic import write_text
from deformnet.paths import CONF_DIR, real_mouse_motion_dir

sys.path.insert(0, str(Path(__file__).resolve().parent))

log = logging.getLogger("benchmarks.imputation")

NETS = ("lstm", "transformer")
GAPS = (1, 5, 15)
TEST_SEED = 90_000  # held out: training uses seed + i and seed + 10_000 + i

#: --real: the recording, its split (fixed before any choice: the last third held out) and gaps
REAL_DATA = real_mouse_motion_dir() / "poses3d.csv"  # $MOUSETRACK_SHARED or ../shared
REAL_TRAIN = (0, 2400)
REAL_HELD_OUT = (2400, 3600)
REAL_GAPS = (1, 5, 15, 45)
REAL_METHODS = ("net", "linear", "kriging", "disk", "rigid")
MIN_CONTEXT = 4  # tokens a window keeps on each side of a gap (gap_step)
REAL_TARGET = 0.7  # the net / linear interpolation at gaps 15 and 45


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


# --- real motion (--real) --------------------------------------------------------------------


def gap_step(gap: int, half_window: int, steps) -> int:
    """The token step at which a window of 2 half_window + 1 tokens sees a `gap`-frame gap
    centred on its mid frame with at least `MIN_CONTEXT` observable tokens on each side: the
    smallest of `steps` (the net's trained steps) that does, else the largest."""
    steps = sorted({int(s) for s in steps})
    room = int(half_window) - MIN_CONTEXT
    for s in steps:
        if room >= 1 and (int(gap) // 2) // s < room:
            return s
    return steps[-1]


def rigid_fit(points: np.ndarray, model_points: np.ndarray, fit: slice) -> tuple:
    """The rigid body model that best explains `points` (T, K, 3) mm: `model_points` (K, 3)
    times one scale (least squares over the frames `fit`, after each frame's rotation), moved
    by each frame's least-squares rigid fit (`deformnet.so3.kabsch`). Returns (rigid (T, K, 3),
    body points (K, 3), scale)."""
    from deformnet.so3 import kabsch

    X = torch.as_tensor(np.asarray(points, dtype=np.float64))
    B = torch.as_tensor(np.asarray(model_points, dtype=np.float64))
    Bc = B - B.mean(0)
    R, _ = kabsch(X[fit], Bc)
    Xc = X[fit] - X[fit].mean(-2, keepdim=True)
    scale = float((Xc * (Bc @ R.transpose(-1, -2))).sum() / (len(Xc) * (Bc * Bc).sum()))
    body = scale * B
    R, t = kabsch(X, body)
    rigid = body @ R.transpose(-1, -2) + t[..., None, :]
    return rigid.numpy(), body.numpy(), scale


def real_tokens(path: Path, parts) -> tuple:
    """The recording's `parts` (the default mouse's names, `MOTION_PAPER8`) in the floor's
    frame (z up, mm) as a `deformnet.windows.SequenceArrays` (rigid: the default mouse's model
    fitted, `rigid_fit` with its scale from frames REAL_TRAIN; deformed: the truth; every
    part-frame observed), the body model and the scale."""
    from adjust.scene.motion import MOTION_FEET, MOTION_PAPER8, floor_frame, load_motion
    from deformnet.body import BodyModel, default_mouse
    from deformnet.windows import SequenceArrays

    X, names = load_motion(path)
    A = floor_frame(X, names, MOTION_FEET)
    X = X @ A[:3, :3].T + A[:3, 3]
    idx = [names.index(MOTION_PAPER8[p]) for p in parts]
    X = X[:, idx]
    mouse = default_mouse()
    model_points = np.array([mouse.points[mouse.parts.index(p)] for p in parts])
    rigid, body_points, scale = rigid_fit(X, model_points, slice(*REAL_TRAIN))
    body = BodyModel.from_mapping(
        {p: [float(c) for c in xyz] for p, xyz in zip(parts, body_points)}, name="real_mouse"
    )
    observed = np.isfinite(X).all(-1)
    seq = SequenceArrays(rigid.astype(np.float32), X.astype(np.float32), observed)
    return seq, body, scale


def cut(seq, start: int, stop: int):
    """Frames start..stop-1 of a `SequenceArrays`."""
    from deformnet.windows import SequenceArrays

    s = slice(start, stop)
    return SequenceArrays(seq.rigid[s], seq.deformed[s], seq.observed[s])


def gap_batches(seq, half_window: int, step: int, gap: int, dropout: float, windows: int,
                seed: int) -> list[dict]:  # fmt: skip
    """Evaluation windows of `seq` at token `step`, evenly spaced (at most `windows`): a gap
    of `gap` frames centred on the mid frame hides every part (ceil(gap / step) tokens; an
    even count reaches one token further before the mid frame), `dropout` of the other tokens
    hidden at random (`deformnet.windows.gap_masks`). Batches of rigid, deformed, observed,
    target, target_mask (`deformnet.windows.WindowBank.batch`)."""
    from deformnet.windows import FixedWindowBatches, WindowBank

    bank = WindowBank([seq], half_window, step)
    tokens = max(1, -(-int(gap) // int(step)))  # the gap's frames, in tokens at this step
    data = FixedWindowBatches.build(bank, windows, 512, seed, gap=tokens, dropout=dropout)
    return data.batches


def disk_training_set(seq, steps, length: int = 400) -> np.ndarray:
    """The DISK-style peer's training sequences (N, length, K, 3): the truth of `seq` at
    every token step of `steps` (each phase), cut into pieces of `length` tokens."""
    out = []
    for s in sorted({int(x) for x in steps}):
        for phase in range(s):
            X = seq.deformed[phase::s]
            out += [X[i : i + length] for i in range(0, len(X) - length + 1, length)]
    return np.stack(out).astype(np.float64)


@torch.no_grad()
def disk_mid(model, batch: dict, mid: int) -> torch.Tensor:
    """The DISK-style peer's prediction of each window's mid frame (B, K, 3): the window's
    observed deformed points, the rest missing (`peers.disk.impute`)."""
    from peers.disk import impute

    X = torch.where(batch["observed"][..., None], batch["deformed"], float("nan")).double()
    out = [torch.as_tensor(impute(model, w.numpy())[mid]) for w in X]
    return torch.stack(out).to(batch["rigid"].dtype)


@torch.no_grad()
def evaluate_real(
    model, seq, cov, disk, gaps, steps, dropout: float, windows: int, seed: int
) -> dict:
    """RMSE (mm) of every method in REAL_METHODS (disk None: left out) at each gap on the
    held-out windows of `seq` (mid frame, all parts), with the token step each gap used (the
    smallest of `steps` that sees past it, `gap_step`)."""
    from adjust.net_gate import kriged_mid
    from deformnet.tokens import linear_baseline

    n = model.half_window
    out: dict = {m: {} for m in REAL_METHODS if m != "disk" or disk is not None}
    out["step"] = {}
    for gap in gaps:
        step = gap_step(gap, n, steps)
        se = {m: 0.0 for m in out if m != "step"}
        count = 0
        for b in gap_batches(seq, n, step, gap, dropout, windows, seed + gap):
            r, d, o = b["rigid"], b["deformed"], b["observed"]
            preds = {
                "net": model(r, d, o),
                "linear": linear_baseline(r, d, o, n),
                "kriging": kriged_mid(b, model.body_points.double(), cov, n, step).float(),
                "rigid": r[:, n],
            }
            if disk is not None:
                preds["disk"] = disk_mid(disk, b, n)
            m = b["target_mask"]
            for k, p in preds.items():
                se[k] += float((((p - b["target"]) ** 2).sum(-1) * m).sum())
            count += int(m.sum())
        for k in se:
            out[k][f"gap{gap}"] = (se[k] / max(count, 1)) ** 0.5
        out["step"][f"gap{gap}"] = step
    return out


def offset_covariance(seq, body_points: np.ndarray):
    """interp's offset covariance (`adjust.lsq.stochastic.OffsetCovariance.estimate`) of a
    sequence's body-axis offsets R^T (deformed - rigid), where observed."""
    from adjust.lsq.stochastic import OffsetCovariance
    from deformnet.so3 import kabsch

    rigid = torch.as_tensor(seq.rigid, dtype=torch.float64)
    R, _ = kabsch(rigid, torch.as_tensor(body_points, dtype=torch.float64))
    d = torch.as_tensor(seq.deformed, dtype=torch.float64) - rigid
    off = torch.einsum("tji,tkj->tki", R, d).numpy()
    return OffsetCovariance.estimate(off, seq.observed)


def main_real(args) -> int:
    """``--real``: the table, runs/benchmarks/imputation_real.json (see the module docstring)."""
    from peers.disk import fit_disk

    from deformnet.deformation import DeformationModel
    from deformnet.pretrained import DEFAULT_CHECKPOINT, load_default

    shipped = load_default() if args.real_checkpoint is None else (
        DeformationModel.from_checkpoint(args.real_checkpoint))  # fmt: skip
    parts = tuple(default_parts()) if shipped.part_agnostic else tuple(shipped.body.parts)
    seq, body, scale = real_tokens(Path(args.data), parts)
    # the shipped net on the recording's body model (its canonical frames), weights as shipped
    model = shipped.for_body(body, "imputation --real").eval()
    train, held = cut(seq, *REAL_TRAIN), cut(seq, *REAL_HELD_OUT)
    cov = offset_covariance(held, np.array(body.points))
    allowed = sorted({*model.steps, *(int(x) for x in args.steps.split(","))})
    steps = sorted({gap_step(g, model.half_window, allowed) for g in REAL_GAPS})
    disk, disk_facts = None, None
    if args.disk_seconds > 0:
        log.info("training the DISK-style peer %.0f s on frames %s (steps %s)",
                 args.disk_seconds, REAL_TRAIN, steps)  # fmt: skip
        torch.manual_seed(0)
        disk, disk_facts = fit_disk(
            disk_training_set(train, steps), seconds=args.disk_seconds, window=model.window
        )
    t0 = time.monotonic()
    res = evaluate_real(
        model, held, cov, disk, REAL_GAPS, allowed, args.dropout, args.windows, TEST_SEED
    )
    cols = [m for m in REAL_METHODS if m in res]
    lines = [
        "",
        f"imputation on real motion (frames {REAL_HELD_OUT[0]}-{REAL_HELD_OUT[1] - 1}, "
        f"{len(parts)} parts): RMSE (mm), mid frame, all parts; {args.dropout:.0%} of the "
        "other tokens missing",
        f"{'gap':>5} {'step':>5} " + " ".join(f"{c:>9}" for c in cols)
        + f" {'net/linear':>11} {'net/kriging':>12}",
    ]  # fmt: skip
    for g in REAL_GAPS:
        k = f"gap{g}"
        lines.append(
            f"{g:>5} {res['step'][k]:>5} " + " ".join(f"{res[c][k]:>9.3f}" for c in cols)
            + f" {res['net'][k] / res['linear'][k]:>11.2f}"
            + f" {res['net'][k] / res['kriging'][k]:>12.2f}"
        )  # fmt: skip
    ratios = {f"gap{g}": res["net"][f"gap{g}"] / res["linear"][f"gap{g}"] for g in REAL_GAPS}
    met = all(ratios[f"gap{g}"] <= REAL_TARGET for g in (15, 45))
    lines.append(
        f"target (net <= {REAL_TARGET}x linear at gaps 15 and 45): "
        f"{'met' if met else 'NOT met'} ({ratios['gap15']:.2f}, {ratios['gap45']:.2f})"
    )
    print("\n".join(lines), flush=True)
    ckpt = Path(args.real_checkpoint) if args.real_checkpoint else DEFAULT_CHECKPOINT
    summary = {
        "data": str(args.data),
        "held_out_frames": list(REAL_HELD_OUT),
        "train_frames": list(REAL_TRAIN),
        "parts": list(parts),
        "tokens": "real 3D truth, rigid body fit (default mouse model, scale fitted on the "
        "train frames)",
        "body_scale": scale,
        "net": {
            "checkpoint": str(ckpt),
            "sha256": hashlib.sha256(ckpt.read_bytes()).hexdigest(),
            "net": (shipped.net_config or {}).get("_target_"),
            "half_window": model.half_window,
            "steps": list(model.steps),
        },  # fmt: skip
        "disk": disk_facts,
        "dropout": args.dropout,
        "windows": args.windows,
        "results": res,
        "net_over_linear": ratios,
        "target": REAL_TARGET,
        "target_met": met,
        "eval_seconds": round(time.monotonic() - t0, 1),
    }
    write_text(Path(args.real_out), json.dumps(summary) + "\n")
    print(json.dumps(summary), flush=True)
    return 0


def default_parts() -> list[str]:
    """The default mouse's parts (the real recording's 8, `MOTION_PAPER8`)."""
    from deformnet.body import default_mouse

    return list(default_mouse().parts)


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
    ap.add_argument("--real", action="store_true", help="real motion (the docstring's --real)")
    ap.add_argument("--data", default=str(REAL_DATA), help="--real: the recording")
    ap.add_argument("--disk-seconds", type=float, default=300.0,
                    help="--real: the DISK-style peer's training (0: left out)")  # fmt: skip
    ap.add_argument("--real-checkpoint", default=None,
                    help="--real: a net instead of the shipped one")  # fmt: skip
    ap.add_argument(
        "--steps",
        default="1,2,3",
        help="--real: token steps a window may use beside the net's (adapt.augment.steps')",
    )
    ap.add_argument("--real-out", default="runs/benchmarks/imputation_real.json")
    args = ap.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    torch.set_num_threads(args.threads)
    if args.real:  # (--windows: at most every window of the held-out third, ~1170)
        return main_real(args)

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
