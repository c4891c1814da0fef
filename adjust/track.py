"""`adjust-track`: complete 3D tracks from a calibration and a folder of DeepLabCut files.

    adjust-track input.calibration=calibration.toml input.detections=trial_000 output.dir=out \
        [body=mouse|auto] [deformation=runs/train/.../checkpoints/best.ckpt] \
        [solver.constraint=spline|grid] [input.likelihood_threshold=0.6]

Pipeline: load the anipose calibration and one DeepLabCut file per camera (`adjust.io`), get
the rigid body model (a config from ``conf/body/``, or with ``body=auto`` estimated from the
data: robust triangulation, then `BodyModel.from_observations`), then the pose-track
adjustment (`adjust.lsq.adjust_poses`: initialisation, banded Levenberg-Marquardt with the
motion-track constraint; rigid observation, or the learned deformation with ``deformation=``),
then each part's position fused from its own detections and the (deformed) model.

Writes into ``output.dir``:

- ``points3d.csv``: anipose's layout. Per part ``{part}_x,_y,_z`` (mm; never empty: a part no
  camera saw comes from the model moved along the track), ``{part}_error`` (mean reprojection
  error, px, of the reported point over the cameras with an accepted detection of it; NaN when
  none), ``{part}_ncams`` (cameras with an accepted detection, likelihood >= threshold; 0
  allowed), ``{part}_score`` (lowest likelihood among those detections; NaN when ``_ncams`` is
  0); then ``pose_rx, pose_ry, pose_rz`` (Rodrigues vector, rad) and ``pose_tx, pose_ty,
  pose_tz`` (mm) of the body model (model -> global), ``pose_sigma_r`` (rad) and
  ``pose_sigma_t`` (mm) (root of the trace of the rotation / translation block of the pose
  covariance), ``{part}_sigma`` (mm, root of the trace of the part's 3x3 covariance: its 3D
  standard error), and ``fnum``.
- ``summary.json``: settings, iterations, costs, convergence, reprojection error statistics
  (all, per camera, per part), completeness, uncertainty, timings.

`run(cfg) -> dict` is the plain function behind the Hydra app (tests call it through Hydra's
compose API); it returns the summary.
"""

from __future__ import annotations

import logging
import math
import time
import warnings
from dataclasses import asdict
from pathlib import Path

import hydra
import numpy as np
import torch
from omegaconf import DictConfig

from adjust.adapt import adapt_net
from adjust.app import OutputSet, load_kwargs, required, run_or_exit
from adjust.camera import CameraTensors
from adjust.export import session_start, write_nwb
from adjust.io import (
    Detections,
    InputError,
    UnknownPartsError,
    check_cameras_usable,
    load_calibration_metadata,
    load_scene,
    recording_fps,
    write_points3d,
)
from adjust.lsq.observation import NetObservation
from adjust.metrics import reprojection_errors
from adjust.session import expand_session_globs, with_session
from adjust.summary import TrackingFailed, result_summary, track_health
from deformnet.behavior_labels import POSE_COLUMNS
from deformnet.body import BodyModel
from deformnet.confutil import to_plain
from deformnet.paths import CONF_DIR, output_dir

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def _triangulate(det: Detections, cams: CameraTensors, robust: bool, max_error_px: float):
    from adjust.triangulate import triangulate

    with torch.no_grad():
        return triangulate(
            torch.as_tensor(det.xy),
            torch.as_tensor(det.weight()),
            cams,
            robust=robust,
            max_error_px=max_error_px,
        )


# --------------------------------------------------------------------------------------------
# body model
# --------------------------------------------------------------------------------------------
def _is_auto(body_cfg) -> bool:
    return body_cfg is not None and bool(body_cfg.get("auto", False))


BODY_SHAPES = ("data", "table")


def body_shape(body_cfg) -> str:
    """``body.shape`` of a named body model (``conf/body/mouse.yaml``): ``data`` = its shape
    estimated from the session (`estimate_body`, then `BodyModel.in_frame_of` the named model),
    ``table`` = the named model's points, scaled (`scale_body`); a body config without the key
    is ``table``."""
    shape = str(body_cfg.get("shape", "table")).lower()
    if shape not in BODY_SHAPES:
        raise InputError(f"body.shape must be one of {', '.join(BODY_SHAPES)}, got {shape!r}")
    return shape


def scale_factor(body: BodyModel, body_cfg) -> tuple[BodyModel, dict]:
    """``body.scale_factor``: the model's size times this (> 0; 1 keeps it)."""
    f = body_cfg.get("scale_factor", 1.0)
    try:
        f = float(f)
    except (TypeError, ValueError):
        f = float("nan")
    if not (math.isfinite(f) and f > 0):
        raise InputError(
            f"body.scale_factor must be a number > 0, got {body_cfg.get('scale_factor')!r}"
        )
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
    body_cfg,
    name: str = "auto",
    cons=None,
    min_frames: int = 0,
) -> tuple[BodyModel, dict]:
    """``body=auto``: robust triangulation, then a rigid model by generalized Procrustes
    (`BodyModel.from_observations`). Returns the model and facts about the estimate, among them
    ``rms_deviation_mm`` (per-coordinate rms distance of the triangulated parts from the model
    fitted per frame: how far the data is from rigid). With the session's 3D observations
    (`cons`), at most `SHAPE_FRAMES` frames, evenly spaced (`shape_frames`), are used."""
    from adjust.lsq.geometry import rigid_points
    from adjust.lsq.init import kabsch_poses

    if cons is not None:  # the session's gated 3D observations
        X = cons.points[shape_frames(len(cons.points))]
    else:
        tri = _triangulate(
            det, cams, bool(body_cfg.get("robust", True)), float(body_cfg.get("max_error_px", 20.0))
        )
        X = tri.points.numpy()
    min_parts = body_cfg.get("min_parts")
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


