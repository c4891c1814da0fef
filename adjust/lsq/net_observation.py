"""The learned deformation as an observation model (`adjust.lsq.observation`'s protocol):

- `DeformableObservation`: the learned net (eq. 11) with its own predictions fed back as the
  window's deformed inputs;
- `NetObservation` (``deformation=CKPT|self|default``): the learned net with the measured
  (triangulated, gated) parts as its deformed inputs, a frozen or finite-difference Jacobian,
  and its deformation variance estimated from its held-out error.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor

from adjust.lsq.geometry import retract, so3_exp
from adjust.lsq.observation import (
    InterpObservation,
    RigidObservation,
    _body_frame_points,
    _rotate_axes_var,
    with_single_views,
)
from deformnet.threads import torch_threads

__all__ = ["DeformableObservation", "NetObservation", "JACOBIANS"]


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


def _near(flags: Tensor, reach: int) -> Tensor:
    """(T, K) bool -> (T, K): a flag of the part within `reach` frames of the frame."""
    if reach <= 0 or flags.shape[0] == 0:
        return flags.clone()
    x = flags.to(torch.float32).T[:, None]  # (K, 1, T)
    pooled = torch.nn.functional.max_pool1d(x, 2 * reach + 1, stride=1, padding=reach)
    return pooled[:, 0].T > 0.5


#: ``deform.beyond_window``: where the net's window does not see a part on both sides
BEYOND_WINDOW = ("net", "interp", "anchored")


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
    ``"net"``: the net there as well; ``"anchored"``: there the interpolation where the part
    has a single-view anchor within the window's reach of the frame (`anchored`), the net
    where it has none. ``interp``: the interpolation's observation to use (e.g. interp's
    stage with its single-view anchors, `InterpObservation.anchored`; a copy is prepared
    here); None: one built from ``data`` and ``observed``. ``net_parts`` (K,) bool: only
    those parts take the net's prediction, the others interp's everywhere (`adjust-track`'s
    held-out check, ``deform.require_better``; None: every part). `use_net` (T, K) says where
    the net was used. ``net_anchors``: the net's window inputs include ``interp``'s
    single-view anchors (their fused points) as observed tokens, as its kriging does
    (``deform.net_anchors``); the held-out `factor` is still taken on the 3D observations.

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
        interp: InterpObservation | None = None,
        net_anchors: bool = False,
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
        if beyond_window not in BEYOND_WINDOW:
            raise ValueError(
                f"deform.beyond_window must be one of {', '.join(BEYOND_WINDOW)}, "
                f"got {beyond_window!r}"
            )
        if int(refresh) < 1:
            raise ValueError(f"deform.refresh must be >= 1, got {refresh}")
        self.data = data
        self.gate_mm = float(gate_mm)
        self.jacobian = jacobian
        self.noise_var = noise_var
        self.refresh = int(refresh)
        self.beyond_window = beyond_window
        self.few_var = few_var
        if interp is not None and tuple(interp.observed.shape) != tuple(observed.shape):
            raise ValueError(
                f"interp must observe {tuple(observed.shape)} part-frames, "
                f"got {tuple(interp.observed.shape)}"
            )
        self._given_interp = interp is not None
        self.interp = (
            InterpObservation(body_points, data, observed, noise_var, few_var, measured_var)
            if interp is None
            else copy.copy(interp)
        )
        # the net's window inputs include interp's single-view anchors as observed tokens
        self.net_anchors = bool(net_anchors)
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
        if self.net_anchors and self.interp.anchors is not None:
            views = self.interp.anchors.to(obs.device)
            data, obs, _ = with_single_views(data, obs, self.interp.data, views)
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
        anchors = self.interp.anchors
        m = self.interp.observed & ~self.interp.outliers.to(torch.bool)
        if anchors is not None:  # the 3D observations only
            m = m & ~anchors
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
        elif self.beyond_window == "anchored" and anchors is not None:
            near = _near(anchors.to(m.device), (self.W // 2) * self.step)
            use = use & (self.reach.to(m.device) | ~near)
        if self.net_parts is not None:
            use = use & self.net_parts.to(m.device)[None, :]
        self.use_net = use
        use = use[..., None]
        M = torch.where(use, M, Mi)
        var = self.interp._var.to(M.dtype)
        if self.measured == "net":  # the net's own held-out error where it is used there
            lead = (1, -1, *([1] * (var.ndim - 2)))  # body-axis variances or covariances
            mm = m.reshape(*m.shape, *([1] * (var.ndim - 2)))
            var = torch.where(mm, var * self.factor.reshape(lead), var)
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

    def world_prior(self, poses: Tensor) -> tuple[Tensor, Tensor] | None:
        """interp's world prior (`InterpObservation.world_prior`, as of its last `prepare`):
        the parts no camera pair sees held near their world neighbours here too."""
        self._ready(poses)
        return self.interp._world

    @property
    def outliers(self) -> Tensor | None:
        """(T, K) the 3D observations interp rejected (the final fusion's `gate_pairs`)."""
        return self.interp.outliers

    @property
    def gate_pairs(self) -> bool:
        """interp's ``gate_pairs``: the final fusion gates an isolated rejected pair's views."""
        return self.interp.gate_pairs

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
            interp=self.interp.window(start, stop) if self._given_interp else None,
        )
