"""`deformnet-classify` mode=predict: a trained classifier labels one track
(`predict_track`: predictions.csv, bouts.csv, summary.json), and `run(cfg)`, the plain function
behind the app (`deformnet.apps.classify`): mode=train (`deformnet.behavior.train`) or predict.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path

import lightning as L
import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf

from deformnet.atomic import atomic_path, finite_or_none, write_text
from deformnet.behavior.features import set_body_scales
from deformnet.behavior.labels import bouts
from deformnet.behavior.model import load_classifier, mechanism_setup, predict_session
from deformnet.behavior.rates import frame_rates
from deformnet.behavior.settings import ClassifySettings
from deformnet.behavior.tracks import Session, read_tracks
from deformnet.behavior.train import train_classifier
from deformnet.confutil import check_fps, to_plain
from deformnet.deformation import check_track_up
from deformnet.paths import output_dir
from deformnet.threads import set_torch_threads

log = logging.getLogger(__name__)

__all__ = ["read_session", "predict_track", "run"]


def _predict_mechanisms(cfg: DictConfig, st: ClassifySettings, model, meta: dict) -> None:
    """mode=predict: the mechanisms' positions in this recording's frame. The classifier's own
    (its training rig's) unless ``mechanisms.positions`` / ``mechanisms.calibration`` give
    this session's (the same mechanisms by name; a moved lock box); its parts and scale stay
    the classifier's."""
    trained = meta.get("mechanisms")
    here = mechanism_setup(st, meta["body"])
    if here is None:
        if trained:
            log.info("lock-box context: the classifier's mechanism positions (%s)",
                     trained.get("source"))  # fmt: skip
        return
    if not trained:
        raise ValueError(
            f"{cfg.checkpoint} was trained without lock-box context: unset mechanisms.positions "
            "/ mechanisms.calibration"
        )
    pos = dict(zip(here["names"], here["positions"]))
    missing = [n for n in trained["names"] if n not in pos]
    if missing:
        raise ValueError(f"{here['source']}: no position for mechanism(s) {missing} "
                         f"(the classifier's: {trained['names']})")  # fmt: skip
    xyz = [pos[n] for n in trained["names"]]  # in the classifier's order
    model.encoder.mechanisms.positions.copy_(torch.tensor(xyz, dtype=torch.float32))
    meta["mechanisms"] = {**trained, "positions": xyz, "source": here["source"]}
    log.info("lock-box context: mechanism positions from %s", here["source"])


def read_session(
    path: str, model, meta: Mapping, interpolate: bool = False, aliases: Mapping | None = None
) -> Session:
    """A track for a trained classifier (`load_classifier`'s model and meta) to label: read in
    its body model's parts (its file's names through the model's aliases and `aliases`),
    checked against the world's up its encoder assumes (its heading frame's, else the
    heights'; or none), unlabelled, with its body scale if the classifier divides it out
    (``body_scale``, as it was trained)."""
    tr = read_tracks(path, meta["body"].with_aliases(aliases), interpolate=interpolate)
    check_track_up(tr["rigid"], meta["body"].points, model.encoder.heights_up, path)
    T = len(tr["fnum"])
    parts = (tr["rigid"], tr["deformed"], tr["observed"], tr["fnum"])
    s = Session(path, *parts, np.full(T, -1), pose=tr["pose"])
    set_body_scales([s], meta.get("body_scale") or "none", meta["body"])
    return s


def predict_track(cfg: DictConfig, st: ClassifySettings, out: Path) -> dict:
    """mode=predict: label ``tracks`` with ``checkpoint``; returns the written files' summary."""
    if isinstance(to_plain(cfg.get("tracks")), list) or cfg.get("labels"):
        raise ValueError("mode=predict labels one track: tracks=points3d.csv (no labels=)")
    if not cfg.get("checkpoint") or not cfg.get("tracks"):
        raise ValueError("mode=predict needs checkpoint=CLASSIFIER.pt and tracks=points3d.csv")
    model, meta = load_classifier(str(cfg.checkpoint))
    classes = list(meta["classes"])
    unf, antialias = st.unfamiliar, bool(st.antialias)
    _predict_mechanisms(cfg, st, model, meta)
    rates = frame_rates(cfg.get("fps"), meta, str(cfg.tracks))  # before the track is read
    s = read_session(
        str(cfg.tracks), model, meta, bool(st.data.interpolate),
        to_plain(cfg.get("aliases")),
    )  # fmt: skip
    T = len(s.fnum)
    smoothing = st.smoothing if cfg.get("smoothing") else meta.get("smoothing")
    rng = meta.get("feature_range")
    pr = predict_session(model, s, smoothing, rng, rates, antialias)
    fnum = s.fnum
    names = np.asarray(classes, dtype=object)
    df = pd.DataFrame(
        {"fnum": fnum, "label": names[pr["labels"]], "label_raw": names[pr["raw"]]}
        | {f"p_{c}": pr["probs"][:, i] for i, c in enumerate(classes)}
    )
    warning, share = None, None
    if rng is None:
        log.info("%s stores no training feature range (an older classifier): the recording is "
                 "not compared with the training data", cfg.checkpoint)  # fmt: skip
    else:
        df["unfamiliar"] = pr["unfamiliar"]
        share = float(np.mean(pr["unfamiliar"] > unf.frame_share))
        if share > unf.warn_share:
            warning = (
                f"{cfg.tracks}: {100 * share:.0f}% of the frames are unlike the classifier's "
                f"training data (more than {100 * unf.frame_share:g}% of their features "
                "outside the training range; column 'unfamiliar'): its labels there are not to "
                "be trusted (another animal, rig or tracker?). Label some of this recording's "
                "frames and train on them too; a forest head (head=forest freeze=true "
                "measurements=true) with body_scale=session transfers best"
            )
            log.warning("%s", warning)
    pred_path, bouts_path = out / "predictions.csv", out / "bouts.csv"
    with atomic_path(pred_path) as tmp:
        df.to_csv(tmp, index=False)
    rows = [
        {
            "start": int(fnum[a]),
            "stop": int(fnum[b]),
            "label": classes[c],
            "mean_probability": float(pr["probs"][a : b + 1, c].mean()),
        }
        for a, b, c in bouts(pr["labels"])
    ]
    with atomic_path(bouts_path) as tmp:
        pd.DataFrame(rows, columns=["start", "stop", "label", "mean_probability"]).to_csv(
            tmp, index=False
        )
    log.info("%d frames, %d bouts -> %s, %s", T, len(rows), pred_path, bouts_path)
    summary = {
        "output_dir": str(out),
        "predictions": str(pred_path),
        "bouts": str(bouts_path),
        "frames": T,
        "num_bouts": len(rows),
        "unfamiliar_frames": share,
        "body_scale": s.scale,
        "pose": s.pose,
        "fps": check_fps(cfg.get("fps"), "fps"),
        "classifier_fps": meta.get("fps"),
        "resampled": rates is not None,
        "antialiased": antialias and rates is not None and rates[1] < rates[0],
        "warning": warning,
    }
    write_text(out / "summary.json", json.dumps(finite_or_none(summary), indent=2) + "\n")
    return summary


def run(cfg: DictConfig) -> dict:
    """mode=train: fine-tune and report (returns output_dir, checkpoint, report, metrics);
    mode=predict: label a track (returns the written files)."""
    set_torch_threads(cfg.get("threads"))
    st = ClassifySettings.from_config(cfg)
    if st.mode not in ("train", "predict"):
        raise ValueError(f"mode must be 'train' or 'predict', got '{st.mode}'")
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    out = output_dir(cfg)
    write_text(out / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))
    return (train_classifier if st.mode == "train" else predict_track)(cfg, st, out)