# --------------------------------------------------------------------------------------------
# deformation
# --------------------------------------------------------------------------------------------
def load_deformation(path: str):
    """`DeformationModel.from_checkpoint`, with a clear error for a missing/unreadable file."""
    from deformnet.deformation import DeformationModel

    p = Path(path)
    if not p.is_file():
        raise InputError(f"deformation checkpoint not found: {p}")
    try:
        return DeformationModel.from_checkpoint(p)
    except InputError:
        raise
    except (ValueError, KeyError, RuntimeError, OSError, EOFError) as exc:
        raise InputError(f"{p}: cannot load a deformation model: {exc}") from None


def make_deformable_observation(
    model,
    body_points: np.ndarray,
    det: Detections,
    cams,
    cfg_def,
    cons=None,
    few_var=None,
    net_parts=None,
):
    """The solver's deformable observation for this data: the net's ``deformed`` inputs for
    observed tokens are the parts triangulated (robustly) from the detections (the session's
    gated 3D observations `cons` when given), gated by their distance from the rigid model
    (`deform.gate_mm`). few_var: (K, 3) torch, the spread of parts with too few 3D observations
    (`refine_body`; NaN: unknown). net_parts: (K,) bool, the parts that take the net's
    prediction (`heldout_check`; None: all)."""
    cfg_def = cfg_def if cfg_def is not None else {}
    if cons is not None:
        X = torch.as_tensor(cons.points, dtype=torch.float64)
    else:
        tri = _triangulate(det, cams, True, float(cfg_def.get("max_error_px", 20.0)))
        X = tri.points.to(torch.float64)
    observed = torch.isfinite(X).all(-1)
    jac = str(cfg_def.get("jacobian", "frozen"))
    # finite differences need float64 through the net; the frozen Jacobian does not
    net = (model.float() if jac == "frozen" else model.double()).eval()
    for p in net.parameters():
        p.requires_grad_(False)
    noise = None if cons is None else torch.as_tensor(cons.noise_var)
    obs = NetObservation(
        net,
        torch.tensor(np.asarray(body_points), dtype=torch.float64),
        int(model.window),
        torch.nan_to_num(X),
        observed,
        float(cfg_def.get("gate_mm", 30.0)),
        int(cfg_def.get("batch_size", 4096)),
        jac,
        noise_var=noise,
        refresh=int(cfg_def.get("refresh", 2)),
        beyond_window=str(cfg_def.get("beyond_window", "interp")),
        measured="net" if str(cfg_def.get("measured", "cv")) == "net" else "interp",
        threads=cfg_def.get("threads"),
        few_var=few_var,
        step=deform_step(model, cfg_def),
        far_steps=far_steps(model, cfg_def),
        net_parts=None if net_parts is None else torch.as_tensor(net_parts, dtype=torch.bool),
    )
    return obs, {"observed_fraction": float(observed.double().mean()) if observed.numel() else 0.0}


REQUIRE_BETTER = ("auto", "parts", "all", "report", "false")


