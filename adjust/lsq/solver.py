"""Pose-track least-squares adjustment: banded Levenberg-Marquardt over per-frame rigid poses.

Unknowns: p_t = (r_t, tau_t), t = 0..T-1 (model -> global, `deformnet.so3`). Cost:

    sum_{t,k,c} w_tkc rho(|x_tkc - proj_c(X_k(p_t))|^2)  +  lambda_track sum_t |d_t(p_{t-2..t+2})|^2

with the observation function X_k(p_t) pluggable (`observation.py`; rigid by default), the
motion-track residual d_t in its spline or grid form (`constraint.py`), weights from the
two-Gaussian mixture and robust kernel (`robust.py`) times the detection weights, and
lambda_track = track_weight / track_sigma_mm^2. The normal equations are block-banded (6 x 6
blocks, frames up to 4 apart: scalar half-bandwidth 29) and solved by banded Cholesky in O(T)
(`banded.py`); rotations are updated multiplicatively, R <- exp(delta) R. Pose covariances are
the 6 x 6 diagonal blocks of the inverse normal matrix (selected inversion, O(T)), in the
tangent space of the left increment (rotation part: rad^2 about the global axes).

The problem's pieces (residuals, IRLS weights, cost, normal equations) are in `problem.py`; this
module runs the loop over them, chunk by chunk, and the per-frame outputs.
"""

from __future__ import annotations

import contextlib
import logging
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from adjust.camera import CameraTensors
from adjust.lsq import banded
from adjust.lsq.config import SolverConfig
from adjust.lsq.constraint import default_rho, make_grid
from adjust.lsq.fusion import fuse_points, innovation_gate, prior_inflation
from adjust.lsq.geometry import retract, so3_exp, so3_log
from adjust.lsq.init import initial_poses
from adjust.lsq.lm import add_ridge, levenberg_marquardt
from adjust.lsq.memory import release_freed_memory
from adjust.lsq.observation import ObservationModel, RigidObservation
from adjust.lsq.problem import (
    MaskedRows,
    Problem,
    as_stored,
    as_tensor,
    deformation_var,
    evaluate,
    irls_weights,
    normal_equations,
    total_cost,
)
from adjust.lsq.robust import kernel_weight
from adjust.lsq.stochastic import count_within
from deformnet.threads import torch_threads

log = logging.getLogger(__name__)


