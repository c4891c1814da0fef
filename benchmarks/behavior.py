"""Behavior benchmark: a lab's ethogram where rules are not enough, labels as a person writes
them, and the library's own recipe (`deformnet-classify`) against hand-written rules and a
SimBA-style forest.

Sessions: `deformnet.sim.ethogram` (the simulator's animation labelled with a lab's ethogram:
walk / approach, rear against a wall / free, sniff / operate a nose mechanism share their
kinematics and differ in context, duration and sequence), one animal per session (its own size,
speed, durations, postures), 1 mm noise on every point, the simulator's missing detections. The
seeds are fixed here: test sessions (animals) are never used for a choice, every choice is made
on the validation sessions. Training labels are a person's bouts (`annotate`: onsets jittered,
some bouts mislabelled, short ones missed), a share of the training frames labelled as whole
bouts (at most 3 s each, classes in turn): `start,stop,label` CSVs as a lab exports them.
Test sessions are scored against the simulator's truth, raw per-frame predictions (macro-F1).

Rows:
- ``rules``: hand-written thresholds (no labels; arena and mechanism positions known): speed,
  nose height, paws at the snout, an effector at a mechanism, run lengths, what a walk ends at;
- ``simba_forest``: a random forest on SimBA-style per-frame features (pairwise distances,
  speeds, heights, mechanism distances, rolling means / sds over 5, 15, 33 frames);
- ``recipe:<name>``: `deformnet-classify` runs (`deformnet.classify.run`, then its classifier
  through the `mode=predict` path on the test sessions) with the `CANDIDATES`' overrides;
  ``default`` is `conf/classify.yaml` with only tracks, labels and the rig's mechanism positions
  given; ``mlp_scratch`` the former default (an MLP head on an LSTM from scratch, 60 s).
``--candidates all`` runs every candidate (the validation sweep that chose the default; with
``--test 0`` the test animals are not even simulated).
(The pretrained-encoder rows of docs/benchmarks.md were measured with ``--encoders`` at commit
2e8c1a5: a forest on the encoder's outputs, `head.inputs=all`, deleted since it did not help;
the bout-feature rows (`bouts.*`) at commit 62cd7fc and the `context.halves` rows before it:
options deleted since they did not help.)

    flock /tmp/mousetrack-cpu.lock .venv/bin/python benchmarks/behavior.py [--quick]
        [--fractions 0.1,0.01] [--candidates default,mlp_scratch|all]

The default run (6 train, 2 validation, 4 test sessions of 4000 frames; two candidates at two
label shares: 4 `deformnet-classify` runs, 2-3.5 min each in the measured run beside other
jobs) stays under 20 min on 2 cores; ``--quick`` is a smoke run (about 1 min).
Prints tables; the last line is JSON, also written to runs/benchmarks/behavior.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np
import pandas as pd
from sklearn.ensemble import RandomForestClassifier

from deformnet.atomic import finite_or_none, write_text
from deformnet.behavior.model import load_classifier, predict_session
from deformnet.behavior.predict import read_session
from deformnet.behavior.predict import run as classify
from deformnet.behavior.report import evaluate
from deformnet.body import default_mouse
from deformnet.confutil import compose
from deformnet.paths import CONF_DIR
from deformnet.sim import MECHANISMS, SimConfig
from deformnet.sim.ethogram import ETHOGRAM, annotate, simulate_ethogram
from deformnet.sim.scene import build_scene

log = logging.getLogger("benchmarks.behavior")

ROOT = CONF_DIR.parent
#: fixed before any choice: test animals are only ever scored, validation animals choose
SEEDS = {"train": 71_000, "val": 71_100, "test": 71_200}
NOISE_MM = 1.0
BOUT_CAP_S = 3.0  # s: a labelled bout's longest span (from its onset) ...
MIN_BOUT_S = 0.5  # ... and at least this, else the share's part per class
_FOREST = ["head=forest", "freeze=true", "net=lstm_small"]
_CTX = "context.frames=[15,33]"  # the former default context
_BAL = "pseudo_labels.balanced=true"  # the former default (until stop 51)
#: `deformnet-classify` candidates (overrides beyond tracks, labels, mechanisms); every one
#: spelt out, so that a change of the defaults does not change what a row measures
CANDIDATES = {
    "default": [],  # conf/classify.yaml: forest_measure_linear_3s with pseudo_labels.balanced=
    # false (student_unbalanced), chosen on validation
    "forest_frame": [*_FOREST, _CTX, "measurements=false", "pseudo_labels.teacher=none"],
    "forest_measure": [*_FOREST, _CTX, "measurements=true", "pseudo_labels.teacher=none"],
    "forest_measure_linear": [*_FOREST, _CTX, "measurements=true",
                              "pseudo_labels.teacher=linear", _BAL],
    "forest_measure_3s": [*_FOREST, "context.frames=[15,33,91]", "measurements=true",
                          "pseudo_labels.teacher=none"],
    "forest_measure_linear_3s": [*_FOREST, "context.frames=[15,33,91]", "measurements=true",
                                 "pseudo_labels.teacher=linear", _BAL],
    "measure_linear_3s": [*_FOREST, "context.frames=[15,33,91]", "frame_features=false",
                          "measurements=true", "pseudo_labels.teacher=linear", _BAL],
    # the default with every frame weighed alike (no class balancing), the self-trained
    # forest's pseudo-labels included: the teacher's class frequencies kept (issue 49, stop 51)
    "class_weights_none": ["loss.class_weights=none"],
    "student_unbalanced": ["pseudo_labels.balanced=false"],  # the refitted forest's only
    "student_balanced": [_BAL],  # the default until stop 51
    # the former default: an MLP head on an LSTM trained from scratch (here for 60 s)
    "mlp_scratch": ["net=lstm", "head=mlp", "freeze=false", _CTX, "measurements=false",
                    "pseudo_labels.teacher=none", "trainer.max_time=00:00:01:00"],
}  # fmt: skip


# --------------------------------------------------------------------------------------------
# sessions and labels
# --------------------------------------------------------------------------------------------
def make_session(work: Path, split: str, i: int, frames: int) -> dict:
    """One simulated animal's session: points3d CSV (noisy, NaN where undetected), its truth
    labels (per frame) and a person's bouts."""
    seed = SEEDS[split] + i
    data, truth = simulate_ethogram(SimConfig(), frames, seed)
    rng = np.random.default_rng([seed, 1])
    pts = data.deformed + rng.normal(0.0, NOISE_MM, data.deformed.shape)
    pts = np.where(data.observed[..., None], pts, np.nan)
    cols = {"fnum": np.arange(frames)}
    for k, name in enumerate(["pose_rx", "pose_ry", "pose_rz", "pose_tx", "pose_ty", "pose_tz"]):
        cols[name] = data.poses[:, k]
    for k, part in enumerate(data.parts):
        for a, ax in enumerate("xyz"):
            cols[f"{part}_{ax}"] = pts[:, k, a]
    d = work / f"{split}{i}"
    d.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(cols).to_csv(d / "points3d.csv", index=False)
    names = np.asarray(ETHOGRAM, dtype=object)
    pd.DataFrame({"fnum": np.arange(frames), "label": names[truth]}).to_csv(
        d / "truth.csv", index=False
    )
    bouts = annotate(truth, data.fps, rng)
    return {"dir": d, "tracks": d / "points3d.csv", "truth": truth, "truth_csv": d / "truth.csv",
            "bouts": bouts, "fps": data.fps, "points": pts, "parts": list(data.parts)}  # fmt: skip