def heldout_check(model, poses, body, cons, cfg_def, where: str, mode: str = "default"):
    """``deform.require_better``: a net not trained on this recording (``deformation=default``
    or a checkpoint) against interpolation (the rigid model plus interpolated offsets, as
    ``deformation=interp``) on the recording's own held-out parts
    (`deformnet.heldout.heldout_errors` on its tokens from the interp poses (T, 6)).
    ``parts``: the net predicts only the parts it predicts better (a part with too few
    held-out targets follows the verdict over all parts); ``all``: every part if it is better
    over all parts, else none; ``report``: every part, the figures computed and a worse part
    logged; ``false``: every part, unchecked; ``auto`` (default): ``parts`` for the shipped
    net (`mode` ``default``), ``report`` for a checkpoint (the user's own net, used as given:
    a ``deformation=self`` run's checkpoint reproduces its tracks).
    Returns (net_parts (K,) bool numpy or None for all, facts); all False: the tracks are
    interpolated, ``deformation=interp``'s model adjusted to convergence (the solver's
    iterations, not ``deform.max_iterations``; logged loudly)."""
    from adjust.tokens import session_tokens
    from deformnet.heldout import MIN_TARGETS, heldout_errors

    spec = str((cfg_def or {}).get("require_better", "auto")).lower()
    if spec not in REQUIRE_BETTER:
        raise InputError(
            f"deform.require_better must be one of {', '.join(REQUIRE_BETTER)}, got {spec!r}"
        )
    if spec == "auto":
        spec = "parts" if mode == "default" else "report"
    if spec == "false" or cons is None:
        return None, {"require_better": spec, "checked": False}
    tokens = session_tokens(poses, body.points, cons, body.parts, body.name, source=where)
    try:
        h = heldout_errors(model, tokens, step=deform_step(model, cfg_def))
    except ValueError as exc:  # shorter than one window: nothing to judge by
        log.warning("deform.require_better: the net is not checked (%s)", exc)
        return None, {"require_better": spec, "checked": False, "reason": str(exc)}
    overall = bool(h["net_all_mm"] < h["interp_all_mm"])
    net_mm, int_mm = np.array(h["net_mm"]), np.array(h["interp_mm"])
    enough = np.array(h["targets"]) >= MIN_TARGETS
    better = np.where(enough, net_mm < int_mm, overall)
    if spec == "parts":
        keep = better
    elif spec == "all":
        keep = np.full(len(body.parts), overall)
    else:  # report
        keep = np.ones(len(body.parts), bool)
    facts = {
        "require_better": spec,
        "checked": True,
        **{k: h[k] for k in ("windows", "targets", "net_all_mm", "interp_all_mm")},
        "net_mm": dict(zip(body.parts, map(float, net_mm))),
        "interp_mm": dict(zip(body.parts, map(float, int_mm))),
        "net_parts": [p for p, k in zip(body.parts, keep) if k],
    }
    worse = ", ".join(p for p, b in zip(body.parts, better) if not b)
    figures = (h["net_all_mm"], h["interp_all_mm"], h["windows"])
    if not keep.any():
        log.warning(
            "deformation: the net does not predict this recording's held-out parts better "
            "than interpolation (RMSE %.2f vs %.2f mm over %d windows%s): the net is not "
            "used, the tracks are interpolated (deformation=interp's model, adjusted to "
            "convergence). A net for this animal: deformation=self "
            "(deform.require_better=false uses the net anyway)",
            *figures,
            "" if spec == "all" else "; per part no better either",
        )
    elif not keep.all():
        log.warning(
            "deformation: the net predicts this recording's held-out parts worse than "
            "interpolation for %s (RMSE over all parts %.2f vs %.2f mm, %d windows): those "
            "parts are interpolated (deform.require_better=%s)",
            worse,
            *figures,
            spec,
        )
    elif worse:  # report: used as given
        log.warning(
            "deformation: the net predicts this recording's held-out parts worse than "
            "interpolation for %s (RMSE over all parts %.2f vs %.2f mm, %d windows); it is "
            "used for every part as given (deform.require_better=parts interpolates those)",
            worse,
            *figures,
        )
    else:
        log.info(
            "deformation: the net beats interpolation on this recording's held-out parts "
            "(RMSE %.2f vs %.2f mm, %d windows)",
            *figures,
        )
    return (None if spec == "report" else keep), facts


def check_world_up(model, poses: np.ndarray, where: str) -> float | None:
    """`deformnet.deformation.check_world_up` for the rigid poses (T, 6) (Rodrigues +
    translation, model -> world) of a session tracked with `model`; an InputError naming
    `where` when the session's world is not the up of the model's heading frame."""
    from deformnet.deformation import check_world_up as check
    from deformnet.so3 import rodrigues_to_matrix

    up = getattr(model, "up", None)
    if up is None:
        return None
    R = rodrigues_to_matrix(torch.as_tensor(np.asarray(poses, dtype=float)[:, :3])).numpy()
    try:
        return check(R, up, where)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def deform_step(model, cfg_def) -> int:
    """Frames between the net's window tokens: ``deform.step`` (null: the step the net was
    trained with, `DeformationModel.step`)."""
    step = (cfg_def or {}).get("step")
    if step is None:
        return int(getattr(model, "step", 1))
    if int(step) < 1:
        raise InputError(f"deform.step must be an integer >= 1, got {step}")
    return int(step)


def far_steps(model, cfg_def) -> tuple[int, ...]:
    """``deform.far_steps``: wider token steps for part-frames the window does not reach
    (``auto``: the larger steps the net was trained with, `DeformationModel.steps`; a list;
    ``[]``: none)."""
    spec = (cfg_def or {}).get("far_steps", "auto")
    if spec is None or str(spec) == "auto":
        base = deform_step(model, cfg_def)
        return tuple(s for s in getattr(model, "steps", ()) if s > base)
    try:
        steps = tuple(int(s) for s in spec)
    except (TypeError, ValueError):
        msg = f"deform.far_steps must be auto or a list of integers, got {spec}"
        raise InputError(msg) from None
    if any(s < 1 for s in steps):
        raise InputError(f"deform.far_steps must be integers >= 1, got {list(steps)}")
    return steps


def deformation_mode(deformation) -> str:
    """``deformation=``: null / ``rigid`` (the rigid model), ``interp`` (each part's body-frame
    offset interpolated from its own observations, `InterpObservation`), ``default`` (the
    shipped pretrained net, `deformnet.pretrained`), ``self`` (that net fine-tuned on this
    recording's own tokens, `adapt_net`), else a checkpoint (``net``)."""
    if deformation is None or str(deformation).lower() in ("", "none", "null", "rigid"):
        return "rigid"
    if str(deformation).lower() in ("interp", "default", "self"):
        return str(deformation).lower()
    return "net"