@dataclass
class AdjustmentResult:
    """Output of `adjust_poses` (numpy float64, but weights, residuals and pose_cov float32; T
    frames, K parts, C cameras). An array not asked for (`adjust_poses`'s ``outputs``) is None.

    poses (T, 6): Rodrigues vector (angle in [0, pi]) + translation mm, model -> global.
    points (T, K, 3): fused part positions (own detections + model), mm; point_cov (T, K, 3, 3)
    mm^2 and point_sigma (T, K, 3) mm their uncertainty.
    model_points (T, K, 3): the observation model's points at the poses; model_sigma (T, K, 3)
    mm: the pose uncertainty propagated to them.
    pose_cov (T, 6, 6): covariance of the left increment (rad^2 about global axes; mm^2).
    residuals (T, K, C, 2) px: detection minus projected model point (NaN: no detection).
    weights (T, K, C): final relative weight of each detection (robust kernel x mixture, scaled
    so that a clean detection of the narrow Gaussian has 1; 0: no detection).
    point_sd (T, K) mm: root of the trace of point_cov (a point's 3D standard error).
    ncams (T, K): accepted detections per part; observed (T,): frame had any detection;
    fitted (T,): frame had its own initial fit; init_poses (T, 6).
    iterations: LM iterations (max over chunks); cost_history: one list of costs per chunk;
    converged: all chunks converged; mixture_share: final share of the narrow Gaussian.
    """

    poses: np.ndarray | None = None
    points: np.ndarray | None = None
    point_cov: np.ndarray | None = None
    point_sigma: np.ndarray | None = None
    model_points: np.ndarray | None = None
    model_sigma: np.ndarray | None = None
    pose_cov: np.ndarray | None = None
    residuals: np.ndarray | None = None
    weights: np.ndarray | None = None
    ncams: np.ndarray | None = None
    observed: np.ndarray | None = None
    fitted: np.ndarray | None = None
    init_poses: np.ndarray | None = None
    point_sd: np.ndarray | None = None
    iterations: int = 0
    cost_history: list[list[float]] = field(default_factory=list)
    converged: bool = False
    mixture_share: float = 1.0
    chunks: int = 1

    @property
    def pose_sigma(self) -> np.ndarray:
        """(T, 6) standard deviations of the pose increments (rad, mm)."""
        return np.sqrt(np.clip(np.diagonal(self.pose_cov, axis1=-2, axis2=-1), 0, None))

    @property
    def reprojection_error(self) -> np.ndarray:
        """(T, K) mean reprojection error (px) of the model points (NaN: no detection)."""
        err = np.linalg.norm(self.residuals, axis=-1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # parts without any detection
            return np.nanmean(err, axis=-1)


#: the per-frame arrays `adjust_poses` can return (``outputs``); poses, pose_cov and fitted
#: always come back
RESULT_ARRAYS = (
    "points",
    "point_cov",
    "point_sigma",
    "model_points",
    "model_sigma",
    "residuals",
    "weights",
    "ncams",
    "observed",
    "point_sd",
    "init_poses",
)
#: what adjust-track writes: fused points, their 3D standard error, the detection weights
TRACK_OUTPUTS = ("points", "point_sd", "weights")
#: stored in float32 (diagnostics; halves the largest arrays of long sessions; pose_cov too)
_FLOAT32_OUTPUTS = ("residuals", "weights")


@contextlib.contextmanager
def _progress(enabled: bool, total: int, label: str) -> Iterator:
    if not enabled:
        yield None
        return
    try:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
    except ImportError:  # pragma: no cover - rich is a dependency
        yield None
        return
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        transient=True,
    ) as bar:
        task = bar.add_task(label, total=total)
        yield lambda desc: bar.update(task, advance=1, description=desc)


def _solve(poses: Tensor, pb: Problem, progress: bool, label: str) -> dict:
    """Levenberg-Marquardt with IRLS reweighting on one problem; returns poses and stats."""
    cfg = pb.cfg
    T = poses.shape[0]
    state = {"share": cfg.mixture_prior if cfg.sigma_def_mm > 0 else 1.0}

    def linearise(p: Tensor):
        pb.obs.prepare(p)
        pb.defvar = deformation_var(pb.obs, p)
        lin = evaluate(p, pb, jacobian=True)
        w, wmix, state["share"] = irls_weights(lin, pb, state["share"])
        blocks, g = normal_equations(lin, w, pb)
        return blocks, g, total_cost(lin, pb, wmix), wmix

    def cost(p: Tensor, wmix: Tensor) -> float:
        return total_cost(evaluate(p, pb, jacobian=False), pb, wmix)

    def step(p: Tensor, delta: np.ndarray) -> Tensor:
        return retract(p, torch.as_tensor(delta, dtype=p.dtype, device=p.device))

    with _progress(progress and T > 0, cfg.max_iterations, label) as tick:
        out = levenberg_marquardt(
            poses,
            linearise,
            cost,
            step,
            max_iterations=cfg.max_iterations,
            min_iterations=cfg.min_iterations,
            ftol=cfg.ftol,
            xtol=cfg.xtol,
            wtol=cfg.wtol,
            stol=cfg.stol,
            atol=cfg.dtol * T,
            lam=cfg.lm_lambda,
            lam_up=cfg.lm_up,
            lam_down=cfg.lm_down,
            ridge=cfg.ridge,
            tick=(lambda d: tick(f"{label} {d}")) if tick is not None else None,
        )
    poses, it, history, converged = out.x, out.iterations, out.history, out.converged
    share = state["share"]
    # covariance: the normal matrix of the last linearisation when converged (the last step
    # was negligible), else a fresh linearisation at the final poses
    if converged and out.blocks is not None:
        blocks = out.blocks
    else:
        blocks, _, c, _ = linearise(poses)
        history.append(c)
        add_ridge(blocks, cfg.ridge)
    cov = banded.diagonal_blocks_of_inverse(blocks) if T else np.zeros((0, 6, 6))
    log.info(
        "%s: %d iterations, cost %.6g -> %.6g, converged=%s",
        label,
        it,
        history[0],
        history[-1],
        converged,
    )
    return dict(
        poses=poses, cov=cov, iterations=it, history=history, converged=converged, share=share
    )


