"""The shipped net as it is (``deformation=default``) with and without its held-out check,
against ``deformation=interp`` (adjust-track's default), on mice it was and was not trained on.

A net trained on one simulated mouse predicts another mouse's hidden parts worse than plain
interpolation for some parts and better for others. ``deform.require_better`` checks the net
on the recording's own held-out windows (`deformnet.heldout`: measured parts hidden as
occlusions hide them, the net against the rigid model plus interpolated offsets) and lets it
predict only the parts it predicts better (``parts``, the default), all parts or none
(``all``), or every part unchecked (``false``, the behaviour before the check). The net runs
after interp's model is adjusted to convergence, while ``deformation=interp`` stops after
``deform.max_iterations`` (10), so ``interp_converged`` (interp with no such limit) is shown
too: the net's own share of a gain is its difference from that row.

Scenes (1500 frames each, the default rig and detector; no training run uses their seeds):
``--other`` seeds of `sim=mouse_b` (1.2x Table 1, 100 fps, trot, spine bending: the second
simulated mouse; by default the seeds of `benchmarks/domain_gap.py`'s two scenes and their
sessions) and ``--own`` seeds of the default simulator (the shipped net's own kind of mouse).
Per scene and method: RMSE all / occluded part-frames (mm), against the truth; the fraction
of part-frames the net predicted; then the means over each group of scenes, their ratios to
interp's and interp_converged's means, and the number of scenes where the method beats
interp.

    .venv/bin/python benchmarks/heldout_gate.py [--other 92000,...] [--own 93000,93001]
        [--frames 1500] [--work runs/benchmarks/heldout_gate] [--out FILE]

Last line JSON, also written to runs/benchmarks/heldout_gate.json. Aniposelib and the other
peers on the same mouse_b scenes: `benchmarks/domain_gap.py`.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, start  # noqa: E402
from domain_gap import evaluate  # noqa: E402
from tracking import ensure_scene, run_track  # noqa: E402

log = logging.getLogger("benchmarks.heldout_gate")
ROOT = Path(__file__).resolve().parent.parent
OTHER = "92000,92001,92002,92003,92010,92011,92012,92013"
OWN = "93000,93001"
METHODS = {
    "interp": ["deformation=interp"],
    # what a net falls back to: interp's model adjusted to convergence (interp: 10 iterations)
    "interp_converged": ["deformation=interp", "deform.max_iterations=null"],
    "default_unchecked": ["deformation=default", "deform.require_better=false"],
    "default_all": ["deformation=default", "deform.require_better=all"],
    "default": ["deformation=default"],  # deform.require_better=parts
}


def seeds(text: str) -> list[int]:
    return [int(s) for s in str(text).split(",") if s.strip()]


def group_summary(rows: dict, names: list[str]) -> dict:
    """Means over the scenes `names`, ratios to interp's, scenes where a method beats interp."""
    out = {}
    for method in METHODS:
        alls = np.array([rows[n][method]["rmse_all"] for n in names])
        occ = np.array([rows[n][method]["rmse_occluded"] for n in names])
        ref = np.array([rows[n]["interp"]["rmse_all"] for n in names])
        conv = np.array([rows[n]["interp_converged"]["rmse_all"] for n in names])
        out[method] = {
            "mean_rmse_all": float(alls.mean()),
            "mean_rmse_occluded": float(occ.mean()),
            "ratio_to_interp": float(alls.mean() / ref.mean()),
            "ratio_to_interp_converged": float(alls.mean() / conv.mean()),
            "scenes_better_than_interp": int((alls < ref - 1e-9).sum()),
            "scenes_worse_than_interp": int((alls > ref + 1e-9).sum()),
        }
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--other", default=OTHER, help="sim=mouse_b scene seeds")
    ap.add_argument("--own", default=OWN, help="default-simulator scene seeds")
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "heldout_gate"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "heldout_gate.json"))
    args = start(ap, argv)
    work = Path(args.work)
    groups = {
        "other_mouse": [(f"mouse_b_{s}", s, ["sim=mouse_b"]) for s in seeds(args.other)],
        "own_mouse": [(f"default_{s}", s, []) for s in seeds(args.own)],
    }
    rows: dict = {}
    for group, scenes in groups.items():
        for name, seed, ov in scenes:
            scene = ensure_scene(work / f"scene_{name}_{args.frames}", args.frames, seed, ov)
            tr = np.load(scene / "truth.npz")
            rows[name] = {"group": group}
            for method, mov in METHODS.items():
                est, secs, summ = run_track(scene, work / name / method, ["threads=1", *mov])
                d = summ.get("deformation", {})
                h = d.get("heldout") or {}
                m = evaluate(est, tr["points"], tr["nviews"])
                rows[name][method] = {
                    **{k: m[k] for k in ("rmse_all", "rmse_occluded")},
                    "net_used_fraction": d.get("net_used_fraction", 0.0),
                    "net_parts": h.get("net_parts"),
                    "seconds": round(secs, 2),
                }
                r = rows[name][method]
                print(
                    f"{name:16s} {method:18s} RMSE all {r['rmse_all']:6.3f}  occluded "
                    f"{r['rmse_occluded']:6.3f}  net used {r['net_used_fraction']:.3f}  "
                    f"({secs:.1f} s)",
                    flush=True,
                )
    summary = {"frames": args.frames, "scenes": rows, "groups": {}}
    for group, scenes in groups.items():
        names = [n for n, _, _ in scenes]
        if not names:
            continue
        g = group_summary(rows, names)
        summary["groups"][group] = g
        print(
            f"\n{group} ({len(names)} scenes): mean RMSE all / occluded mm, ratio to interp "
            "and to interp_converged"
        )
        for method, v in g.items():
            print(
                f"  {method:18s} {v['mean_rmse_all']:6.3f} / {v['mean_rmse_occluded']:6.3f}  "
                f"x{v['ratio_to_interp']:.3f} x{v['ratio_to_interp_converged']:.3f}  "
                "better than interp on "
                f"{v['scenes_better_than_interp']}, worse on {v['scenes_worse_than_interp']}"
            )
    return emit(summary, args.out)


if __name__ == "__main__":
    logging.getLogger("lightning").setLevel(logging.WARNING)
    main()