def scale_body(body: BodyModel, body_cfg, cons) -> tuple[BodyModel, dict]:
    """``body.scale``: ``auto`` (default) fits the model's size to the session's triangulated
    parts (`BodyModel.estimate_scale`), a number scales by it (1 keeps the model as is)."""
    want = body_cfg.get("scale", "auto") if body_cfg is not None else "auto"
    if want is None or (isinstance(want, str) and want.lower() == "auto"):
        if cons is None:
            return body, {"scale": 1.0, "scale_source": "none (stochastic.estimate=false)"}
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
    from adjust.estimate import deformation_moments
    from adjust.lsq.init import kabsch_poses
    from adjust.lsq.observation import RigidObservation

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


def refine_body(body: BodyModel, body_cfg, poses, det, weight, cams, cons, rigid_obs):
    """``body=auto``: the rigid model re-estimated from the detections themselves at the rigid
    adjustment's poses (`adjust.estimate.place_from_rays`: each part where its views' rays meet
    in the body frame across all frames, robustly; the structure step of a bundle adjustment).
    The Procrustes model (`BodyModel.from_observations`) averages triangulated points, each
    resting on the views that saw it in its frame and carrying their errors; this one weighs
    every detection, single views included, as the pose adjustment does. ``body.refine``:
    ``views`` (default) re-estimates every part, ``unplaced`` only the parts with fewer than
    ``body.rays_below`` 3D observations (no two cameras see them together, so the Procrustes
    model could not place them), ``none`` keeps the Procrustes model. Those parts' spread about
    their points comes from their views' residuals (their deformation variance); the others
    keep the spread of their 3D observations. On long sessions the rays of `shape_frames`
    (at most `SHAPE_FRAMES`, evenly spaced) place the parts.
    Returns None (nothing done) or (body, rigid observation, few_var (K, 3) torch, NaN for
    parts with enough 3D observations, facts)."""
    from adjust.estimate import place_from_rays
    from adjust.lsq.observation import RigidObservation

    mode = str(body_cfg.get("refine", "views")).lower()
    if mode not in ("views", "unplaced", "none"):
        raise ValueError(f"body.refine must be views, unplaced or none, got {mode!r}")
    below = int(body_cfg.get("rays_below", 20) or 0)
    few = cons.observed.sum(0) < below
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
        min_views=int(body_cfg.get("rays_min_views", 10)),
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


def interp_facts(observation, body: BodyModel) -> dict:
    """The estimated offset covariance of ``deformation=interp`` for the summary."""
    cov = observation.cov
    if cov is None:
        return {}
    return {
        "deformation_sigma_mm_per_part": {p: float(v) for p, v in zip(body.parts, cov.sigma_mm)},
        "mean_offset_mm_per_part": {p: [float(c) for c in m] for p, m in zip(body.parts, cov.mean)},
        "nugget_mm_per_part": {
            p: float(math.sqrt(v)) for p, v in zip(body.parts, cov.nugget.sum(-1))
        },
    }


# --------------------------------------------------------------------------------------------
# the app
# --------------------------------------------------------------------------------------------
def run(cfg: DictConfig) -> dict:
    """Load, adjust, write points3d.csv and summary.json; returns the summary.

    ``threads`` (torch's intra-op threads) applies for the call and is restored after it."""
    from deformnet.threads import torch_threads

    with torch_threads(cfg.get("threads")):
        return _run(cfg)


