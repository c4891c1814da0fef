"""Pluggable observation functions: the 3D body-part positions X_i(p_t) the cameras observe.

An observation model maps the poses (T, 6) to global part positions (T, K, 3) and their
Jacobian w.r.t. the left increment of each frame's *own* pose, (T, K, 3, 6). Models whose
points depend on neighbouring frames too (the learned deformation, which reads a window of
rigid positions around t) hold the neighbours' inputs fixed per outer iteration: `prepare` is
called with the current poses at the start of every Gauss-Newton iteration, so the normal
equations keep their block-banded structure and the deformation is re-evaluated as the poses
converge (a fixed-point / block-Jacobi treatment of the cross-frame coupling).

The models (the tracker, `adjust.deformation_modes`, only picks one):
- `RigidObservation`: the rigid body moved by the pose (eq. 4), optionally with each part's
  estimated deformation variance;
- `InterpObservation` (``deformation=interp``): plus each part's body-frame offset interpolated
  from its own 3D observations in the neighbouring frames;
- `DeformableObservation`: the learned net (eq. 11) with its own predictions fed back as the
  window's deformed inputs;
- `NetObservation` (``deformation=CKPT``): the learned net with the measured (triangulated,
  gated) parts as its deformed inputs, a frozen or finite-difference Jacobian, and its
  deformation variance estimated from its held-out error.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from adjust.lsq.geometry import retract, rigid_points, so3_exp
from adjust.lsq.stochastic import OffsetCovariance, krige_offsets
from deformnet.so3 import skew
from deformnet.threads import torch_threads


@runtime_checkable
class ObservationModel(Protocol):
    """What the solver needs from an observation function."""

    @property
    def num_parts(self) -> int: ...

    def prepare(self, poses: Tensor) -> None:
        """Called with the current poses (T, 6) at the start of every outer iteration."""

    def points(self, poses: Tensor, jacobian: bool = True) -> tuple[Tensor, Tensor | None]:
        """poses (T, 6) -> X (T, K, 3) global mm and, if asked, dX/d(delta_t) (T, K, 3, 6)."""

    def rigid_points(self, poses: Tensor) -> tuple[Tensor, Tensor]:
        """The rigid model's points (T, K, 3) and Jacobian (T, K, 3, 6) (for fusion/uncertainty)."""

    def window(self, start: int, stop: int) -> ObservationModel:
        """The same model for frames start..stop-1 (chunked solving)."""


def _rotate_axes_var(R: Tensor, var: Tensor) -> Tensor:
    """Body-axis variances var (T, K, 3) -> global covariances R diag(var) R^T (T, K, 3, 3)."""
    return torch.einsum("tij,tkj,tlj->tkil", R, var, R)


def _body_frame_points(poses: Tensor, M: Tensor, jacobian: bool) -> tuple[Tensor, Tensor | None]:
    """Points held in each frame's body coordinates, M (T, K, 3), moved by the poses (T, 6):
    X = R M + tau, and the Jacobian w.r.t. the frame's left increment [-[R M]_x, I]
    (T, K, 3, 6) (the prediction held fixed: a rigid point's Jacobian)."""
    a = torch.einsum("tij,tkj->tki", so3_exp(poses[:, :3]), M.to(poses.dtype))
    X = a + poses[:, None, 3:]
    if not jacobian:
        return X, None
    eye = torch.eye(3, dtype=X.dtype, device=X.device).expand(*a.shape[:-1], 3, 3)
    return X, torch.cat((-skew(a), eye), -1)


