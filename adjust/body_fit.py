"""The body model of an `adjust-track` session: its shape (named, or estimated from the data),
its size, its parts' deformation moments and its structure step (`refine_body`).

Each step is a plain function of the session's detections (`adjust.io.Detections`), cameras
(`adjust.camera.CameraTensors`), 3D observations (`adjust.estimate.Consensus`), the ``body``
config group (``conf/body/``: which model, `adjust.track_config.BodyConfig`) and the estimate's
settings (``body_fit:``, `adjust.track_config.BodyFitConfig`); `fit_body` is the order
`adjust.pipeline` runs them in.
"""

from __future__ import annotations

import logging
import math
import warnings

import numpy as np
import torch

from adjust.camera import CameraTensors
from adjust.estimate import deformation_moments, place_from_rays
from adjust.io import Detections, InputError
from adjust.lsq.geometry import rigid_points
from adjust.lsq.init import kabsch_poses
from adjust.lsq.observation import RigidObservation
from adjust.track_config import BodyConfig, BodyFitConfig
from adjust.triangulate import triangulate
from deformnet.body import BodyModel
from deformnet.deformation import check_world_up as check_model_up
from deformnet.so3 import rodrigues_to_matrix

log = logging.getLogger(__name__)

__all__ = [
    "MIN_SHAPE_FRAMES",
    "SHAPE_FRAMES",
    "check_world_up",
    "estimate_body",
    "fit_body",
    "refine_body",
    "rigid_observation",
    "scale_body",
    "scale_factor",
    "shape_frames",
    "triangulate_points",
]


def triangulate_points(det: Detections, cams: CameraTensors, robust: bool, max_error_px: float):
    with torch.no_grad():
        return triangulate(
            torch.as_tensor(det.xy),
            torch.as_tensor(det.weight()),
            cams,
            robust=robust,
            max_error_px=max_error_px,
        )


def scale_factor(body: BodyModel, fit: BodyFitConfig) -> tuple[BodyModel, dict]:
    """``body_fit.scale_factor``: the model's size times this (> 0; 1 keeps it)."""
    f = fit.scale_factor
    try:
        f = float(f)
    except (TypeError, ValueError):
        f = float("nan")
    if not (math.isfinite(f) and f > 0):
        raise InputError(f"body_fit.scale_factor must be a number > 0, got {fit.scale_factor!r}")
    return (body, {}) if f == 1.0 else (body.scaled(f), {"scale_factor": f})


#: a body's shape is estimated from at most this many frames, evenly spaced (a rigid shape is
#: settled long before; time and memory stay bounded on long sessions)
SHAPE_FRAMES = 20_000
#: ... and from no fewer than this many frames with >= 3 parts in 3D (a shape from a handful of
#: frames is not trusted: body.shape=data then falls back to the named model, scaled)
MIN_SHAPE_FRAMES = 30


def shape_frames(num_frames: int) -> np.ndarray:
    """The frames a body's shape is estimated from: all, or `SHAPE_FRAMES` evenly spaced."""
    if num_frames <= SHAPE_FRAMES:
        return np.arange(num_frames)
    return np.unique(np.linspace(0, num_frames - 1, SHAPE_FRAMES).astype(np.int64))


