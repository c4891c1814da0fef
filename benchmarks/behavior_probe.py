"""Behavior probe benchmark: how much a frozen encoder's features are worth with few labels.

The encoders (each the default LSTM of `deformnet-train`): ``pretrained`` (deformnet-train's
masked-token objective), ``contrast`` (the same plus the temporal-contrastive term,
`contrast.weight=1`, `contrast.max_shift=12`), both trained here for `--pretrain-seconds`
unless given as checkpoints, and ``random`` (the same architecture, random weights, seed 0);
``heading`` and ``random_heading``: the masked-token net trained, and the random net, reading
each window in its heading frame (`up=[0,0,1]`: yaw removed, pitch and roll against gravity
kept, `deformnet.tokens.canonicalize`) instead of the body frame (which removes the whole mid
pose; the classifier's frame features carry it either way); ``forecast``: ``heading`` plus the
forecasting term (`forecast.weight=1`: predict every part 10-45 frames before or after the
window, `deformnet.lit`).
Each is frozen; the classifier's features (`deformnet-classify`'s: the encoder outputs with
the frame features and the temporal context) are computed once for every frame of the
behavior benchmark's sessions (`benchmarks/behavior.py`: 6 training and 4 test sessions,
tracked by adjust-track, seeds no training uses), and the default head (conf/head: an
ensemble of 5 MLPs) is fitted by L-BFGS (`fit_head_lbfgs`, the linear-probe protocol) on the
labelled frames: 1% (three draws of the labelled frames, `labels.seed` 0-2, the same for every
encoder and for the random forest) and 10%. Reported: test macro-F1 (scikit-learn), the
mean over draws, and the SimBA-style random forest of `benchmarks/behavior.py` on the same
labelled frames.

Beside them, the forest head (`head=forest`, conf/head/forest.yaml: the same random forest
settings as the SimBA-style baseline) on the first encoder's classifier features:
``forest_frame`` reads only the frame features (the tracked pose, the per-part offsets and
their temporal context; no encoder output: the same for every encoder), ``forest_all`` every
feature; ``forest_all_<encoder>``: the same on each further encoder's features (pretrained vs
random encoder under the forest). forest_frame vs rf is the same learner on the tracked-pose
features vs SimBA's.
``mlp_frame``: the default head (the same MLP ensemble, L-BFGS) on the frame features alone:
against an encoder's row, what the encoder's outputs add to that head.
``forest_pca_<encoder>`` (``--pca K``, default 16; 0 skips): the same forest on the frame
features plus the first K principal components of that encoder's outputs (PCA fitted on every
training frame, labelled or not), so the encoder can add to the frame features without
outnumbering them; against forest_frame it says whether the encoder adds anything, against the
random encoder's whether pretraining does. Per-class F1 at 1% labels is printed too.
``knn_<encoder>`` (``--knn K``, default 32; 0 skips): a 1-nearest-neighbour classifier on the
first K principal components of that encoder's outputs alone (``knn_frame``: of the frame
features alone): nothing fitted to the labels, so it says whether the encoder's pretraining put
frames of one behavior near each other, pretrained against random.
``--box``: every classifier with the lock-box context (`mechanisms.calibration`: the distance
of the snout and front paws to each mechanism among the frame features) and the random forest
with the same distances as SimBA's ROI features (`benchmarks/behavior.py --box`).
``--measurements``: every classifier with `measurements=true` (SimBA-style pairwise part
distances, part speeds and part heights among the frame features,
`deformnet.heads.pose_measurements`; the body-frame encoders with `heights_up=[0,0,1]`).
``--transfer-sim sim=mouse_b,sim.fps=30``: every classifier (fitted on the default mouse's
sessions as above) is also tested on `--test` sessions of another simulated mouse (these
`adjust-simulate` overrides, seeds 95300..; same rig and lock box, tracked the same way; at
another frame rate, e.g. `sim=mouse_b`'s 100 fps, read resampled to the training rate,
`resample_session`): the macro-F1 on a mouse the labels and the pretraining never saw
("transfer" columns).
``--body-scale session|none``: every classifier's `body_scale` (as `benchmarks/behavior.py`).

    .venv/bin/python benchmarks/behavior_probe.py [--pretrained CKPT] [--contrast CKPT]
        [--heading CKPT] [--forecast CKPT] [--pretrain-seconds 240] [--draws 3]
        [--encoders pretrained,contrast,random,heading,random_heading,forecast] [--pca 16]
        [--knn 32]
        [--box] [--measurements] [--transfer-sim sim=mouse_b,sim.fps=30] [--body-scale session]

Prints a table; the last line is JSON, also written atomically to
runs/benchmarks/behavior_probe.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

import numpy as np
import torch
from behavior import (
    ROOT,
    SEEDS,
    TRANSFER_SEED,
    _round,
    add_context_args,
    add_transfer_sessions,
    make_session,
    pretrain,
    rig_mechanisms,
    run_rf,
)
from common import emit, start, subset

from deformnet.confutil import compose, to_plain

log = logging.getLogger("benchmarks.behavior_probe")

CONTRAST = ["contrast.weight=1.0", "contrast.max_shift=12"]
HEADING = ["up=[0,0,1]"]  # the heading frame (the simulator's z is up)
NAMES = ("pretrained", "contrast", "random", "heading", "random_heading", "forecast")
FORECAST = [*HEADING, "forecast.weight=1.0"]  # + the forecasting term (conf/train.yaml)
BODY_FRAME = ("pretrained", "contrast", "random")  # the encoders reading the body frame
HEIGHTS = ["heights_up=[0,0,1]"]  # --measurements: their part heights (the simulator's up)


def encoder_features(
    spec: str, sessions: dict, overrides=(), no_resample: bool = False
) -> tuple[dict, object]:
    """Classifier features of every train / test frame for one encoder ("random" or a
    deformnet-train checkpoint; overrides: deformnet-classify's), with the classifier (its
    default head, untrained); sessions at another frame rate than the training ones read
    resampled to it (no_resample: as they are)."""
    from deformnet.behavior_labels import (
        Session,
        read_labels,
        read_tracks,
        resample_session,
        same_fps,
    )
    from deformnet.classify import (
        SessionBank,
        _encoder_config,
        classifier_from_config,
        context_features,
        set_body_scales,
    )

    cfg = compose("classify", [*overrides, *([] if spec == "random" else [f"pretrained={spec}"])])
    classes = [str(c) for c in cfg.labels.classes]
    net_cfg, body, hw, state, up = _encoder_config(cfg, classes)
    torch.manual_seed(0)
    model, _ = classifier_from_config(cfg, net_cfg, body, hw, len(classes), up)
    if state is not None:
        model.encoder.net.load_state_dict(state)
    model.eval()
    out = {}
    rate = sessions["train"][0]["fps"]
    for split in [k for k in ("train", "test", "transfer") if k in sessions]:
        ss = []
        for s in sessions[split]:
            tr = read_tracks(str(s["track"]), body)
            lab = read_labels(str(s["labels"]), tr["fnum"], classes)
            ss.append(Session(str(s["track"]), tr["rigid"], tr["deformed"], tr["observed"],
                              tr["fnum"], lab))  # fmt: skip
            if not (no_resample or same_fps(s["fps"], rate)):  # another frame rate (e.g.
                ss[-1] = resample_session(ss[-1], s["fps"], rate)  # sim=mouse_b): the training's
        set_body_scales(ss, cfg.body_scale, body)  # as deformnet-classify does
        bank = SessionBank(ss, model.half_window)
        out[split] = {
            "features": context_features(model, bank, torch.arange(len(bank))),
            "labels": bank.labels.clone(),
            "sessions": ss,
        }
    return out, (model, cfg, classes)


def labelled(feats: dict, built, fraction: float, draw: int) -> tuple:
    """The labelled training frames of one draw: their indices (N,), labels (N,) and the
    balanced class weights (C,) (the classifier's: total / (C count), 0 for absent classes)."""
    from deformnet.behavior_labels import Session, subsample_labels

    _, cfg, classes = built
    ss = [Session(s.name, None, None, None, s.fnum, s.labels.copy())
          for s in feats["train"]["sessions"]]  # fmt: skip
    subsample_labels(ss, fraction, int(cfg.labels.segment), draw)
    lab = torch.from_numpy(np.concatenate([s.labels for s in ss]))
    idx = torch.nonzero(lab >= 0).flatten()
    y = lab[idx]
    C = len(classes)
    counts = np.bincount(y.numpy(), minlength=C)
    w = np.where(counts > 0, counts.sum() / np.maximum(C * counts, 1), 0.0)
    return idx, y, w


def probe_pca(feats: dict, built, fraction: float, draw: int, forest: dict, k: int) -> dict:
    """The forest head's learner (scikit-learn's random forest with `forest`'s settings,
    class-weighted) on the frame features plus the first `k` principal components of the
    encoder's outputs (the remaining columns, standardised; PCA fitted on every training
    frame, labelled or not); test macro-F1. Whether the encoder adds anything to the
    frame features once it cannot swamp them."""
    from sklearn.decomposition import PCA
    from sklearn.ensemble import RandomForestClassifier

    model, _, classes = built
    idx, y, w = labelled(feats, built, fraction, draw)
    xtr = feats["train"]["features"].double()
    mu, sd = xtr.mean(0), xtr.std(0)
    sd = torch.where(sd > 1e-3, sd, torch.ones_like(sd))
    xtr = ((xtr - mu) / sd).numpy()
    fcols = model.frame_columns().numpy()
    ecols = np.setdiff1d(np.arange(xtr.shape[1]), fcols)
    pca = PCA(int(k), random_state=0).fit(xtr[:, ecols])
    ztr = np.hstack([xtr[:, fcols], pca.transform(xtr[:, ecols])])
    yy = y.numpy()
    rf = RandomForestClassifier(
        n_estimators=int(forest["trees"]), min_samples_leaf=int(forest["min_samples_leaf"]),
        max_features=forest["max_features"], random_state=int(forest["seed"]), n_jobs=1,
        class_weight={int(c): float(w[int(c)]) for c in np.unique(yy)},
    ).fit(ztr[idx.numpy()], yy)  # fmt: skip
    out = {"labelled_frames": int(len(yy)),
           "explained_variance": float(pca.explained_variance_ratio_.sum())}  # fmt: skip
    for split in [k for k in ("test", "transfer") if k in feats]:
        x = ((feats[split]["features"].double() - mu) / sd).numpy()
        z = np.hstack([x[:, fcols], pca.transform(x[:, ecols])])
        out |= scores(feats[split]["labels"].numpy(), rf.predict(z), classes, split)
    return out


def probe_knn(feats: dict, built, fraction: float, draw: int, k: int, columns: str) -> dict:
    """A nearest-neighbour classifier (1-NN, scikit-learn) on the first `k` principal
    components of the standardised encoder outputs alone (columns="encoder") or of the frame
    features alone ("frame"), PCA fitted on every training frame, labelled or not; test
    macro-F1. No parameters are fitted to the labels, so it measures the geometry of the
    features: whether frames of one behavior lie near each other (what the encoder's
    pretraining would have to give for a few labels to go far)."""
    from sklearn.decomposition import PCA
    from sklearn.neighbors import KNeighborsClassifier

    model, _, classes = built
    idx, y, _ = labelled(feats, built, fraction, draw)
    xtr = feats["train"]["features"].double()
    mu, sd = xtr.mean(0), xtr.std(0)
    sd = torch.where(sd > 1e-3, sd, torch.ones_like(sd))
    fcols = model.frame_columns().numpy()
    cols = fcols if columns == "frame" else np.setdiff1d(np.arange(xtr.shape[1]), fcols)
    pca = PCA(int(k), random_state=0).fit(((xtr - mu) / sd).numpy()[:, cols])

    def embed(x: torch.Tensor) -> np.ndarray:
        return pca.transform(((x.double() - mu) / sd).numpy()[:, cols])

    nn = KNeighborsClassifier(1).fit(embed(feats["train"]["features"][idx]), y.numpy())
    out = {"labelled_frames": int(len(y)), "components": int(k)}
    for split in [s for s in ("test", "transfer") if s in feats]:
        pred = nn.predict(embed(feats[split]["features"]))
        out |= scores(feats[split]["labels"].numpy(), pred, classes, split)
    return out


def scores(truth: np.ndarray, pred: np.ndarray, classes, split: str) -> dict:
    """macro-F1 and per-class F1 (scikit-learn, `deformnet.behavior_report.evaluate`) of one
    test split: {"macro_f1", "f1"} for "test", {"transfer_macro_f1", "transfer_f1"} for the
    other mouse's sessions."""
    from deformnet.behavior_report import evaluate

    ev = evaluate(truth, pred, classes)
    pre = "" if split == "test" else f"{split}_"
    return {f"{pre}macro_f1": ev["macro_f1"],
            f"{pre}f1": {c: v["f1"] for c, v in ev["per_class"].items()}}  # fmt: skip


class _FrameHead(torch.nn.Module):
    """The classifier's default head on the frame-feature columns alone, in the shape
    `fit_head_lbfgs` fits (head, feature_mean, feature_std)."""

    def __init__(self, head_cfg: dict, cols: torch.Tensor, classes: int) -> None:
        from deformnet.heads import build_head

        super().__init__()
        torch.manual_seed(0)  # a fresh head, the same for every draw and fraction
        self.cols = cols
        self.head = build_head(head_cfg, len(cols), classes)
        self.register_buffer("feature_mean", torch.zeros(len(cols)))
        self.register_buffer("feature_std", torch.ones(len(cols)))

    def classify(self, x: torch.Tensor) -> torch.Tensor:
        return self.head((x[:, self.cols] - self.feature_mean) / self.feature_std)


def probe(
    feats: dict, built, fraction: float, draw: int, head: dict | None = None, frame: bool = False
) -> dict:
    """Fit the (fresh, seed 0) head on the labelled training frames; test macro-F1. head: a
    forest head's config (fitted by `fit_head_forest`), else the classifier's own head
    (L-BFGS); frame: that head on the frame features alone (`_FrameHead`: the tracked pose,
    the per-part offsets and their temporal context; no encoder output), what the encoder's
    outputs add to the MLP head as forest_frame says for the forest."""
    import copy

    from deformnet.classify import fit_head_forest, fit_head_lbfgs
    from deformnet.heads import build_head

    model, cfg, classes = built
    idx, y, w = labelled(feats, built, fraction, draw)
    C = len(classes)
    X = feats["train"]["features"][idx]
    if frame:
        m = _FrameHead(dict(to_plain(cfg.head)), model.frame_columns(), C)
        X = X[:, m.cols]
        sd = X.std(0)
        m.feature_mean.copy_(X.mean(0))
        m.feature_std.copy_(torch.where(sd > 1e-3, sd, torch.ones_like(sd)))
    else:
        m = copy.deepcopy(model)  # the same untrained head for every draw and fraction
        m.set_standardization(X)
    t0 = time.perf_counter()
    if head is not None:
        m.head = build_head(head, m.out_dim, C)
        fit_head_forest(m, X, y, w.tolist())
    else:
        fit_head_lbfgs(m, X, y, w.tolist(), float(cfg.head_l2), int(cfg.head_max_iter))
    out = {"labelled_frames": int(len(y)), "fit_seconds": round(time.perf_counter() - t0, 1)}
    for split in [k for k in ("test", "transfer") if k in feats]:
        with torch.no_grad():
            pred = m.classify(feats[split]["features"]).argmax(-1).numpy()
        out |= scores(feats[split]["labels"].numpy(), pred, classes, split)
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--train", type=int, default=6)
    ap.add_argument("--test", type=int, default=4)
    ap.add_argument("--pretrained", default=None, help="deformnet-train checkpoint (else train)")
    ap.add_argument("--contrast", default=None, help="the same with contrast (else train)")
    ap.add_argument("--heading", default=None, help="the same in the heading frame (else train)")
    ap.add_argument("--forecast", default=None, help="heading + forecasting term (else train)")
    ap.add_argument("--pretrain-seconds", type=int, default=240)
    ap.add_argument("--draws", type=int, default=3, help="label draws at 1%%")
    ap.add_argument("--encoders", default=",".join(NAMES),
                    help="which encoders to probe (comma-separated)")  # fmt: skip
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "behavior"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "behavior_probe.json"))
    ap.add_argument("--pca", type=int, default=16,
                    help="forest_pca_<encoder>: frame features + this many principal "
                         "components of the encoder's outputs (0: skip)")  # fmt: skip
    ap.add_argument("--knn", type=int, default=32,
                    help="knn_<encoder> / knn_frame: 1-NN on this many principal components of "
                         "the encoder's outputs / the frame features (0: skip)")  # fmt: skip
    add_context_args(ap)
    ap.add_argument("--threads", type=int, default=1)
    args = start(ap, argv)
    logging.getLogger("lightning.pytorch").setLevel(logging.WARNING)
    t_start = time.perf_counter()
    work = Path(args.work)
    sessions = {
        split: [make_session(work, SEEDS[split] + i, args.frames) for i in range(n)]
        for split, n in (("train", args.train), ("test", args.test))
    }
    transfer = add_transfer_sessions(sessions, work, args)
    box, mech = rig_mechanisms(sessions) if args.box else (None, None)
    extra: dict = {"box": box, "transfer_sim": list(transfer) or None}
    names = NAMES
    chosen = subset(ap, args.encoders, names, "--encoders")
    ckpts = {"pretrained": args.pretrained, "contrast": args.contrast, "heading": args.heading,
             "forecast": args.forecast}  # fmt: skip
    ckpts = {k: v for k, v in ckpts.items() if k in chosen}
    todo = (("pretrained", []), ("contrast", CONTRAST), ("heading", HEADING),
            ("forecast", FORECAST))  # fmt: skip
    for name, overrides in todo:
        if name in ckpts and ckpts[name] is None:
            log.info("%s: a %d s deformnet-train run %s", name, args.pretrain_seconds, overrides)
            ckpts[name], secs = pretrain(work / f"probe_{name}", args.pretrain_seconds, overrides)
            extra[f"{name}_pretrain_seconds"] = round(secs, 1)
            m = json.loads((work / f"probe_{name}" / "metrics.json").read_text())["metrics"]
            extra[f"{name}_best_val_rmse_mm"] = m.get("best/val_rmse_mm")
    randoms = {"random": (), "random_heading": HEADING}
    ctx = [f"mechanisms.calibration={box}"] if box else []
    ctx += ["measurements=true"] if args.measurements else []
    ctx += [f"body_scale={args.body_scale}"]
    extra["body_scale"] = args.body_scale
    extra["measurements"] = bool(args.measurements)
    encoders = {k: (v, tuple(ctx)) for k, v in ckpts.items()}
    encoders |= {k: ("random", (*ov, *ctx)) for k, ov in randoms.items() if k in chosen}
    encoders = {k: encoders[k] for k in names if k in encoders}  # the table's order
    if args.measurements:  # the body-frame encoders' measurements get the heights too (the
        for k in BODY_FRAME:  # heading-frame ones have them from their up): the same features
            if k in encoders:
                encoders[k] = (encoders[k][0], (*encoders[k][1], *HEIGHTS))
    plan = [(0.01, d) for d in range(args.draws)] + [(0.1, 0)]
    results: dict = {}
    forest = dict(to_plain(compose("classify", ["head=forest"]).head))
    for name, (spec, overrides) in encoders.items():
        t0 = time.perf_counter()
        feats, built = encoder_features(spec, sessions, overrides, args.no_resample)
        runs = {f"{f:g}/{d}": probe(feats, built, f, d) for f, d in plan}
        results[name] = {"runs": runs, "features_seconds": round(time.perf_counter() - t0, 1)}
        log.info("%s: %s", name, {k: round(v["macro_f1"], 3) for k, v in runs.items()})
        if args.pca > 0:
            fp = {f"{f:g}/{d}": probe_pca(feats, built, f, d, forest, args.pca) for f, d in plan}
            results[f"forest_pca_{name}"] = {"runs": fp, "encoder": name, "components": args.pca}
            log.info("forest_pca_%s: %s", name, {k: round(v["macro_f1"], 3) for k, v in fp.items()})
        if args.knn > 0:
            kn = {f"{f:g}/{d}": probe_knn(feats, built, f, d, args.knn, "encoder") for f, d in plan}
            results[f"knn_{name}"] = {"runs": kn, "encoder": name, "components": args.knn}
            log.info("knn_%s: %s", name, {k: round(v["macro_f1"], 3) for k, v in kn.items()})
        if name == next(iter(encoders)):  # the encoder-free heads, on the first one's features
            if args.knn > 0:
                kn = {f"{f:g}/{d}": probe_knn(feats, built, f, d, args.knn, "frame")
                      for f, d in plan}  # fmt: skip
                results["knn_frame"] = {"runs": kn, "encoder": name, "components": args.knn}
                log.info("knn_frame: %s", {k: round(v["macro_f1"], 3) for k, v in kn.items()})
            fr = {f"{f:g}/{d}": probe(feats, built, f, d, frame=True) for f, d in plan}
            results["mlp_frame"] = {"runs": fr, "encoder": name}
            log.info("mlp_frame: %s", {k: round(v["macro_f1"], 3) for k, v in fr.items()})
            for inputs in ("frame", "all"):
                head = {**forest, "inputs": inputs}
                fr = {f"{f:g}/{d}": probe(feats, built, f, d, head) for f, d in plan}
                results[f"forest_{inputs}"] = {"runs": fr, "encoder": name}
                log.info(
                    "forest_%s: %s", inputs, {k: round(v["macro_f1"], 3) for k, v in fr.items()}
                )
        else:  # the forest on every feature of this encoder too (pretrained vs random)
            head = {**forest, "inputs": "all"}
            fr = {f"{f:g}/{d}": probe(feats, built, f, d, head) for f, d in plan}
            results[f"forest_all_{name}"] = {"runs": fr, "encoder": name}
            log.info("forest_all_%s: %s", name, {k: round(v["macro_f1"], 3) for k, v in fr.items()})
    # the SimBA-style forest (tested on the other mouse too, --transfer-sim)
    rf_runs = {f"{f:g}/{d}": run_rf(sessions, "track", f, label_seed=d, mechanisms=mech,
                                    resample=not args.no_resample)
               for f, d in plan}  # fmt: skip
    results["rf"] = {"runs": rf_runs}
    table = {}
    for name, r in results.items():
        one = [r["runs"][f"0.01/{d}"]["macro_f1"] for d in range(args.draws)]
        per = [r["runs"][f"0.01/{d}"].get("f1") for d in range(args.draws)]
        f1 = None
        if all(per):  # a class absent from the test labels: None, left out of its mean
            f1 = {c: float(np.nanmean([np.nan if p[c] is None else p[c] for p in per]))
                  for c in per[0]}  # fmt: skip
        table[name] = {"1%": float(np.mean(one)), "1%_draws": one,
                       "10%": r["runs"]["0.1/0"]["macro_f1"], "1%_f1": f1}  # fmt: skip
        if transfer:
            tr = [r["runs"][f"0.01/{d}"]["transfer_macro_f1"] for d in range(args.draws)]
            table[name] |= {"transfer_1%": float(np.mean(tr)), "transfer_1%_draws": tr,
                            "transfer_10%": r["runs"]["0.1/0"]["transfer_macro_f1"]}  # fmt: skip
    print(f"\nbehavior probe: frozen encoders, the default head fitted by L-BFGS; test macro-F1 "
          f"({args.train} train / {args.test} test sessions x {args.frames} frames)")  # fmt: skip
    other = f"  {'/'.join(transfer)}: 1% / 10%" if transfer else ""
    w = max(16, *(len(n) + 2 for n in table))  # the name column
    print(f"{'encoder':<{w}}{'1% (mean)':>10}{'1% draws':>26}{'10%':>8}{other}")
    for name, t in table.items():
        draws = " / ".join(f"{x:.3f}" for x in t["1%_draws"])
        tr = f"{t['transfer_1%']:>12.3f} / {t['transfer_10%']:.3f}" if transfer else ""
        print(f"{name:<{w}}{t['1%']:>10.3f}{draws:>26}{t['10%']:>8.3f}{tr}")
    classes = next((t["1%_f1"] for t in table.values() if t["1%_f1"]), None)
    if classes:
        print("\nper-class F1 at 1% labels (mean over the draws)")
        print(f"{'':<{w}}" + "".join(f"{c:>8}" for c in classes))
        for name, t in table.items():
            if t["1%_f1"]:
                print(f"{name:<{w}}" + "".join(f"{t['1%_f1'][c]:>8.3f}" for c in classes))
    checks = {}
    pairs = [("pretrained", "random"), ("heading", "random_heading"), ("heading", "rf"),
             ("contrast", "pretrained"), ("pretrained", "rf"), ("forest_frame", "rf"),
             ("forecast", "random_heading"), ("forecast", "heading"),
             ("forecast", "rf"), ("pretrained", "mlp_frame"), ("heading", "mlp_frame"),
             ("random_heading", "mlp_frame"), ("forecast", "mlp_frame")]  # fmt: skip
    pairs += [(f"forest_pca_{n}", "forest_frame") for n in encoders]
    first = next(iter(encoders))  # forest_all is the first encoder's
    pairs += [("forest_all", f"forest_all_{n}") for n in encoders if n != first]
    pairs += [("forest_all", "rf"), ("forest_all", "forest_frame")]
    pairs += [(f"knn_{n}", f"knn_{r}") for n, r in
              (("pretrained", "random"), ("heading", "random_heading"),
               ("forecast", "random_heading"), ("contrast", "random"))]  # fmt: skip
    pairs += [(f"knn_{n}", "knn_frame") for n in encoders]
    pairs += [(f"forest_pca_{n}", f"forest_pca_{r}") for n, r in
              (("pretrained", "random"), ("heading", "random_heading"),
               ("forecast", "random_heading"))]  # fmt: skip
    for a, b in pairs:  # a beats b at 1% labels (the mean over the draws)
        if a in table and b in table:
            checks[f"{a}_beats_{b}_1pct"] = table[a]["1%"] > table[b]["1%"]
            if transfer:
                checks[f"{a}_beats_{b}_transfer_1pct"] = (
                    table[a]["transfer_1%"] > table[b]["transfer_1%"]
                )
    print("checks: " + ", ".join(f"{k}={v}" for k, v in checks.items()))
    summary = {
        "table": table,
        "results": results,
        "checks": checks,
        "checkpoints": ckpts,
        **extra,
        "setup": {
            "frames": args.frames,
            "train": args.train,
            "test": args.test,
            "draws": args.draws,
            "seeds": SEEDS | ({"transfer": TRANSFER_SEED} if transfer else {}),
        },  # fmt: skip
        "total_seconds": round(time.perf_counter() - t_start, 1),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    return emit(_round(summary), args.out)


if __name__ == "__main__":
    main()
