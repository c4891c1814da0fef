"""Behavior benchmark: few-label behavior classification on the pretrained encoder, and lock-box
events, on held-out simulated sessions tracked end to end.

Sessions: `adjust-simulate` scenes (default rig and detector) with seeds no training uses
(train 95000.., val 95100.., test 95200..; deformnet-train simulates seeds 0.. and 10000..),
each tracked by `adjust-track` (default settings) and triangulated by `adjust-triangulate`
(DLT; a user fills its gaps by linear interpolation: `data.interpolate=true`). Labels: the
simulator's per-frame behavior (truth.npz) written as `fnum,label` CSVs.

Classifiers (`deformnet-classify`, each `trainer.max_time` seconds), at label fractions 1%,
10%, 100% of the training sessions' frames (and of the validation session's):
At 1% (about 180 labelled frames) each method runs on `--label-draws` (3) draws of the
labelled frames (`labels.seed` 0, 1, 2; the same frames for every method) and reports the mean:
one draw moves macro-F1 by several points.
- ``pretrained``: the encoder of a deformnet-train checkpoint (`--pretrained`, else a short
  `deformnet-train` run here), fine-tuned with its head;
- ``frozen``: the same encoder frozen, head only;
- ``scratch``: the same architecture from random weights, trained end to end (reading windows
  in the checkpoint's frame: body, or heading with its `up`);
- ``scratch_frozen``: the same architecture, random weights frozen, the head probed (L-BFGS) on
  their context features (what pretraining adds over the architecture and the pooling alone;
  "pretrained beats scratch" is checked against the better of the two);
- ``forest``: the forest head (`head=forest freeze=true`: the same random-forest settings as
  ``rf``) on the classifier's frame features (the tracked pose, the per-part offsets and their
  temporal context; the encoder's outputs are not read): ``rf`` and ``forest`` are the same
  learner on SimBA's features and on the tracked pose's;
- ``forest_self``: ``forest`` self-trained (`pseudo_labels.teacher=self`, `deformnet.pseudo`):
  the forest fitted on the labelled frames labels the other training frames, each class's most
  confident 30% of them join the labelled ones, and the forest is fitted again on both;
- ``forest_linear``: the same with a logistic regression on the binned frame features as the
  teacher (`pseudo_labels.teacher=linear`: no encoder, no pretraining);
- ``forest_sequence``: ``forest`` taught by the pretrained behavior-scale sequence encoder
  (`pseudo_labels.teacher=sequence`, `deformnet.sequence`): a temporal conv net over each
  session's per-frame features, pretrained without labels (`--sequence-steps`, 1000) to fill in
  hidden spans on the training sessions and `--unlabelled` (8) more sessions of the same mouse
  (seeds 95500..; `data.unlabelled_tracks`); a logistic regression on its embedding beside the
  binned frame features labels the other training frames, each class's most confident 30% join
  the labelled ones. Pretrained once (the first run), its `sequence_encoder.pt` reused by the
  other label draws and fractions (`pseudo_labels.sequence.encoder`: no labels are involved);
  ``forest_sequence_random``: the same with the net's random weights (`steps=0`: what the
  pretraining adds);
  ``forest_cotrain``: two teachers instead (`pseudo_labels.teacher=cotrain`, co-training): the
  logistic regression on the binned frame features and one on the sequence encoder's embedding
  alone, each view's confident frames pooled, conflicts dropped (the same pretrained encoder
  as ``forest_sequence``, reused when that ran first); ``forest_cotrain_random``: the same
  with the net's random weights;
  with ``--teach-unlabelled`` the teachers (``forest_linear`` and these four) also pseudo-label
  the unlabelled sessions' frames, and the forest learns from them
  (`pseudo_labels.unlabelled=true`); without it only the pretraining reads them;
- ``forest_all``: the same forest head on every feature (`head.inputs=all`: the pretrained
  encoder's outputs with their temporal context besides the frame features);
  ``scratch_forest_all``: the same on the same architecture's random weights (what pretraining
  adds to it);
- ``rf``: a random forest (scikit-learn, balanced class weights) on SimBA-style hand-made
  per-frame features: centroid, body length, heading / elevation of the nose-tail axis, part
  heights, all pairwise part distances, part speeds, each with rolling means and standard
  deviations over 5, 15 and 33 frames.
``--box``: lock-box context for every method: `deformnet-classify mechanisms.calibration=` (the
sessions' calibration: each frame's distance of the snout and front paws to each mechanism
among the frame features, `deformnet.heads.MechanismFeatures`), and for ``rf`` SimBA's ROI
features (the same distances, with the same rolling statistics).
``--measurements``: every `deformnet-classify` method with `measurements=true` (SimBA-style
pairwise part distances, part speeds and part heights among the frame features, the measures
``rf`` has; `deformnet.heads.pose_measurements`).
``--transfer-sim sim=mouse_b,sim.fps=30``: every classifier (trained on the default mouse's
sessions) also labels `--test` sessions of another simulated mouse (these `adjust-simulate`
overrides; seeds 95300..; same rig and lock box; tracked the same way), each
`deformnet-classify` classifier through its `mode=predict` path (`load_classifier`,
`frame_rates`, `predict_session`: a mouse at another frame rate, e.g. `sim=mouse_b` at its
100 fps, is labelled resampled to the training rate), ``rf`` with its features in time (speeds
in mm/s, windows scaled to the frame rate, as SimBA's): the macro-F1 on a mouse that neither the
labels nor the pretraining saw ("transfer").
``--transfer-frames N``: the other mouse's sessions have N frames (default ``--frames``; e.g.
900 at 30 fps for the 30 s of 3000 frames at `sim=mouse_b`'s 100 fps).
Resampled to a lower rate, the sessions are low-passed first (`deformnet-classify
antialias=true`, the default); each deformnet-classify method is then also scored resampled
without it (``transfer_no_antialias``), side by side in the same run.
``--no-resample``: the other mouse's sessions at another frame rate are labelled frame by frame
as they are (``rf``'s features in training-rate frames), not resampled: what a classifier
without `fps=` does.
``--body-scale session|none``: every `deformnet-classify` classifier's `body_scale` (session, the
default: each session's animal size against the body model divided out of its pose features;
none: the points as they are, as every run before stop 29).
``--test-offset N``: the test sessions are seeds 95200+N.. (e.g. 12: sessions simulated after
every choice of the pseudo-label methods was made; 95200-95211 were looked at).
Input comparison: ``pretrained`` and ``rf`` at 10% on DLT (gap-filled) vs adjust-track output.
Test macro-F1 over the test sessions (scikit-learn), raw and with the smoothing (median 9 +
min bout 5) reported separately.

Lock-box events (`adjust-events`, default settings; mechanism positions from the scenes'
calibration metadata) on every session, from adjust-track output, from DLT (gap-filled) and,
for reference, from the true 3D points: operations (events of a mechanism, any part) matched to
the simulator's mechanism bouts (lever, splint, ball, slider labels) by overlap; precision,
recall, mean absolute onset error (frames), and the fraction of sessions whose first-operation
order of the mechanisms is right.

Targets: macro-F1 >= 0.9 at 10% labels (pretrained, tracked input); pretrained > scratch and
> rf at 1%; event precision and recall >= 0.9 from adjust-track and better than from DLT.

    .venv/bin/python benchmarks/behavior.py [--frames 3000] [--train 6] [--test 4]
        [--pretrained runs/train/.../best.ckpt] [--pretrain-seconds 240] [--frame body]
        [--seconds 75]
        [--label-draws 3] [--fractions 0.01,0.1,1] [--methods pretrained,...,forest,rf] [--box]
        [--measurements] [--transfer-sim sim=mouse_b,sim.fps=30] [--body-scale session|none]
        [--unlabelled 8] [--sequence-steps 1000] [--sequence-encoder sequence_encoder.pt]
        [--heights-up] [--test-offset 0]

At 100% labels the head is one MLP (`head.ensemble=1`): the 5-MLP ensemble is for few labels,
and five L-BFGS fits on all 18000 training frames take about 20 min per method. A run with a
subset of `--fractions` or `--methods` (part of the table) still runs the 10% input comparison
and the events.

Prints tables; the last line is JSON, also written atomically to runs/benchmarks/behavior.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from common import subset

from adjust.app import finite_or_none
from deformnet.atomic import write_text
from deformnet.behavior_labels import same_fps
from deformnet.confutil import compose
from deformnet.paths import CONF_DIR

log = logging.getLogger("benchmarks.behavior")

ROOT = CONF_DIR.parent
SEEDS = {"train": 95_000, "val": 95_100, "test": 95_200}
MECHANISMS = ("lever", "splint", "ball", "slider")
METHODS = (
    "pretrained",
    "frozen",
    "scratch",
    "scratch_frozen",
    "forest",
    "forest_self",
    "forest_linear",
    "forest_sequence",
    "forest_sequence_random",
    "forest_cotrain",
    "forest_cotrain_random",
    "forest_all",
    "scratch_forest_all",
    "rf",
)
TRANSFER_SEED = 95_300  # --transfer-sim: the other mouse's sessions (nothing trains on them)
UNLABELLED_SEED = 95_500  # sessions without labels (sequence pretraining only; behavior_mae too)
SEQUENCE_METHODS = ("forest_sequence", "forest_sequence_random", "forest_cotrain",
                    "forest_cotrain_random")  # fmt: skip
# the co-training teachers read the same sequence encoder as these (reused when they ran first)
SAME_ENCODER = {"forest_cotrain": "forest_sequence",
                "forest_cotrain_random": "forest_sequence_random"}  # fmt: skip
TEACHERS = ("forest_linear", *SEQUENCE_METHODS)  # they read the unlabelled sessions


# --------------------------------------------------------------------------------------------
# sessions
# --------------------------------------------------------------------------------------------
def make_session(work: Path, seed: int, frames: int, sim: tuple[str, ...] = ()) -> dict:
    """Scene, adjust-track and DLT outputs and a labels CSV for one seed (cached in `work`);
    sim: `adjust-simulate` overrides (e.g. ("sim=mouse_b", "sim.fps=30"): another mouse), named
    in the folder."""
    from adjust.scene import write_truth_labels
    from adjust.scene_cli import run as simulate
    from adjust.track import run as track
    from adjust.triangulate_cli import run as triangulate

    tag = "".join(f"{o.split('=')[-1].replace('.', '')}_" for o in sim)  # mouse_b_30_
    d = work / f"session_{tag}{seed}_{frames}"
    scene = d / "scene"
    t0 = time.perf_counter()
    if not (scene / "truth.npz").exists():
        ov = [f"output.dir={scene}", f"num_frames={frames}", f"seed={seed}", *sim]
        simulate(compose("scene", ov))
    inputs = [
        f"input.calibration={scene / 'calibration.toml'}",
        f"input.detections={scene / 'detections'}",
    ]
    if not (d / "track" / "points3d.csv").exists():
        track(compose("track", [*inputs, f"output.dir={d / 'track'}", "progress=false"]))
    if not (d / "dlt" / "points3d.csv").exists():
        triangulate(compose("triangulate", [*inputs, f"output.dir={d / 'dlt'}", "body=mouse"]))
    truth = np.load(scene / "truth.npz")
    behaviors = [str(b) for b in truth["behaviors"]]
    labels = d / "labels.csv"
    if not labels.exists():
        write_truth_labels(scene, labels)
    log.info("session %d: %d frames ready (%.1f s)", seed, frames, time.perf_counter() - t0)
    return {
        "seed": seed,
        "dir": d,
        "calibration": scene / "calibration.toml",
        "track": d / "track" / "points3d.csv",
        "dlt": d / "dlt" / "points3d.csv",
        "labels": labels,
        "truth_labels": truth["labels"],
        "truth_points": truth["points"],
        "parts": [str(p) for p in truth["parts"]],
        "behaviors": behaviors,
        "fps": float(truth["fps"]),
    }


def add_context_args(ap: argparse.ArgumentParser) -> None:
    """The options shared with `benchmarks/behavior_probe.py`: --box, --measurements,
    --transfer-sim and --body-scale (see the module docstrings)."""
    ap.add_argument("--box", action="store_true",
                    help="lock-box context for every classifier (ROI features for rf)")  # fmt: skip
    ap.add_argument("--measurements", action="store_true",
                    help="measurements=true for every deformnet-classify classifier")  # fmt: skip
    ap.add_argument(
        "--transfer-sim",
        default=None,
        help="also test every classifier on --test sessions of another simulated mouse "
        "(adjust-simulate overrides: sim=mouse_b,sim.fps=30)",
    )
    ap.add_argument("--transfer-frames", type=int, default=None,
                    help="--transfer-sim: frames per session of the other mouse (default "
                         "--frames)")  # fmt: skip
    ap.add_argument("--no-resample", action="store_true",
                    help="--transfer-sim at another frame rate: label its sessions frame by "
                         "frame as they are (as deformnet-classify without fps=), not "
                         "resampled to the training rate")  # fmt: skip
    ap.add_argument("--body-scale", default="session", choices=("session", "none"),
                    help="deformnet-classify body_scale for every classifier (none: the "
                         "points as they are, before stop 29)")  # fmt: skip


def add_transfer_sessions(sessions: dict, work: Path, args) -> tuple[str, ...]:
    """--transfer-sim: the other mouse's sessions (`args.test` of them, seeds TRANSFER_SEED..)
    as sessions["transfer"], with the training sessions' behaviors (ValueError otherwise);
    the overrides (empty: none)."""
    transfer = tuple(o.strip() for o in (args.transfer_sim or "").split(",") if o.strip())
    if transfer:
        frames = args.transfer_frames or args.frames
        sessions["transfer"] = [make_session(work, TRANSFER_SEED + i, frames, transfer)
                                for i in range(args.test)]  # fmt: skip
        behaviors = sessions["train"][0]["behaviors"]
        for s in sessions["transfer"]:
            if s["behaviors"] != behaviors:
                raise ValueError(f"{s['dir']}: behaviors {s['behaviors']} != {behaviors}")
    return transfer


def pretrain(out: Path, seconds: int, overrides: list[str] | None = None) -> tuple[str, float]:
    """A `deformnet-train` run of `seconds` (extra `overrides`, e.g. contrast.weight=1);
    (its best checkpoint, seconds taken)."""
    from deformnet.train import run

    t0 = time.perf_counter()
    secs = f"00:00:{seconds // 60:02d}:{seconds % 60:02d}"
    ov = [f"output.dir={out}", "logger=none", "progress_bar=none", f"trainer.max_time={secs}"]
    res = run(compose("train", ov + list(overrides or [])))
    ckpt = res.get("best_checkpoint") or res.get("last_checkpoint")
    if not ckpt:
        raise RuntimeError(f"deformnet-train wrote no checkpoint into {out}")
    return str(ckpt), time.perf_counter() - t0


# --------------------------------------------------------------------------------------------
# classifiers
# --------------------------------------------------------------------------------------------
def _list(paths) -> str:
    return "[" + ",".join(str(p) for p in paths) + "]"


def scratch_like(ckpt: str) -> list[str]:
    """deformnet-classify overrides for a from-scratch encoder that reads windows in the
    checkpoint's frame (its `up`, the heading frame; none for the body frame)."""
    from deformnet.deformation import DeformationModel

    up = DeformationModel.from_checkpoint(ckpt).up
    return [] if up is None else ["up=[" + ",".join(f"{v:g}" for v in up) + "]"]


