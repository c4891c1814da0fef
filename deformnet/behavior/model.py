"""A behavior classifier built from a config or a checkpoint, saved and loaded as data
(`export_classifier`, `load_classifier`), and a session labelled by it (`predict_session`);
the lock-box context a config describes (`mechanism_setup`)."""

from __future__ import annotations

import functools
import os
from collections.abc import Mapping

import numpy as np
import torch
from torch import Tensor

from deformnet.behavior.encoder import MechanismFeatures, WindowEncoder
from deformnet.behavior.features import SessionBank, context_features, unfamiliar_share
from deformnet.behavior.heads import BehaviorClassifier, build_head
from deformnet.behavior.labels import smooth
from deformnet.behavior.lockbox import calibration_mechanisms, mechanism_table
from deformnet.behavior.rates import resample_session, to_track_frames
from deformnet.behavior.settings import ClassifySettings, SmoothingSettings
from deformnet.behavior.tracks import Session
from deformnet.body import BodyModel
from deformnet.checkpoint import load_checkpoint
from deformnet.confutil import checked_fields
from deformnet.deformation import build_net
from deformnet.sim import MECHANISMS, SimConfig
from deformnet.sim.scene import build_scene

__all__ = ["CHECKPOINT_KIND", "build_classifier", "export_classifier", "load_classifier",
           "features_probs", "predict_session", "mechanism_setup",
           "classifier_from_config"]  # fmt: skip

CHECKPOINT_KIND = "mousetrack-behavior-classifier"


def build_classifier(
    net_cfg: dict,
    body,
    half_window: int,
    head_cfg: dict,
    frame_features: bool,
    C: int,
    context: dict | None = None,
    up=None,
    mechanisms: dict | None = None,
    measurements: bool = False,
    heights_up=None,
    source: str = "",
):
    """The classifier a config or a checkpoint describes (``source``: the checkpoint file, for
    errors); its net and head are built from allow-lists with plain arguments only
    (`deformnet.deformation.build_net`, `deformnet.behavior.heads.build_head`)."""
    mech = None
    if mechanisms:
        parts = [body.parts.index(p) for p in mechanisms["parts"]]
        mech = MechanismFeatures(
            mechanisms["positions"], parts, mechanisms["names"], float(mechanisms["scale"])
        )
    enc = WindowEncoder(
        build_net(net_cfg, source), np.asarray(body.points), half_window, frame_features, up, mech,
        measurements, heights_up,
    )  # fmt: skip
    ctx = dict(context or {})
    frames = [int(f) for f in (ctx.get("frames") or [])]
    dim = BehaviorClassifier.feature_dim(enc.out_dim, frames)
    return BehaviorClassifier(
        enc, build_head(head_cfg, dim, C, source), frames, int(ctx.get("stride", 1) or 1)
    )


def export_classifier(model, meta: dict) -> dict:
    return {
        "kind": CHECKPOINT_KIND,
        **meta,
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
    }