def _run(cfg: DictConfig) -> dict:
    from adjust.lsq.config import SolverConfig
    from adjust.lsq.solver import TRACK_OUTPUTS, adjust_poses

    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    cfg = with_session(cfg)  # input.session=DIR: DIR/calibration.toml, DIR[/detections]
    calibration = required(cfg, "input.calibration", "track")
    detections = required(cfg, "input.detections", "track")
    kwargs = load_kwargs(cfg.input)
    body_cfg = cfg.get("body")
    deformation = cfg.get("deformation")
    solver_cfg = SolverConfig.from_config(cfg.get("solver"))
    if body_cfg is None:
        raise ValueError(
            "adjust-track needs a body model: body=mouse, body=auto (estimated from the data) or "
            "your own conf/body/<name>.yaml"
        )
    auto = _is_auto(body_cfg)
    frame_of = None  # a named model whose frame an estimated one is moved into
    model = None
    body_facts: dict = {}
    mode = deformation_mode(deformation)
    est_cfg = cfg.get("stochastic") or {}
    estimate = bool(est_cfg.get("estimate", True))
    if cfg.output.get("nwb", False):  # before any computing: the NWB times need a frame rate
        meta = load_calibration_metadata(calibration)
        if recording_fps(cfg.output.get("fps"), meta) is None:
            raise InputError(
                f"output.nwb=true needs the recording's frame rate: set output.fps=... (Hz), or "
                f"give a calibration whose [metadata] has fps ({calibration} has none)"
            )
        try:
            session_start(cfg.output.get("session_start_time"), meta, calibration)
        except InputError as exc:
            raise InputError(f"output.nwb=true: {exc} (output.session_start_time=...)") from None
    if mode in ("interp", "self", "default") and not estimate:
        raise ValueError(f"deformation={mode} needs stochastic.estimate=true (its 3D observations)")

    # --- inputs and body model ----------------------------------------------------------
    t0 = time.perf_counter()
    if mode == "net":
        model = load_deformation(str(deformation))
        if auto:
            raise ValueError(
                "deformation= needs the body model the net was trained with; drop body=auto "
                f"(the checkpoint's model: '{model.body.name}', parts {list(model.body.parts)})"
            )
        given = BodyModel.from_config(body_cfg)
        body = model.body
        if given.parts != body.parts or not np.allclose(given.points, body.points):
            log.warning(
                "deformation: using the checkpoint's body model '%s' (the net was trained with "
                "it), not body=%s",
                body.name,
                given.name,
            )
        # the checkpoint's model may lack the config's aliases: merge them
        aliases = {k: v for k, v in given.aliases.items() if v in body.parts}
        body = BodyModel(body.parts, body.points, {**aliases, **body.aliases}, body.name)
        cameras, det = load_scene(calibration, detections, body, **kwargs)
    elif auto:
        cameras, det = load_scene(calibration, detections, None, **kwargs)
    else:
        body = BodyModel.from_config(body_cfg)
        try:
            cameras, det = load_scene(calibration, detections, body, **kwargs)
        except UnknownPartsError as exc:
            if str(body_cfg.get("other_parts", "error")).lower() != "auto":
                raise
            log.warning(
                "the detection files have parts that body '%s' does not know (%s): their own "
                "body is estimated from the data (as body=auto) and every part is tracked "
                "(body.other_parts=error stops instead)",
                body.name,
                ", ".join(exc.parts),
            )
            cameras, det = load_scene(calibration, detections, None, **kwargs)
            auto = True
            body_facts["other_parts"] = list(exc.parts)
        frame_of = body
    estimated = mode != "net" and (auto or body_shape(body_cfg) == "data")
    from adjust.camera_check import check_from_config  # input.camera_check, exclude_cameras

    cameras, det, camera_report = check_from_config(cameras, det, cfg.get("input"))
    check_cameras_usable(det, str(detections))  # one camera: depth unobserved, refused
    cams = CameraTensors.from_cameras(cameras, dtype=torch.float64)
    timings["load_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    weight = det.weight()
    cons = None
    if estimate:
        from adjust.estimate import consensus

        cons = consensus(
            det.xy,
            weight,
            cams,
            max_error_px=float(est_cfg.get("max_error_px", 20.0)),
            gate_sigmas=float(est_cfg.get("gate_sigmas", 4.0)),
            sigma_det_px=est_cfg.get("sigma_det_px"),
        )
        weight = np.where(cons.dropped, 0.0, weight)
        solver_cfg = solver_cfg.replace(sigma_det_px=cons.sigma_det_px)
    timings["consensus_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if estimated:
        try:
            name = str(body_cfg.get("name", "auto"))
            est = estimate_body(det, cams, body_cfg, name, cons, 0 if auto else MIN_SHAPE_FRAMES)
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
            body_facts["shape_fallback"] = str(exc)
    if estimated:
        body, est_facts = est
        body_facts.update(est_facts)
        if frame_of is not None:
            body, body_facts["frame"] = body.in_frame_of(frame_of)
            aliases = {k: v for k, v in frame_of.aliases.items() if v in body.parts}
            body = BodyModel(body.parts, body.points, aliases, body.name)
        sig = body_cfg.get("sigma_def_mm")
        if sig == "auto" and math.isfinite(body_facts["rms_deviation_mm"]):
            value = max(float(body_facts["rms_deviation_mm"]), 0.5)
            solver_cfg = solver_cfg.replace(sigma_def_mm=value)
            log.info(
                "body from the data: solver.sigma_def_mm = %.2f mm (the data's rms deviation)",
                value,
            )
        elif sig not in (None, "auto"):
            solver_cfg = solver_cfg.replace(sigma_def_mm=float(sig))
    if tuple(body.parts) != tuple(det.parts):  # load_scene orders parts as the model does
        raise InputError(f"parts {list(det.parts)} do not match the body model {list(body.parts)}")
    if not estimated and model is None:
        body, scale_facts = scale_body(body, body_cfg, cons)
        body_facts.update(scale_facts)
    if model is None:
        body, factor_facts = scale_factor(body, body_cfg)
        body_facts.update(factor_facts)
    if mode == "default":
        from deformnet.pretrained import load_default

        model = load_default()
        if tuple(model.body.parts) != tuple(body.parts):
            raise InputError(
                f"deformation=default: the shipped net knows the parts {list(model.body.parts)}, "
                f"this recording has {list(body.parts)}; use deformation=self (it trains a net "
                "for this skeleton)"
            )
        # the net predicts in canonical coordinates; it runs on this session's (scaled) body
        model.body = body
        model.body_points = torch.tensor(np.array(body.points), dtype=torch.float32)
    rigid_obs = None
    if cons is not None:
        rigid_obs, moment_facts = rigid_observation(body, cons)
        body_facts.update(moment_facts)
    timings["body_s"] = time.perf_counter() - t0

    # --- adjustment ---------------------------------------------------------------------
    t0 = time.perf_counter()
    observation = None
    def_facts: dict | None = None
    progress = bool(cfg.get("progress", True))
    init_poses = None
    rigid_iterations = 0
    deform_cfg = cfg.get("deform") or {}
    # views of a unanimous camera consensus are fused without a gate; where the consensus had
    # to outvote a camera, the track decides which views to believe (a consistent wrong pair,
    # e.g. a left/right swap seen alike by two cameras, can outvote the right one)
    trusted = None
    if cons is not None:
        trusted = cons.used & (cons.observed & ~cons.dropped.any(-1))[..., None]

    def solve(config, obs, init=None):
        """One pose-track adjustment of this session (only the outputs that are written:
        long sessions in bounded memory)."""
        return adjust_poses(
            det.xy,
            weight,
            cams,
            np.array(body.points),  # a writable copy
            config,
            init_poses=init,
            observation=obs,
            progress=progress,
            trusted=trusted,
            outputs=TRACK_OUTPUTS,
        )

    staged = mode != "rigid" and cons is not None  # rigid -> interp -> (net)
    few_var = None  # (K, 3) the spread of parts placed from their single views (else NaN)
    if mode == "rigid" or staged or bool(deform_cfg.get("rigid_first", True)):
        # the rigid adjustment: the result itself, or the start of a deformable one
        rigid = solve(solver_cfg, rigid_obs)
        if estimated and rigid_obs is not None:  # the model from the detections themselves
            refined = refine_body(body, body_cfg, rigid.poses, det, weight, cams, cons, rigid_obs)
            if refined is not None:
                body, rigid_obs, few_var, body_facts["refined"] = refined
                rigid = solve(solver_cfg, rigid_obs, rigid.poses)
        res = rigid
        init_poses, rigid_iterations = rigid.poses, int(rigid.iterations)
        timings["rigid_s"] = time.perf_counter() - t0
    if staged:
        from adjust.lsq.observation import InterpObservation

        interp_obs = InterpObservation(
            torch.tensor(np.array(body.points)),
            torch.as_tensor(cons.points),
            torch.as_tensor(cons.observed),
            torch.as_tensor(cons.noise_var),
            few_var=few_var,
        )
        if mode == "interp":
            observation = interp_obs
        else:  # the net starts from the interp poses
            t1 = time.perf_counter()
            res = solve(solver_cfg, interp_obs, init_poses)
            init_poses = res.poses
            timings["interp_s"] = time.perf_counter() - t1
    adapt_facts = None
    if mode == "self":
        from adjust.tokens import session_tokens

        t1 = time.perf_counter()
        tokens = session_tokens(
            init_poses, body.points, cons, body.parts, body.name, source=str(detections)
        )
        model, adapt_facts = adapt_net(tokens, output_dir(cfg), cfg.get("adapt"), progress)
        timings["adapt_s"] = time.perf_counter() - t1
        net_mm, lin_mm = adapt_facts.get("val_rmse_mm"), adapt_facts.get("val_rmse_mm_linear")
        if bool((cfg.get("adapt") or {}).get("require_better", True)) and not (
            net_mm is not None and lin_mm is not None and net_mm < lin_mm
        ):
            log.warning(
                "deformation=self: the adapted net does not predict held-out parts better "
                "than linear interpolation (val RMSE %s vs %s mm; too little data or time?): "
                "the tracks are interpolated (deformation=interp's model, adjusted to "
                "convergence; adapt.require_better=false uses the net "
                "anyway; its checkpoint is %s)",
                f"{net_mm:.2f}" if net_mm is not None else "n/a",
                f"{lin_mm:.2f}" if lin_mm is not None else "n/a",
                adapt_facts["checkpoint"],
            )
            adapt_facts["used"] = False
            model = None  # `res`: the interp adjustment's, outputs complete
        else:
            adapt_facts["used"] = True
    up_deg = None
    if model is not None and init_poses is not None:
        up_deg = check_world_up(model, init_poses, str(detections))
    heldout_facts, net_parts = None, None
    if model is not None and mode in ("default", "net") and init_poses is not None:
        t1 = time.perf_counter()
        net_parts, heldout_facts = heldout_check(
            model, init_poses, body, cons, deform_cfg, str(detections), mode
        )
        timings["heldout_check_s"] = time.perf_counter() - t1
        if net_parts is not None and not bool(net_parts.any()):
            model = None  # `res`: the interp adjustment's, outputs complete
    if model is not None:
        t1 = time.perf_counter()
        observation, def_facts = make_deformable_observation(
            model,
            body.points,
            det,
            cams,
            cfg.get("deform"),
            cons=cons,
            few_var=few_var,
            net_parts=net_parts,
        )
        if adapt_facts is not None:
            def_facts["adapt"] = adapt_facts
        if up_deg is not None:  # a heading-frame net: how far the mouse's up is from its up
            def_facts["world_up"] = {"up": list(model.up), "median_body_up_deg": round(up_deg, 1)}
    if observation is not None and mode != "interp":
        t_net = time.perf_counter()
    if observation is not None:
        dcfg = solver_cfg
        if deform_cfg.get("max_iterations") is not None:
            dcfg = dcfg.replace(max_iterations=int(deform_cfg["max_iterations"]))
        if deform_cfg.get("sigma_def_mm") is not None:
            dcfg = dcfg.replace(sigma_def_mm=float(deform_cfg["sigma_def_mm"]))
        res = solve(dcfg, observation, init_poses)
    measured_facts = None
    measured = str(deform_cfg.get("measured", "cv"))
    if measured not in ("cv", "interp", "rigid", "net"):
        raise ValueError(f"deform.measured must be cv, interp, rigid or net, got {measured!r}")
    learned = mode in ("self", "default", "net") and rigid_obs is not None
    if learned and (observation is not None or mode == "self") and measured in ("cv", "rigid"):
        # the learned modes: the measured part-frames' prior, by held-out cameras
        t1 = time.perf_counter()
        choice = measured
        if measured == "cv":
            from adjust.validate import choose_measured_prior

            choice, measured_facts = choose_measured_prior(
                res.poses,
                det.xy,
                weight,
                res.weights > 0,
                cams,
                np.array(body.points),
                rigid_obs.var.numpy(),
                solver_cfg.sigma_det_px,
                consensus_kwargs={
                    "max_error_px": float(est_cfg.get("max_error_px", 20.0)),
                    "gate_sigmas": float(est_cfg.get("gate_sigmas", 4.0)),
                },
                few_var=few_var,
            )
        else:
            measured_facts = {"choice": choice, "reason": "deform.measured"}
        if choice == "rigid":  # the shape prior where a part has its own 3D observation
            target = observation if observation is not None else interp_obs
            target.set_measured_var(rigid_obs.var)
            res = solve(dcfg if observation is not None else solver_cfg, target, res.poses)
        timings["measured_prior_s"] = time.perf_counter() - t1
    if mode == "interp" or (mode in ("self", "default", "net") and model is None):
        def_facts = interp_facts(observation if mode == "interp" else interp_obs, body)
        if adapt_facts is not None:
            def_facts["adapt"] = adapt_facts
    elif model is not None:
        timings["net_s"] = time.perf_counter() - t_net
        def_facts["net_passes"] = int(observation.evaluations)
        def_facts["held_out_ratio_net_over_interp"] = {
            p: float(v) for p, v in zip(body.parts, observation.factor)
        }
        def_facts["net_reach_fraction"] = float(observation.reach.double().mean())
        def_facts["net_used_fraction"] = float(observation.use_net.double().mean())
        used = observation.step_used[observation.use_net.to(observation.step_used.device)]
        def_facts["net_used_by_step"] = {
            int(s): float((used == s).double().sum() / max(used.numel(), 1))
            for s in (observation.step, *observation.far_steps)
        }
    if measured_facts is not None:
        def_facts["measured_prior"] = measured_facts
    if heldout_facts is not None:
        def_facts["heldout"] = heldout_facts
    timings["adjust_s"] = time.perf_counter() - t0 - timings.get("adapt_s", 0.0)

    # --- outputs ------------------------------------------------------------------------
    t0 = time.perf_counter()
    T, K, C = det.num_frames, det.num_parts, det.num_cameras
    points = res.points
    observed = res.weights > 0  # the detections the fused points rest on
    ncams = observed.sum(-1)
    view_err = reprojection_errors(points, det.xy, cams, observed)
    with warnings.catch_warnings():  # all-NaN rows (no detection) are expected
        warnings.simplefilter("ignore", RuntimeWarning)
        error = np.nanmean(view_err, axis=-1) if C else np.full((T, K), np.nan)
    score = np.where(observed, det.likelihood, np.inf).min(-1)
    score = np.where((ncams > 0) & np.isfinite(score), score, np.nan)
    sigma = res.point_sd  # root of the trace of each point's covariance (mm)
    pc = res.pose_cov
    extra: dict[str, np.ndarray] = {n: res.poses[:, i] for i, n in enumerate(POSE_COLUMNS)}
    extra["pose_sigma_r"] = np.sqrt(np.clip(np.trace(pc[:, :3, :3], axis1=-2, axis2=-1), 0, None))
    extra["pose_sigma_t"] = np.sqrt(np.clip(np.trace(pc[:, 3:, 3:], axis1=-2, axis2=-1), 0, None))
    extra["{part}_sigma"] = sigma
    fnum = det.frames if det.frames is not None else None
    out = output_dir(cfg)
    points_path = out / "points3d.csv"

    def write_points(path: Path) -> Path:
        return write_points3d(path, det.parts, points, error, ncams, score, extra=extra, fnum=fnum)

    summary = {
        "inputs": {
            "calibration": str(Path(calibration).resolve()),
            "detections": str(Path(detections).resolve()),
            "files": {c: str(f) for c, f in zip(det.cameras, det.files)},
        },
        "body": {
            "name": body.name,
            "source": "auto"
            if auto
            else ("checkpoint" if mode == "net" else ("data" if estimated else "config")),
            **body_facts,
        },
        "deformation": {"mode": mode, **(def_facts or {})}
        if model is None
        else {
            "mode": mode,
            "checkpoint": str(
                Path(str(deformation)).resolve()
                if mode == "net"
                else (out / "deformation.ckpt" if mode == "self" else "default")
            ),
            "window": int(model.window),
            "step": int(observation.step) if observation is not None else int(model.step),
            **(def_facts or {}),
        },
        "stochastic": None if cons is None else cons.facts(det.cameras),
        "cameras": list(det.cameras),
        "camera_check": camera_report,
        "parts": list(det.parts),
        "num_frames": T,
        "settings": {
            "likelihood_threshold": det.threshold,
            "individual": kwargs["individual"],
            "solver": asdict(solver_cfg),
        },
        "rigid_iterations": rigid_iterations,  # of the rigid run that started a deformable one
        **result_summary(res, det, error, view_err),
        "health": (
            health := track_health(points, view_err, solver_cfg.sigma_det_px, poses=res.poses)
        ),
        "time_s": {},
        "outputs": {"points3d": str(points_path), "summary": str(out / "summary.json")},
    }
    timings["write_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    summary["time_s"] = {k: round(v, 3) for k, v in timings.items()}
    # every output as one set (adjust.app.OutputSet): a run stopped at any moment (SIGKILL
    # included) leaves the previous run's outputs whole; summary.json last, with every file's
    # sha256 (outputs.files)
    with OutputSet(out) as staged:
        # which detections every point rests on (for figures: adjust-plot, the demo report)
        np.savez_compressed(
            staged.path("accepted.npz"),
            accepted=observed,
            parts=np.asarray(det.parts),
            cameras=np.asarray(det.cameras),
        )
        summary["outputs"]["accepted"] = str(out / "accepted.npz")
        if cons is not None:  # self-supervised tokens for deformnet-train data=sessions
            from adjust.tokens import session_tokens

            tokens = session_tokens(
                res.poses, body.points, cons, body.parts, body.name, source=str(out)
            )
            tokens.save(staged.path("tokens.npz"))
            summary["outputs"]["tokens"] = str(out / "tokens.npz")
        write_points(staged.path("points3d.csv"))
        if cfg.output.get("nwb", False):  # the same tracks as NWB (ndx-pose), adjust.export
            write_nwb(
                staged.path("tracks.nwb"),
                staged.path("points3d.csv"),
                calibration,
                fps=cfg.output.get("fps"),
                session_start_time=cfg.output.get("session_start_time"),
                subject=to_plain(cfg.output.get("subject")) or None,
                detections=detections,
            )
            summary["outputs"]["nwb"] = str(out / "tracks.nwb")
        summary = staged.commit(summary)
    if health["status"] == "failed":
        frames = health["frames"] if fnum is None else [int(fnum[f]) for f in health["frames"]]
        raise TrackingFailed(
            f"{detections}: the tracks cannot be trusted: {health['bad_frames']} frames "
            f"(e.g. {frames}) have non-finite points or points whose own detections reproject "
            f"beyond {health['limit_px']:.0f} px (summary.json 'health'; outputs kept in {out} "
            "for inspection)"
        )
    if health["status"] == "suspect":
        frames = health["turn_frames"]
        log.warning(
            "the body's pose turns by more than %.0f degrees between two frames at %d frames "
            "(e.g. %s): the track may have left the animal there (summary.json 'health')",
            health["max_turn_deg"],
            health["turn_frames_count"],
            frames if fnum is None else [int(fnum[f]) for f in frames],
        )
    alone = summary["from_model_only"]["fraction"]
    if alone > 0.25:
        worst = sorted(summary["from_model_only"]["per_part"].items(), key=lambda kv: -kv[1])[:3]
        log.warning(
            "%.0f%% of the part-frames rest on no accepted detection (tracked from the model "
            "alone; their _ncams is 0 and their _sigma large): most for %s",
            100 * alone,
            ", ".join(f"{p} {100 * v:.0f}%" for p, v in worst),
        )
    err = summary["reprojection_error_px"]
    log.info(
        "tracked %d frames x %d parts (completeness %.1f%%) in %d iterations (%.1f s); "
        "reprojection error median %s px, p90 %s px; wrote %s",
        T,
        K,
        100 * summary["completeness"],
        summary["iterations"],
        timings["total_s"],
        f"{err['median']:.2f}" if err["median"] is not None else "n/a",
        f"{err['p90']:.2f}" if err["p90"] is not None else "n/a",
        out,
    )
    return summary


@hydra.main(config_path=str(CONF_DIR), config_name="track", version_base=None)
def _main(cfg: DictConfig) -> dict | None:
    from adjust.batch import in_multirun, run_session

    if in_multirun():  # one session of a batch (adjust.batch): records a failure, never raises
        return run_session(cfg)
    run_or_exit(run, cfg)


def main() -> None:
    """Console script: ``input.session=glob(PATTERN)`` -> the matching folders, then Hydra."""
    import sys

    try:
        sys.argv = expand_session_globs(sys.argv)
    except ValueError as exc:
        log.error("%s", exc)
        raise SystemExit(2) from None
    _main()


if __name__ == "__main__":  # pragma: no cover
    main()