def adjust_poses(
    xy: Tensor | np.ndarray,
    weight: Tensor | np.ndarray | None,
    cams: CameraTensors,
    body_points: Tensor | np.ndarray,
    config: SolverConfig | None = None,
    init_poses: Tensor | np.ndarray | None = None,
    observation: ObservationModel | None = None,
    progress: bool = True,
    trusted: Tensor | np.ndarray | None = None,
    outputs: Sequence[str] | None = None,
) -> AdjustmentResult:
    """Complete 3D pose track and part positions from incomplete multi-camera detections.

    xy: (T, K, C, 2) detections px, NaN where missing; weight: (T, K, C) >= 0 per detection
    (e.g. DeepLabCut likelihood; None = 1; NaN/<= config.min_weight = missing); cams: C fixed
    cameras; body_points: (K, 3) model points mm; init_poses: (T, 6) or None (from
    config.init); observation: observation function (default: rigid body_points); progress: a
    rich progress bar over the iterations. Never returns NaN in poses, points or covariances:
    frames without detections get their pose from the track constraint (or, with nothing to
    go by, from the initialisation with a huge covariance). trusted: (T, K, C) bool, optional:
    views of a camera consensus (e.g. `adjust.estimate.consensus`), fused without being gated
    against the model's prediction (used only with an observation model that states its
    deformation covariance). outputs: names from `RESULT_ARRAYS` to return (None: all; the others
    are None; `TRACK_OUTPUTS`: what adjust-track needs): long sessions keep only what they use.
    """
    cfg = (config if config is not None else SolverConfig()).resolved()
    with torch_threads(cfg.num_threads):
        return _adjust_poses(
            xy, weight, cams, body_points, cfg, init_poses, observation, progress, trusted, outputs
        )