class RigidObservation:
    """The rigid body model moved by the pose (paper eq. 4): X_i = R(r_t) X_i^m + tau_t.

    ``var_mm2`` (K, 3), optional: the parts' deformation second moments per body axis (mm^2),
    i.e. how far each part strays from its rigid point (estimated from the data by
    `adjust.lsq.stochastic`); then the solver weights each detection by its own part's
    deformation and the fusion uses it as the prior (`deformation_cov`). Without it the solver
    uses its single ``sigma_def_mm`` for every part.
    """

    def __init__(self, body_points: Tensor, var_mm2: Tensor | None = None) -> None:
        if body_points.dim() != 2 or body_points.shape[-1] != 3:
            raise ValueError(f"body_points must have shape (K, 3), got {tuple(body_points.shape)}")
        if var_mm2 is not None and tuple(var_mm2.shape) != (body_points.shape[0], 3):
            raise ValueError(f"var_mm2 must be (K, 3), got {tuple(var_mm2.shape)}")
        self.body = body_points
        self.var = var_mm2

    def deformation_cov(self, poses: Tensor) -> Tensor | None:
        """(T, K, 3, 3) global covariance of the parts about the model points, or None."""
        if self.var is None:
            return None
        R = so3_exp(poses[:, :3])
        v = self.var.to(poses.dtype).expand(poses.shape[0], -1, -1)
        return _rotate_axes_var(R, v)

    @property
    def num_parts(self) -> int:
        return self.body.shape[0]

    def prepare(self, poses: Tensor) -> None:  # nothing depends on other frames
        return None

    def points(self, poses: Tensor, jacobian: bool = True) -> tuple[Tensor, Tensor | None]:
        X, J = self.rigid_points(poses)
        return X, (J if jacobian else None)

    def rigid_points(self, poses: Tensor) -> tuple[Tensor, Tensor]:
        return rigid_points(poses, self.body.to(poses.dtype))

    def window(self, start: int, stop: int) -> RigidObservation:
        return self