def run_classifier(
    out: Path,
    sessions: dict,
    source: str,
    fraction: float,
    method: str,
    ckpt: str,
    seconds: int,
    label_seed: int = 0,
    box: str | None = None,
    measurements: bool = False,
    transfer: list[dict] | None = None,
    body_scale: str = "session",
    resample: bool = True,
    sequence: dict | None = None,
    extra: tuple[str, ...] = (),
) -> dict:
    """One deformnet-classify run; box: a calibration.toml whose lock box gives the lock-box
    context (`mechanisms.calibration`), None: without it; measurements: `measurements=true`;
    transfer: sessions the trained classifier then labels (`transfer_score`); body_scale:
    the classifier's; sequence (the TEACHERS methods): {"unlabelled": sessions, "steps":
    pretraining steps, "encoder": a sequence_encoder.pt to reuse or None, "teach": the teacher
    pseudo-labels the unlabelled sessions too}; extra: more deformnet-classify overrides."""
    from deformnet.classify import run

    ov = [f"output.dir={out}", "logger=none", f"labels.fraction={fraction}"]
    ov += [f"labels.seed={label_seed}", f"body_scale={body_scale}"]
    ov.append(f"trainer.max_time=00:00:{seconds // 60:02d}:{seconds % 60:02d}")
    for split in ("train", "val", "test"):
        ov.append(f"data.{split}_tracks={_list(s[source] for s in sessions[split])}")
        ov.append(f"data.{split}_labels={_list(s['labels'] for s in sessions[split])}")
    if source == "dlt":
        ov.append("data.interpolate=true")
    rates = {s["fps"] for split in ("train", "val", "test") for s in sessions[split]}
    if len(rates) == 1:  # the training rate, stored in classifier.pt (transfer_score resamples
        ov.append(f"fps={rates.pop():g}")  # another mouse's sessions of another rate to it)
    if box:
        ov.append(f"mechanisms.calibration={box}")
    if measurements:
        ov.append("measurements=true")
    ov += list(extra)
    if fraction >= 1.0:  # the head's ensemble is for few labels; one MLP on all 18000 frames
        ov.append("head.ensemble=1")  # (five L-BFGS fits on them: about 20 min per method)
    sq, pretrains = sequence or {}, False  # the teachers': unlabelled sessions, pretraining
    if method in ("scratch", "scratch_frozen", "scratch_forest_all"):  # the checkpoint's
        ov += ["pretrained=null", *scratch_like(ckpt)]  # architecture and frame
        if method != "scratch":
            ov.append("freeze=true")
        if method == "scratch_forest_all":
            ov += ["head=forest", "head.inputs=all"]
    elif method in ("forest", "forest_self", "forest_linear", "forest_all"):
        ov += [f"pretrained={ckpt}", "freeze=true", "head=forest"]
        ov += ["head.inputs=all"] if method == "forest_all" else []
        ov += ["pseudo_labels.teacher=self"] if method == "forest_self" else []
        ov += ["pseudo_labels.teacher=linear"] if method == "forest_linear" else []
    elif method in SEQUENCE_METHODS:
        teacher = "cotrain" if method.startswith("forest_cotrain") else "sequence"
        ov += [f"pretrained={ckpt}", "freeze=true", "head=forest",
               f"pseudo_labels.teacher={teacher}"]  # fmt: skip
        steps = 0 if method.endswith("_random") else int(sq.get("steps", 1000))
        if sq.get("encoder"):
            ov.append(f"pseudo_labels.sequence.encoder={sq['encoder']}")
        else:  # forest_*_random: the same net's random weights (no pretraining)
            ov.append(f"pseudo_labels.sequence.steps={steps}")
            pretrains = steps > 0
    else:
        ov += [f"pretrained={ckpt}", f"freeze={'true' if method == 'frozen' else 'false'}"]
    if method in TEACHERS:  # the unlabelled sessions: pseudo-labelled (teach) at every draw,
        # else only read by a sequence pretraining here
        if sq.get("unlabelled") and (sq.get("teach") or pretrains):
            ov.append(f"data.unlabelled_tracks={_list(u[source] for u in sq['unlabelled'])}")
        ov.append(f"pseudo_labels.unlabelled={'true' if sq.get('teach') else 'false'}")
    t0 = time.perf_counter()
    rep = run(compose("classify", ov))["report"]
    out_ = {
        "macro_f1": rep["raw"]["macro_f1"],
        "macro_f1_smoothed": rep["smoothed"]["macro_f1"],
        "f1": {c: v["f1"] for c, v in rep["raw"]["per_class"].items()},
        "labelled_frames": rep["labelled_training_frames"],
        "unfamiliar_frames": rep.get("unfamiliar_frames"),
        "steps": rep["training_steps"],
        "seconds": round(time.perf_counter() - t0, 1),
    }
    pl = (rep.get("probe") or {}).get("pseudo_labels")
    if pl:  # the teacher's facts (its pseudo-labels, the sequence encoder's pretraining)
        out_["pseudo_labels"] = {k: v for k, v in pl.items() if k != "forest"}
    if transfer:
        out_ |= transfer_score(out / "classifier.pt", transfer, source, resample)
        train_rate = sessions["train"][0]["fps"]
        if resample and any(s["fps"] > train_rate and not same_fps(s["fps"], train_rate)
                            for s in transfer):  # fmt: skip
            plain = transfer_score(out / "classifier.pt", transfer, source, True, False)
            out_["transfer_no_antialias"] = {  # the same, resampled without the low-pass
                k: plain[f"transfer_{k}"] for k in ("macro_f1", "macro_f1_smoothed", "f1")
            }
    return out_