def _adjust_poses(
    xy, weight, cams, body_points, cfg, init_poses, observation, progress, trusted, outputs=None
):
    dt = cfg.torch_dtype
    xy_t = as_stored(xy, dt)
    if xy_t.dim() != 4 or xy_t.shape[-1] != 2:
        raise ValueError(f"xy must have shape (T, K, C, 2), got {tuple(xy_t.shape)}")
    T, K, C, _ = xy_t.shape
    body = as_tensor(body_points, dt)
    if body.shape != (K, 3):
        raise ValueError(
            f"body_points must have shape ({K}, 3) for xy {tuple(xy_t.shape)}, "
            f"got {tuple(body.shape)}"
        )
    if cams.num_cameras != C:
        raise ValueError(f"xy has {C} cameras, cams has {cams.num_cameras}")
    w_t = torch.ones((T, K, C), dtype=dt) if weight is None else as_stored(weight, dt)
    if w_t.shape != (T, K, C):
        raise ValueError(f"weight must have shape ({T}, {K}, {C}), got {tuple(w_t.shape)}")
    cams = cams.to(dtype=dt)
    valid = torch.isfinite(xy_t).all(-1) & torch.isfinite(w_t) & (w_t > cfg.min_weight)
    xy0 = MaskedRows(xy_t, valid[..., None], dt)  # xy0[a:b]: one chunk's, made on demand
    base = MaskedRows(w_t, valid, dt)
    obs = observation if observation is not None else RigidObservation(body)
    # initialisation
    if init_poses is not None:
        p0 = as_tensor(init_poses, dt)
        if p0.shape != (T, 6):
            raise ValueError(f"init_poses must have shape ({T}, 6), got {tuple(p0.shape)}")
        p0 = torch.nan_to_num(p0)
        fitted = torch.ones(T, dtype=torch.bool)
    else:
        p0, fitted = initial_poses(
            xy0.full(), valid, cams, body, cfg.init, (cfg.kalman_accel_rad, cfg.kalman_accel_mm)
        )
    rho = cfg.rotation_scale_mm if cfg.rotation_scale_mm is not None else default_rho(body)
    grid = make_grid(body, cfg.grid_size) if cfg.constraint == "grid" else None
    focal = cams.focal

    trusted_t = None if trusted is None else torch.as_tensor(np.asarray(trusted, dtype=bool))
    if trusted_t is not None and trusted_t.shape != (T, K, C):
        raise ValueError(f"trusted must have shape ({T}, {K}, {C}), got {tuple(trusted_t.shape)}")

    def problem(a: int, b: int) -> Problem:
        pb = Problem(xy0[a:b], base[a:b], valid[a:b], cams, obs.window(a, b), cfg, rho, grid, focal)
        pb.trusted = None if trusted_t is None else trusted_t[a:b]
        return pb

    # chunks: cores [a, b) solved with `overlap` extra frames each side, the core kept
    ov = cfg.overlap
    if cfg.chunk_size and T > cfg.chunk_size + 2 * ov:
        cores = [(a, min(a + cfg.chunk_size, T)) for a in range(0, T, cfg.chunk_size)]
    else:
        cores = [(0, T)]
    poses = p0.clone()
    pose_cov = np.zeros((T, 6, 6), dtype=np.float32)  # float32: 144 B per frame, not 288
    histories, iters, conv, shares = [], 0, True, []
    for i, (a, b) in enumerate(cores):
        ea, eb = (max(0, a - ov), min(T, b + ov)) if len(cores) > 1 else (a, b)
        label = f"adjust chunk {i + 1}/{len(cores)}" if len(cores) > 1 else "adjust"
        out = _solve(p0[ea:eb].clone(), problem(ea, eb), progress, label)
        poses[a:b] = out["poses"][a - ea : b - ea]
        pose_cov[a:b] = out["cov"][a - ea : b - ea]
        histories.append(out["history"])
        iters = max(iters, out["iterations"])
        conv = conv and out["converged"]
        shares.append(out["share"])
        del out
        if len(cores) > 1:
            release_freed_memory()
    share = float(np.mean(shares)) if shares else 1.0
    # per-frame outputs, chunk by chunk (cache-friendly; neighbours for windowed models)
    # ... each chunk's core written into arrays of all frames (only those asked for)
    keep = set(RESULT_ARRAYS if outputs is None else outputs)
    unknown = keep - set(RESULT_ARRAYS)
    if unknown:
        raise ValueError(f"unknown outputs {sorted(unknown)} (known: {list(RESULT_ARRAYS)})")
    init_out = p0.detach().cpu().numpy().astype(np.float64) if "init_poses" in keep else None
    del p0  # not needed past the solve
    arrays: dict[str, np.ndarray] = {}
    for a, b in cores:
        ea, eb = (max(0, a - ov), min(T, b + ov)) if len(cores) > 1 else (a, b)
        out = _frame_outputs(poses[ea:eb], pose_cov[ea:eb], problem(ea, eb), share)
        if "point_sd" in keep:  # (T, K) mm: root of the trace of each point's covariance
            tr = np.trace(out["point_cov"], axis1=-2, axis2=-1)
            out["point_sd"] = np.sqrt(np.clip(tr, 0, None))
        for k, v in out.items():
            if k == "poses" or k in keep:
                if k not in arrays:
                    dtype = np.float32 if k in _FLOAT32_OUTPUTS else v.dtype
                    arrays[k] = np.empty((T, *v.shape[1:]), dtype=dtype)
                arrays[k][a:b] = v[a - ea : b - ea]
        del out
        if len(cores) > 1:
            release_freed_memory()
    return AdjustmentResult(
        pose_cov=pose_cov,
        fitted=fitted.cpu().numpy(),
        init_poses=init_out,
        iterations=iters,
        cost_history=histories,
        converged=conv,
        mixture_share=share,
        chunks=len(cores),
        **arrays,
    )


