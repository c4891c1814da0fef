"""Two ways to give a behavior classifier more than a few seconds of context, checked on the
ethogram benchmark's validation animals (`benchmarks/behavior.py`'s sessions, seeds and label
draws; the test animals are not simulated): (1) stacking: the SimBA-style forest with the
hand-written rules' per-frame output (one-hot, no labels) added to its features; (2) decoding:
the default recipe's per-frame probabilities decoded with a switch penalty (Viterbi) or
averaged over label-free segments (the body's moving / still runs split where the nearest
mechanism comes within 10 mm), against the raw argmax.

    /tmp/helpers/cpu .venv/bin/python benchmarks/behavior_context.py    # about 5 min
Prints a table; the last line is JSON, also written to runs/benchmarks/behavior_context.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from sklearn.ensemble import RandomForestClassifier

sys.path.insert(0, str(Path(__file__).resolve().parent))
import behavior as bb  # noqa: E402  (the benchmark's sessions, rules and forest)

from deformnet.atomic import write_text  # noqa: E402
from deformnet.behavior.model import load_classifier, predict_session  # noqa: E402
from deformnet.behavior.predict import read_session  # noqa: E402
from deformnet.body import default_mouse  # noqa: E402
from deformnet.sim import SimConfig  # noqa: E402
from deformnet.sim.ethogram import ETHOGRAM  # noqa: E402
from deformnet.sim.scene import build_scene  # noqa: E402

FPS = 30.0


def viterbi(p: np.ndarray, penalty: float) -> np.ndarray:
    """The label path (T,) maximising sum log p[t, c_t] - penalty * (number of switches)."""
    lp = np.log(np.clip(p, 1e-6, 1.0))
    score, back = lp[0].copy(), np.zeros(p.shape, int)
    for t in range(1, len(p)):
        best = int(score.argmax())
        stay = score >= score[best] - penalty
        back[t] = np.where(stay, np.arange(p.shape[1]), best)
        score = np.where(stay, score, score[best] - penalty) + lp[t]
    path = np.zeros(len(p), int)
    path[-1] = int(score.argmax())
    for t in range(len(p) - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path


def segment_mean(p: np.ndarray, s: dict, mech: np.ndarray) -> np.ndarray:
    """p (T, C) averaged over segments: the body's moving / still runs (rules' 25 mm/s), split
    where the nose or a front paw comes within 10 mm of a mechanism or leaves."""
    P = s["points"]
    parts = s["parts"]
    body = np.nan_to_num(np.nanmean(P, 1))
    speed = bb._rolling(np.r_[0.0, np.linalg.norm(np.diff(body[:, :2], axis=0), axis=1)] * FPS, 9)
    eff = P[:, [parts.index(q) for q in ("nose_tip", "left_front_paw", "right_front_paw")]]
    d = np.nan_to_num(np.linalg.norm(eff[:, :, None] - mech, axis=-1), nan=1e3).min((1, 2))
    key = (speed > 25.0).astype(int) * 2 + (bb._rolling(d, 9) < 10.0)
    seg = np.cumsum(np.r_[True, key[1:] != key[:-1]]) - 1
    out = np.zeros_like(p)
    for k in range(seg.max() + 1):
        out[seg == k] = p[seg == k].mean(0)
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=4000)
    ap.add_argument("--fractions", default="0.1,0.01")
    ap.add_argument("--work", default="runs/benchmarks/behavior_context_work")
    ap.add_argument("--out", default="runs/benchmarks/behavior_context.json")
    args = ap.parse_args(argv)
    work = Path(args.work)
    S = {sp: [bb.make_session(work, sp, i, args.frames) for i in range(n)]
         for sp, n in (("train", 6), ("val", 2))}  # fmt: skip
    scene = build_scene(SimConfig(), default_mouse())
    mech = scene.mech_pos
    C = len(ETHOGRAM)
    rules = [bb.rules_predict(s["points"], s["parts"], FPS, mech, scene.free_lo, scene.free_hi)
             for s in S["train"] + S["val"]]  # fmt: skip
    res: dict = {"rules": bb.scored(S["val"], rules[len(S["train"]) :])["macro_f1"]}
    for frac in [float(f) for f in args.fractions.split(",")]:
        chosen = bb.choose_bouts(S["train"], frac, 7, FPS)  # draw 0, as behavior.py's
        row: dict = {}
        variants = (("simba_forest", False, "sqrt"), ("simba_forest+rules", True, "sqrt"),
                    ("simba_forest+rules, max_features 1", True, 1.0))  # fmt: skip
        for name, stack, mf in variants:
            feats = [bb.simba_features(s["points"], s["parts"], mech, FPS) for s in S["train"]
                     + S["val"]]  # fmt: skip
            if stack:
                feats = [np.concatenate([f, np.eye(C)[r]], 1) for f, r in zip(feats, rules)]
            X = np.concatenate([feats[i][a : b + 1] for i, rows in enumerate(chosen)
                                for a, b, _ in rows])  # fmt: skip
            y = np.concatenate([np.full(b - a + 1, c) for rows in chosen for a, b, c in rows])
            rf = RandomForestClassifier(n_estimators=200, class_weight="balanced",
                                        min_samples_leaf=2, max_features=mf, n_jobs=1,
                                        random_state=0).fit(X, y)  # fmt: skip
            pred = [rf.predict(f) for f in feats[len(S["train"]) :]]
            row[name] = bb.scored(S["val"], pred)["macro_f1"]
        lab_dir = work / "labels" / f"{frac:g}"
        lab_dir.mkdir(parents=True, exist_ok=True)
        files = [bb.write_bouts(lab_dir / f"train{i}.csv", r) for i, r in enumerate(chosen)]
        out = work / "runs" / f"default_{frac:g}"
        bb.run_recipe(out, S["train"], files, S["val"], [], mech, [])
        model, meta = load_classifier(out / "classifier.pt")
        probs = [predict_session(model, read_session(str(s["tracks"]), model, meta), {})["probs"]
                 for s in S["val"]]  # fmt: skip
        row["default raw"] = bb.scored(S["val"], [p.argmax(1) for p in probs])["macro_f1"]
        for pen in (2.0, 5.0, 10.0, 20.0):
            row[f"default viterbi {pen:g}"] = bb.scored(
                S["val"], [viterbi(p, pen) for p in probs])["macro_f1"]  # fmt: skip
        row["default segment mean"] = bb.scored(
            S["val"], [segment_mean(p, s, mech).argmax(1) for p, s in zip(probs, S["val"])]
        )["macro_f1"]  # fmt: skip
        res[f"{frac:g}"] = row
    print(f"validation macro-F1 (2 animals, label draw 0); rules {res['rules']:.3f}")
    fr = [k for k in res if k != "rules"]
    print(f"{'row':40s}" + "".join(f"{f:>8s}" for f in fr))
    for name in res[fr[0]]:
        print(f"{name:40s}" + "".join(f"{res[f][name]:8.3f}" for f in fr))
    text = json.dumps(res | {"settings": vars(args)})
    write_text(Path(args.out), text + "\n")
    print(text)
    return res


if __name__ == "__main__":
    main()