def transfer_score(
    ckpt: Path, sessions: list[dict], source: str, resample: bool = True, antialias: bool = True
) -> dict:
    """A trained classifier on other sessions (another mouse), as `deformnet-classify
    mode=predict` labels them (its own mechanism positions and smoothing; resampled to its
    rate, low-passed first when that is lower unless `antialias` is false): macro-F1 and
    per-class F1 over all their frames, raw and smoothed, and the share of their frames that
    the classifier finds unlike its training data, and each session's body scale
    ({"transfer_macro_f1", ..., "transfer_unfamiliar_frames", "transfer_body_scales"})."""
    from deformnet.behavior_report import evaluate
    from deformnet.classify import frame_rates, load_classifier, predict_session, read_session

    model, meta = load_classifier(ckpt)
    truth, raw, smoothed, unfamiliar, scales = [], [], [], [], []
    frame_share = float(compose("classify").unfamiliar.frame_share)
    for s in sessions:
        rates = frame_rates(s.get("fps"), meta, str(s[source])) if resample else None
        sess = read_session(str(s[source]), model, meta, interpolate=source == "dlt")
        scales.append(sess.scale)
        pr = predict_session(model, sess, dict(meta.get("smoothing") or {}),
                             meta.get("feature_range"), rates, antialias)  # fmt: skip
        if pr["unfamiliar"] is not None:
            unfamiliar.append(pr["unfamiliar"] > frame_share)
        truth.append(np.asarray(s["truth_labels"])[sess.fnum])
        raw.append(pr["raw"])
        smoothed.append(pr["labels"])
    y = np.concatenate(truth)
    classes = list(meta["classes"])
    ev = evaluate(y, np.concatenate(raw), classes)
    return {
        "transfer_macro_f1": ev["macro_f1"],
        "transfer_macro_f1_smoothed": evaluate(y, np.concatenate(smoothed), classes)["macro_f1"],
        "transfer_f1": {c: v["f1"] for c, v in ev["per_class"].items()},
        "transfer_unfamiliar_frames": (
            float(np.concatenate(unfamiliar).mean()) if unfamiliar else None
        ),
        "transfer_body_scales": scales,  # each session's (None: body_scale=none)
    }


