"""`deformnet-classify` mode=train: fit a behavior classifier on labelled sessions and report
on its evaluation sessions (`train_classifier`).

Sessions are split into train / val / test by session (`data.*_tracks`, `data.*_labels`; or
``tracks=[...] labels=[...]``, the training sessions). A frozen encoder's features are computed
once and the head fitted on them (a forest by scikit-learn, taught by `pseudo_labels.teacher`;
another head by full-batch L-BFGS); with ``freeze=false`` the encoder is then fine-tuned with
the head (Lightning, `deformnet.behavior.lit.ClassifyLit`). Writes classifier.pt, report.json,
confusion.png, ethogram.png into the output folder.
"""

from __future__ import annotations

import logging
from dataclasses import asdict
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import numpy as np
import torch
from omegaconf import DictConfig

from deformnet.atomic import atomic_path
from deformnet.behavior.features import (
    BODY_SCALE_MODES,
    Frames,
    SessionBank,
    context_features,
    feature_range,
    set_body_scales,
)
from deformnet.behavior.fit import fit_head_forest, fit_head_lbfgs, teach_forest
from deformnet.behavior.labels import read_labels, subsample_labels
from deformnet.behavior.lit import ClassifyLit
from deformnet.behavior.model import classifier_from_config, export_classifier, predict_session
from deformnet.behavior.rates import resample_session, same_fps
from deformnet.behavior.report import macro_f1, write_report
from deformnet.behavior.settings import ClassifySettings
from deformnet.behavior.tracks import Session, read_tracks
from deformnet.body import BodyModel
from deformnet.confutil import check_fps, to_plain
from deformnet.deformation import DeformationModel, check_track_up, frame_up
from deformnet.train import net_config

log = logging.getLogger(__name__)

__all__ = ["train_classifier"]


def _sessions(cfg: DictConfig, st: ClassifySettings, split: str, body, classes) -> list[Session]:
    """The sessions of a split (train, val, test; or unlabelled: data.unlabelled_tracks, no
    labels files, every frame's label -1) as the config reads them (`data.*_tracks` and
    `data.*_labels`; `classes`: the label names)."""
    d = cfg.data
    tracks = [str(p) for p in (d.get(f"{split}_tracks") or [])]
    labels = [str(p) for p in (d.get(f"{split}_labels") or [])]
    if split == "unlabelled":
        labels = [None] * len(tracks)
    if split == "train" and cfg.get("tracks") and not tracks:  # tracks=[...] labels=[...]
        tracks, labels = _path_list(cfg.get("tracks")), _path_list(cfg.get("labels"))
        if len(tracks) != len(labels):
            raise ValueError(f"tracks= has {len(tracks)} files but labels= {len(labels)} (one "
                             "labels file per session)")  # fmt: skip
    if len(tracks) != len(labels):
        raise ValueError(
            f"data.{split}_tracks has {len(tracks)} files but data.{split}_labels {len(labels)}"
        )
    rates = to_plain(d.get(f"{split}_fps"))
    fps = check_fps(cfg.get("fps"), "fps")
    if rates is not None:
        if not isinstance(rates, list) or len(rates) != len(tracks):
            raise ValueError(
                f"data.{split}_fps must list one frame rate per session of data.{split}_tracks "
                f"({len(tracks)}), got {rates!r}"
            )
        if fps is None:
            raise ValueError(
                f"data.{split}_fps gives each session's frame rate: set fps= too, the rate the "
                "classifier reads them at"
            )
        rates = [check_fps(r, f"data.{split}_fps[{i}]") for i, r in enumerate(rates)]
    out = []
    for i, (tp, lp) in enumerate(zip(tracks, labels)):
        tr = read_tracks(tp, body, interpolate=bool(st.data.interpolate))
        if lp is None:
            lab = np.full(len(tr["fnum"]), -1, dtype=np.int64)
        else:
            rate = fps if rates is None else rates[i]  # BORIS events in seconds
            lab = read_labels(lp, tr["fnum"], classes, tracks=tp, fps=rate)
        parts = (tr["rigid"], tr["deformed"], tr["observed"], tr["fnum"])
        s = Session(tp, *parts, lab, pose=tr["pose"])
        if rates is not None and not same_fps(rates[i], fps):
            log.info("%s: %g Hz, read resampled to %g Hz (fps)", tp, rates[i], fps)
            s = resample_session(s, rates[i], fps, st.antialias)
        out.append(s)
    return out


