"""Where the occluded error of `benchmarks/real_motion.py`'s tracks sits: inside the net's reach
or beyond it (issue 48: why a net that beats interpolation on masked windows does not move the
tracks).

The net (``deformation=default|self``) predicts an unmeasured part-frame only where its window
sees the part on both sides (``deform.beyond_window=interp``, the default): within
``half_window`` token steps at step 1, else at a far step (``deform.far_steps``: 2, 3); every
other part-frame takes interp's prediction. This reads a real_motion.py work folder (the
scenes' truth.npz and each method's tracks, ``--work``), takes the measured part-frames from
the defaults' tokens.npz (the consensus observations every mode starts from) and splits each
method's occluded part-frames (seen by < 2 cameras) into: measured; reached at step 1; reached
only at a far step; not reached (one side or none). Per class: its share of the occluded
part-frames, RMSE (mm), its share of the occluded squared error; and the bound: the occluded
RMSE ratio to the defaults if every reached part-frame were exact (the best any net used
where it is used today can do).

    .venv/bin/python benchmarks/occluded_split.py --work runs/benchmarks/real_motion \\
        --methods default,net,self --out runs/benchmarks/occluded_split.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, start  # noqa: E402

from adjust.io import read_points3d  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CLASSES = ("measured", "reach_step1", "reach_far", "beyond")


def one_sided(obs: np.ndarray, n: int, step: int) -> tuple[np.ndarray, np.ndarray]:
    """(T, K) whether the part is observed within n token steps of `step` frames before /
    after each frame (obs (T, K) bool)."""
    T, K = obs.shape
    before, after = np.zeros((T, K), bool), np.zeros((T, K), bool)
    for d in range(1, n + 1):
        s = d * step
        if s >= T:
            break
        before[s:] |= obs[:-s]
        after[:-s] |= obs[s:]
    return before, after


def classes(obs: np.ndarray, half_window: int, far_steps) -> dict[str, np.ndarray]:
    """Each part-frame's class (CLASSES) as (T, K) masks."""
    b, a = one_sided(obs, half_window, 1)
    r1 = b & a
    rf = np.zeros_like(r1)
    for s in far_steps:
        b, a = one_sided(obs, half_window, s)
        rf |= b & a
    return {
        "measured": obs,
        "reach_step1": ~obs & r1,
        "reach_far": ~obs & ~r1 & rf,
        "beyond": ~obs & ~r1 & ~rf,
    }


def split(err2: np.ndarray, occ: np.ndarray, cls: dict[str, np.ndarray]) -> dict:
    """Per class: share of occluded part-frames, RMSE mm, share of the squared error."""
    total, n = float(err2[occ].sum()), int(occ.sum())
    out = {"rmse_occluded": float(np.sqrt(total / max(n, 1)))}
    for name, m in cls.items():
        mm = occ & m
        out[name] = {
            "share": round(float(mm.sum() / max(n, 1)), 4),
            "rmse": round(float(np.sqrt(err2[mm].mean())), 3) if mm.any() else None,
            "error_share": round(float(err2[mm].sum() / total), 4) if total else None,
        }
    reached = occ & (cls["reach_step1"] | cls["reach_far"])
    out["bound_rmse"] = float(np.sqrt(err2[occ & ~reached].sum() / max(n, 1)))
    return out


def scene_rows(run: Path, scene: Path, methods, half_window: int, far_steps) -> dict:
    tr = np.load(scene / "truth.npz")
    truth, occ = tr["points"], tr["nviews"] < 2
    parts = [str(p) for p in tr["parts"]]
    tok = np.load(run / "default" / "tokens.npz")
    order = [list(map(str, tok["parts"])).index(p) for p in parts]
    cls = classes(np.asarray(tok["observed"], bool)[:, order], half_window, far_steps)
    rows = {}
    for m in methods:
        csv = run / m / "points3d.csv"
        if not csv.is_file():
            continue
        p = read_points3d(csv)
        est = np.asarray(p["points"])[:, [list(p["parts"]).index(q) for q in parts]]
        rows[m] = split(((est - truth) ** 2).sum(-1), occ, cls)
    if "default" in rows:
        ref = rows["default"]["rmse_occluded"]
        for r in rows.values():
            r["ratio_default"] = round(r["rmse_occluded"] / ref, 4)
            r["bound_ratio_default"] = round(r["bound_rmse"] / ref, 4)
    return rows


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "real_motion"),
                    help="real_motion.py's --work folder")  # fmt: skip
    ap.add_argument("--methods", default="default,net,self")
    ap.add_argument("--half-window", type=int, default=12, help="the net's (the shipped: 12)")
    ap.add_argument("--far-steps", default="2,3", help="deform.far_steps (the shipped net's)")
    ap.add_argument("--split", default="", help="only scenes whose name starts with this")
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "occluded_split.json"))
    args = start(ap, argv)
    methods = [m for m in args.methods.split(",") if m]
    far = [int(s) for s in args.far_steps.split(",") if s]
    work = Path(args.work)
    runs = sorted(p for p in work.glob("*/runs/*") if p.is_dir())
    scenes = {}
    for run in runs:
        scene = run.parent.parent / "scenes" / run.name
        if not run.name.startswith(args.split) or not (run / "default" / "tokens.npz").is_file():
            continue
        rows = scene_rows(run, scene, methods, args.half_window, far)
        scenes[run.name] = rows
        for m, r in rows.items():
            print(f"{run.name} {m}: occluded {r['rmse_occluded']:.3f} mm "
                  f"({r.get('ratio_default', float('nan')):.3f}x default); "
                  + "; ".join(f"{c} {r[c]['share']:.2f} of part-frames, {r[c]['rmse']} mm, "
                              f"{r[c]['error_share']:.2f} of the error" for c in CLASSES)
                  + f"; bound {r.get('bound_ratio_default', float('nan')):.3f}x",
                  flush=True)  # fmt: skip
    if not scenes:
        raise SystemExit(f"no real_motion.py runs with a default track under {work}")
    return emit({"work": str(work), "half_window": args.half_window, "far_steps": far,
                 "methods": methods, "scenes": scenes}, args.out)  # fmt: skip


if __name__ == "__main__":
    main()