def choose_bouts(sessions: list[dict], fraction: float, seed: int, fps: float) -> list[list]:
    """A person labelling a share ``fraction`` of the sessions' frames as bouts: each class in
    turn, a random one of its annotated bouts (at most `BOUT_CAP_S` from its onset, and not
    over the share's part per class unless under `MIN_BOUT_S`) until the share is reached.
    Returns per session [(start, stop, class), ...]."""
    rng = np.random.default_rng(seed)
    total = sum(len(s["truth"]) for s in sessions)
    n_classes = len({c for s in sessions for _, _, c in s["bouts"]})
    cap = int(min(BOUT_CAP_S * fps, max(MIN_BOUT_S * fps, fraction * total / n_classes)))
    pool: dict[int, list] = {}
    for si, s in enumerate(sessions):
        for a, b, c in s["bouts"]:
            pool.setdefault(c, []).append((si, a, min(b, a + cap - 1), c))
    for c in pool:
        rng.shuffle(pool[c])
    chosen: list[list] = [[] for _ in sessions]
    n = 0
    while n < fraction * total and any(pool.values()):
        for c in sorted(pool):
            if pool[c] and n < fraction * total:
                si, a, b, c_ = pool[c].pop()
                chosen[si].append((a, b, c_))
                n += b - a + 1
    return chosen


def write_bouts(path: Path, rows: list) -> Path:
    pd.DataFrame(
        [(a, b, ETHOGRAM[c]) for a, b, c in sorted(rows)], columns=["start", "stop", "label"]
    ).to_csv(path, index=False)
    return path


