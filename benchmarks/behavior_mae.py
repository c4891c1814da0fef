"""Behavior-scale masked pretraining: does a self-supervised encoder over seconds of a session
give few-label behavior heads more than a random one, and more than the hand-made features?

Every pretraining objective the deformation net was given (masked frame, temporal contrast,
forecasting; `benchmarks/behavior_probe.py`) leaves its encoder's features worth no more than a
random net's to a head with about 180 labels: its windows (33 frames, in the body frame)
are too short and too local to need the behavior. This benchmark pretrains at the behavior's
own scale instead. Each frame of a session is the classifier's per-frame feature vector
(`deformnet-classify`'s, without temporal context: the frozen deformation encoder's output, the
mid pose, the per-part offsets, the lock-box mechanism distances and the SimBA-style
measurements; `context.frames=[]`, `mechanisms.calibration`, `measurements=true`). A temporal
convolutional net (`deformnet.sequence.SequenceEncoder`, the one `deformnet-classify
pseudo_labels.teacher=sequence` pretrains: by default here five residual dilated convolutions,
63 frames of receptive field, 128 channels) reads a session's sequence of them with spans of
frames hidden (half of the frames, spans of 4-23) and is trained for `--steps` (1000) to
reconstruct the hidden frames' features (MSE on the standardised features;
`deformnet.sequence.pretrain_sequences`), on the training sessions and `--unlabelled` more
sessions of the same simulated mouse, no labels (seeds 95500.., which no other benchmark
uses). Its per-frame outputs, with their mean and standard deviation over centred spans of 15
and 33 frames (as `deformnet-classify`'s context), are a frame's embedding.

Then, on the behavior benchmark's sessions (`benchmarks/behavior.py`: 6 training and 4 test
sessions of 3000 frames, tracked by adjust-track) at 1% labels (three draws, the same as
`behavior_probe.py`'s) and 10%, test macro-F1 (scikit-learn) of:
``lr_pretrained`` / ``forest_pretrained``: a class-weighted logistic regression (C=1) / the
forest head's random forest (conf/head/forest.yaml) on the pretrained embedding;
``lr_random`` / ``forest_random``: the same on the same net with random weights (seed 0);
``lr_frame`` / ``forest_frame``: the same on the classifier's frame features with their context
(no encoder: `behavior_probe.py`'s forest_frame); ``lr_frame_pretrained`` /
``forest_frame_pretrained``: the same on both; ``rf``: the SimBA-style random forest with ROI
features (`behavior.py --box`). With ``--finetune STEPS``, also the issue's fine-tuning
protocol on this encoder: ``finetune_pretrained``, the pretrained net and a linear head on its
embedding trained end to end on the labelled frames (the head alone for ``--probe-steps``, then
the net too at ``--encoder-lr``), and ``finetune_scratch``, the same architecture from random
weights (seed 0) trained the same way at 1e-3 (`finetune`). With ``--target frame`` the net
reconstructs only the hidden frames' frame features (pose, offsets, mechanism distances,
measurements: the hand-made features labs read), not the deformation encoder's outputs, as in
"task programming" (Sun et al., CVPR 2021: self-supervision that predicts expert features).
``lr_binned`` / ``lr_binned_random`` / ``lr_binned_pretrained``: the logistic regression on
the frame features beside their one-hot quantile bins (BINS per feature, `binned`: a linear
head that can threshold a feature, as the forest's splits do), alone / beside the random
net's / beside the pretrained net's embedding. This head was chosen after looking at the test
sessions' macro-F1 of several heads; ``--test-offset 4`` tests on 4 other sessions (seeds
95204..) to measure it without that choice's optimism.
``pseudo_*``: the pretrained encoder as a teacher. A class-weighted logistic regression on a
teacher's features labels the unlabelled training frames (class-balanced: each class's most
confident 30% of the frames it predicts, its probabilities averaged over 9 frames;
`deformnet.pseudo`), and the forest head's random forest on the frame features (the student,
`forest_frame`'s learner) is fitted on the labelled and the pseudo-labelled frames
(`fit_pseudo`). Teachers: ``pseudo_pretrained`` the binned frame features beside the
pretrained embedding (`lr_binned_pretrained`'s features), ``pseudo_random`` beside the random
net's, ``pseudo_binned`` the binned frame features alone (no encoder), ``pseudo_forest`` the
forest on the frame features itself (self-training). The student reads no embedding: at test
time the classifier is a forest on the frame features; what the encoder adds is in the labels it
was fitted on. These rows were designed on the first 8 test sessions (seeds 95200-95207);
``--test-offset 8`` tests them on 4 sessions no choice looked at (seeds 95208..).
``pseudo_ensemble_*``: the teacher's probabilities averaged with the frame-feature forest's
(two views; ``emb``: the embedding alone beside the forest). Students that read the embedding
too: ``pseudo_<teacher>_forest_frame_<net>`` (the forest on the frame features beside the
embedding) and ``pseudo_<teacher>_lr_binned_<net>`` (the regression on the teacher's own
features). ``--pseudo`` picks rows, ``--pseudo-only`` skips the rows without pseudo-labels, and
``--sequence-encoder`` reads a `sequence_encoder.pt` that `deformnet-classify
pseudo_labels.teacher=sequence` wrote (its own architecture and pretraining) instead of
pretraining one.
``pseudo_<teacher>_tcn_<net>`` (``--student-steps N``; not run by default): the student is the
sequence encoder itself with a linear head on its embedding, fine-tuned end to end on the
labelled and pseudo-labelled frames (`finetune`, batches of 8 crops of 512 frames, the
pretrained net's head alone for ``--probe-steps`` first, then the net at ``--encoder-lr``; the
same net from random weights, ``scratch``, at 1e-3 throughout): the issue's fine-tuned
pretrained encoder, given the teacher's thousands of pseudo-labels instead of 180 labels.

    .venv/bin/python benchmarks/behavior_mae.py [--pretrained CKPT] [--steps 1000]
        [--unlabelled 8] [--draws 3] [--mask-ratio 0.5] [--longest-span 23]
        [--dilations 1,2,4,8,16] [--target all|frame]
        [--finetune 150 [--probe-steps 50] [--encoder-lr 1e-4]] [--test-offset 4|8]
        [--sequence-encoder sequence_encoder.pt] [--pseudo ROWS] [--pseudo-only]
        [--student-steps 300]

Prints a table, then for each pair of rows it compares (the pretrained teacher against the one
with no encoder, against the random weights, against the random forest...) the difference at
1% paired over the label draws (macro-F1 on all the test sessions) and over the test sessions
(each one's macro-F1, the mean over the draws): mean, 95% t interval, draws or sessions ahead
and behind, Wilcoxon signed-rank p (`deformnet.behavior_report.paired_difference`; "better"
when both intervals lie above 0 with p < 0.05). The last line is JSON, also written
atomically to runs/benchmarks/behavior_mae.json ("paired": those comparisons).
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from pathlib import Path

import numpy as np
import torch
from behavior import (
    ROOT,
    SEEDS,
    UNLABELLED_SEED,
    _round,
    make_session,
    pretrain,
    rig_mechanisms,
    run_rf,
)
from behavior_probe import encoder_features, labelled, scores
from common import emit, start
from torch import nn

from deformnet.checkpoint import load_checkpoint
from deformnet.confutil import compose, to_plain
from deformnet.pseudo import co_training_pseudo_labels, pseudo_sample_weights
from deformnet.sequence import (
    SequenceEncoder,
    embeddings,
    load_sequence_encoder,
    pooled,
    pretrain_sequences,
    quantile_binner,
)

log = logging.getLogger("benchmarks.behavior_mae")

CONTEXT = (15, 33)  # the embedding's context spans (deformnet-classify's context.frames)
BINS = 4  # quantile bins per frame feature of the binned rows (`binned`)
SMOOTH = 9  # frames over which a teacher's probabilities are averaged (`fit_pseudo`)
KEEP = 0.3  # share of each class's most confident frames pseudo-labelled
LABELLED_WEIGHT = 5.0  # a labelled frame's weight against a pseudo-labelled one's
EMBEDDING_KEEP = 0.5  # co-training: share of each class's frames the embedding's teacher keeps


def finetune(
    model: SequenceEncoder,
    xtr: torch.Tensor,
    rows: np.ndarray,
    labels: np.ndarray,
    weights: np.ndarray,
    xte: torch.Tensor,
    steps: int,
    probe_steps: int,
    encoder_lr: float,
    num_classes: int,
    crop: int | None = None,
    batch: int = 8,
) -> np.ndarray:
    """End-to-end fine-tuning (the issue's protocol) of a copy of `model` with a linear head on
    its pooled embedding (`pooled`, standardised by the initial net's training frames as the
    training sees them, input dropout included; inverted dropout keeps their mean): cross-
    entropy on the training frames ``rows`` (R,) of the training sessions xtr (S, T, D) with
    their ``labels`` (R,), each weighted by ``weights`` (R,) (the loss is their weighted mean),
    input dropout 0.1; AdamW, weight decay 0.01, head lr 1e-3; the head alone for the first
    `probe_steps`, then the net too at `encoder_lr`; `steps` in all, a fixed budget (no
    validation split at 1% labels); ``num_classes`` outputs. Each step reads the whole
    sessions (``crop`` None) or ``batch`` random crops of ``crop`` frames (their rows among
    ``rows``; seed 0). The test sessions' (xte) predicted classes (S' T,)."""
    import copy

    net = copy.deepcopy(model)
    drop = nn.Dropout(0.1)
    S, T = xtr.shape[:2]

    def feats(x: torch.Tensor) -> torch.Tensor:  # (B, T, D) -> (B, T, E)
        z = net._hidden(drop(net.normalize(x)), x.new_zeros(x.shape[:2]))
        return pooled(z, CONTEXT, 1e-8)

    net.eval()
    with torch.no_grad():
        f = feats(xtr).flatten(0, 1)
        fm, fs = f.mean(0), f.std(0).clamp_min(1e-6)
    # per frame of the training sessions: its label and weight (0: not a training row)
    r = torch.as_tensor(np.asarray(rows, np.int64))
    W = torch.zeros(S * T)
    W[r] = torch.as_tensor(np.asarray(weights), dtype=torch.float32)
    L = torch.zeros(S * T, dtype=torch.long)
    L[r] = torch.as_tensor(np.asarray(labels, np.int64))
    W, L = W.reshape(S, T), L.reshape(S, T)
    torch.manual_seed(0)
    head = nn.Linear(f.shape[1], int(num_classes))
    opt = torch.optim.AdamW(
        [{"params": net.parameters(), "lr": encoder_lr}, {"params": head.parameters()}],
        lr=1e-3, weight_decay=1e-2,
    )  # fmt: skip
    gen = torch.Generator().manual_seed(0)
    drop.train()  # the net has no dropout or batch statistics of its own
    for step in range(steps):
        if step in (0, probe_steps):  # the head alone, then the net too
            net.requires_grad_(step >= probe_steps)
        if crop is None:
            xb, wb, lb = xtr, W, L
        else:
            si = torch.randint(0, S, (batch,), generator=gen).tolist()
            st = torch.randint(0, T - crop + 1, (batch,), generator=gen).tolist()
            xb, wb, lb = (torch.stack([a[i, s : s + crop] for i, s in zip(si, st)])
                          for a in (xtr, W, L))  # fmt: skip
        ce = nn.functional.cross_entropy(head((feats(xb) - fm) / fs).flatten(0, 1),
                                         lb.flatten(), reduction="none")  # fmt: skip
        loss = (ce * wb.flatten()).sum() / wb.sum().clamp_min(1e-12)
        opt.zero_grad()
        loss.backward()
        opt.step()
    drop.eval()
    with torch.no_grad():
        return head((feats(xte).flatten(0, 1) - fm) / fs).argmax(-1).numpy()


def standardised(xtr: np.ndarray, xte: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Training and test features standardised by every training frame's mean and std."""
    mu, sd = xtr.mean(0), xtr.std(0)
    sd = np.where(sd > 1e-6, sd, 1.0)
    return (xtr - mu) / sd, (xte - mu) / sd