class InterpObservation:
    """``deformation=interp``: the rigid model plus each part's offset in body coordinates
    predicted from the part's own observations in the neighbouring frames.

    data (T, K, 3) global mm: the parts triangulated from >= 2 cameras (gated against
    mis-detections), observed (T, K) bool where they are; noise_var (T, K) mm^2 their
    triangulation variance per axis (trace / 3 of the covariance), or None. At every
    `prepare` (each outer iteration, with the current poses) the offsets
    o_t = R_t^T (X_t - tau_t) - B are formed, their covariance in time is estimated
    (`adjust.lsq.stochastic.OffsetCovariance`: mean, per-part deformation variance, nugget,
    semivariogram), observations their neighbours contradict are dropped, and each
    part-frame's offset is interpolated from the previous and next observed frame, excluding
    the frame itself, with the variance the semivariogram gives (`krige_offsets`). The
    model point is X_t = R_t (B + o_hat_t) + tau_t, its Jacobian the rigid-point one with the
    prediction held fixed (as the net's "frozen" Jacobian), and `deformation_cov` the kriging
    variance rotated to global coordinates: on a gap the interpolation across it, on an
    observed frame an independent prediction to fuse with the frame's own detections.

    few_var (K, 3) mm^2, optional: the spread of parts with too few 3D observations to
    estimate it (e.g. placed from their single views, `adjust.body_fit.refine_body`; NaN: unknown).
    measured_var (K, 3) mm^2, optional: then a part-frame with its own 3D observation takes
    the rigid model point with this variance (the shape prior) instead of the prediction from
    its neighbours (`deformation=self` chooses between the two by held-out cameras,
    `adjust.validate.choose_measured_prior`).
    """

    def __init__(
        self,
        body_points: Tensor,
        data: Tensor,
        observed: Tensor,
        noise_var: Tensor | None = None,
        few_var: Tensor | None = None,
        measured_var: Tensor | None = None,
    ) -> None:
        self.rigid = RigidObservation(body_points)
        T, K = observed.shape
        if tuple(data.shape) != (T, K, 3) or K != body_points.shape[0]:
            raise ValueError(
                f"data must be (T, K, 3) for observed {tuple(observed.shape)} and "
                f"{body_points.shape[0]} body points, got {tuple(data.shape)}"
            )
        if noise_var is not None and tuple(noise_var.shape) != (T, K):
            raise ValueError(f"noise_var must be (T, K), got {tuple(noise_var.shape)}")
        self.data = torch.nan_to_num(data)
        self.observed = observed & torch.isfinite(data).all(-1)
        self.noise_var = noise_var
        if few_var is not None and tuple(few_var.shape) != (K, 3):
            raise ValueError(f"few_var must be ({K}, 3), got {tuple(few_var.shape)}")
        self.few_var = few_var
        self.cov = None  # the last OffsetCovariance
        self.outlier_rounds = 2
        self.outliers = None  # (T, K) observations rejected as contradicting their neighbours
        self.neighbours = None  # (T, K, 3) body-frame prediction from the neighbouring frames
        self._M: Tensor | None = None  # (T, K, 3) body-frame model points
        self._var: Tensor | None = None  # (T, K, 3) body-axis variances
        self.set_measured_var(measured_var)

    @property
    def num_parts(self) -> int:
        return self.rigid.num_parts

    @property
    def body(self) -> Tensor:
        return self.rigid.body

    def prepare(self, poses: Tensor) -> None:
        import numpy as np

        R = so3_exp(poses[:, :3]).detach()
        Rn = R.cpu().numpy().astype(np.float64)
        tn = poses[:, 3:].detach().cpu().numpy().astype(np.float64)
        X = self.data.cpu().numpy().astype(np.float64)
        m = self.observed.cpu().numpy()
        B = self.body.cpu().numpy().astype(np.float64)
        o = np.einsum("tji,tkj->tki", Rn, X - tn[:, None, :]) - B[None]
        nugget = None
        if self.noise_var is not None and m.any():  # per part: the mean over its observations
            nv = self.noise_var.cpu().numpy().astype(np.float64)
            per = np.where(m, nv, 0.0).sum(0) / np.maximum(m.sum(0), 1)
            nugget = np.repeat(per[:, None], 3, axis=1)
        # robust: an observation its own neighbours contradict (chi-square, 3 dof, p = 0.001)
        # is a mis-detection, not deformation; re-estimate without it
        few = None if self.few_var is None else self.few_var.cpu().numpy().astype(np.float64)
        good = m
        for _ in range(self.outlier_rounds + 1):
            self.cov = OffsetCovariance.estimate(o, good, nugget=nugget, few_var=few)
            pred, var = krige_offsets(o, good, self.cov, skip_self=True)
            if _ == self.outlier_rounds:
                break
            d2 = ((o - pred) ** 2 / (var + self.cov.nugget[None])).sum(-1)
            new = m & ~(d2 > 16.3)
            if (new == good).all():
                break
            good = new
        self.outliers = torch.as_tensor(m & ~good)
        dt = poses.dtype
        # the neighbours' prediction, also where the rigid point replaces it (diagnostics)
        self.neighbours = torch.as_tensor(B[None] + pred, dtype=dt, device=poses.device)
        if self.measured_var is not None:  # measured part-frames: the rigid model point
            mv = self.measured_var.cpu().numpy().astype(np.float64)
            pred = np.where(good[..., None], 0.0, pred)
            var = np.where(good[..., None], mv[None], var)
        self._M = torch.as_tensor(B[None] + pred, dtype=dt, device=poses.device)
        self._var = torch.as_tensor(var, dtype=dt, device=poses.device)

    def set_measured_var(self, measured_var: Tensor | None) -> None:
        """Switch the measured part-frames' prior: the rigid model point with this (K, 3)
        variance, or (None) the neighbours' prediction; predicted afresh at the next use."""
        if measured_var is not None and tuple(measured_var.shape) != (self.num_parts, 3):
            raise ValueError(
                f"measured_var must be ({self.num_parts}, 3), got {tuple(measured_var.shape)}"
            )
        self.measured_var = measured_var
        self._M = None

    def _ready(self, poses: Tensor) -> None:
        if self._M is None or self._M.shape[0] != poses.shape[0]:
            self.prepare(poses)

    def points(self, poses: Tensor, jacobian: bool = True) -> tuple[Tensor, Tensor | None]:
        self._ready(poses)
        return _body_frame_points(poses, self._M, jacobian)

    def deformation_cov(self, poses: Tensor) -> Tensor:
        self._ready(poses)
        return _rotate_axes_var(so3_exp(poses[:, :3]), self._var.to(poses.dtype))

    def rigid_points(self, poses: Tensor) -> tuple[Tensor, Tensor]:
        return self.rigid.rigid_points(poses)

    def window(self, start: int, stop: int) -> InterpObservation:
        if start == 0 and stop == self.observed.shape[0]:
            return self
        nc = None if self.noise_var is None else self.noise_var[start:stop]
        return InterpObservation(
            self.body,
            self.data[start:stop],
            self.observed[start:stop],
            nc,
            self.few_var,
            self.measured_var,
        )