#: frames either side within which a rejected 3D observation must be the part's only one
#: for its two views to lose their trust (`isolated_pairs`)
ISOLATED = 2


def isolated_pairs(rejected: Tensor, trusted: Tensor) -> Tensor:
    """(T, K) bool: the 3D observations rejected (T, K) that no other rejection of the same part
    lies within ISOLATED frames of, made by exactly two trusted views (T, K, C)."""
    r = rejected.to(torch.bool)
    alone = torch.as_tensor(count_within(r.cpu().numpy(), ISOLATED) == 1, device=r.device)
    return r & alone & (trusted.sum(-1) == 2)


def _frame_outputs(poses: Tensor, pose_cov: np.ndarray, pb: Problem, share: float) -> dict:
    """Per-frame outputs at the final poses: residuals, weights, fused points, uncertainties."""
    cfg = pb.cfg
    dt = poses.dtype
    pb.obs.prepare(poses)
    pb.defvar = deformation_var(pb.obs, poses)
    lin = evaluate(poses, pb, jacobian=False)
    _, wmix, _ = irls_weights(lin, pb, share)
    e2 = torch.where(pb.valid, lin.e2, torch.zeros_like(lin.eu))
    rob = kernel_weight((e2 * wmix).sqrt(), cfg.robust, cfg.robust_scale)
    cov_t = torch.as_tensor(pose_cov, dtype=dt)
    if isinstance(pb.obs, RigidObservation):
        _, JX = pb.obs.rigid_points(poses)
    else:
        _, JX = pb.obs.points(poses, jacobian=True)
    model_cov = JX @ cov_t[:, None] @ JX.transpose(-1, -2)  # (T, K, 3, 3)
    eye = torch.eye(3, dtype=dt)
    dcov_fn = getattr(pb.obs, "deformation_cov", None)
    dcov = dcov_fn(poses) if dcov_fn is not None else None
    if dcov is None:  # the fixed stochastic model: one sigma_def for all parts, robust weights
        prior = model_cov + (cfg.sigma_def_mm**2 + 1e-6) * eye
        accepted = pb.valid
        w_fuse = pb.base * rob / cfg.sigma_det_px**2
        pts, pcov = fuse_points(
            lin.X, prior, pb.xy, w_fuse, pb.cams, cfg.fuse_iterations, pb.W6, pb.Wg
        )
    else:  # estimated: each part-frame's own prior, detections gated against it, to convergence
        prior0 = model_cov + dcov + 1e-6 * eye
        # calibrate the prior on the single detections (independent of it): per part inflation
        single = pb.valid & (pb.valid.sum(-1, keepdim=True) == 1)
        alpha = prior_inflation(lin.X, prior0, pb.xy, single, pb.cams, cfg.sigma_det_px)
        pb.inflation = alpha
        # ... applied where the part is predicted across a gap (no camera consensus in the frame)
        gap = torch.ones_like(single[..., 0]) if pb.trusted is None else ~pb.trusted.any(-1)
        infl = torch.where(gap, alpha[None, :], torch.ones_like(alpha)[None, :])  # (T, K)
        prior = prior0 * infl[..., None, None]
        # cameras that agree with each other outvote the prior: with a consensus, only its
        # views (two failing views need not agree: a correct one and a far outlier, or two
        # far outliers, fused, cost tens of mm)
        # ... unless the observation rejected their 3D point as contradicting its neighbours,
        # alone among the part's frames within ISOLATED frames, and only two views made it
        # (they agree along their epipolar line, one of them may be wrong; a third view would
        # have told; a run of rejections is the part moving fast, not a wrong view): then they
        # are gated against the prediction like any other view, and outvote it only if
        # neither passes
        trusted, rejected = pb.trusted, getattr(pb.obs, "outliers", None)
        if trusted is not None and rejected is not None and getattr(pb.obs, "gate_pairs", False):
            trusted = trusted & ~isolated_pairs(rejected, trusted)[..., None]
        accepted, _ = innovation_gate(
            lin.X, prior, pb.xy, pb.valid, pb.cams, cfg.sigma_det_px, agree=trusted
        )
        if trusted is not None:
            trusted = torch.where(accepted.any(-1, keepdim=True), trusted, pb.trusted)
            accepted = accepted | (trusted & pb.valid)
        w_fuse = accepted.to(dt) / cfg.sigma_det_px**2
        pts, pcov = fuse_points(lin.X, prior, pb.xy, w_fuse, pb.cams, 50, pb.W6, pb.Wg, tol=1e-4)
        rob = rob * accepted.to(dt)
    e = torch.stack((lin.eu, lin.ev), -1)
    res = torch.where(pb.valid[..., None], e, torch.full_like(e, float("nan")))
    inv_det = 1.0 / cfg.sigma_det_px**2
    poses_c = torch.cat((so3_log(so3_exp(poses[:, :3])), poses[:, 3:]), -1)

    def np_(x: Tensor) -> np.ndarray:
        return x.detach().cpu().numpy().astype(np.float64)

    return {
        "poses": np_(poses_c),
        "points": np_(pts),
        "point_cov": np_(pcov),
        "point_sigma": np_(torch.diagonal(pcov, dim1=-2, dim2=-1).clamp_min(0).sqrt()),
        "model_points": np_(lin.X),
        "model_sigma": np_(torch.diagonal(model_cov, dim1=-2, dim2=-1).clamp_min(0).sqrt()),
        "residuals": np_(res),
        "weights": np_(torch.where(pb.valid, wmix * rob / inv_det, torch.zeros_like(rob))),
        "ncams": accepted.sum(-1).cpu().numpy(),
        "observed": pb.valid.any(-1).any(-1).cpu().numpy(),
    }


