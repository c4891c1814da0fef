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
- `DeformableObservation`, `NetObservation` (``deformation=CKPT|self|default``): the learned
  net (eq. 11), `adjust.lsq.net_observation`.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Protocol, runtime_checkable

import numpy as np
import torch
from torch import Tensor

from adjust.lsq.geometry import rigid_points, so3_exp
from adjust.lsq.smoother import across_ray_rms, ray_information, smooth_offsets
from adjust.lsq.stochastic import (
    OffsetCovariance,
    all_last,
    krige_offsets,
    neighbours,
)
from deformnet.so3 import skew

#: chi-square quantiles at p = 0.001: an observation its prediction contradicts
CHI2_3DOF_P001 = 16.3
CHI2_2DOF_P001 = 13.8
#: `InterpObservation`'s smoother check (``ray_outliers``): rounds at most, and the frames
#: either side within which only the most contradicted observation of a part is rejected
RAY_OUTLIER_ROUNDS = 3
RAY_OUTLIER_SPAN = 3


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
    """Body-axis variances var (T, K, 3), or covariances in body axes (T, K, 3, 3) -> global
    covariances R diag(var) R^T, or R var R^T (T, K, 3, 3)."""
    if var.ndim == 4:
        return torch.einsum("tij,tkjm,tlm->tkil", R, var, R)
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