# --------------------------------------------------------------------------------------------
# rules (no labels)
# --------------------------------------------------------------------------------------------
def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop inclusive) of the True runs of a boolean (T,)."""
    m = np.r_[False, mask, False].astype(np.int8)
    d = np.flatnonzero(np.diff(m))
    return [(int(a), int(b) - 1) for a, b in zip(d[::2], d[1::2])]


def _rolling(x: np.ndarray, n: int, how: str = "mean") -> np.ndarray:
    s = pd.Series(x).rolling(n, center=True, min_periods=1)
    return (s.mean() if how == "mean" else s.std().fillna(0.0)).to_numpy()


def rules_predict(points: np.ndarray, parts: list[str], fps: float, mech: np.ndarray,
                  free_lo: np.ndarray, free_hi: np.ndarray) -> np.ndarray:  # fmt: skip
    """Hand-written ethogram (T,) from a session's points (T, K, 3) (NaN: undetected): moving
    (centroid speed > 25 mm/s over 0.3 s) is walking, or approaching when the moving run ends
    with an effector at a mechanism; at rest: an effector within 8 mm of a mechanism is that
    mechanism (a nose mechanism for under 1.5 s: sniff), the nose above 40 mm a rear (against
    the wall when the body is within 25 mm of the walkable region's edge), both front paws
    within 14 mm of the nose grooming, a rest of over 1 s with sweeping head scanning, a
    shorter one still walking."""
    P = pd.DataFrame(points.reshape(len(points), -1)).interpolate(limit_direction="both")
    P = P.to_numpy().reshape(points.shape)
    ix = {p: i for i, p in enumerate(parts)}
    nose, lf, rf = P[:, ix["nose_tip"]], P[:, ix["left_front_paw"]], P[:, ix["right_front_paw"]]
    body = P[:, [ix[p] for p in parts if p not in ("nose_tip",)]].mean(1)
    speed = _rolling(np.r_[0.0, np.linalg.norm(np.diff(body[:, :2], axis=0), axis=1)] * fps, 9)
    moving = speed > 25.0
    eff = {"lever": rf, "splint": nose, "ball": lf, "slider": nose}
    at = np.full(len(P), -1)
    for m, name in enumerate(MECHANISMS):
        near = _rolling(np.linalg.norm(eff[name] - mech[m], axis=1), 5) < 8.0
        at[near & (at < 0)] = m
    yaw = np.unwrap(np.arctan2(*(nose[:, :2] - body[:, :2]).T[::-1]))
    sweep = _rolling(yaw - _rolling(yaw, 31), 31, "std")
    groom = (np.linalg.norm(lf - nose, axis=1) < 14) & (np.linalg.norm(rf - nose, axis=1) < 14)
    rear = _rolling(nose[:, 2], 5) > 40.0
    xy = body[:, :2]
    edge = np.minimum(xy - free_lo, free_hi - xy).min(1)
    name = {c: i for i, c in enumerate(ETHOGRAM)}
    out = np.full(len(P), name["walk"])
    for a, b in _runs(~moving):
        seg = slice(a, b + 1)
        long_rest = b - a + 1 > fps
        out[seg] = name["scan"] if long_rest and sweep[seg].mean() > 0.15 else name["walk"]
    out[_rolling(groom.astype(float), 15) > 0.5] = name["groom"]
    for a, b in _runs(rear & ~moving):
        wall = np.median(edge[a : b + 1]) < 25.0 + 10.0
        out[a : b + 1] = name["rear_wall"] if wall else name["rear_free"]
    ramp = int(0.3 * fps)  # an effector reaches (and leaves) a mechanism in about 0.3 s
    for m, mname in enumerate(MECHANISMS):
        for a, b in _runs(at == m):
            short = b - a + 1 < 1.5 * fps - ramp
            a, b = max(a - ramp, 0), min(b + ramp, len(P) - 1)
            out[a : b + 1] = name["sniff"] if (mname in ("splint", "slider") and short) else (
                name[mname])  # fmt: skip
    for a, b in _runs(moving):  # a walk that ends at a mechanism is an approach
        after = at[b + 1 : b + 1 + int(fps)]
        if after.size and (after >= 0).mean() > 0.3:
            out[a : b + 1] = name["approach"]
    return out


# --------------------------------------------------------------------------------------------
# SimBA-style forest
# --------------------------------------------------------------------------------------------
def simba_features(points: np.ndarray, parts: list[str], mech: np.ndarray, fps: float):
    """SimBA-style per-frame features (T, F): centroid, heights, pairwise distances, speeds,
    the nose's and front paws' distances to each mechanism, with rolling means and sds over 5,
    15, 33 frames."""
    P = pd.DataFrame(points.reshape(len(points), -1)).interpolate(limit_direction="both")
    P = P.to_numpy().reshape(points.shape)
    T, K = P.shape[:2]
    iu = np.triu_indices(K, 1)
    dist = np.linalg.norm(P[:, :, None] - P[:, None], axis=-1)[:, iu[0], iu[1]]
    speed = np.linalg.norm(np.diff(P, axis=0, prepend=P[:1]), axis=-1) * fps
    roi = P[:, [parts.index(p) for p in ("nose_tip", "left_front_paw", "right_front_paw")]]
    md = np.linalg.norm(roi[:, :, None] - mech[None, None], axis=-1).reshape(T, -1)
    base = np.concatenate([P.mean(1), P[:, :, 2], dist, speed, md], 1)
    frame = pd.DataFrame(base)
    feats = [base]
    for w in (5, 15, 33):
        roll = frame.rolling(w, center=True, min_periods=1)
        feats += [roll.mean().to_numpy(), roll.std().fillna(0.0).to_numpy()]
    return np.nan_to_num(np.concatenate(feats, 1))


def run_simba(train: list[dict], chosen: list[list], score: list[dict], mech: np.ndarray,
              seed: int = 0) -> dict:  # fmt: skip
    X, y = [], []
    for s, rows in zip(train, chosen):
        f = simba_features(s["points"], s["parts"], mech, s["fps"])
        for a, b, c in rows:
            X.append(f[a : b + 1])
            y.append(np.full(b - a + 1, c))
    rf = RandomForestClassifier(n_estimators=200, class_weight="balanced", min_samples_leaf=2,
                                n_jobs=1, random_state=seed)  # fmt: skip
    rf.fit(np.concatenate(X), np.concatenate(y))
    pred = [rf.predict(simba_features(s["points"], s["parts"], mech, s["fps"])) for s in score]
    return scored(score, pred)


def scored(sessions: list[dict], pred: list[np.ndarray]) -> dict:
    ev = evaluate(np.concatenate([s["truth"] for s in sessions]), np.concatenate(pred), ETHOGRAM)
    return {"macro_f1": ev["macro_f1"], "f1": {c: v["f1"] for c, v in ev["per_class"].items()}}


# --------------------------------------------------------------------------------------------
# the library's recipe
# --------------------------------------------------------------------------------------------
def _list(paths) -> str:
    return "[" + ",".join(str(p) for p in paths) + "]"


def mechanism_override(mech: np.ndarray) -> str:
    inner = ",".join(f"{n}:[{','.join(f'{v:.3f}' for v in p)}]" for n, p in zip(MECHANISMS, mech))
    return "mechanisms.positions={" + inner + "}"


def run_recipe(out: Path, train: list[dict], label_files: list[Path], val: list[dict],
               test: list[dict], mech: np.ndarray, overrides: list[str]) -> dict:  # fmt: skip
    """One `deformnet-classify` training run on the labelled bouts of the training sessions
    (its report: the validation sessions' truth), then its classifier labels each test
    session through the `mode=predict` path (`read_session`, `predict_session`).
    Returns {"val": ..., "test": ...} (macro-F1 raw, smoothed; per-class F1)."""
    ov = [f"output.dir={out}", "logger=none", "classes=" + _list(ETHOGRAM),
          f"data.train_tracks={_list(s['tracks'] for s in train)}",
          f"data.train_labels={_list(label_files)}",
          f"data.test_tracks={_list(s['tracks'] for s in val)}",
          f"data.test_labels={_list(s['truth_csv'] for s in val)}",
          mechanism_override(mech), "fps=30", *overrides]  # fmt: skip
    t0 = time.perf_counter()
    rep = classify(compose("classify", ov))["report"]
    res = {"val": {"macro_f1": rep["raw"]["macro_f1"],
                   "macro_f1_smoothed": rep["smoothed"]["macro_f1"],
                   "f1": {c: v["f1"] for c, v in rep["raw"]["per_class"].items()}},
           "labelled_frames": rep["labelled_training_frames"]}  # fmt: skip
    model, meta = load_classifier(out / "classifier.pt")
    raw, smoothed = [], []
    for s in test:
        pr = predict_session(model, read_session(str(s["tracks"]), model, meta),
                             dict(meta.get("smoothing") or {}))  # fmt: skip
        raw.append(pr["raw"])
        smoothed.append(pr["labels"])
    if test:  # --test 0: a validation run
        res["test"] = scored(test, raw) | {"macro_f1_smoothed": scored(test, smoothed)["macro_f1"]}
    return res | {"seconds": round(time.perf_counter() - t0, 1)}


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.3f}"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="a smoke run (small sessions)")
    ap.add_argument("--frames", type=int, default=4000)
    ap.add_argument("--train", type=int, default=6)
    ap.add_argument("--val", type=int, default=2)
    ap.add_argument("--test", type=int, default=4)
    ap.add_argument("--fractions", default="0.1,0.01")
    ap.add_argument("--label-draws", type=int, default=1)
    ap.add_argument("--candidates", default="default,mlp_scratch",
                    help=f"comma-separated, of {','.join(CANDIDATES)}; all: every one")  # fmt: skip
    ap.add_argument("--work", default="runs/benchmarks/behavior_work")
    ap.add_argument("--out", default="runs/benchmarks/behavior.json")
    args = ap.parse_args(argv)
    if args.quick:
        args.frames, args.train, args.val, args.test = 1500, 3, 1, 1
    logging.basicConfig(level=logging.WARNING)
    t0 = time.time()
    work = Path(args.work)
    sessions = {
        split: [make_session(work, split, i, args.frames) for i in range(getattr(args, split))]
        for split in ("train", "val", "test")
    }
    scene = build_scene(SimConfig(), default_mouse())
    mech = scene.mech_pos
    fps = 30.0
    results: dict = {"rules": {}, "simba_forest": {}, "recipe": {}}
    splits = [s for s in ("val", "test") if sessions[s]]  # --test 0: validation only
    for split in splits:
        pred = [rules_predict(s["points"], s["parts"], fps, mech, scene.free_lo, scene.free_hi)
                for s in sessions[split]]  # fmt: skip
        results["rules"][split] = scored(sessions[split], pred)
    fractions = [float(f) for f in args.fractions.split(",")]
    names = list(CANDIDATES) if args.candidates == "all" else args.candidates.split(",")
    names = [c for c in names if c]
    unknown = sorted(set(names) - set(CANDIDATES))
    if unknown:
        ap.error(f"unknown candidates {unknown} (known: {', '.join(CANDIDATES)})")
    for frac in fractions:
        for draw in range(args.label_draws):
            key = f"{frac:g}/{draw}"
            tag = key.replace("/", "_")
            chosen = choose_bouts(sessions["train"], frac, 1000 * draw + 7, fps)
            lab_dir = work / "labels" / tag
            lab_dir.mkdir(parents=True, exist_ok=True)
            files = [write_bouts(lab_dir / f"train{i}.csv", r) for i, r in enumerate(chosen)]
            for split in splits:
                results["simba_forest"].setdefault(split, {})[key] = run_simba(
                    sessions["train"], chosen, sessions[split], mech
                )
            for name in names:
                ov = CANDIDATES[name]
                out = work / "runs" / f"{name.replace(':', '_')}_{tag}"
                r = run_recipe(out, sessions["train"], files, sessions["val"], sessions["test"],
                               mech, ov)  # fmt: skip
                for split in splits:
                    results["recipe"].setdefault(name, {}).setdefault(split, {})[key] = r[split]
                print(f"{key} {name}: val {r['val']['macro_f1']:.3f} test "
                      f"{_fmt(r.get('test', {}).get('macro_f1'))} ({r['seconds']} s)",
                      flush=True)  # fmt: skip
    # tables
    for split in splits:
        print(f"\n{split} sessions (seeds {SEEDS[split]}..), macro-F1 (raw)")
        print(f"{'row':28s}" + "".join(f"{f:>10g}" for f in fractions))
        print(f"{'rules (no labels)':28s}" + f"{results['rules'][split]['macro_f1']:10.3f}" * len(
            fractions))  # fmt: skip

        row = results["simba_forest"][split]
        print(f"{'simba_forest':28s}" + "".join(f"{mean_of_f(row, f, args):10.3f}"
                                                  for f in fractions))  # fmt: skip
        for name in names:
            row = results["recipe"][name][split]
            print(f"{'recipe:' + name:28s}" + "".join(f"{mean_of_f(row, f, args):10.3f}"
                                                      for f in fractions))  # fmt: skip
    results["settings"] = {**vars(args), "seeds": SEEDS, "seconds": round(time.time() - t0)}
    text = json.dumps(finite_or_none(results), default=str)
    write_text(Path(args.out), text + "\n")
    print(text)
    return results


def mean_of_f(row: dict, f: float, args) -> float:
    return float(np.mean([row[f"{f:g}/{k}"]["macro_f1"] for k in range(args.label_draws)]))


if __name__ == "__main__":
    main()