class DeformableObservation:
    """The learned deformation on top of the rigid model (paper: deep-learned body deformation).

    `model` follows the `DeformationModel` contract: ``model(rigid (B, W, K, 3), deformed
    (B, W, K, 3), observed (B, W, K) bool) -> (B, K, 3)`` global mm for the window's mid frame
    (W = 2n + 1). Per outer iteration (`prepare`) the window inputs of every frame are rebuilt
    from the current poses (rigid positions; `deformed` = current predictions, `observed` from
    the detections); within the iteration only the mid frame's own rigid input moves with p_t,
    and the Jacobian dX_t/d(delta_t) is taken by batched reverse-mode autograd through the
    model (three backward passes: one per output coordinate, summed over independent frames,
    since the mid-frame output depends only on its own frame's increment).
    """

    def __init__(
        self,
        model: torch.nn.Module,
        body_points: Tensor,
        window: int,
        observed: Tensor | None = None,
        batch_size: int = 4096,
        step: int = 1,
    ) -> None:
        if window < 1 or window % 2 != 1:
            raise ValueError(f"window must be odd and >= 1, got {window}")
        if int(step) < 1:
            raise ValueError(f"step must be >= 1, got {step}")
        self.step = int(step)  # frames between the window's tokens
        self.model = model
        self.rigid = RigidObservation(body_points)
        self.W = int(window)
        self.observed = observed  # (T, K) bool or None (= all observed)
        self.batch_size = int(batch_size)
        self._rigid_win: Tensor | None = None
        self._deformed_win: Tensor | None = None
        self._observed_win: Tensor | None = None

    @property
    def num_parts(self) -> int:
        return self.rigid.num_parts

    def _index(self, frames: Tensor, T: int, step: int | None = None) -> tuple[Tensor, Tensor]:
        """Frame indices (F, W) of the windows around ``frames`` (F,) of a T-frame sequence at a
        token step (None: ``self.step``), clamped to it (edge frames repeated), and (F, W)
        whether each is a real frame."""
        n = self.W // 2
        idx = frames[:, None] + (self.step if step is None else step) * torch.arange(-n, n + 1)
        real = (idx >= 0) & (idx < T)
        return idx.clamp(0, T - 1), real

    def _model_dtype(self, like: Tensor) -> torch.dtype:
        return next(self.model.parameters(), torch.empty(0, dtype=like.dtype)).dtype

    def _windows(self, X: Tensor) -> Tensor:
        """(T, K, 3) -> (T, W, K, 3) windows, edge frames repeated at the sequence ends."""
        T = X.shape[0]
        return X[self._index(torch.arange(T), T)[0]]

    def prepare(self, poses: Tensor) -> None:
        Xr, _ = self.rigid.rigid_points(poses)
        self._rigid_win = self._windows(Xr.detach())
        if self._deformed_win is None or self._deformed_win.shape[0] != poses.shape[0]:
            self._deformed_win = self._rigid_win.clone()
        T, K = Xr.shape[:2]
        obs = self.observed if self.observed is not None else torch.ones(T, K, dtype=torch.bool)
        self._observed_win = self._windows(obs[..., None].to(torch.float32))[..., 0] > 0.5
        with torch.no_grad():
            Xd, _ = self.points(poses, jacobian=False)
        self._deformed_win = self._windows(Xd.detach())

    def points(self, poses: Tensor, jacobian: bool = True) -> tuple[Tensor, Tensor | None]:
        if self._rigid_win is None or self._rigid_win.shape[0] != poses.shape[0]:
            self.prepare(poses)
        if jacobian:
            return self._part_jacobian(poses)
        return self._forward(poses), None

    def _forward(self, poses: Tensor) -> Tensor:
        """The net's mid-frame prediction (T, K, 3) for the poses (T, 6), no gradient, batched."""
        n = self.W // 2
        outs = []
        with torch.no_grad():
            for s in range(0, poses.shape[0], self.batch_size):
                e = min(poses.shape[0], s + self.batch_size)
                Xmid, _ = self.rigid.rigid_points(poses[s:e])
                outs.append(self._model(Xmid, s, e, n).to(poses.dtype))
        return torch.cat(outs, 0) if outs else poses.new_zeros((0, self.num_parts, 3))

    def _model(self, Xmid: Tensor, s: int, e: int, n: int) -> Tensor:
        rw = self._rigid_win[s:e].clone()
        rw[:, n] = Xmid
        mdt = self._model_dtype(Xmid)
        return self.model(rw.to(mdt), self._deformed_win[s:e].to(mdt), self._observed_win[s:e])

    def _part_jacobian(self, poses: Tensor) -> tuple[Tensor, Tensor]:
        """X (T, K, 3) and dX_t,k / d delta_t (T, K, 3, 6) by batched reverse mode.

        Frames are independent given the fixed neighbour inputs, so one backward pass per
        (part, coordinate) of the output summed over frames gives every frame's row at once.
        """
        n = self.W // 2
        T, K = poses.shape[0], self.num_parts
        X = poses.new_zeros((T, K, 3))
        J = poses.new_zeros((T, K, 3, 6))
        for s in range(0, T, self.batch_size):
            e = min(T, s + self.batch_size)
            delta = torch.zeros_like(poses[s:e], requires_grad=True)
            with torch.enable_grad():
                Xmid, _ = self.rigid.rigid_points(retract(poses[s:e].detach(), delta))
                out = self._model(Xmid, s, e, n)
                X[s:e] = out.detach().to(poses.dtype)
                for k in range(K):
                    for i in range(3):
                        (g,) = torch.autograd.grad(out[:, k, i].sum(), delta, retain_graph=True)
                        J[s:e, k, i] = g.to(poses.dtype)
        return X, J

    def rigid_points(self, poses: Tensor) -> tuple[Tensor, Tensor]:
        return self.rigid.rigid_points(poses)

    def window(self, start: int, stop: int) -> DeformableObservation:
        obs = None if self.observed is None else self.observed[start:stop]
        return DeformableObservation(
            self.model, self.rigid.body, self.W, obs, self.batch_size, self.step
        )


