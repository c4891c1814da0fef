"""The pieces of one pose-track adjustment problem (`solver.py` runs the loop over them): the
problem's tensors (`Problem`), its residuals and derivatives at a set of poses
(`evaluate` -> `Linearisation`), the IRLS weights of the stochastic model (`irls_weights`), the
cost, and the block-banded normal equations (`normal_equations`).

Shapes: T frames, K parts, C cameras; poses (T, 6) Rodrigues vector + translation mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from adjust.camera import CameraTensors
from adjust.lsq import banded
from adjust.lsq.config import SolverConfig
from adjust.lsq.constraint import add_track_normal, track_residuals
from adjust.lsq.geometry import normal_blocks_3d, project_components, rotation_gemm_weights
from adjust.lsq.observation import ObservationModel
from adjust.lsq.robust import kernel_cost, kernel_weight, mixture_weights


class MaskedRows:
    """``x`` where ``mask``, else 0, made per block of frames on indexing (``[a:b]``) in
    ``dtype``: the problem's inputs without a full-length copy (x: (T, ...) as stored)."""

    def __init__(self, x: Tensor, mask: Tensor, dtype: torch.dtype) -> None:
        self.x, self.mask, self.dtype = x, mask, dtype

    def __getitem__(self, s: slice) -> Tensor:
        x = self.x[s].to(self.dtype, copy=True)  # one copy, zeroed in place (no temporaries)
        return x.masked_fill_(~self.mask[s], 0.0)

    def full(self) -> Tensor:
        """All frames in the stored dtype (float32 detections stay float32: the initialisation
        computes in the cameras' dtype, with the same result)."""
        return self.x.clone().masked_fill_(~self.mask, 0.0)


def as_stored(x, dtype: torch.dtype) -> Tensor:
    """Inputs as the caller stores them when that is float32 (converted per chunk), else in
    ``dtype``: float32 detections of a long session are not copied to float64 whole."""
    if isinstance(x, Tensor) and x.dtype == torch.float32:
        return x
    if not isinstance(x, Tensor) and np.asarray(x).dtype == np.float32:
        return as_tensor(x, torch.float32)
    return as_tensor(x, dtype)


@dataclass
class Problem:
    """One (chunk of the) adjustment problem in torch."""

    xy: Tensor  # (T, K, C, 2), zeros where not valid
    base: Tensor  # (T, K, C) detection weights, 0 where not valid
    valid: Tensor  # (T, K, C) bool
    cams: CameraTensors
    obs: ObservationModel
    cfg: SolverConfig
    rho: float
    grid: Tensor | None
    focal: Tensor  # (C,) px
    W6: Tensor | None = None  # (C 6, 9): camera-frame 3x3 (6 unique) -> world, summed over C
    Wg: Tensor | None = None  # (C 3, 3): camera-frame gradient -> world, summed over C
    defvar: Tensor | None = None  # (T, K) mm^2 per-part-frame deformation variance (per axis)
    trusted: Tensor | None = None  # (T, K, C) bool: views of a camera consensus (no gate)
    inflation: Tensor | None = None  # (K,) prior covariance inflation found by the fusion

    def __post_init__(self) -> None:
        self.xu, self.xv = self.xy[..., 0], self.xy[..., 1]
        if self.W6 is None:
            self.W6, self.Wg = rotation_gemm_weights(self.cams.R)

    @property
    def track_w(self) -> float:
        return (
            self.cfg.track_weight / self.cfg.track_sigma_mm**2
            if self.cfg.constraint != "none"
            else 0.0
        )


@dataclass
class Linearisation:
    """Residuals (and, with `jacobian`, derivatives) at one set of poses."""

    eu: Tensor  # (T, K, C) px, detection minus projection (garbage where not valid)
    ev: Tensor
    z: Tensor  # (T, K, C) depth mm
    r: Tensor  # (R, m) track residuals
    X: Tensor  # (T, K, 3)
    A: tuple[Tensor, ...] | None = None  # d(u, v)/dX_cam entries, (T, K, C) each
    JX: Tensor | None = None  # (T, K, 3, 6)
    poses: Tensor | None = None  # (T, 6) where linearised
    wr: Tensor | None = None  # (T, K, 3) mm, the world prior minus the model point
    winfo: Tensor | None = None  # (T, K) mm^-2 its information per axis (0: none)

    @property
    def e2(self) -> Tensor:
        return self.eu * self.eu + self.ev * self.ev


def evaluate(poses: Tensor, pb: Problem, jacobian: bool) -> Linearisation:
    X, JX = pb.obs.points(poses, jacobian=jacobian)
    u, v, z, A = project_components(X, pb.cams, jacobian)
    eu = pb.xu - u
    ev = pb.xv - v
    if pb.cfg.constraint == "none":
        r = poses.new_zeros((0, 6))
    elif jacobian:  # computed with the normal equations (`normal_equations`)
        r = None
    else:
        r, _ = track_residuals(poses, pb.cfg.constraint, rho=pb.rho, grid=pb.grid, jacobian=False)
    wr = winfo = None
    prior = getattr(pb.obs, "world_prior", None)
    prior = prior(poses) if callable(prior) else None
    if prior is not None:  # the parts no camera pair sees, held near their world neighbours
        W, winfo = prior
        wr = W - X
    return Linearisation(eu, ev, z, r, X, A, JX, poses, wr, winfo)