def _path_list(value) -> list[str]:
    """A path or a list of paths (``tracks=a.csv``, ``tracks=[a.csv,b.csv]``) as a list."""
    value = to_plain(value)
    if value is None:
        return []
    return [str(p) for p in value] if isinstance(value, list) else [str(value)]


def _loader(bank, idx: np.ndarray, batch_size: int, samples: int | None, seed: int):
    ds = Frames(bank, idx)
    sampler = None
    if samples:
        gen = torch.Generator().manual_seed(int(seed))
        sampler = torch.utils.data.RandomSampler(
            ds, replacement=True, num_samples=int(samples), generator=gen
        )
    return torch.utils.data.DataLoader(
        ds, batch_size=int(batch_size), sampler=sampler, shuffle=False, collate_fn=ds.collate
    )


def _encoder_config(cfg: DictConfig, classes):
    """(net config, body, half_window, pretrained-net state or None, world up or None: the
    canonical frame the encoder reads, `deformnet.tokens.canonicalize`)."""
    if cfg.get("pretrained"):
        dm = DeformationModel.from_checkpoint(str(cfg.pretrained))
        log.info(
            "encoder: %s from %s", dm.net_config.get("_target_"), cfg.pretrained
        )  # fmt: skip
        up = frame_up(to_plain(cfg.get("up")), dm, str(cfg.pretrained))
        return dict(dm.net_config), dm.body, dm.half_window, dm.net.state_dict(), up

    body = BodyModel.from_config(cfg.body)
    _, ncfg = net_config(cfg, body.num_parts)
    return ncfg, body, int(cfg.half_window), None, frame_up(to_plain(cfg.get("up")))