#: finite-difference steps of the deformable Jacobian: rotation (rad), translation (mm)
FD_STEP = {"forward": (1e-6, 1e-4), "central": (1e-5, 1e-3)}  # (rad, mm) steps
JACOBIANS = ("frozen", *FD_STEP)


def _both_sides(observed_win: Tensor) -> Tensor:
    """(F, W, K) observed flags of windows -> (F, K): the part is seen both before and after
    the mid frame (the window reaches it)."""
    n = observed_win.shape[1] // 2
    return observed_win[:, :n].any(1) & observed_win[:, n + 1 :].any(1)


class NetObservation(DeformableObservation):
    """``deformation=CKPT|self|default``: the learned net inside the observation function, a
    `DeformableObservation` whose ``deformed`` window inputs are measurements.

    The net was trained with the observed tokens' deformed halves being the measured part
    positions. Here they are the parts triangulated from the detections, ``data (T, K, 3)``
    with ``observed (T, K)``; a measurement farther than ``gate_mm`` from the current rigid
    model point (a mis-detection) is treated as unobserved.

    Cost: the net runs once per `prepare` (each outer iteration), for at most ``refresh``
    iterations; its prediction is kept in each frame's body coordinates,
    M_t = R_t^T (X_t - tau_t), so the model point between net passes is R_t M_t + tau_t (as
    `InterpObservation`'s) and after the last refresh the prediction is held while the poses
    converge (the poses start from the rigid/interp adjustment; they move little).

    Where the net's prediction is used: on the part-frames without a measurement of their
    own (occluded, or a mis-detection), where the net beats the interpolation. A measured
    part-frame's model point, which is fused with its own detections, is
    ``deformation=interp``'s prediction from the neighbouring frames (``measured="interp"``,
    default; ``"net"``: the net there too): across a one-frame hole the kriging is the more
    accurate of the two (`factor`, below, measures it on every run). A window reaches only
    ``half_window`` frames to each side; ``beyond_window="interp"`` (default): a part-frame
    whose window holds no observation of the part on one side of the mid frame takes the
    interpolation's prediction too (kriged across the whole gap, `InterpObservation`);
    ``"net"``: the net there as well. ``net_parts`` (K,) bool: only those parts take the net's
    prediction, the others interp's everywhere (`adjust-track`'s held-out check,
    ``deform.require_better``; None: every part). `use_net` (T, K) says where the net was used.

    `deformation_cov`: the interpolation's kriging variance (how uncertainty grows with the
    distance to the part's observations; conservative for the net in gaps, where it is the
    better predictor). `factor` (K,): the net's held-out mean-square error over the
    interpolation's on the measured part-frames (the net never sees the mid frame's
    measurement; the kriging skips it too); with ``measured="net"`` it scales the variance
    there.
    """

    def __init__(
        self,
        model,
        body_points,
        window,
        data,
        observed,
        gate_mm,
        batch_size,
        jacobian,
        noise_var: Tensor | None = None,
        refresh: int = 2,
        beyond_window: str = "interp",
        measured: str = "interp",
        threads: int | None = None,
        few_var: Tensor | None = None,
        measured_var: Tensor | None = None,
        step: int = 1,
        far_steps: tuple[int, ...] = (),
        net_parts: Tensor | None = None,
    ):
        super().__init__(model, body_points, window, observed, batch_size, step)
        K = observed.shape[-1]
        if net_parts is not None and tuple(net_parts.shape) != (K,):
            raise ValueError(f"net_parts must be ({K},) bool, got {tuple(net_parts.shape)}")
        # (K,) bool: the parts whose predictions may come from the net (None: all)
        self.net_parts = None if net_parts is None else net_parts.to(torch.bool)
        self.far_steps = tuple(sorted(int(s) for s in far_steps if int(s) > self.step))
        if self.far_steps and jacobian != "frozen":
            raise ValueError("deform.far_steps needs deform.jacobian=frozen")
        self.step_used: Tensor | None = None  # (T, K) token step of the net's prediction (0: none)
        self.threads = threads  # torch threads for the net's passes (None: unchanged)
        if measured not in ("interp", "net"):
            raise ValueError(f"deform.measured must be interp or net, got {measured!r}")
        self.measured = measured
        self.use_net: Tensor | None = None  # (T, K) where the net's prediction is the model
        if jacobian not in JACOBIANS:
            raise ValueError(f"deform.jacobian must be one of {list(JACOBIANS)}, got {jacobian!r}")
        if beyond_window not in ("interp", "net"):
            raise ValueError(f"deform.beyond_window must be interp or net, got {beyond_window!r}")
        if int(refresh) < 1:
            raise ValueError(f"deform.refresh must be >= 1, got {refresh}")
        self.data = data
        self.gate_mm = float(gate_mm)
        self.jacobian = jacobian
        self.noise_var = noise_var
        self.refresh = int(refresh)
        self.beyond_window = beyond_window
        self.few_var = few_var
        self.interp = InterpObservation(
            body_points, data, observed, noise_var, few_var, measured_var
        )
        self.evaluations = 0  # net passes over the whole sequence so far
        self.factor: Tensor | None = None  # (K,) net / interp held-out mean-square error
        self.reach: Tensor | None = None  # (T, K) the window sees the part on both sides
        self._M: Tensor | None = None  # (T, K, 3) body-frame model points
        self._var: Tensor | None = None  # (T, K, 3) body-axis variances

    def _net_inputs(self, poses: Tensor) -> None:
        Xr, _ = self.rigid.rigid_points(poses)
        Xr = Xr.detach()
        data = self.data.to(Xr.dtype)
        obs = self.observed & torch.isfinite(data).all(-1)
        if self.gate_mm > 0:
            obs = obs & ((data - Xr).norm(dim=-1) <= self.gate_mm)
        self._rigid_win = self._windows(Xr)
        self._deformed_win = self._windows(torch.where(obs[..., None], data, Xr))
        self._observed_win = self._windows(obs[..., None].to(Xr.dtype))[..., 0] > 0.5
        # edge frames are repeated by _windows: count only real neighbours on each side
        T = obs.shape[0]
        real = self._index(torch.arange(T), T)[1]
        self.reach = _both_sides(self._observed_win & real[..., None])
        self._inputs = (Xr, torch.where(obs[..., None], data, Xr), obs)

    def _far(self, X: Tensor) -> Tensor:
        """Predictions (T, K, 3) where the window at ``step`` does not see the part on both
        sides but a wider one (``far_steps``: every s-th frame, the same number of tokens)
        does; `reach` and `step_used` updated. Runs the net on those frames only."""
        Xr, D, obs = self._inputs
        T = Xr.shape[0]
        reach = self.reach.clone()
        used = torch.where(reach, self.step, 0)
        X = X.clone()
        mdt = self._model_dtype(Xr)
        with torch.no_grad():
            for s in self.far_steps:
                frames = (~reach).any(1).nonzero().flatten()
                if frames.numel() == 0:
                    break
                for chunk in frames.split(self.batch_size):
                    idx, real = self._index(chunk, T, s)
                    ow = obs[idx] & real[..., None]
                    take = _both_sides(ow) & ~reach[chunk]
                    if not bool(take.any()):
                        continue
                    pred = self.model(Xr[idx].to(mdt), D[idx].to(mdt), ow).to(X.dtype)
                    X[chunk] = torch.where(take[..., None], pred, X[chunk])
                    reach[chunk] = reach[chunk] | take
                    used[chunk] = torch.where(take, s, used[chunk])
        self.reach, self.step_used = reach, used
        return X

    def prepare(self, poses: Tensor) -> None:
        same = self._M is not None and self._M.shape[0] == poses.shape[0]
        if same and self.jacobian == "frozen" and self.evaluations >= self.refresh:
            return  # the prediction is held in body coordinates from here on

        self._net_inputs(poses)
        self.interp.prepare(poses)
        with torch_threads(self.threads):
            X = self._far(self._forward(poses))
        self.evaluations += 1
        R = so3_exp(poses[:, :3]).detach()
        M = torch.einsum("tji,tkj->tki", R, X - poses[:, None, 3:].detach())
        Mi = self.interp._M.to(M.dtype)
        # held-out errors on the measured part-frames (the net's and the kriging's)
        data = self.data.to(M.dtype)
        m = self.interp.observed & ~self.interp.outliers.to(torch.bool)
        d_net = ((data - X) ** 2).sum(-1)
        Mn = self.interp.neighbours.to(M.dtype)  # the kriging, not the rigid point
        Xi = torch.einsum("tij,tkj->tki", R, Mn) + poses[:, None, 3:].detach()
        d_int = ((data - Xi) ** 2).sum(-1)
        num = torch.where(m, d_net, torch.zeros_like(d_net)).sum(0)
        den = torch.where(m, d_int, torch.zeros_like(d_int)).sum(0)
        factor = torch.where(m.sum(0) >= 10, num / den.clamp_min(1e-9), torch.ones_like(num))
        self.factor = factor.clamp(0.25, 4.0)
        use = torch.ones_like(m)
        if self.measured == "interp":
            use = use & ~m
        if self.beyond_window == "interp":
            use = use & self.reach.to(m.device)
        if self.net_parts is not None:
            use = use & self.net_parts.to(m.device)[None, :]
        self.use_net = use
        use = use[..., None]
        M = torch.where(use, M, Mi)
        var = self.interp._var.to(M.dtype)
        if self.measured == "net":  # the net's own held-out error where it is used there
            var = torch.where(m[..., None], var * self.factor[None, :, None], var)
        self._M, self._var = M, var

    def set_measured_var(self, measured_var: Tensor | None) -> None:
        """`InterpObservation.set_measured_var` for the measured part-frames (the net does
        not predict them); the next use predicts afresh, the net's pass included."""
        self.interp.set_measured_var(measured_var)
        self._M = None

    def _ready(self, poses: Tensor) -> None:
        if self._M is None or self._M.shape[0] != poses.shape[0]:
            self.prepare(poses)

    def deformation_cov(self, poses: Tensor) -> Tensor:
        """(T, K, 3, 3) global covariance of the parts about the model points."""
        self._ready(poses)
        return _rotate_axes_var(so3_exp(poses[:, :3]), self._var.to(poses.dtype))

    def points(self, poses: Tensor, jacobian: bool = True):
        """X (T, K, 3) and, if asked, dX_t/d(delta_t) (T, K, 3, 6).

        ``jacobian="frozen"`` (default): the prediction in the frame's own body coordinates
        is held fixed between net passes, so dX_t/d(delta_t) = [-[X_t - tau_t]_x, I] as for
        a rigid point; it neglects how the prediction changes with the frame's pose relative
        to its fixed neighbours (a Gauss-Newton with that approximate Jacobian).
        ``"forward"`` / ``"central"``: the net is evaluated at every call and the full
        Jacobian taken by finite differences through it; frames are independent given the
        fixed neighbour inputs, so one batched forward pass per perturbed pose component
        gives every frame's column at once (6 or 12 passes)."""
        self._ready(poses)
        if self.jacobian == "frozen":
            return _body_frame_points(poses, self._M, jacobian)
        X = self._forward(poses)
        Xi, Ji = self.interp.points(poses, jacobian)
        use = self.use_net[..., None]
        X = torch.where(use, X, Xi)
        if not jacobian:
            return X, None
        J = poses.new_zeros((*X.shape, 6))
        for j in range(6):
            h = FD_STEP[self.jacobian][j // 3]
            d = torch.zeros_like(poses)
            d[:, j] = h
            Xp = self._forward(retract(poses, d))
            if self.jacobian == "central":
                J[..., j] = (Xp - self._forward(retract(poses, -d))) / (2 * h)
            else:
                J[..., j] = (Xp - X) / h
        J = torch.where(use[..., None], J, Ji)
        return X, J

    def window(self, start: int, stop: int):
        if start == 0 and stop == self.observed.shape[0]:
            return self
        nv = None if self.noise_var is None else self.noise_var[start:stop]
        return NetObservation(
            self.model,
            self.rigid.body,
            self.W,
            self.data[start:stop],
            self.observed[start:stop],
            self.gate_mm,
            self.batch_size,
            self.jacobian,
            noise_var=nv,
            refresh=self.refresh,
            beyond_window=self.beyond_window,
            measured=self.measured,
            threads=self.threads,
            few_var=self.few_var,
            measured_var=self.interp.measured_var,
            step=self.step,
            far_steps=self.far_steps,
            net_parts=self.net_parts,
        )