#: the parts whose distances to the mechanisms are SimBA's ROI features (--box)
ROI_PARTS = ("nose_tip", "left_front_paw", "right_front_paw")


def rig_mechanisms(sessions: dict) -> tuple[str, np.ndarray]:
    """The sessions' lock box: (the first session's calibration.toml, the mechanisms' positions
    (M, 3) from its [metadata.mechanisms]); every session's must be the same (one rig)."""
    from deformnet.lockbox import calibration_mechanisms

    pos, first = None, None
    for s in (x for split in sessions.values() for x in split):
        table = calibration_mechanisms(s["calibration"])
        p = np.asarray([table[m] for m in sorted(table)], dtype=np.float64)
        if pos is None:
            pos, first = p, str(s["calibration"])
        elif p.shape != pos.shape or not np.allclose(p, pos):
            raise ValueError(f"{s['calibration']}: its lock box differs from {first}'s")
    return first, pos


def window_features(
    path: Path,
    parts: list[str],
    interpolate: bool,
    mechanisms: np.ndarray | None = None,
    fps: float = 30.0,
    ref_fps: float = 30.0,
) -> np.ndarray:
    """SimBA-style per-frame features (T, F) from a points3d CSV (see the module docstring);
    mechanisms (M, 3): with SimBA's ROI features (the distances of `ROI_PARTS` to each, and
    the nearest of them per mechanism, mm). As SimBA, in time: speeds in mm/s for a track at
    `fps`, the rolling windows' lengths (frames at `ref_fps`, the training rate) scaled to it."""
    df = pd.read_csv(path)
    P = np.stack([df[[f"{p}_{a}" for a in "xyz"]].to_numpy(np.float64) for p in parts], 1)
    if interpolate:
        from deformnet.series import interpolate_gaps

        P = interpolate_gaps(P)
    T, K = P.shape[:2]
    nose, tail = P[:, parts.index("nose_tip")], P[:, parts.index("tail_root")]
    axis = nose - tail
    length = np.linalg.norm(axis, axis=-1)
    heading = np.arctan2(axis[:, 1], axis[:, 0])
    elevation = np.arcsin(np.clip(axis[:, 2] / np.maximum(length, 1e-9), -1, 1))
    centroid = P.mean(1)
    iu = np.triu_indices(K, 1)
    dist = np.linalg.norm(P[:, :, None] - P[:, None, :], axis=-1)[:, iu[0], iu[1]]
    speed = np.linalg.norm(np.diff(P, axis=0, prepend=P[:1]), axis=-1) * fps
    base = np.concatenate(
        [
            centroid,
            length[:, None],
            np.cos(heading)[:, None],
            np.sin(heading)[:, None],
            elevation[:, None],
            P[:, :, 2],
            dist,
            speed,
        ],
        1,
    )
    if mechanisms is not None:
        roi = P[:, [parts.index(p) for p in ROI_PARTS]]
        d = np.linalg.norm(roi[:, :, None] - np.asarray(mechanisms)[None, None], axis=-1)
        base = np.concatenate([base, d.reshape(T, -1), d.min(1)], 1)
    frame = pd.DataFrame(base)
    feats = [base]
    for w in (5, 15, 33):
        roll = frame.rolling(max(1, round(w * fps / ref_fps)), center=True, min_periods=1)
        feats += [roll.mean().to_numpy(), roll.std().fillna(0.0).to_numpy()]
    return np.nan_to_num(np.concatenate(feats, 1), nan=0.0)