def train_classifier(cfg: DictConfig, st: ClassifySettings, out: Path) -> dict:
    """mode=train: returns output_dir, checkpoint, report (`write_report`), metrics."""
    classes = [str(c) for c in cfg.classes]
    C = len(classes)
    net_cfg, body, hw, state, up = _encoder_config(cfg, classes)
    body = body.with_aliases(to_plain(cfg.get("aliases")))  # kept in classifier.pt
    head_cfg = dict(to_plain(cfg.head))
    forest = head_cfg.get("name") == "forest"
    if forest and not bool(cfg.freeze):  # before any data is read
        raise ValueError(
            "head=forest is fitted by scikit-learn on a frozen encoder's features: set freeze=true"
        )
    pseudo = st.pseudo_labels  # settings checked (ClassifySettings) before any data is read
    if pseudo.teacher != "none" and not forest:
        raise ValueError(f"pseudo_labels.teacher={pseudo.teacher} self-trains the forest head: "
                         "set head=forest freeze=true (or pseudo_labels.teacher=none)")  # fmt: skip
    scale_mode = str(st.body_scale)
    if scale_mode not in BODY_SCALE_MODES:
        raise ValueError(f"body_scale must be one of {BODY_SCALE_MODES}, got '{scale_mode}'")
    fps = check_fps(cfg.get("fps"), "fps")  # the training sessions' rate (None: unknown)
    model, mech = classifier_from_config(st, head_cfg, net_cfg, body, hw, C, up)
    ff, meas = model.encoder.frame_features, model.encoder.measurements
    if mech is not None:
        log.info("lock-box context: %s from %s (parts %s)", mech["names"], mech["source"],
                 mech["parts"])  # fmt: skip
    if state is not None:
        model.encoder.net.load_state_dict(state)
    span = model.half_window  # the encoder's half window plus the context's

    train, val, test = (_sessions(cfg, st, k, body, classes) for k in ("train", "val", "test"))
    # more recordings without labels: the teachers label their frames too (the forest learns
    # from them), and the cotrain teacher's sequence pretraining reads them
    unlabelled = _sessions(cfg, st, "unlabelled", body, classes)
    if unlabelled and pseudo.teacher == "none":
        log.warning("data.unlabelled_tracks: %d sessions not used (only "
                    "pseudo_labels.teacher=linear|cotrain learns from them)",
                    len(unlabelled))  # fmt: skip
        unlabelled = []
    elif (
        unlabelled
        and not pseudo.unlabelled
        and (pseudo.teacher == "linear" or pseudo.sequence.encoder)
    ):
        log.warning("data.unlabelled_tracks: %d sessions not used (pseudo_labels.unlabelled="
                    "false, and no sequence pretraining reads them)", len(unlabelled))  # fmt: skip
        unlabelled = []
    hup = model.encoder.heights_up if meas else None
    for s in (*train, *val, *test, *unlabelled):  # a heading-frame encoder or the heights: the
        check_track_up(s.rigid, body.points, model.encoder.heights_up, s.name)  # tracks' up
    set_body_scales((*train, *val, *test, *unlabelled), scale_mode, body)
    if not train:
        raise ValueError("no training sessions: set data.train_tracks / data.train_labels")
    frac, seg = float(cfg.label_fraction), int(st.label_segment)
    subsample_labels(train, frac, seg, int(cfg.label_seed))
    subsample_labels(val, frac, seg, int(cfg.label_seed) + 1)
    bank = SessionBank(train, span)
    idx = np.flatnonzero(bank.labels.numpy() >= 0)
    if idx.size == 0:
        raise ValueError("the training sessions have no labelled frames")
    counts = np.bincount(bank.labels.numpy()[idx], minlength=C)
    weights = None
    if str(cfg.loss.class_weights) == "balanced":
        weights = np.where(counts > 0, counts.sum() / np.maximum(C * counts, 1), 0.0)
    elif str(cfg.loss.class_weights) != "none":
        raise ValueError(f"loss.class_weights must be 'balanced' or 'none', got {cfg.loss}")
    log.info("labelled training frames: %d (%s)", idx.size, dict(zip(classes, counts.tolist())))
    # the head's inputs standardised by the labelled training frames' features (at the start)
    train_features = context_features(model, bank, idx)
    if idx.size >= 2:
        model.set_standardization(train_features)

    d = st.data
    bs = int(cfg.data.batch_size)
    train_dl = _loader(bank, idx, bs, int(cfg.data.steps_per_epoch) * bs, int(cfg.seed))
    val_dl = None
    if val:
        vbank = SessionBank(val, span)
        vidx = np.flatnonzero(vbank.labels.numpy() >= 0)
        if d.val_frames and vidx.size > int(d.val_frames):
            vidx = vidx[np.linspace(0, vidx.size - 1, int(d.val_frames)).round().astype(int)]
        if vidx.size:
            val_dl = _loader(vbank, vidx, 512, None, 0)

    lit = ClassifyLit(
        model,
        classes,
        class_weights=None if weights is None else weights.tolist(),
        freeze=bool(cfg.freeze),
        lr=float(cfg.optim.lr),
        encoder_lr=float(cfg.optim.encoder_lr),
        weight_decay=float(cfg.optim.weight_decay),
        token_dropout=float(d.token_dropout),
    )
    logger: Any = False
    lcfg = to_plain(cfg.get("logger")) or {}
    if lcfg.get("_target_"):
        logger = hydra.utils.instantiate(lcfg)

    def fit(train_loader, val_loader, **changes) -> Any:
        tcfg = {**dict(to_plain(cfg.trainer)), **changes}
        if val_loader is None:
            tcfg["limit_val_batches"] = 0
            tcfg["num_sanity_val_steps"] = 0
        trainer = L.Trainer(
            **tcfg,
            logger=logger,
            enable_progress_bar=str(st.progress_bar) != "none",
            enable_checkpointing=False,
            default_root_dir=str(out),
        )
        trainer.fit(lit, train_dataloaders=train_loader, val_dataloaders=val_loader)
        return trainer

    # A frozen encoder's features are computed once (no token dropout) and the head is fitted
    # on them: a forest by scikit-learn, another head by full-batch L-BFGS to convergence (the
    # linear-probe protocol); a pretrained encoder that is fine-tuned gets such a probe first,
    # then trains with the encoder.
    solver = "forest" if forest else "lbfgs"
    probe = state is not None
    steps = 0
    trainer = None
    probe_facts: dict = {}
    all_features = None  # every training frame's features (the forest's self-training)
    if bool(cfg.freeze) or probe:
        labels = bank.labels[torch.as_tensor(idx)]  # the labelled frames' (features: above)
        lit.head_only = True
        if forest:
            probe_facts = fit_head_forest(model, train_features, labels, weights)
            if pseudo.teacher != "none":
                probe_facts["pseudo_labels"], all_features = teach_forest(
                    model, bank, [len(s) for s in train], idx, train_features, unlabelled,
                    pseudo, weights, mech, scale_mode, out,
                )  # fmt: skip
                pl = probe_facts["pseudo_labels"]
                log.info("self-training: %d pseudo-labelled frames (%s)", pl["frames"],
                         dict(zip(classes, pl["per_class"])))  # fmt: skip
        else:
            probe_facts = fit_head_lbfgs(
                model,
                train_features,
                labels,
                weights,
                float(st.head_l2),
                int(st.head_max_iter),
            )
        if val_dl is not None:  # the probe's validation score: the state to beat
            with torch.no_grad():
                pv = model.classify(context_features(model, vbank, vidx)).argmax(-1).numpy()
            score, per = macro_f1(vbank.labels.numpy()[vidx], pv, C)
            probe_facts["val_macro_f1"] = score
            lit.best_score = score
            lit.best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
            if logger:
                logger.log_metrics(
                    {"val/macro_f1": score}
                    | ({"train/loss": probe_facts["loss"]} if "loss" in probe_facts else {})
                    | {f"val/f1/{c}": float(f) for c, f in zip(classes, per) if np.isfinite(f)},
                    step=0,
                )
        log.info("head fitted by %s (%s)", "scikit-learn" if forest else "L-BFGS", probe_facts)
        if not bool(cfg.freeze):
            lit.head_only = False
            trainer = fit(train_dl, val_dl)
    else:
        trainer = fit(train_dl, val_dl)
    steps += int(trainer.global_step) if trainer is not None else 0
    if lit.best_state is not None:
        model.load_state_dict(lit.best_state)
    model.eval()
    # what the training data look like to the trained classifier: each feature's range over
    # every training frame (labelled or not), for telling a recording unlike them (predict)
    if all_features is None:
        all_features = context_features(model, bank, torch.arange(len(bank)))
    rng = feature_range(all_features)

    smoothing = asdict(st.smoothing)
    meta = {
        "net_config": net_cfg,
        "body": body.to_mapping(),
        "half_window": hw,
        "up": None if up is None else list(up),
        "head": head_cfg,
        "frame_features": ff,
        "context": {
            "frames": list(model.context_frames),
            "stride": model.stride,
        },  # fmt: skip
        "mechanisms": mech,
        "measurements": meas,
        "heights_up": None if hup is None else list(hup),
        "classes": classes,
        "smoothing": smoothing,
        "pretrained": str(cfg.pretrained) if cfg.get("pretrained") else None,
        "freeze": bool(cfg.freeze),
        "label_fraction": frac,
        "feature_range": rng,
        "body_scale": scale_mode,
        "fps": fps,
        "pseudo_labels": pseudo.facts(),  # how the forest head was taught (None: labelled only)
    }
    ckpt = out / "classifier.pt"
    with atomic_path(ckpt) as tmp:
        torch.save(export_classifier(model, meta), tmp)
    # the report on the test sessions (else validation, else training)
    split, sessions = ("test", test) if test else (("val", val) if val else ("train", train))
    preds = [predict_session(model, s, st.smoothing, rng) for s in sessions]
    unfamiliar = np.concatenate([p["unfamiliar"] > st.unfamiliar.frame_share for p in preds])
    facts = {
        "smoothing": smoothing,
        "labelled_training_frames": int(idx.size),
        "body_scales": None if scale_mode == "none"
        else {s.name: round(float(s.scale), 4) for s in (*train, *val, *test)},
        "unfamiliar_frames": float(unfamiliar.mean()),
        "training_steps": steps,
        "head_solver": solver,
        "mechanisms": None if mech is None else {k: mech[k] for k in ("names", "parts", "source")},
        "probe": probe_facts or None,
        "best_val_macro_f1": lit.best_score if lit.best_state is not None else None,
        "checkpoint": str(ckpt),
    }  # fmt: skip
    report = write_report(out, split, sessions, preds, classes, fps, facts, logger, steps)
    log.info("classifier %s", ckpt)
    metrics = {} if trainer is None else trainer.callback_metrics
    return {
        "output_dir": str(out),
        "checkpoint": str(ckpt),
        "report": report,
        "metrics": {k: float(v) for k, v in metrics.items() if v.numel() == 1},
    }