def binned(xtr: np.ndarray, xte: np.ndarray, bins: int = BINS) -> tuple[np.ndarray, np.ndarray]:
    """The standardised frame features xtr (N, F) / xte (M, F) beside their one-hot quantile
    bins (`bins` per feature, fewer where a feature has fewer distinct values; edges from every
    training frame, labelled or not): (N, B + F), (M, B + F), B the bins in all. A linear head
    on them can threshold a feature, as a forest's split does."""
    transform = quantile_binner(xtr, bins)
    return transform(xtr), transform(xte)


def fit_pseudo(
    teacher_kind: str, ta, sa, sb, idx, y, w, yte, classes, forest: dict, frames: int,
    student_kind: str = "forest", fa=None, student_fn=None, tb=None,
) -> dict:  # fmt: skip
    """The forest head's random forest (the student) on the frame features sa / sb, fitted on
    the labelled frames idx (labels y) and the teacher's class-balanced pseudo-labels of the
    other training frames (`deformnet.pseudo.class_balanced_pseudo_labels`: each class's most
    confident KEEP share, probabilities averaged over SMOOTH frames); the teacher ("lr": the
    class-weighted logistic regression, or "forest": the same forest on the frame features,
    i.e. self-training) fitted on the labelled frames of its features ta. Sample weights
    (`deformnet.pseudo.pseudo_sample_weights`): balanced over the labels and pseudo-labels
    together, a labelled frame LABELLED_WEIGHT times a pseudo-labelled one. Test
    macro-F1, per-class F1 and the test predictions ("pred"). Teacher "co" (co-training): the
    logistic regression on ta and another on a second view tb (the embedding alone), each
    view's class-balanced pseudo-labels (KEEP and EMBEDDING_KEEP) pooled, frames the two give
    different classes dropped (`deformnet.pseudo.co_training_pseudo_labels`).
    ``student_fn(rows, labels, weights)``, when given, is the student instead: it learns from
    those training rows and returns the test predictions."""
    from sklearn.ensemble import RandomForestClassifier
    from sklearn.linear_model import LogisticRegression

    C = len(classes)
    cw = {int(c): float(w[int(c)]) for c in np.unique(y)}

    def new_forest(class_weight):
        return RandomForestClassifier(
            n_estimators=int(forest["trees"]), min_samples_leaf=int(forest["min_samples_leaf"]),
            max_features=forest["max_features"], random_state=int(forest["seed"]), n_jobs=1,
            class_weight=class_weight,
        )  # fmt: skip

    def probs(teacher, x):
        teacher.fit(x[idx], y)
        P = np.zeros((len(x), C))
        P[:, teacher.classes_] = teacher.predict_proba(x)
        return P

    if teacher_kind in ("lr", "co"):
        P = probs(LogisticRegression(C=1.0, max_iter=3000, class_weight=cw), ta)
    elif teacher_kind == "forest":
        P = probs(new_forest(cw), ta)
    else:  # "ensemble": the mean of the logistic regression's and the forest's (frame features)
        P = 0.5 * (probs(LogisticRegression(C=1.0, max_iter=3000, class_weight=cw), ta)
                   + probs(new_forest(cw), sa if fa is None else fa))  # fmt: skip
    labelled_rows = np.zeros(len(ta), bool)
    labelled_rows[idx] = True
    sessions = [frames] * (len(ta) // frames)
    views, keeps = [P], [KEEP]  # one view: class-balanced pseudo-labels alone
    if teacher_kind == "co":
        views.append(probs(LogisticRegression(C=1.0, max_iter=3000, class_weight=cw), tb))
        keeps.append(EMBEDDING_KEEP)
    rows, yp, _ = co_training_pseudo_labels(views, sessions, labelled_rows, keeps, SMOOTH)
    Y = np.concatenate([y, yp])
    sw = pseudo_sample_weights(Y, len(y), C, LABELLED_WEIGHT)
    if student_fn is not None:
        pred = student_fn(np.concatenate([idx, rows]), Y, sw)
        return scores(yte, pred, classes, "test") | {"pred": pred}
    if student_kind == "lr":
        student = LogisticRegression(C=1.0, max_iter=3000)
    else:
        student = new_forest(None)
    student.fit(np.vstack([sa[idx], sa[rows]]), Y, sample_weight=sw)
    pred = student.predict(sb)
    return scores(yte, pred, classes, "test") | {"pred": pred}


def fit_score(kind: str, a, b, idx, y, w, yte, classes, forest: dict) -> dict:
    """Test macro-F1, per-class F1 and predictions ({"macro_f1", "f1", "pred"}) of one learner
    ("lr" or "forest") fitted on the labelled rows idx of the standardised training features a,
    tested on the test features b."""
    from sklearn.ensemble import RandomForestClassifier
    from sklearn.linear_model import LogisticRegression

    cw = {int(c): float(w[int(c)]) for c in np.unique(y)}
    if kind == "lr":
        clf = LogisticRegression(C=1.0, max_iter=3000, class_weight=cw)
    else:
        clf = RandomForestClassifier(
            n_estimators=int(forest["trees"]), min_samples_leaf=int(forest["min_samples_leaf"]),
            max_features=forest["max_features"], random_state=int(forest["seed"]), n_jobs=1,
            class_weight=cw,
        )  # fmt: skip
    clf.fit(a[idx], y)
    pred = clf.predict(b)
    return scores(yte, pred, classes, "test") | {"pred": pred}


def session_scores(preds: dict, yte: np.ndarray, classes, sessions: int, draws: int) -> dict:
    """Each method's test macro-F1 per test session, the mean over the 1% label draws:
    {method: (sessions,)}; preds: {method: {"0.01/<draw>": (sessions x T,) predictions}}."""
    T = len(yte) // sessions
    cut = [slice(s * T, (s + 1) * T) for s in range(sessions)]
    out = {}
    for name, p in preds.items():
        sizes = {len(p[f"0.01/{d}"]) for d in range(draws)}
        if len(yte) != sessions * T or sizes != {len(yte)}:
            raise RuntimeError(f"{name}: {sorted(sizes)} test predictions for {len(yte)} test "
                               f"frames of {sessions} sessions")  # fmt: skip
        per = [[scores(yte[c], p[f"0.01/{d}"][c], classes, "test")["macro_f1"] for c in cut]
               for d in range(draws)]  # fmt: skip
        out[name] = np.mean(per, axis=0)
    return out


def paired_table(pairs: list, table: dict, per_session: dict) -> dict:
    """For each pair (a, b) at 1%: a - b paired over the label draws (macro-F1 on every test
    session) and over the test sessions (each session's macro-F1, the mean over the draws),
    `deformnet.behavior_report.paired_difference`; printed, and returned as
    {"<a>_vs_<b>": {"draws": ..., "sessions": ..., "better": both better}}."""
    from deformnet.behavior_report import paired_difference

    out = {}
    print("\npaired differences at 1% (mean, 95% CI, ahead/behind, Wilcoxon p): over the "
          "label draws | over the test sessions")  # fmt: skip
    for a, b in pairs:
        by_draw = paired_difference(table[a]["1%_draws"], table[b]["1%_draws"])
        by_session = paired_difference(per_session[a], per_session[b])
        both = by_draw["better"] and by_session["better"]
        out[f"{a}_vs_{b}"] = {"draws": by_draw, "sessions": by_session, "better": both}
        text = [f"{r['mean']:+.3f} [{r['ci'][0]:+.3f}, {r['ci'][1]:+.3f}] "
                f"{r['wins']}/{r['losses']} p={r['wilcoxon_p']:.3f}"
                for r in (by_draw, by_session)]  # fmt: skip
        print(f"  {a} vs {b}: {text[0]} | {text[1]}{'  BETTER' if both else ''}")
    return out


# the pseudo-label rows: name -> (teacher learner, teacher features[, student learner,
# student features]); the student is by default the forest on the frame features
PSEUDO = {
    "pseudo_pretrained": ("lr", "binned_pretrained"),
    "pseudo_random": ("lr", "binned_random"),
    "pseudo_binned": ("lr", "binned"),
    "pseudo_forest": ("forest", "frame"),
    "pseudo_ensemble_pretrained": ("ensemble", "binned_pretrained"),
    "pseudo_ensemble_random": ("ensemble", "binned_random"),
    "pseudo_ensemble_binned": ("ensemble", "binned"),
    "pseudo_ensemble_emb_pretrained": ("ensemble", "pretrained"),
    "pseudo_ensemble_emb_random": ("ensemble", "random"),
    # students that read the embedding too
    "pseudo_pretrained_forest_frame_pretrained": ("lr", "binned_pretrained", "forest",
                                                  "frame_pretrained"),
    "pseudo_random_forest_frame_random": ("lr", "binned_random", "forest", "frame_random"),
    "pseudo_pretrained_lr_binned_pretrained": ("lr", "binned_pretrained", "lr",
                                               "binned_pretrained"),
    "pseudo_random_lr_binned_random": ("lr", "binned_random", "lr", "binned_random"),
    "pseudo_binned_lr_binned": ("lr", "binned", "lr", "binned"),
    # the unlabelled sessions' frames pseudo-labelled too (the student learns from them)
    "pseudo_pretrained_unl": ("lr", "binned_pretrained"),
    "pseudo_binned_unl": ("lr", "binned"),
    "pseudo_random_unl": ("lr", "binned_random"),
    # co-training: the binned frame features' teacher and the embedding's own (`fit_pseudo`)
    "pseudo_cotrain": ("co:pretrained", "binned"),
    "pseudo_cotrain_random": ("co:random", "binned"),
    "pseudo_cotrain_unl": ("co:pretrained", "binned"),
    "pseudo_cotrain_random_unl": ("co:random", "binned"),
    # the student a sequence encoder fine-tuned end to end (`finetune`, --student-steps): the
    # pretrained one, or the same net from random weights
    "pseudo_pretrained_tcn_pretrained": ("lr", "binned_pretrained", "tcn", "pretrained"),
    "pseudo_pretrained_tcn_scratch": ("lr", "binned_pretrained", "tcn", "scratch"),
    "pseudo_binned_tcn_pretrained": ("lr", "binned", "tcn", "pretrained"),
}  # fmt: skip
TCN_ROWS = [n for n, v in PSEUDO.items() if v[2:3] == ("tcn",)]  # need --student-steps


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--train", type=int, default=6)
    ap.add_argument("--test", type=int, default=4)
    ap.add_argument("--unlabelled", type=int, default=8,
                    help="more sessions of the mouse for the pretraining (no labels)")  # fmt: skip
    ap.add_argument("--pretrained", default=None,
                    help="deformnet-train checkpoint (the frozen deformation encoder whose "
                         "outputs are among the per-frame features; else a 240 s run)")  # fmt: skip
    ap.add_argument("--steps", type=int, default=1000, help="masked-span pretraining steps")
    ap.add_argument("--mask-ratio", type=float, default=0.5, help="share of the frames hidden")
    ap.add_argument("--longest-span", type=int, default=23, help="longest hidden span, frames")
    ap.add_argument("--target", choices=("all", "frame"), default="all",
                    help="what a hidden frame's reconstruction is of: all its features, or "
                         "only the frame features (pose, offsets, mechanism distances, "
                         "measurements), not the deformation encoder's outputs")  # fmt: skip
    ap.add_argument("--dilations", default="1,2,4,8,16",
                    help="the residual blocks' dilations (receptive field 1 + 2 sum)")  # fmt: skip
    ap.add_argument("--finetune", type=int, default=0,
                    help="steps of end-to-end fine-tuning of the pretrained net with a linear "
                         "head, and of the same net from scratch (0: not run)")  # fmt: skip
    ap.add_argument("--probe-steps", type=int, default=50,
                    help="fine-tuning the pretrained net: the head alone first, steps")  # fmt: skip
    ap.add_argument("--encoder-lr", type=float, default=1e-4,
                    help="fine-tuning: the pretrained net's learning rate "
                         "(from scratch: 1e-3)")  # fmt: skip
    ap.add_argument("--test-offset", type=int, default=0,
                    help="the test sessions' seeds start this far after the usual ones "
                         "(e.g. 4: sessions no earlier choice of a head looked at)")  # fmt: skip
    ap.add_argument("--draws", type=int, default=3, help="label draws at 1%%")
    ap.add_argument("--sequence-encoder", default=None,
                    help="a sequence_encoder.pt deformnet-classify (teacher=sequence) saved, "
                         "pretrained on these per-frame features: used instead of pretraining "
                         "one (--steps, --mask-ratio, --longest-span, --dilations, --target "
                         "are then its own)")  # fmt: skip
    ap.add_argument("--pseudo-only", action="store_true",
                    help="only the pseudo_* rows (and rf): the teachers")  # fmt: skip
    ap.add_argument("--pseudo", default=",".join(n for n in PSEUDO if n not in TCN_ROWS),
                    help="the pseudo_* rows to run, comma-separated (default: all but the "
                         "*_tcn_* rows)")  # fmt: skip
    ap.add_argument("--student-steps", type=int, default=0,
                    help="the *_tcn_* rows: fine-tuning steps of the sequence-encoder student "
                         "(batches of 8 crops of 512 frames)")  # fmt: skip
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "behavior"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "behavior_mae.json"))
    ap.add_argument("--threads", type=int, default=1)
    args = start(ap, argv)
    if (args.unlabelled < 0 or args.train < 1 or args.test < 1 or args.frames < 300
            or args.test_offset < 0):  # fmt: skip
        ap.error("--frames must be >= 300, --train and --test >= 1 and --unlabelled and "
                 "--test-offset >= 0")  # fmt: skip
    if SEEDS["test"] + args.test_offset + args.test > UNLABELLED_SEED:
        ap.error(f"--test-offset {args.test_offset}: the test seeds would reach the unlabelled "
                 f"sessions' ({UNLABELLED_SEED}..)")  # fmt: skip
    pseudo_rows = [n for n in args.pseudo.split(",") if n]
    if set(pseudo_rows) - set(PSEUDO):
        ap.error(f"--pseudo: unknown rows {sorted(set(pseudo_rows) - set(PSEUDO))} "
                 f"(known: {', '.join(PSEUDO)})")  # fmt: skip
    if set(pseudo_rows) & set(TCN_ROWS) and args.student_steps < 1:
        ap.error(f"--pseudo {','.join(sorted(set(pseudo_rows) & set(TCN_ROWS)))}: these rows "
                 "need --student-steps >= 1")  # fmt: skip
    if args.finetune < 0 or args.probe_steps < 0 or args.encoder_lr <= 0:
        ap.error("--finetune and --probe-steps must be >= 0, --encoder-lr > 0")
    if args.finetune and args.probe_steps > args.finetune:
        ap.error(f"--probe-steps {args.probe_steps} is more than --finetune {args.finetune}")
    logging.getLogger("lightning.pytorch").setLevel(logging.WARNING)
    t_start = time.perf_counter()
    work = Path(args.work)
    sessions = {
        split: [make_session(work, SEEDS[split] + off + i, args.frames) for i in range(n)]
        for split, n, off in (("train", args.train, 0), ("test", args.test, args.test_offset))
    }
    unl = [make_session(work, UNLABELLED_SEED + i, args.frames) for i in range(args.unlabelled)]
    box, mech = rig_mechanisms({**sessions, "unlabelled": unl})
    extra: dict = {}
    ckpt = args.pretrained
    if ckpt is None:
        ckpt, secs = pretrain(work / "probe_pretrained", 240)
        extra["deformation_pretrain_seconds"] = round(secs, 1)
    ov = [f"mechanisms.calibration={box}", "measurements=true", "heights_up=[0,0,1]"]
    per, built = encoder_features(ckpt, sessions, [*ov, "context.frames=[]"])
    per_unl = None  # --unlabelled 0: the training sessions alone
    if unl:
        per_unl, _ = encoder_features(ckpt, {"train": unl}, [*ov, "context.frames=[]"])
    ctx, built_ctx = encoder_features(ckpt, sessions, ov)
    classes = built[2]
    T = args.frames

    def seqs(x: torch.Tensor) -> torch.Tensor:
        return x.float().reshape(-1, T, x.shape[-1])

    xtr, xte = seqs(per["train"]["features"]), seqs(per["test"]["features"])
    xun = xtr[:0] if per_unl is None else seqs(per_unl["train"]["features"])
    pool = torch.cat([xtr, xun])  # no test frame sets the standardisation
    D = xtr.shape[-1]
    # --target frame: only the frame features' columns (not the deformation encoder's outputs)
    target = built[0].frame_columns() if args.target == "frame" else None
    dil = tuple(int(d) for d in args.dilations.split(","))
    if args.sequence_encoder:  # deformnet-classify's: its own architecture and target
        net = load_sequence_encoder(args.sequence_encoder)
        if net.dim != D:
            ap.error(f"--sequence-encoder {args.sequence_encoder} reads {net.dim} features per "
                     f"frame, these sessions have {D}")  # fmt: skip
        saved = load_checkpoint(args.sequence_encoder, "sequence encoder")  # weights_only=True
        extra["pretraining"] = {**saved["facts"], "encoder": args.sequence_encoder}
        dil, target = tuple(net.dilations), net.target
    torch.manual_seed(0)
    random_net = SequenceEncoder(D, dilations=dil, target=target)  # 128 channels
    random_net.set_standardization(pool.flatten(0, 1))
    if not args.sequence_encoder:
        torch.manual_seed(0)
        net = SequenceEncoder(D, dilations=dil, target=target)
        log.info("masked-span pretraining on %d sessions, %d steps", len(pool), args.steps)
        extra["pretraining"] = pretrain_sequences(
            net, list(pool), args.steps, args.mask_ratio, args.longest_span
        )

    def emb(model: SequenceEncoder, x: torch.Tensor) -> np.ndarray:
        return embeddings(model, list(x), CONTEXT).numpy()

    fcols = built_ctx[0].frame_columns().numpy()
    # the *_unl rows: the unlabelled sessions' frames ride behind the test frames through the
    # same standardisation and bins (training frames' statistics), then are split off
    with_unl = bool(unl) and any(n.endswith("_unl") for n in pseudo_rows)
    xte_ = torch.cat([xte, xun]) if with_unl else xte
    fte = ctx["test"]["features"].numpy()[:, fcols]
    if with_unl:
        ctx_unl, _ = encoder_features(ckpt, {"train": unl}, ov)
        fte = np.vstack([fte, ctx_unl["train"]["features"].numpy()[:, fcols]])
    feats = {
        "pretrained": (emb(net, xtr), emb(net, xte_)),
        "random": (emb(random_net, xtr), emb(random_net, xte_)),
        "frame": (ctx["train"]["features"].numpy()[:, fcols], fte),
    }
    for name in ("pretrained", "random"):
        feats[f"frame_{name}"] = tuple(
            np.hstack([f, p]) for f, p in zip(feats["frame"], feats[name])
        )
    feats = {k: standardised(*v) for k, v in feats.items()}
    feats["binned"] = binned(*feats["frame"])
    for name in ("pretrained", "random"):  # the binned frame features beside an embedding
        feats[f"binned_{name}"] = tuple(np.hstack(p) for p in zip(feats["binned"], feats[name]))
    n_te = len(xte) * T
    unl_feats = {k: v[1][n_te:] for k, v in feats.items()}  # empty without *_unl rows
    feats = {k: (v[0], v[1][:n_te]) for k, v in feats.items()}
    forest = dict(to_plain(compose("classify", ["head=forest"]).head))
    yte = per["test"]["labels"].numpy()
    plan = [(0.01, d) for d in range(args.draws)] + [(0.1, 0)]
    methods = [("lr", "pretrained"), ("lr", "random"), ("lr", "frame"),
               ("forest", "pretrained"), ("forest", "random"), ("forest", "frame"),
               ("lr", "frame_pretrained"), ("forest", "frame_pretrained"),
               ("lr", "binned"), ("lr", "binned_random"), ("lr", "binned_pretrained")]  # fmt: skip
    if args.pseudo_only:
        methods = []
    results: dict = {}
    per_class: dict = {}  # method -> {plan: {class: F1}}
    preds: dict = {}  # method -> {plan: test predictions (test sessions x T frames)}

    def record(name: str, key: str, sc: dict) -> None:  # one method's scores at one plan
        results.setdefault(name, {})[key] = sc["macro_f1"]
        per_class.setdefault(name, {})[key] = sc["f1"]
        preds.setdefault(name, {})[key] = sc["pred"]

    for f, d in plan:
        idx, y, w = labelled(per, built, f, d)
        idx, y = idx.numpy(), y.numpy()
        for kind, name in methods:
            xa, xb = feats[name]
            record(f"{kind}_{name}", f"{f:g}/{d}",
                   fit_score(kind, xa, xb, idx, y, w, yte, classes, forest))  # fmt: skip
        for name in pseudo_rows:  # a student, taught
            kind, teacher, *student = PSEUDO[name]
            kind, _, view = kind.partition(":")  # co:<net>: the second view, an embedding
            skind, sname = student or ("forest", "frame")
            student_fn = None
            if skind == "tcn":  # a sequence encoder, fine-tuned on the sessions' frames
                init, probe, lr = ((net, args.probe_steps, args.encoder_lr)
                                   if sname == "pretrained" else (random_net, 0, 1e-3))  # fmt: skip

                def student_fn(rows, labels, weights, init=init, probe=probe, lr=lr):
                    return finetune(init, xtr, rows, labels, weights, xte, args.student_steps,
                                    min(probe, args.student_steps), lr, len(classes),
                                    crop=min(512, T))  # fmt: skip

                sname = "frame"  # (unused: the student reads the sessions themselves)
            ta, (sa, sb), fa = feats[teacher][0], feats[sname], feats["frame"][0]
            tb = feats[view][0] if view else None
            if name.endswith("_unl"):  # the unlabelled sessions' frames pseudo-labelled too
                ta, sa, fa = (np.vstack([a, unl_feats[k]]) for a, k in
                              ((ta, teacher), (sa, sname), (fa, "frame")))  # fmt: skip
                tb = None if tb is None else np.vstack([tb, unl_feats[view]])
            sc = fit_pseudo(
                kind, ta, sa, sb, idx, y, w, yte, classes, forest, T, skind, fa, student_fn, tb
            )
            record(name, f"{f:g}/{d}", sc)
        if args.finetune:
            for name, model, probe, lr in (
                ("finetune_pretrained", net, args.probe_steps, args.encoder_lr),
                ("finetune_scratch", random_net, 0, 1e-3),
            ):
                t_ft = time.perf_counter()
                pred = finetune(model, xtr, idx, y, w[y], xte, args.finetune, probe, lr, len(w))
                record(name, f"{f:g}/{d}", scores(yte, pred, classes, "test") | {"pred": pred})
                extra.setdefault("finetune_seconds", []).append(
                    round(time.perf_counter() - t_ft, 1)
                )
        sc = run_rf(sessions, "track", f, label_seed=d, mechanisms=mech, predictions=True)
        results.setdefault("rf", {})[f"{f:g}/{d}"] = sc["macro_f1"]  # (no per-class F1 kept)
        preds.setdefault("rf", {})[f"{f:g}/{d}"] = sc["pred"]
        now = {k: round(v[f"{f:g}/{d}"], 3) for k, v in results.items()}
        log.info("%g / draw %d: %s", f, d, now)
    table = {}
    for name, r in results.items():
        one = [r[f"0.01/{d}"] for d in range(args.draws)]
        table[name] = {"1%": float(np.mean(one)), "1%_draws": one, "10%": r["0.1/0"]}
        if name in per_class:  # per-class F1: mean of the 1% draws, and at 10%
            pc = per_class[name]
            table[name]["1%_f1"] = {
                c: float(np.mean([pc[f"0.01/{d}"][c] for d in range(args.draws)])) for c in classes
            }
            table[name]["10%_f1"] = pc["0.1/0"]
    print(f"\nbehavior-scale masked pretraining: test macro-F1 ({args.train} train / {args.test} "
          f"test sessions x {T} frames; pretrained on {args.train + args.unlabelled} sessions, "
          f"{extra['pretraining']['steps']} steps)")  # fmt: skip
    w_ = max(len(n) for n in table) + 2
    wd = 8 * args.draws + 2  # "0.123 / " per draw
    print(f"{'method':<{w_}}{'1% (mean)':>10}{'1% draws':>{wd}}{'10%':>8}")
    for name, t in table.items():
        draws = " / ".join(f"{x:.3f}" for x in t["1%_draws"])
        print(f"{name:<{w_}}{t['1%']:>10.3f}{draws:>{wd}}{t['10%']:>8.3f}")
    pairs = [("lr_pretrained", "lr_random"), ("forest_pretrained", "forest_random"),
             ("lr_pretrained", "lr_frame"), ("lr_pretrained", "rf"), ("forest_pretrained", "rf"),
             ("lr_frame_pretrained", "lr_frame"), ("forest_frame_pretrained", "forest_frame"),
             ("forest_frame", "rf"), ("lr_binned_pretrained", "rf"),
             ("lr_binned_pretrained", "lr_binned_random"),
             ("lr_binned_pretrained", "lr_binned"),
             ("pseudo_pretrained", "rf"), ("pseudo_pretrained", "pseudo_random"),
             ("pseudo_pretrained", "pseudo_binned"), ("pseudo_pretrained", "pseudo_forest"),
             ("pseudo_pretrained", "forest_frame")]  # fmt: skip
    if args.finetune:
        pairs += [("finetune_pretrained", "finetune_scratch"), ("finetune_pretrained", "rf"),
                  ("finetune_pretrained", "lr_pretrained")]  # fmt: skip
    pairs += [("pseudo_ensemble_pretrained", "pseudo_ensemble_random"),
              ("pseudo_ensemble_pretrained", "pseudo_ensemble_binned"),
              ("pseudo_ensemble_pretrained", "pseudo_pretrained"),
              ("pseudo_ensemble_emb_pretrained", "pseudo_ensemble_emb_random"),
              ("pseudo_ensemble_emb_pretrained", "pseudo_pretrained"),
              ("pseudo_pretrained_tcn_pretrained", "pseudo_pretrained_tcn_scratch"),
              ("pseudo_pretrained_tcn_pretrained", "pseudo_pretrained"),
              ("pseudo_pretrained_tcn_pretrained", "rf")]  # fmt: skip
    pairs += [("pseudo_pretrained_unl", "pseudo_binned_unl"), ("pseudo_pretrained_unl", "rf"),
              ("pseudo_pretrained_unl", "pseudo_random_unl"),
              ("pseudo_pretrained_unl", "pseudo_pretrained"),
              ("pseudo_binned_unl", "pseudo_binned"), ("pseudo_random_unl", "pseudo_random"),
              ("pseudo_binned", "pseudo_random"), ("pseudo_binned", "rf")]  # fmt: skip
    pairs += [("pseudo_cotrain_unl", "pseudo_cotrain_random_unl"),
              ("pseudo_cotrain_unl", "pseudo_binned_unl"),
              ("pseudo_cotrain_unl", "pseudo_random_unl"),
              ("pseudo_cotrain_unl", "pseudo_pretrained_unl"), ("pseudo_cotrain_unl", "rf"),
              ("pseudo_cotrain", "pseudo_cotrain_random"), ("pseudo_cotrain", "pseudo_binned"),
              ("pseudo_cotrain", "pseudo_pretrained"), ("pseudo_cotrain", "rf")]  # fmt: skip
    checks = {f"{a}_beats_{b}_1pct": table[a]["1%"] > table[b]["1%"]
              for a, b in pairs if a in table and b in table}  # fmt: skip
    print("checks: " + ", ".join(f"{k}={v}" for k, v in checks.items()))
    paired = {}
    if args.draws >= 2:  # is the difference more than the draws' and the sessions' spread?
        per_session = session_scores(preds, yte, classes, args.test, args.draws)
        for name, v in per_session.items():
            table[name]["1%_sessions"] = v.tolist()
        paired = paired_table(
            [(a, b) for a, b in pairs if a in table and b in table], table, per_session
        )
    summary = {
        "table": table,
        "checks": checks,
        "paired": paired,
        "checkpoint": ckpt,
        **extra,
        "setup": {
            "frames": T,
            "train": args.train,
            "test": args.test,
            "test_offset": args.test_offset,
            "unlabelled": args.unlabelled,
            # a loaded encoder (--sequence-encoder): its own pretraining, in "pretraining"
            "sequence_encoder": args.sequence_encoder,
            "steps": None if args.sequence_encoder else args.steps,
            "draws": args.draws,
            "mask_ratio": None if args.sequence_encoder else args.mask_ratio,
            "longest_span": None if args.sequence_encoder else args.longest_span,
            "dilations": list(dil),
            "target": None if args.sequence_encoder else args.target,
            "pseudo": pseudo_rows,
            "finetune": args.finetune,
            "student_steps": args.student_steps,
            "probe_steps": args.probe_steps,
            "encoder_lr": args.encoder_lr,
            "seeds": SEEDS | {"unlabelled": UNLABELLED_SEED},
        },  # fmt: skip
        "total_seconds": round(time.perf_counter() - t_start, 1),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    return emit(_round(summary), args.out)


if __name__ == "__main__":
    main()