def run_rf(
    sessions: dict,
    source: str,
    fraction: float,
    seed: int = 0,
    label_seed: int = 0,
    mechanisms: np.ndarray | None = None,
    resample: bool = True,
    predictions: bool = False,
) -> dict:
    """The SimBA-style random forest trained on the labelled frames of sessions["train"],
    scored on sessions["test"] and, when there (--transfer-sim), the same forest on
    sessions["transfer"] ("transfer_macro_f1", "transfer_f1"); ``predictions``: the test
    sessions' predicted labels too ("pred", their frames in order)."""
    from sklearn.ensemble import RandomForestClassifier

    from deformnet.behavior_labels import Session, subsample_labels
    from deformnet.behavior_report import evaluate

    classes = sessions["train"][0]["behaviors"]
    parts = sessions["train"][0]["parts"]
    t0 = time.perf_counter()

    rate = sessions["train"][0]["fps"]

    def load(split):
        X = [window_features(s[source], parts, source == "dlt", mechanisms,
                             s["fps"] if resample else rate, rate)
             for s in sessions[split]]  # fmt: skip
        y = [np.asarray(s["truth_labels"], np.int64) for s in sessions[split]]
        return X, y

    Xtr, ytr = load("train")
    # the same labelled frames the nets get (deformnet.behavior_labels.subsample_labels)
    dummy = [
        Session(str(i), None, None, None, np.arange(len(y)), y.copy()) for i, y in enumerate(ytr)
    ]  # fmt: skip
    subsample_labels(dummy, fraction, 1, label_seed)
    X = np.concatenate([x[s.labels >= 0] for x, s in zip(Xtr, dummy)])
    y = np.concatenate([s.labels[s.labels >= 0] for s in dummy])
    rf = RandomForestClassifier(
        n_estimators=200, class_weight="balanced", n_jobs=1, random_state=seed, min_samples_leaf=2
    )
    rf.fit(X, y)
    out = {"labelled_frames": int(len(y))}
    for split in [k for k in ("test", "transfer") if k in sessions]:
        Xte, yte = load(split)
        pred = rf.predict(np.concatenate(Xte))
        ev = evaluate(np.concatenate(yte), pred, classes)
        pre = "" if split == "test" else "transfer_"
        if predictions and split == "test":
            out["pred"] = pred
        out |= {f"{pre}macro_f1": ev["macro_f1"],
                f"{pre}f1": {c: v["f1"] for c, v in ev["per_class"].items()}}  # fmt: skip
    return out | {"seconds": round(time.perf_counter() - t0, 1)}


def averaged(runs: list[dict]) -> dict:
    """One method's result over several label draws: the mean macro-F1 (raw, smoothed) and
    per-class F1, each draw's macro-F1, the total seconds."""
    if len(runs) == 1:
        return runs[0]
    out = dict(runs[0])
    for pre in ("", "transfer_"):  # the test sessions' and (--transfer-sim) the other mouse's
        if f"{pre}macro_f1" not in runs[0]:
            continue
        out[f"{pre}macro_f1"] = float(np.mean([r[f"{pre}macro_f1"] for r in runs]))
        out[f"{pre}macro_f1_draws"] = [r[f"{pre}macro_f1"] for r in runs]
        if runs[0].get(f"{pre}macro_f1_smoothed") is not None:
            sm = [r[f"{pre}macro_f1_smoothed"] for r in runs]
            out[f"{pre}macro_f1_smoothed"] = float(np.mean(sm))
        out[f"{pre}f1"] = {
            c: float(np.nanmean([np.nan if r[f"{pre}f1"][c] is None else r[f"{pre}f1"][c]
                                 for r in runs]))
            for c in runs[0][f"{pre}f1"]
        }  # fmt: skip
    if all("transfer_no_antialias" in r for r in runs):  # the other mouse without the low-pass
        out["transfer_no_antialias"] = averaged([r["transfer_no_antialias"] for r in runs])
    for k in ("unfamiliar_frames", "transfer_unfamiliar_frames"):
        if all(r.get(k) is not None for r in runs):
            out[k] = float(np.mean([r[k] for r in runs]))
    if all("seconds" in r for r in runs):
        out["seconds"] = round(sum(r["seconds"] for r in runs), 1)
    return out


# --------------------------------------------------------------------------------------------
# events
# --------------------------------------------------------------------------------------------
def truth_bouts(labels: np.ndarray, behaviors: list[str]) -> list[dict]:
    from deformnet.behavior_labels import bouts

    out = []
    for a, b, c in bouts(np.asarray(labels)):
        if behaviors[c] in MECHANISMS:
            out.append({"mechanism": behaviors[c], "start": a, "stop": b})
    return out


def match_events(ops: list[dict], truth: list[dict]) -> dict:
    """Greedy one-to-one matching by overlap (same mechanism): tp, fp, fn, onset errors."""
    used = set()
    onset = []
    tp = 0
    for o in ops:
        best, overlap = None, 0
        for i, t in enumerate(truth):
            if i in used or t["mechanism"] != o["mechanism"]:
                continue
            ov = min(o["stop"], t["stop"]) - max(o["start"], t["start"]) + 1
            if ov > overlap:
                best, overlap = i, ov
        if best is not None:
            used.add(best)
            tp += 1
            onset.append(abs(o["start"] - truth[best]["start"]))
    return {"tp": tp, "fp": len(ops) - tp, "fn": len(truth) - len(used), "onset": onset}