def estimate_body(
    det: Detections,
    cams: CameraTensors,
    fit: BodyFitConfig,
    name: str = "auto",
    cons=None,
    min_frames: int = 0,
    max_error_px: float = 20.0,
) -> tuple[BodyModel, dict]:
    """``body=auto``: robust triangulation, then a rigid model by generalized Procrustes
    (`BodyModel.from_observations`). Returns the model and facts about the estimate, among them
    ``rms_deviation_mm`` (per-coordinate rms distance of the triangulated parts from the model
    fitted per frame: how far the data is from rigid). With the session's 3D observations
    (`cons`), at most `SHAPE_FRAMES` frames, evenly spaced (`shape_frames`), are used; without,
    a robust triangulation (``body_fit.robust``, `max_error_px`); frames with at least
    ``body_fit.min_parts`` parts."""
    if cons is not None:  # the session's gated 3D observations
        X = cons.points[shape_frames(len(cons.points))]
    else:
        tri = triangulate_points(det, cams, bool(fit.robust), float(max_error_px))
        X = tri.points.numpy()
    min_parts = fit.min_parts
    try:
        body = BodyModel.from_observations(
            X, parts=det.parts, min_parts=None if min_parts is None else int(min_parts), name=name
        )
    except ValueError as exc:
        raise InputError(f"body from the data: {exc}") from None
    # the data's spread around the model (trimmed: the worst 5% are mostly mis-detections)
    seen = np.isfinite(X).all(-1)
    Xt = torch.as_tensor(np.nan_to_num(X))
    B = torch.tensor(body.points)
    poses, ok = kabsch_poses(B, Xt, torch.as_tensor(seen), min_parts=max(3, body.num_parts // 2))
    Xm, _ = rigid_points(poses, B)
    fit = ok.numpy()[:, None] & seen
    dist = np.where(fit, np.linalg.norm(Xm.numpy() - np.nan_to_num(X), axis=-1), np.nan)
    with warnings.catch_warnings():  # a part never fitted: NaN, said as such
        warnings.simplefilter("ignore", RuntimeWarning)
        # each model point's standard error: its spread about the frames' fits / sqrt(frames)
        n = fit.sum(0)
        se = np.sqrt(np.nanmean(dist**2, 0) / np.maximum(n, 1))
    d = dist[fit]
    d = np.sort(d[np.isfinite(d)])
    d = d[: max(1, int(math.ceil(0.95 * d.size)))] if d.size else d
    rms = float(np.sqrt(np.mean(d**2) / 3.0)) if d.size else float("nan")
    facts = {
        "frames_used": int((seen.sum(1) >= 3).sum()),
        "triangulated_fraction": float(seen.mean()) if seen.size else 0.0,
        "rms_deviation_mm": rms,
        "points": {p: [float(c) for c in xyz] for p, xyz in zip(body.parts, body.points)},
        "points_se_mm": {p: float(v) for p, v in zip(body.parts, se)},
        "frames_per_part": {p: int(v) for p, v in zip(body.parts, n)},
    }
    if facts["frames_used"] < max(min_frames, MIN_SHAPE_FRAMES):
        msg = (
            f"body shape from the data: only {facts['frames_used']} frames have >= 3 parts "
            f"seen by two cameras (at least {MIN_SHAPE_FRAMES} wanted)"
        )
        if facts["frames_used"] < min_frames:
            raise InputError(msg)
        log.warning("%s; its points are rough (summary.json body.points_se_mm)", msg)
    log.info(
        "body from the data: a rigid model of %d parts from %d frames; the data deviate %.2f mm "
        "rms per coordinate from it",
        body.num_parts,
        facts["frames_used"],
        rms,
    )
    return body, facts


def check_world_up(model, poses: np.ndarray, where: str) -> float | None:
    """`deformnet.deformation.check_world_up` for the rigid poses (T, 6) (Rodrigues +
    translation, model -> world) of a session tracked with `model`; an InputError naming
    `where` when the session's world is not the up of the model's heading frame."""
    up = getattr(model, "up", None)
    if up is None:
        return None
    R = rodrigues_to_matrix(torch.as_tensor(np.asarray(poses, dtype=float)[:, :3])).numpy()
    try:
        return check_model_up(R, up, where)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def scale_body(body: BodyModel, spec: BodyConfig, cons) -> tuple[BodyModel, dict]:
    """``body.scale``: ``auto`` (default) fits the model's size to the session's triangulated
    parts (`BodyModel.estimate_scale`), a number scales by it (1 keeps the model as is)."""
    want = spec.scale
    if want is None or (isinstance(want, str) and want.lower() == "auto"):
        if cons is None:
            return body, {"scale": 1.0, "scale_source": "none (consensus.estimate=false)"}
        s, n = body.estimate_scale(cons.points)
        if not math.isfinite(s) or n < 5:
            log.warning(
                "body.scale=auto: only %d frames with >= 4 triangulated parts; keeping body "
                "'%s' at its configured size",
                n,
                body.name,
            )
            return body, {"scale": 1.0, "scale_source": f"config (too few frames: {n})"}
        log.info("body '%s' scaled by %.3f to the data (%d frames)", body.name, s, n)
        return body.scaled(s), {"scale": s, "scale_source": "estimated", "scale_frames": n}
    try:
        s = float(want)
    except (TypeError, ValueError):
        raise ValueError(f"body.scale must be 'auto' or a number > 0, got {want!r}") from None
    return body.scaled(s), {"scale": s, "scale_source": "config"}


def rigid_observation(body: BodyModel, cons) -> tuple:
    """The rigid observation with each part's deformation second moment estimated from the
    session (Kabsch poses on its 3D observations, `adjust.estimate.deformation_moments`)."""
    B = torch.tensor(np.array(body.points))
    seen = torch.as_tensor(cons.observed)  # gated by the cameras' consensus already
    poses, ok = kabsch_poses(B, torch.as_tensor(np.nan_to_num(cons.points)), seen)
    okn = ok.numpy()
    mom, mean = deformation_moments(
        poses.numpy(), cons.points, cons.observed & okn[:, None], np.array(body.points)
    )
    sig = np.sqrt(mom.sum(-1))
    log.info(
        "rigid model: parts stray %s mm rms from it",
        ", ".join(f"{p} {v:.1f}" for p, v in zip(body.parts, sig)),
    )
    facts = {
        "rigid_rms_mm_per_part": {p: float(v) for p, v in zip(body.parts, sig)},
        "rigid_rms_mm": float(np.sqrt(np.mean(sig**2))),
    }
    return RigidObservation(B, torch.as_tensor(mom)), facts


def unplaced_parts(fit: BodyFitConfig, cons) -> np.ndarray:
    """(K,) bool: the parts with fewer than ``body_fit.rays_below`` 3D observations, which no
    two cameras see together often enough for the Procrustes model to place them
    (`BodyModel.from_observations` puts them by translation only, or at the body's centre);
    `refine_body` places them from their single-view rays."""
    return np.asarray(cons.observed).sum(0) < int(fit.rays_below or 0)


def refine_body(body: BodyModel, fit: BodyFitConfig, poses, det, weight, cams, cons, rigid_obs):
    """``body=auto``: the rigid model re-estimated from the detections themselves at the rigid
    adjustment's poses (`adjust.estimate.place_from_rays`: each part where its views' rays meet
    in the body frame across all frames, robustly; the structure step of a bundle adjustment).
    The Procrustes model (`BodyModel.from_observations`) averages triangulated points, each
    resting on the views that saw it in its frame and carrying their errors; this one weighs
    every detection, single views included, as the pose adjustment does. ``body_fit.refine``:
    ``views`` (default) re-estimates every part, ``unplaced`` only the parts with fewer than
    ``body_fit.rays_below`` 3D observations (no two cameras see them together, so the Procrustes
    model could not place them), ``none`` keeps the Procrustes model. Those parts' spread about
    their points comes from their views' residuals (their deformation variance); the others
    keep the spread of their 3D observations. On long sessions the rays of `shape_frames`
    (at most `SHAPE_FRAMES`, evenly spaced) place the parts.
    Returns None (nothing done) or (body, rigid observation, few_var (K, 3) torch, NaN for
    parts with enough 3D observations, facts)."""
    mode = fit.refine
    below = int(fit.rays_below or 0)
    few = unplaced_parts(fit, cons)
    which = np.ones_like(few) if mode == "views" else few
    if mode == "none" or few.all() or not which.any():
        return None
    B = np.array(body.points, dtype=np.float64)
    # the prior's spread: the rms radius of the parts the triangulations placed
    prior_sd = float(np.sqrt(np.mean(np.sum((B[~few] - B[~few].mean(0)) ** 2, -1))))
    var0 = rigid_obs.var.numpy()
    sel = shape_frames(len(poses))
    pl = place_from_rays(
        np.asarray(poses)[sel],
        det.xy[sel],
        np.asarray(weight)[sel],
        cams,
        B,
        var0,
        which,
        cons.sigma_det_px,
        max(prior_sd, 1.0),
        min_views=int(fit.rays_min_views),
    )
    if not pl.placed.any():
        return None
    placed_few = pl.placed & few
    var = np.where(placed_few[:, None], pl.var, var0)
    moved = np.linalg.norm(pl.points - B, axis=-1)
    facts = {
        "refine": mode,
        "moved_mm_per_part": {p: float(v) for p, v in zip(body.parts, moved)},
        "rms_px_per_part": {
            p: float(pl.rms_px[k]) for k, p in enumerate(body.parts) if pl.placed[k]
        },
        "from_single_views": {
            p: {"views": int(pl.views[k]), "sd_mm": float(np.sqrt(pl.var[k].sum()))}
            for k, p in enumerate(body.parts)
            if placed_few[k]
        },
    }
    log.info(
        "body from the data: the rigid model re-estimated from the detections (%d parts; moved "
        "by a median of %.1f mm from the Procrustes model)",
        int(pl.placed.sum()),
        float(np.median(moved[pl.placed])),
    )
    if placed_few.any():
        log.warning(
            "body from the data: %s seen by fewer than 2 cameras at a time (< %d 3D observations): "
            "placed from their single-view rays across frames (%s)",
            ", ".join(facts["from_single_views"]),
            below,
            ", ".join(f"{p} {f['sd_mm']:.1f} mm" for p, f in facts["from_single_views"].items()),
        )
    new = BodyModel(body.parts, pl.points, body.aliases, body.name)
    few_var = torch.as_tensor(np.where(placed_few[:, None], pl.var, np.nan))
    return new, RigidObservation(torch.tensor(pl.points), torch.as_tensor(var)), few_var, facts


def fit_body(
    det: Detections,
    cams: CameraTensors,
    body: BodyModel | None,
    spec: BodyConfig,
    fit: BodyFitConfig,
    cons,
    solver_cfg,
    *,
    auto: bool,
    frame_of: BodyModel | None,
    from_checkpoint: bool,
    facts: dict,
    sigma_def_mm: float | None = None,
    max_error_px: float = 20.0,
) -> tuple[BodyModel, object, bool]:
    """The session's body model: its shape estimated from the data (`body=auto` or
    ``body.shape=data``, unless the model comes from a net's checkpoint; a named model too short
    of data falls back to its own shape), moved into the frame of the named model `frame_of`;
    then sized (`scale_body`, `scale_factor`) unless it comes from a net's checkpoint.

    body: the named (or the checkpoint's) model, None for ``body=auto``; spec: the ``body``
    group's settings; fit: ``body_fit``'s (the estimate's); facts: summary.json's
    ``body`` block, added to; sigma_def_mm: ``solver.sigma_def_mm`` (None: the data's rms
    deviation from the rigid model where the shape is estimated); max_error_px:
    ``consensus.max_error_px``. Returns (body, the solver config with the deformation std
    applied, whether the shape was estimated)."""
    estimated = not from_checkpoint and (auto or spec.shape == "data")
    if estimated:
        try:
            est = estimate_body(
                det,
                cams,
                fit,
                str(spec.name),
                cons,
                0 if auto else MIN_SHAPE_FRAMES,
                max_error_px,
            )
        except InputError as exc:
            if auto:
                raise
            log.warning(  # too little data for a shape: the named model's, scaled
                "body.shape=data: %s; body '%s' is used at its configured shape, scaled "
                "(body.shape=table)",
                exc,
                body.name,
            )
            estimated = False
            facts["shape_fallback"] = str(exc)
    if estimated:
        body, est_facts = est
        facts.update(est_facts)
        if frame_of is not None:
            body, facts["frame"] = body.in_frame_of(frame_of)
            aliases = {k: v for k, v in frame_of.aliases.items() if v in body.parts}
            body = BodyModel(body.parts, body.points, aliases, body.name)
        if sigma_def_mm is None and math.isfinite(facts["rms_deviation_mm"]):
            value = max(float(facts["rms_deviation_mm"]), 0.5)
            solver_cfg = solver_cfg.replace(sigma_def_mm=value)
            log.info(
                "body from the data: solver.sigma_def_mm = %.2f mm (the data's rms deviation)",
                value,
            )
    if tuple(body.parts) != tuple(det.parts):  # load_scene orders parts as the model does
        raise InputError(f"parts {list(det.parts)} do not match the body model {list(body.parts)}")
    if not estimated and not from_checkpoint:
        body, scale_facts = scale_body(body, spec, cons)
        facts.update(scale_facts)
    if not from_checkpoint:
        body, factor_facts = scale_factor(body, fit)
        facts.update(factor_facts)
    return body, solver_cfg, estimated