def deformation_var(obs: ObservationModel, poses: Tensor) -> Tensor | None:
    """(T, K) mean per-axis deformation variance (mm^2) the observation model states for each
    part-frame (trace / 3 of its `deformation_cov`), or None (then the solver's fixed
    ``sigma_def_mm`` mixture applies)."""
    fn = getattr(obs, "deformation_cov", None)
    cov = fn(poses) if fn is not None else None
    if cov is None:
        return None
    return torch.diagonal(cov, dim1=-2, dim2=-1).sum(-1) / 3.0


def irls_weights(lin: Linearisation, pb: Problem, share: float) -> tuple[Tensor, Tensor, float]:
    """IRLS weights (T, K, C) px^-2, the stochastic model's inverse variances (T, K, C), the
    new mixture share.

    With a per-part-frame deformation variance from the observation model (`pb.defvar`,
    estimated from the data) each detection's variance is sigma_det^2 + (sigma_def f / z)^2
    (its own part's deformation projected to px); otherwise the two-Gaussian mixture of
    sigma_det and the solver's single sigma_def_mm (EM responsibilities). Then the robust kernel.
    """
    cfg = pb.cfg
    e2 = torch.where(pb.valid, lin.e2, torch.zeros_like(lin.eu))
    if pb.defvar is not None:
        s2 = (
            cfg.sigma_det_px**2
            + pb.defvar[..., None] * (pb.focal / lin.z.abs().clamp_min(1e-6)) ** 2
        )
        wmix = 1.0 / s2
        u = (e2 * wmix).sqrt()
        w = pb.base * wmix * kernel_weight(u, cfg.robust, cfg.robust_scale)
        return w, wmix, 1.0
    sdef = None
    if cfg.sigma_def_mm > 0:
        sdef = cfg.sigma_def_mm * pb.focal / lin.z.abs().clamp_min(1e-6)
    wmix, _, share = mixture_weights(e2, pb.base, cfg.sigma_det_px, sdef, share)
    u = (e2 * wmix).sqrt()
    w = pb.base * wmix * kernel_weight(u, cfg.robust, cfg.robust_scale)  # 0 where not valid
    return w, wmix, share


def total_cost(lin: Linearisation, pb: Problem, wmix: Tensor) -> float:
    e2 = torch.where(pb.valid, lin.e2, torch.zeros_like(lin.eu))
    c = (pb.base * kernel_cost(e2 * wmix, pb.cfg.robust, pb.cfg.robust_scale)).sum()
    if lin.wr is not None:
        c = c + 0.5 * (lin.winfo * (lin.wr * lin.wr).sum(-1)).sum()
    return float(c) + 0.5 * pb.track_w * float((lin.r * lin.r).sum())


def normal_equations(lin: Linearisation, w: Tensor, pb: Problem) -> tuple[np.ndarray, np.ndarray]:
    """Banded normal matrix (5, T, 6, 6) and right-hand side (T, 6) of the weighted GN step."""
    T, K, C = lin.eu.shape
    Hx, gx = normal_blocks_3d(lin.A, lin.eu, lin.ev, w, pb.W6, pb.Wg)
    if lin.wr is not None:  # the world prior: information winfo I on each model point
        Hx = Hx + lin.winfo[..., None, None] * torch.eye(3, dtype=Hx.dtype, device=Hx.device)
        gx = gx + lin.winfo[..., None] * lin.wr
    Hx = Hx.reshape(T * K, 3, 3)
    gx = gx.reshape(T, K * 3, 1)
    JX = lin.JX.reshape(T * K, 3, 6)
    HJ = torch.bmm(Hx, JX).reshape(T, K * 3, 6)
    JXt = lin.JX.reshape(T, K * 3, 6).transpose(1, 2)
    H = torch.bmm(JXt, HJ)  # (T, 6, 6)
    g = torch.bmm(JXt, gx)[..., 0]
    blocks = banded.zeros(T)
    banded.add_diagonal(blocks, H)
    g = g.detach().cpu().numpy().astype(np.float64)
    if pb.cfg.constraint != "none":
        lin.r = add_track_normal(
            blocks, g, lin.poses, pb.cfg.constraint, pb.track_w, rho=pb.rho, grid=pb.grid
        )
    return blocks, g


def as_tensor(x, dtype: torch.dtype) -> Tensor:
    if isinstance(x, Tensor):
        return x.to(dtype)
    arr = np.asarray(x)
    if not arr.flags.writeable:  # e.g. BodyModel.points (read-only): copy, torch needs writable
        arr = arr.copy()
    return torch.as_tensor(arr, dtype=dtype)