def first_order(items: list[dict]) -> list[str]:
    first: dict[str, int] = {}
    for e in items:
        first.setdefault(e["mechanism"], e["start"])
        first[e["mechanism"]] = min(first[e["mechanism"]], e["start"])
    return sorted(first, key=first.get)


#: how the simulated lab's mechanisms are operated (the simulator's effectors: a paw for the
#: lever and the ball, the snout for the splint and the slider): adjust-events' mechanism_parts
LAB_PARTS = (
    "mechanism_parts={lever: [left_front_paw, right_front_paw], "
    "ball: [left_front_paw, right_front_paw], splint: [nose_tip], slider: [nose_tip]}"
)


def event_scores(sessions: list[dict], overrides: list[str], tag: str) -> dict:
    from adjust.events import detect_events, operations
    from adjust.events_cli import mechanism_positions, run
    from deformnet.confutil import to_plain

    totals = {k: {"tp": 0, "fp": 0, "fn": 0, "onset": [], "order_ok": 0, "inferred": 0}
              for k in ("track", "dlt", "truth3d")}  # fmt: skip
    for s in sessions:
        truth = truth_bouts(s["truth_labels"], s["behaviors"])
        cfg_d = compose("events", ["tracks=x", *overrides])
        for source in ("track", "dlt", "truth3d"):
            if source == "truth3d":
                c = cfg_d.contact
                mech = mechanism_positions(compose("events", [f"calibration={s['calibration']}"]))
                ev = detect_events(
                    s["truth_points"], s["parts"], mech, list(cfg_d.parts), float(c.on_mm),
                    float(c.off_mm), int(c.min_frames), int(c.merge_gap),
                    mechanism_parts=to_plain(cfg_d.mechanism_parts),
                )  # fmt: skip
                ops = operations(ev, int(c.merge_gap))
                inferred = 0
            else:
                ov = [
                    f"tracks={s[source]}",
                    f"calibration={s['calibration']}",
                    f"output.dir={s['dir'] / f'events_{tag}_{source}'}",
                    *overrides,
                ]
                if source == "dlt":
                    ov.append("interpolate=true")
                res = run(compose("events", ov))
                ops, inferred = res["operation_list"], res["inferred_events"]
            m = match_events(ops, truth)
            t = totals[source]
            for k in ("tp", "fp", "fn"):
                t[k] += m[k]
            t["onset"] += m["onset"]
            t["inferred"] += inferred
            t["order_ok"] += int(first_order(ops) == first_order(truth))
    out = {}
    for source, t in totals.items():
        det, true = t["tp"] + t["fp"], t["tp"] + t["fn"]
        out[source] = {
            "precision": t["tp"] / det if det else float("nan"),
            "recall": t["tp"] / true if true else float("nan"),
            "onset_error_frames": float(np.mean(t["onset"])) if t["onset"] else float("nan"),
            "order_correct": t["order_ok"] / len(sessions),
            "true_operations": true,
            "detected_operations": det,
            "inferred_events": t["inferred"],
        }
    return out


