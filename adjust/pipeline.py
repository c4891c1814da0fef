"""`adjust-track`'s recipe: detections and a calibration in, points3d.csv and summary.json out.

Load the calibration and one detection file per camera (`adjust.io`), check the cameras
(`adjust.camera_check`), the consensus triangulation (`adjust.estimate.consensus`: the
session's 3D observations and detector noise), the body model (`adjust.body_fit`), the rigid
pose-track adjustment (`adjust.lsq.adjust_poses`), then the deformation mode
(`adjust.deformation_modes`, chosen once from ``deformation=``), then the outputs, written as
one set (`adjust.track_outputs`) with the summary (`adjust.summary`).

`track(cfg)` is the plain function; `run(cfg)` is it within the configured torch threads
(``threads``), the function behind `adjust-track` (`adjust.apps.track`) and its batches.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from adjust.body_fit import fit_body, refine_body, rigid_observation, unplaced_parts
from adjust.camera import CameraTensors
from adjust.camera_check import check_from_config
from adjust.chunks import ChunkHooks, track_long
from adjust.deformation_modes import Adjusting, mode_from_config
from adjust.estimate import consensus
from adjust.io import (
    UnknownPartsError,
    calibration_units,
    check_cameras_usable,
    load_scene,
)
from adjust.lsq.solver import TRACK_OUTPUTS, adjust_poses
from adjust.session import with_session
from adjust.settings import required
from adjust.summary import report_result, result_summary, track_columns, track_health
from adjust.track_config import TrackConfig, resolve_deprecated
from adjust.track_outputs import check_nwb_output, write_outputs
from deformnet.body import BodyModel
from deformnet.paths import output_dir
from deformnet.threads import torch_threads

log = logging.getLogger(__name__)

__all__ = ["run", "track"]


def run(cfg: DictConfig) -> dict:
    """`track` with ``threads`` (torch's intra-op threads: the one thread setting) set for the
    call and restored after it, values under deprecated names moved to their new ones first
    (`adjust.track_config.resolve_deprecated`); returns the summary."""
    cfg = resolve_deprecated(cfg)
    with torch_threads(TrackConfig.from_config(cfg).threads):
        summary = track_long(cfg, track)  # a long session, in chunks (adjust.chunks)
        return summary if summary is not None else track(cfg)


def track(cfg: DictConfig, chunk: ChunkHooks | None = None) -> dict:
    """Load, adjust, write points3d.csv and summary.json; returns the summary. chunk: one pass
    over part of a long session (`adjust.chunks.ChunkHooks`: its rows are read, the session's
    model estimated once is used, and the result is handed to it instead of written)."""
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    cfg = with_session(cfg)  # input.session=DIR: DIR/calibration.toml, DIR[/detections]
    calibration = required(cfg, "input.calibration", "track")
    detections = required(cfg, "input.detections", "track")
    where = str(detections)
    if "body" not in cfg or cfg.body is None:
        raise ValueError(
            "adjust-track needs a body model: body=mouse, body=auto (estimated from the data) or "
            "your own conf/body/<name>.yaml"
        )
    body_cfg = cfg.body  # the model's node (`BodyModel.from_config`; `tc.body`, `tc.body_fit`)
    tc = TrackConfig.from_config(cfg)
    kwargs = tc.input.load_kwargs()
    solver_cfg, spec, fit = tc.solver, tc.body, tc.body_fit
    auto = spec.auto
    mode = mode_from_config(tc.deformation)
    if chunk is not None:  # a long session's chunk: the mode (and net) its sample chose
        mode = chunk.deformation_mode(mode)
    estimate = tc.consensus.estimate
    check_nwb_output(tc.output, calibration)
    if mode.needs_consensus and not estimate:
        raise ValueError(
            f"deformation={mode.name} needs consensus.estimate=true (its 3D observations)"
        )

    # --- inputs and body model ----------------------------------------------------------
    t0 = time.perf_counter()
    body_facts: dict = {}
    load = load_scene if chunk is None else chunk.load_scene
    model = None if chunk is None else chunk.model  # a long session's, from its sample
    frame_of = None  # a named model whose frame an estimated one is moved into
    body = mode.checkpoint_body(body_cfg)
    from_checkpoint = body is not None
    if from_checkpoint:
        if auto:
            raise ValueError(
                "deformation= needs the body model the net was trained with; drop body=auto "
                f"(the checkpoint's model: '{body.name}', parts {list(body.parts)})"
            )
        cameras, det = load(calibration, detections, body, **kwargs)
    elif auto:
        cameras, det = load(calibration, detections, None, **kwargs)
    else:
        body = BodyModel.from_config(body_cfg)
        try:
            cameras, det = load(calibration, detections, body, **kwargs)
        except UnknownPartsError as exc:
            if str(spec.other_parts).lower() != "auto":
                raise
            log.warning(
                "the detection files have parts that body '%s' does not know (%s): their own "
                "body is estimated from the data (as body=auto) and every part is tracked "
                "(body.other_parts=error stops instead)",
                body.name,
                ", ".join(exc.parts),
            )
            cameras, det = load(calibration, detections, None, **kwargs)
            auto = True
            body_facts["other_parts"] = list(exc.parts)
        frame_of = body
    check = check_from_config if chunk is None else chunk.check_cameras
    cameras, det, camera_report = check(cameras, det, tc.input, None if auto else body)
    check_cameras_usable(det, where)  # one camera: depth unobserved, refused
    cams = CameraTensors.from_cameras(cameras, dtype=torch.float64)
    timings["load_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    weight = det.weight()
    cons = None
    if estimate:
        cons = consensus(
            det.xy,
            weight,
            cams,
            max_error_px=float(tc.consensus.max_error_px),
            gate_sigmas=float(tc.consensus.gate_sigmas),
            sigma_det_px=tc.sigma_det_px if model is None else model.sigma_det_px,
        )
        weight = np.where(cons.dropped, 0.0, weight)
        solver_cfg = solver_cfg.replace(sigma_det_px=cons.sigma_det_px)
    timings["consensus_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if model is None:
        body, solver_cfg, estimated = fit_body(
            det,
            cams,
            body,
            spec,
            fit,
            cons,
            solver_cfg,
            auto=auto,
            frame_of=frame_of,
            from_checkpoint=from_checkpoint,
            facts=body_facts,
            sigma_def_mm=tc.sigma_def_mm,
            max_error_px=tc.consensus.max_error_px,
        )
        rigid_obs = None
        if cons is not None:
            rigid_obs, moment_facts = rigid_observation(body, cons)
            body_facts.update(moment_facts)
    else:  # a long session's chunk: the body model and sigmas estimated once (adjust.chunks)
        body, solver_cfg, rigid_obs = model.body, model.solver_cfg, model.rigid_obs
        estimated = False
    mode.prepare(body)
    timings["body_s"] = time.perf_counter() - t0

    # --- adjustment ---------------------------------------------------------------------
    t0 = time.perf_counter()
    progress = tc.progress
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

    # (K, 3) the spread of parts placed from their single views (else NaN)
    few_var = None if model is None else model.few_var
    rigid, rigid_iterations, start_cfg = None, 0, None
    if mode.rigid_first(tc.deform, cons):
        # the rigid adjustment: the result itself, or the start of a deformable one
        start_cfg = mode.start_cfg(solver_cfg, tc.deform)
        first_cfg = start_cfg
        if estimated and rigid_obs is not None and unplaced_parts(fit, cons).any():
            # parts the triangulations could not place sit in the model by translation only
            # or at the body's centre until their rays place them (refine_body, from these
            # poses): a model error, which the solver's robust kernel is for; without it the
            # poses follow those parts and the rays place them tens of mm off (the real SLEAP
            # mouse with 2 cameras: a left-out camera's median error 20-31 px, against 4-9)
            first_cfg = solver_cfg
            body_facts["unplaced_start_robust"] = solver_cfg.robust
        rigid = solve(first_cfg, rigid_obs)
        if estimated and rigid_obs is not None:  # the model from the detections themselves
            refined = refine_body(body, fit, rigid.poses, det, weight, cams, cons, rigid_obs)
            if refined is not None:
                body, rigid_obs, few_var, body_facts["refined"] = refined
                rigid = solve(start_cfg, rigid_obs, rigid.poses)
        rigid_iterations = int(rigid.iterations)
        timings["rigid_s"] = time.perf_counter() - t0
    out = output_dir(cfg)
    res, deformation_facts = mode.adjust(
        Adjusting(
            det=det,
            weight=weight,
            cams=cams,
            body=body,
            cons=cons,
            rigid_obs=rigid_obs,
            few_var=few_var,
            solver_cfg=solver_cfg,
            solve=solve,
            rigid=rigid,
            deform=tc.deform,
            adapt_cfg=tc.adapt,
            consensus=tc.consensus,
            where=where,
            out=out,
            progress=progress,
            timings=timings,
        )
    )
    timings["adjust_s"] = time.perf_counter() - t0 - timings.get("adapt_s", 0.0)

    # --- outputs ------------------------------------------------------------------------
    t0 = time.perf_counter()
    cols = track_columns(res, det, cams)
    fnum = det.frames if det.frames is not None else None
    points_path = out / "points3d.csv"
    source = "config"
    if auto:
        source = "auto"
    elif from_checkpoint:
        source = "checkpoint"
    elif estimated:
        source = "data"
    summary = {
        "inputs": {
            "calibration": str(Path(calibration).resolve()),
            # the file's declared length unit (null: none, read as mm); every output is in mm
            "calibration_units": calibration_units(calibration),
            "detections": str(Path(detections).resolve()),
            "files": {c: str(f) for c, f in zip(det.cameras, det.files)},
        },
        "body": {"name": body.name, "source": source, **body_facts},
        "deformation": deformation_facts,
        "stochastic": None if cons is None else cons.facts(det.cameras),
        "cameras": list(det.cameras),
        "camera_check": camera_report,
        "parts": list(det.parts),
        "num_frames": det.num_frames,
        "settings": {
            "likelihood_threshold": det.threshold,
            "individual": kwargs["individual"],
            "solver": asdict(solver_cfg),
            # the rigid adjustment's kernel (deform.rigid_robust; null: no rigid adjustment)
            "rigid_robust": None if start_cfg is None else start_cfg.robust,
        },
        "rigid_iterations": rigid_iterations,  # of the rigid run that started a deformable one
        **result_summary(res, det, cols.error, cols.view_err),
        "health": track_health(
            cols.points, cols.view_err, solver_cfg.sigma_det_px, poses=res.poses
        ),
        "time_s": {},
        "outputs": {"points3d": str(points_path), "summary": str(out / "summary.json")},
    }
    timings["write_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    summary["time_s"] = {k: round(v, 3) for k, v in timings.items()}
    if chunk is not None:  # one pass over part of a long session: adjust.chunks writes it
        kept = {"body": body, "solver_cfg": solver_cfg, "rigid_obs": rigid_obs, "few_var": few_var}
        return chunk.take(summary, res=res, cols=cols, det=det, cons=cons, **kept)
    summary = write_outputs(
        out, summary, det, cols, res.poses, body, cons, tc.output, calibration, detections
    )
    report_result(summary, where, out, fnum)
    return summary