def normal_matrix(
    poses: Tensor,
    xy: Tensor,
    weight: Tensor,
    cams: CameraTensors,
    body_points: Tensor,
    config: SolverConfig | None = None,
) -> np.ndarray:
    """The banded normal matrix (5, T, 6, 6) J^T W J at `poses` with the plain (non-robust,
    single-Gaussian) weights weight / sigma_det^2 and the track constraint: the Fisher
    information of the problem (for Cramer-Rao bounds and tests)."""
    cfg = (config if config is not None else SolverConfig()).resolved()
    dt = poses.dtype
    valid = torch.isfinite(xy).all(-1) & (weight > cfg.min_weight)
    base = torch.where(valid, weight, torch.zeros_like(weight))
    body = body_points.to(dt)
    rho = cfg.rotation_scale_mm if cfg.rotation_scale_mm is not None else default_rho(body)
    grid = make_grid(body, cfg.grid_size) if cfg.constraint == "grid" else None
    focal = cams.focal
    pb = Problem(
        torch.where(valid[..., None], xy, torch.zeros_like(xy)),
        base,
        valid,
        cams,
        RigidObservation(body),
        cfg,
        rho,
        grid,
        focal,
    )
    lin = evaluate(poses, pb, jacobian=True)
    blocks, _ = normal_equations(lin, base / cfg.sigma_det_px**2, pb)
    return blocks