# --------------------------------------------------------------------------------------------
def _fmt(v) -> str:
    if isinstance(v, float):
        return "   n/a" if not math.isfinite(v) else f"{v:6.3f}"
    return str(v)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3000, help="frames per session")
    ap.add_argument("--train", type=int, default=6, help="training sessions")
    ap.add_argument("--val", type=int, default=1, help="validation sessions")
    ap.add_argument("--test", type=int, default=4, help="test sessions")
    ap.add_argument("--pretrained", default=None, help="deformnet-train checkpoint (else train)")
    ap.add_argument("--pretrain-seconds", type=int, default=240)
    ap.add_argument(
        "--frame",
        choices=("body", "heading"),
        default="body",
        help="without --pretrained: the pretraining run's canonical frame (heading: up=[0,0,1])",
    )
    ap.add_argument("--seconds", type=int, default=75, help="trainer.max_time per classifier")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--label-draws", type=int, default=3, help="label draws averaged at 1%% labels")
    ap.add_argument(
        "--fractions", default="0.01,0.1,1", help="label fractions (a subset: part of a run)"
    )
    ap.add_argument(
        "--methods",
        default=",".join(METHODS),
        help="classifiers to run (a subset: part of a run; the 10%% input comparison and the "
        "events always run)",
    )
    add_context_args(ap)
    ap.add_argument("--heights-up", action="store_true",
                    help="--measurements with a body-frame encoder: heights_up=[0,0,1] (the "
                         "parts' heights in the measurements, as behavior_mae.py has)")  # fmt: skip
    ap.add_argument("--sequence-encoder", default=None,
                    help="forest_sequence: a sequence_encoder.pt an earlier run pretrained on "
                         "these training sessions, reused (no pretraining)")  # fmt: skip
    ap.add_argument("--test-offset", type=int, default=0,
                    help="the test sessions' seeds start this far after 95200 (e.g. 12: "
                         "sessions no choice of a method looked at)")  # fmt: skip
    ap.add_argument("--unlabelled", type=int, default=8,
                    help="forest_sequence*: more sessions without labels (seeds 95500..; "
                         "data.unlabelled_tracks) the sequence encoder pretrains on (and, with "
                         "--teach-unlabelled, the teachers pseudo-label)")  # fmt: skip
    ap.add_argument("--teach-unlabelled", action="store_true",
                    help="the teachers also pseudo-label the unlabelled sessions' frames "
                         "(pseudo_labels.unlabelled=true); else only the sequence encoder "
                         "pretrains on them")  # fmt: skip
    ap.add_argument(
        "--sequence-steps",
        type=int,
        default=1000,
        help="forest_sequence: pretraining steps (pseudo_labels.sequence.steps)",
    )
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "behavior"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "behavior.json"))
    args = ap.parse_args(argv)
    if args.unlabelled < 0 or args.sequence_steps < 1 or args.test_offset < 0:
        ap.error("--unlabelled and --test-offset must be >= 0 and --sequence-steps >= 1")
    if SEEDS["test"] + args.test_offset + args.test > TRANSFER_SEED:
        ap.error(f"--test-offset {args.test_offset}: the test seeds would reach the other "
                 f"mouse's ({TRANSFER_SEED}..)")  # fmt: skip
    methods = subset(ap, args.methods, METHODS, "--methods")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logging.getLogger(name).setLevel(logging.WARNING)
    torch.set_num_threads(args.threads)
    work = Path(args.work)
    t_start = time.perf_counter()

    counts = {"train": args.train, "val": args.val, "test": args.test}
    offsets = {"test": args.test_offset}
    sessions = {
        split: [make_session(work, SEEDS[split] + offsets.get(split, 0) + i, args.frames)
                for i in range(n)]
        for split, n in counts.items()
    }  # fmt: skip
    transfer = add_transfer_sessions(sessions, work, args)
    t_sessions = time.perf_counter() - t_start
    extra: dict = {"sessions_seconds": round(t_sessions, 1)}
    ckpt = args.pretrained
    if ckpt is None:
        log.info(
            "no --pretrained: a %d s deformnet-train run (default LSTM)", args.pretrain_seconds
        )
        heading = args.frame == "heading"
        ckpt, secs = pretrain(
            work / ("pretrain_heading" if heading else "pretrain"),
            args.pretrain_seconds,
            ["up=[0,0,1]"] if heading else [],
        )
        extra["pretrain_seconds"] = round(secs, 1)
    extra["pretrained"] = str(ckpt)
    extra["scratch_overrides"] = scratch_like(ckpt)  # the encoder's frame (up) for scratch
    box, mech = rig_mechanisms(sessions) if args.box else (None, None)
    extra["box"] = box
    extra["measurements"] = bool(args.measurements)
    extra["transfer_sim"] = list(transfer) or None
    tag = ("box_" if box else "") + ("meas_" if args.measurements else "")  # output folders
    tag += "" if args.body_scale == "session" else f"scale{args.body_scale}_"
    extra["body_scale"] = args.body_scale
    extra["transfer_resampled"] = bool(transfer) and not args.no_resample
    extra["transfer_fps"] = sorted({s["fps"] for s in sessions.get("transfer", [])}) or None

    # the sequence methods' unlabelled sessions (made only where one of them runs)
    teaching = set(SEQUENCE_METHODS) | ({"forest_linear"} if args.teach_unlabelled else set())
    n_unl = args.unlabelled if teaching & set(methods) else 0
    unlabelled = [make_session(work, UNLABELLED_SEED + i, args.frames) for i in range(n_unl)]
    extra_ov = ("heights_up=[0,0,1]",) if args.heights_up else ()
    seq_encoders: dict[str, str] = {}  # forest_sequence*: the first run's sequence encoder
    if args.sequence_encoder:
        seq_encoders["forest_sequence"] = args.sequence_encoder
    results: dict[str, dict] = {}
    for frac in [float(f) for f in args.fractions.split(",")]:
        key = f"{frac:g}"
        results[key] = {}
        # at 1% (a few labelled frames per class) which frames get labels moves macro-F1 by
        # several points: every method is run on the same `--label-draws` draws, averaged
        draws = range(args.label_draws if frac <= 0.01 else 1)
        for method in [m for m in methods if m != "rf"]:
            runs = []
            for d in draws:
                out = (work / f"{tag}cls_track_{method}_{key}" / f"draw{d}" if len(draws) > 1
                       else work / f"{tag}cls_track_{method}_{key}")  # fmt: skip
                sq = None
                if method in TEACHERS:  # the unlabelled sessions; a sequence encoder is
                    # pretrained once (no labels), then reused
                    sq = {"unlabelled": unlabelled, "steps": args.sequence_steps,
                          "encoder": seq_encoders.get(method,
                                                      seq_encoders.get(SAME_ENCODER.get(method))),
                          "teach": args.teach_unlabelled}  # fmt: skip
                runs.append(run_classifier(
                    out, sessions, "track", frac, method, ckpt, args.seconds, label_seed=d,
                    box=box, measurements=args.measurements, transfer=sessions.get("transfer"),
                    body_scale=args.body_scale, resample=not args.no_resample, sequence=sq,
                    extra=extra_ov,
                ))  # fmt: skip
                if method in SEQUENCE_METHODS and method not in seq_encoders:
                    seq_encoders[method] = (sq or {}).get("encoder") or str(
                        out / "sequence_encoder.pt"
                    )  # fmt: skip
            results[key][method] = averaged(runs)
            log.info("labels %s %s: macro-F1 %.3f", key, method, results[key][method]["macro_f1"])
        if "rf" in methods:
            runs = [run_rf(sessions, "track", frac, label_seed=d, mechanisms=mech,
                           resample=not args.no_resample) for d in draws]  # fmt: skip
            results[key]["rf"] = averaged(runs)  # (and on the other mouse, --transfer-sim)
            log.info("labels %s rf: macro-F1 %.3f", key, results[key]["rf"]["macro_f1"])
    r10 = dict(results.get("0.1") or {})  # what a partial run did not measure, run here
    if "pretrained" not in r10:
        r10["pretrained"] = run_classifier(
            work / f"{tag}cls_track_pretrained_0.1", sessions, "track", 0.1, "pretrained", ckpt,
            args.seconds, box=box, measurements=args.measurements, body_scale=args.body_scale,
            extra=extra_ov,
        )  # fmt: skip
    if "rf" not in r10:
        r10["rf"] = run_rf(sessions, "track", 0.1, mechanisms=mech)
    same_mouse = {k: v for k, v in sessions.items() if k != "transfer"}  # DLT: not transferred
    inputs = {
        "track": {
            "pretrained": r10["pretrained"]["macro_f1"],
            "rf": r10["rf"]["macro_f1"],
        },
        "dlt": {
            "pretrained": run_classifier(
                work / f"{tag}cls_dlt_pretrained_0.1",
                sessions,
                "dlt",
                0.1,
                "pretrained",
                ckpt,
                args.seconds,
                box=box,
                measurements=args.measurements,
                body_scale=args.body_scale,
                extra=extra_ov,
            )["macro_f1"],  # fmt: skip
            "rf": run_rf(same_mouse, "dlt", 0.1, mechanisms=mech)["macro_f1"],
        },
    }
    all_sessions = [s for split in ("train", "val", "test") for s in sessions[split]]
    events = event_scores(all_sessions, [LAB_PARTS], "lab")
    events_any = event_scores(all_sessions, [], "any")

    print(
        f"\nbehavior: {sum(counts.values())} sessions x {args.frames} frames (train "
        f"{args.train}, val {args.val}, test {args.test}); test macro-F1 (raw / smoothed)"
    )
    print(f"{'labels':<8}" + "".join(f"{m:>24}" for m in methods))
    for key, r in results.items():
        cells = []
        for m in methods:
            sm = r[m].get("macro_f1_smoothed")
            cells.append(f"{_fmt(r[m]['macro_f1'])}" + (f" / {_fmt(sm)}" if sm is not None else ""))
        print(f"{key:<8}" + "".join(f"{c:>24}" for c in cells))
    if transfer:
        print(f"\nthe other mouse ({', '.join(transfer)}; {args.test} sessions): macro-F1 (raw)")
        print(f"{'labels':<8}" + "".join(f"{m:>24}" for m in methods))
        for key, r in results.items():
            print(f"{key:<8}" + "".join(f"{_fmt(r[m].get('transfer_macro_f1')):>24}"
                                        for m in methods))  # fmt: skip
        if any("transfer_no_antialias" in r[m] for r in results.values() for m in methods):
            print("the same, resampled to the training rate without the low-pass (antialias=false)")
            for key, r in results.items():
                print(f"{key:<8}" + "".join(
                    f"{_fmt(r[m].get('transfer_no_antialias', {}).get('macro_f1')):>24}"
                    for m in methods))  # fmt: skip
        print("unfamiliar frames (deformnet-classify's check), test sessions / the other mouse")
        for key, r in results.items():
            cells = [f"{_fmt(r[m].get('unfamiliar_frames'))} / "
                     f"{_fmt(r[m].get('transfer_unfamiliar_frames'))}" if m != "rf" else "n/a"
                     for m in methods]  # fmt: skip
            print(f"{key:<8}" + "".join(f"{c:>24}" for c in cells))
    print("\ninput (10% labels)  pretrained      rf")
    for src, r in inputs.items():
        print(f"{src:<18}{_fmt(r['pretrained']):>11}{_fmt(r['rf']):>9}")
    print(
        "\nevents (all sessions)  precision  recall  onset(frames)  order-correct  true  detected"
    )
    for src, r in events.items():
        print(
            f"{src:<22}{_fmt(r['precision']):>10}{_fmt(r['recall']):>8}"
            f"{_fmt(r['onset_error_frames']):>15}{_fmt(r['order_correct']):>15}"
            f"{r['true_operations']:>6}{r['detected_operations']:>10}"
        )
    checks = {"pretrained_10pct_ge_0.9": r10["pretrained"]["macro_f1"] >= 0.9}
    r1 = results.get("0.01", {})
    if {"pretrained", "scratch", "scratch_frozen", "rf"} <= set(r1):
        # against the better of the two from-scratch variants (end to end; random encoder, probe)
        checks["pretrained_beats_scratch_1pct"] = r1["pretrained"]["macro_f1"] > max(
            r1["scratch"]["macro_f1"], r1["scratch_frozen"]["macro_f1"]
        )
        checks["pretrained_beats_rf_1pct"] = r1["pretrained"]["macro_f1"] > r1["rf"]["macro_f1"]
    if {"forest", "rf"} <= set(r1):
        checks["forest_beats_rf_1pct"] = r1["forest"]["macro_f1"] > r1["rf"]["macro_f1"]
    if {"forest_self", "forest"} <= set(r1):
        checks["forest_self_beats_forest_1pct"] = (
            r1["forest_self"]["macro_f1"] > r1["forest"]["macro_f1"]
        )
    for b in ("rf", "forest_sequence_random", "forest_linear", "forest_self", "forest"):
        if {"forest_sequence", b} <= set(r1):  # the pretrained sequence encoder as a teacher
            checks[f"forest_sequence_beats_{b}_1pct"] = (
                r1["forest_sequence"]["macro_f1"] > r1[b]["macro_f1"]
            )
    for b in ("rf", "forest_cotrain_random", "forest_sequence", "forest_linear"):
        if {"forest_cotrain", b} <= set(r1):  # ... and as the second view of a co-training
            checks[f"forest_cotrain_beats_{b}_1pct"] = (
                r1["forest_cotrain"]["macro_f1"] > r1[b]["macro_f1"]
            )
    for key in [k for k in ("0.01", "0.1") if transfer and k in results]:
        r, pct = results[key], f"{float(key) * 100:g}pct"
        for a, b in (("pretrained", "rf"), ("forest_all", "rf"), ("forest_all", "forest"),
                     ("pretrained", "scratch"), ("frozen", "scratch_frozen"),
                     ("forest_all", "scratch_forest_all")):  # fmt: skip
            if {a, b} <= set(r):
                checks[f"{a}_beats_{b}_transfer_{pct}"] = (
                    r[a]["transfer_macro_f1"] > r[b]["transfer_macro_f1"]
                )
    checks |= {
        "events_track_ge_0.9": events["track"]["precision"] >= 0.9
        and events["track"]["recall"] >= 0.9,
        "events_track_beat_dlt": events["track"]["precision"] >= events["dlt"]["precision"]
        and events["track"]["recall"] >= events["dlt"]["recall"]
        and (
            events["track"]["precision"] + events["track"]["recall"]
            > events["dlt"]["precision"] + events["dlt"]["recall"]
        ),
        "tracked_input_beats_dlt": inputs["track"]["pretrained"] > inputs["dlt"]["pretrained"],
    }
    print("checks: " + ", ".join(f"{k}={v}" for k, v in checks.items()))
    summary = {
        "classification": results,
        "input_comparison_10pct": inputs,
        "events": events,
        "events_any_part": events_any,
        "checks": checks,
        "setup": {
            "frames": args.frames,
            "sessions": counts,
            "seeds": SEEDS
            | ({"transfer": TRANSFER_SEED} if transfer else {})
            | ({"unlabelled": UNLABELLED_SEED} if unlabelled else {}),
            "test_offset": args.test_offset,
            "heights_up": bool(args.heights_up),
            "sequence_encoder": args.sequence_encoder,
            "unlabelled_sessions": len(unlabelled),
            "teach_unlabelled": bool(args.teach_unlabelled),
            "sequence_steps": args.sequence_steps,
            "seconds_per_classifier": args.seconds,
            "label_draws_at_1pct": args.label_draws,
            "fractions": args.fractions,
            "methods": methods,
        },
        **extra,
        "total_seconds": round(time.perf_counter() - t_start, 1),
        "threads": args.threads,
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    line = json.dumps(finite_or_none(_round(summary)))
    write_text(args.out, line + "\n")
    print(line, flush=True)
    return summary


def _round(x):
    if isinstance(x, dict):
        return {k: _round(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_round(v) for v in x]
    return round(x, 4) if isinstance(x, float) and math.isfinite(x) else x


if __name__ == "__main__":
    main()