def with_single_views(
    data: Tensor, observed: Tensor, points: Tensor, views: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Part-frames seen through one view (`InterpObservation.anchored`'s anchors) added to the
    observations where there is no 3D one: data (..., K, 3) mm, observed (..., K) bool, points
    (..., K, 3) mm the views' fused points, views (..., K) bool. Returns (data, observed, one),
    one (..., K) the part-frames added."""
    one = views.to(torch.bool) & ~observed
    return torch.where(one[..., None], points.to(data), data), observed | one, one


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
        self.anchors = None  # (T, K) part-frames observed through one view (`anchored`)
        self.anchor_var = None  # (T, K) their noise variance per body axis, mm^2
        # with ``rays`` (T, K, 3) global unit vectors and ``ray_var`` (T, K) mm^2: each anchor
        # is its camera's ray (`anchored`), the offsets smoothed (`adjust.lsq.smoother`)
        self.rays = None
        self.ray_var = None
        self.ray_parts = None  # (K,) bool after `prepare`: the parts the smoother predicts
        # with ``rays``: the smoother's covariance gains this times d d^T, d its prediction
        # minus the kriging's (`anchored`'s ``disagreement``)
        self.ray_disagreement = 0.0
        # with ``rays``: reject the observations the smoother contradicts (`_contradicted`,
        # decided at the first `prepare`, in rounds: ``ray_rejected`` (T, K) bool, then kept)
        self.ray_outliers = False
        self.ray_rejected: Tensor | None = None
        self._ray_rounds = 0
        self.outlier_rounds = 2
        # the parts no camera pair sees also held near their global neighbours' prediction
        # (``world_prior_on``: `world_prior`); ``_world`` its (W, information) after `prepare`
        self.world_prior_on = False
        self._world: tuple[Tensor, Tensor] | None = None
        # the final fusion gates the two views of an isolated rejected 3D observation
        # (`adjust.lsq.solver.isolated_pairs`) instead of accepting them as a consensus
        self.gate_pairs = False
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
        R = so3_exp(poses[:, :3]).detach()
        Rn = R.cpu().numpy().astype(np.float64)
        tn = poses[:, 3:].detach().cpu().numpy().astype(np.float64)
        X = self.data.cpu().numpy().astype(np.float64)
        m = self.observed.cpu().numpy()
        B = self.body.cpu().numpy().astype(np.float64)
        o = np.einsum("tji,tkj->tki", Rn, X - tn[:, None, :]) - B[None]
        anchor = None if self.anchors is None else self.anchors.cpu().numpy()
        m3 = m if anchor is None else m & ~anchor  # the 3D observations
        nugget = None
        if self.noise_var is not None and m3.any():  # per part: the mean over its observations
            nv = self.noise_var.cpu().numpy().astype(np.float64)
            per = np.where(m3, nv, 0.0).sum(0) / np.maximum(m3.sum(0), 1)
            nugget = np.repeat(per[:, None], 3, axis=1)
        # robust: an observation its own neighbours contradict (chi-square, 3 dof, p = 0.001)
        # is a mis-detection, not deformation; re-estimate without it
        few = None if self.few_var is None else self.few_var.cpu().numpy().astype(np.float64)
        base = m if self.ray_rejected is None else m & ~self.ray_rejected.cpu().numpy()
        good = base
        for _ in range(self.outlier_rounds + 1):
            # single-view anchors (`anchored`) count in the covariance too (they show where a
            # part goes while it is hidden) and are interpolated from with their own noise
            self.cov = OffsetCovariance.estimate(o, good, nugget=nugget, few_var=few)
            noise = None
            if anchor is not None:
                av = self.anchor_var.cpu().numpy().astype(np.float64)
                noise = np.where(anchor[..., None], av[..., None], self.cov.nugget[None])
            pred, var = krige_offsets(o, good, self.cov, skip_self=True, noise=noise)
            if _ == self.outlier_rounds:
                break
            own = self.cov.nugget[None] if noise is None else noise
            d2 = ((o - pred) ** 2 / (var + own)).sum(-1)
            new = base & ~(d2 > CHI2_3DOF_P001)
            if (new == good).all():
                break
            good = new
        self.outliers = torch.as_tensor(m & ~good)
        smooth = None
        if self.rays is not None and anchor is not None:
            # the smoother where no 3D observation is; a 3D-observed frame keeps the kriging
            # from its neighbours (the prior its own detections are fused with, calibrated).
            # The smoother's covariance is scaled up to at least the kriging's variance (its
            # trace): its depth along a ray rests on rays of other frames crossing, and is
            # overconfident there (real motion, validation: 1.3-3x), which no view can check
            u = np.einsum("tji,tkj->tki", Rn, self.rays.cpu().numpy().astype(np.float64))
            ps, vs = self._smoothed(o, good, anchor, u)
            tr = np.trace(vs, axis1=-2, axis2=-1)
            vs = vs * np.maximum(1.0, var.sum(-1) / np.maximum(tr, 1e-12))[..., None, None]
            if self.ray_outliers and self._ray_rounds < RAY_OUTLIER_ROUNDS:
                # the observations the smoother (every other frame, the rays included)
                # contradicts: e.g. two views fused where one is an outlier along the epipolar
                # line, which the kriging from the fused points alone let through. In rounds at
                # the first poses, the most contradicted of each stretch first (its neighbours'
                # predictions carry it), the whole prediction re-made without them; then kept
                self._ray_rounds += 1
                new = self._contradicted(o, good, anchor, u, ps, vs)
                if new.any():
                    old = None if self.ray_rejected is None else self.ray_rejected.numpy()
                    self.ray_rejected = torch.as_tensor(new if old is None else old | new)
                    return self.prepare(poses)
                self._ray_rounds = RAY_OUTLIER_ROUNDS
            # ... and by what the two label-free predictions disagree on: mostly the depth
            # along the rays one camera cannot see, where both rest on the motion model alone
            # (2 cameras, validation: occluded rms error / rms sigma 1.32 -> 1.15 at weight 1)
            d = ps - pred
            vs = vs + self.ray_disagreement * d[..., :, None] * d[..., None, :]
            # per part, the smoother only where it predicts the left-out views better across
            # their rays than the kriging does (label-free; NaN: too few views to tell)
            one = good & anchor
            self.ray_parts = across_ray_rms(o - ps, u, one) <= across_ray_rms(o - pred, u, one)
            smooth = ~(good & ~anchor) & self.ray_parts[None, :]
        if anchor is not None:  # an anchor's prior is no surer than the anchor itself (its
            # neighbours' single views were fused with the same first-pass prediction)
            var = np.where(anchor[..., None], np.maximum(var, av[..., None]), var)
        if smooth is not None:
            pred = np.where(smooth[..., None], ps, pred)
            var = np.where(smooth[..., None, None], vs, var[..., None] * np.eye(3))
        dt = poses.dtype
        self._world = None
        if self.world_prior_on:
            vo = np.trace(var, axis1=-2, axis2=-1) / 3 if var.ndim == 4 else var.mean(-1)
            Xr = np.einsum("tij,kj->tki", Rn, B) + tn[:, None, :]  # the rigid points
            three = good if anchor is None else good & ~anchor
            W, info = self._world_prior(X, three, Xr, nugget, vo)
            self._world = (
                torch.as_tensor(W, dtype=dt, device=poses.device),
                torch.as_tensor(info, dtype=dt, device=poses.device),
            )
        # the neighbours' prediction, also where the rigid point replaces it (diagnostics)
        self.neighbours = torch.as_tensor(B[None] + pred, dtype=dt, device=poses.device)
        if self.measured_var is not None:  # measured part-frames: the rigid model point
            mv = self.measured_var.cpu().numpy().astype(np.float64)
            pred = np.where(good[..., None], 0.0, pred)
            if var.ndim == 4:  # full body-axis covariances (the smoothed anchors)
                mv = mv[..., None] * np.eye(3)
            var = np.where(good.reshape(*good.shape, *([1] * (var.ndim - 2))), mv[None], var)
        self._M = torch.as_tensor(B[None] + pred, dtype=dt, device=poses.device)
        self._var = torch.as_tensor(var, dtype=dt, device=poses.device)

    @staticmethod
    def _world_prior(X, three, rigid, nugget, offset_var) -> tuple[np.ndarray, np.ndarray]:
        """Each part-frame without a 3D observation predicted in global coordinates from the
        part's 3D observations in the neighbouring frames (`krige_offsets` on the points
        themselves): X (T, K, 3) global mm, three (T, K) the 3D observations kept, rigid
        (T, K, 3) the rigid model points at the current poses, nugget (K, 3) or None,
        offset_var (T, K) mm^2 the part-frame's body-frame prediction's variance per axis.
        How far a part goes in the world in h frames is measured on its rigid point over every
        frame (the part's own 3D observations would measure it only while the part is seen,
        e.g. while the animal stands still), and only between two observations where that
        kriging is nearer than the part's spread over the session. Returns the prediction W
        (T, K, 3) and its information (T, K) mm^-2 per axis, 1 / (kriging variance +
        offset_var), 0 elsewhere. The model point R (B + o) + t of a part no camera pair sees
        then also stays near where its neighbouring frames put it in the world: a body frame
        turned by the parts that are seen (a head turning while the rear is hidden) no longer
        carries the hidden parts with it."""
        T, K, _ = X.shape
        cov = OffsetCovariance.estimate(rigid, np.ones((T, K), bool), nugget=np.zeros((K, 3)))
        if nugget is not None:
            cov = replace(cov, nugget=np.repeat(nugget.mean(1, keepdims=True), 3, axis=1))
        W, vw = krige_offsets(X, three, cov, skip_self=True)
        prev, nxt = neighbours(three, skip_self=True)
        inside = (prev >= 0) & (nxt < T) & all_last(vw < cov.sill[None])
        info = np.where(inside & ~three, 1.0 / np.maximum(vw.mean(-1) + offset_var, 1e-6), 0.0)
        return W, info

    def world_prior(self, poses: Tensor) -> tuple[Tensor, Tensor] | None:
        """(W (T, K, 3) global mm, information (T, K) mm^-2 per axis) of ``world_prior`` (see
        `_world_prior`), or None when it is off (``world_prior_on``)."""
        self._ready(poses)
        return self._world

    def _contradicted(self, o, good, anchor, u, ps, vs) -> np.ndarray:
        """(T, K) bool: the observations (of ``good``) that the smoother's prediction from every
        other frame, ps (T, K, 3) with covariance vs (T, K, 3, 3) in body axes, contradicts
        (chi-square, p = 0.001): a 3D observation by its distance (3 dof, with the nugget), a
        single view (``anchor``, ray u (T, K, 3) in body axes) by its distance across its ray
        (2 dof, with the view's variance across it). Shapes as `prepare`'s."""
        r = o - ps
        eye = np.eye(3)
        S = vs + np.maximum(self.cov.nugget, 1e-6)[None, :, :, None] * eye
        three = good & ~anchor
        score = np.einsum("tki,tki->tk", r, np.linalg.solve(S, r[..., None])[..., 0])
        out = three & (score > CHI2_3DOF_P001)
        one = good & anchor
        if one.any():
            rv = self.ray_var.cpu().numpy().astype(np.float64)
            un = u / np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-12)
            P = eye - un[..., :, None] * un[..., None, :]  # across the ray
            rp = (P @ r[..., None])[..., 0]
            # the along-ray direction made free: (P S P + var P + big u u^T)^-1 on rp
            big = 1e6 * (np.trace(vs, axis1=-2, axis2=-1) + rv + 1.0)
            S1 = P @ vs @ P + rv[..., None, None] * P + big[..., None, None] * (eye - P)
            d1 = np.einsum("tki,tki->tk", rp, np.linalg.solve(S1, rp[..., None])[..., 0])
            out = out | (one & (d1 > CHI2_2DOF_P001))
            score = np.where(three, score, d1)
        # only the most contradicted within RAY_OUTLIER_SPAN frames of each part: a wrong
        # observation also moves its neighbours' predictions, which then contradict them
        score = np.where(out, score, -np.inf)
        w = RAY_OUTLIER_SPAN
        pad = np.pad(score, ((w, w), (0, 0)), constant_values=-np.inf)
        top = np.max(np.stack([pad[i : i + len(score)] for i in range(2 * w + 1)]), 0)
        return out & (score >= top)

    def _smoothed(self, o, good, anchor, u) -> tuple:
        """The offsets' prediction (T, K, 3) and covariance (T, K, 3, 3) in body axes from every
        other frame (`adjust.lsq.smoother.smooth_offsets`): the 3D observations with the
        nugget, the anchors as their camera's ray (u (T, K, 3): in body axes)."""
        T, K = good.shape
        J = np.zeros((T, K, 3, 3))
        three = good & ~anchor
        nug = np.maximum(self.cov.nugget, 1e-6)  # (K, 3)
        J[three] = np.eye(3) / np.broadcast_to(nug[None], (T, K, 3))[three][:, None, :]
        one = good & anchor
        rv = self.ray_var.cpu().numpy().astype(np.float64)[one]
        J[one] = ray_information(u[one], rv)
        return smooth_offsets(o, J, self.cov)

    def anchored(
        self,
        points,
        point_sd,
        ncams,
        rays=None,
        ray_var=None,
        disagreement=0.0,
        outliers=False,
    ) -> InterpObservation:
        """This observation with the part-frames one camera saw among the observations too.

        points (T, K, 3) global mm and point_sd (T, K) mm (root of the trace of the covariance)
        from an adjustment with this observation, ncams (T, K) the views it accepted per
        part-frame: a part-frame without a 3D observation whose one view was accepted is
        observed at its fused point, with noise variance point_sd^2 per body axis (the whole
        trace: the error lies mostly along the camera's ray, in no known body axis). Inside a
        gap a single view is the only evidence of where the part is, and a part is hidden most
        when it is away from its usual place (its offsets in the gaps stray 1.5-3x further than
        where it is seen, `benchmarks/interp_variants.py`): the kriging across the gap then
        rests on these anchors instead of reverting to the part's mean, and the offsets'
        covariance (`prepare`) counts them too (the nugget: the 3D observations' noise). The
        anchors are kept as ``anchors`` (T, K) and ``anchor_var`` (T, K).
        rays (T, K, 3), ray_var (T, K): each anchor read as its camera's ray (``rays`` above);
        disagreement >= 0: the weight of the smoother's and the kriging's disagreement in the
        smoothed part-frames' covariance (``ray_disagreement``); outliers: with rays, the
        observations the smoother contradicts are rejected (``ray_outliers``)."""
        pts = torch.as_tensor(points, dtype=self.data.dtype)
        sd = torch.as_tensor(point_sd, dtype=self.data.dtype)
        T, K = self.observed.shape
        if tuple(pts.shape) != (T, K, 3) or tuple(sd.shape) != (T, K):
            raise ValueError(
                f"points (T, K, 3) and point_sd (T, K) must match the observation's "
                f"{(T, K)}, got {tuple(pts.shape)}, {tuple(sd.shape)}"
            )
        one = torch.as_tensor(ncams) == 1
        one = one & ~self.observed & torch.isfinite(pts).all(-1) & torch.isfinite(sd)
        data = torch.where(self.observed[..., None], self.data, torch.nan_to_num(pts))
        out = InterpObservation(
            self.body, data, self.observed | one, self.noise_var, self.few_var, self.measured_var
        )
        out.anchors = one
        out.anchor_var = torch.where(one, sd * sd, torch.zeros_like(sd))
        if rays is not None:
            out.rays = torch.as_tensor(rays, dtype=self.data.dtype)
            out.ray_var = torch.as_tensor(ray_var, dtype=self.data.dtype)
        if not float(disagreement) >= 0.0:
            raise ValueError(f"disagreement must be >= 0, got {disagreement}")
        out.ray_disagreement = float(disagreement)
        out.ray_outliers = bool(outliers) and rays is not None
        out.world_prior_on, out.gate_pairs = self.world_prior_on, self.gate_pairs
        return out

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
        out = InterpObservation(
            self.body,
            self.data[start:stop],
            self.observed[start:stop],
            nc,
            self.few_var,
            self.measured_var,
        )
        if self.anchors is not None:
            out.anchors = self.anchors[start:stop]
            out.anchor_var = self.anchor_var[start:stop]
        if self.rays is not None:
            out.rays, out.ray_var = self.rays[start:stop], self.ray_var[start:stop]
        # every setting of the whole (a chunk rejects its own outliers, at its own first poses)
        out.ray_disagreement, out.ray_outliers = self.ray_disagreement, self.ray_outliers
        out.world_prior_on, out.gate_pairs = self.world_prior_on, self.gate_pairs
        return out