def load_classifier(path: str | os.PathLike):
    """(model in eval mode, metadata) from a `classifier.pt` written by training. Read as data
    (`deformnet.checkpoint.load_checkpoint`, weights only); its net and head are built from
    the allow-lists of this project's classes with plain arguments (`build_classifier`);
    anything else is a ValueError naming the file."""
    blob = load_checkpoint(path, "classifier checkpoint")
    if not isinstance(blob, dict) or blob.get("kind") != CHECKPOINT_KIND:
        raise ValueError(f"{path} is not a behavior classifier (write it with deformnet-classify)")
    try:
        b = blob["body"]
        body = BodyModel.from_mapping(b["parts"], b.get("aliases"), b.get("name", "body"))
        model = build_classifier(
            blob["net_config"],
            body,
            int(blob["half_window"]),
            blob["head"],
            bool(blob["frame_features"]),
            len(blob["classes"]),
            blob.get("context"),
            blob.get("up"),
            blob.get("mechanisms"),
            bool(blob.get("measurements", False)),
            blob.get("heights_up"),
            os.fspath(path),
        )
        model.load_state_dict(blob["state_dict"])
    except (KeyError, TypeError, AttributeError, RuntimeError, IndexError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(
            f"{path}: the classifier checkpoint does not fit this version of deformnet-classify "
            f"(written by an older or newer one?): {first[:200]}"
        ) from None
    return model.eval(), {**{k: v for k, v in blob.items() if k != "state_dict"}, "body": body}


@torch.no_grad()
def features_probs(model, bank: SessionBank, batch_size: int = 512) -> tuple[Tensor, np.ndarray]:
    """Every bank frame's classifier features (N, D) and class probabilities (N, C)."""
    feats = context_features(model, bank, torch.arange(len(bank)), batch_size)
    return feats, torch.softmax(model.classify(feats), -1).numpy()


def predict_session(
    model,
    session: Session,
    smoothing: SmoothingSettings | Mapping | None,
    rng: Mapping | None = None,
    rates: tuple[float, float] | None = None,
    antialias: bool = True,
) -> dict:
    """{"probs" (T, C), "raw" (T,), "labels" (T,) smoothed (= raw without smoothing),
    "unfamiliar" (T,) each frame's `unfamiliar_share` given the training range `rng`, else
    None}. rates: (the session's frame rate, the classifier's) in Hz, when they differ: the
    session is labelled resampled to the classifier's rate (`resample_session`: its windows,
    speeds and smoothing in the time the classifier learnt them), the results taken back to
    the session's own frames (`to_track_frames`: probabilities interpolated, the smoothed
    labels and unfamiliar shares of the nearest resampled frame); to a lower rate low-passed
    first unless `antialias` is false."""
    if not isinstance(smoothing, SmoothingSettings):  # a mapping (classifier.pt's)
        smoothing = SmoothingSettings(**checked_fields(SmoothingSettings, smoothing, "smoothing"))
    if rates is not None:
        fps, rate = rates
        low = resample_session(session, fps, rate, antialias)
        res = predict_session(model, low, smoothing, rng)
        back = functools.partial(to_track_frames, fnum=session.fnum, fps=fps, rate=rate)
        probs = back(res["probs"], kind="linear")
        return {
            "probs": probs,
            "raw": probs.argmax(-1),
            "labels": back(res["labels"]),
            "unfamiliar": None if res["unfamiliar"] is None else back(res["unfamiliar"]),
        }
    feats, probs = features_probs(model, SessionBank([session], model.half_window))
    raw = probs.argmax(-1)
    lab = smooth(probs, smoothing.median, smoothing.min_bout)
    unfamiliar = None if rng is None else unfamiliar_share(feats, rng)
    return {"probs": probs, "raw": raw, "labels": lab, "unfamiliar": unfamiliar}


def mechanism_setup(settings: ClassifySettings, body) -> dict | None:
    """The lock-box context (`deformnet.behavior.encoder.MechanismFeatures`) from the
    ``mechanisms`` block: {"names", "positions" (M x [x, y, z] mm), "parts" (the body model's
    names), "scale", "source"}, or None when neither ``mechanisms.positions`` ({name: [x, y,
    z]}, or ``sim``: the simulator's lock box) nor ``mechanisms.calibration`` (a
    calibration.toml with a [metadata.mechanisms] table, as `adjust-simulate` writes and
    `adjust-events` reads) is set. Errors name the file, mechanism or part."""
    m = settings.mechanisms
    pos, calib = m.positions, m.calibration
    if pos is None and not calib:
        return None
    if pos is not None and calib:
        raise ValueError("set mechanisms.positions or mechanisms.calibration, not both")
    if calib:
        try:
            pos = calibration_mechanisms(str(calib))
        except ValueError as exc:
            raise ValueError(f"mechanisms.calibration: {exc}") from None
        source = f"{calib} [metadata.mechanisms]"
    elif pos == "sim":
        scene = build_scene(SimConfig.from_config(settings.sim), body)
        pos = dict(zip(MECHANISMS, scene.mech_pos.tolist()))
        source = "the simulator's lock box (sim.lockbox)"
    else:
        source = "mechanisms.positions"
    table = mechanism_table(pos, source)
    names, xyz = list(table), list(table.values())
    parts = []
    for q in list(m.parts or []):
        r = body.resolve(str(q))
        if r is None:
            raise ValueError(
                f"mechanisms.parts: unknown body part '{q}' (the body model's: {list(body.parts)})"
            )
        parts.append(r)
    if not parts:
        raise ValueError("mechanisms.parts: name at least one body part (e.g. nose_tip)")
    scale = float(m.scale)
    if not scale > 0:
        raise ValueError(f"mechanisms.scale must be > 0 mm, got {scale}")
    return {"names": names, "positions": xyz, "parts": parts, "scale": scale, "source": source}


def classifier_from_config(
    settings: ClassifySettings, head_cfg: dict, net_cfg: dict, body, half_window: int, C: int, up
):
    """The classifier the config describes (its head, and from its `settings` the frame
    features, lock-box context, measurements and temporal context) on an encoder config
    (`_encoder_config`'s), untrained; (model, its `mechanism_setup` or None). A forest head
    reads the frame features: it needs some (ValueError)."""
    ff, meas = bool(settings.frame_features), bool(settings.measurements)
    mech = mechanism_setup(settings, body)
    if settings.heights_up is not None and not meas:
        raise ValueError("heights_up is the up of the measurements' part heights: set "
                         "measurements=true too (or leave heights_up unset)")  # fmt: skip
    if head_cfg.get("name") == "forest" and not (ff or mech or meas):
        raise ValueError("head=forest reads the frame features: set frame_features=true, "
                         "measurements=true or lock-box context (mechanisms.*)")  # fmt: skip
    context = {"frames": settings.context.frames, "stride": settings.context.stride}
    model = build_classifier(
        net_cfg, body, half_window, head_cfg, ff, C, context, up, mech, meas, settings.heights_up
    )
    return model, mech
