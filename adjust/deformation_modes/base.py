"""What every ``deformation=`` mode shares: the session being adjusted (`Adjusting`), the
modes' base class (`DeformationMode`), the rigid and interpolation modes (`RigidMode`,
`InterpMode`) and the ``deform`` settings' token steps (`deform_step`, `far_steps`). The net modes
are `adjust.deformation_modes.net`'s; the package picks one (`mode_from_config`)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from adjust.camera import CameraTensors
from adjust.io import Detections, InputError
from adjust.lsq.observation import InterpObservation
from adjust.lsq.smoother import view_rays
from adjust.track_config import ConsensusConfig, DeformConfig
from deformnet.body import BodyModel


def _deform(cfg_def) -> DeformConfig:
    """A `DeformConfig` (as given, or from a mapping of ``deform`` settings)."""
    return cfg_def if isinstance(cfg_def, DeformConfig) else DeformConfig.from_config(cfg_def)


def deform_step(model, cfg_def) -> int:
    """Frames between the net's window tokens: ``deform.step`` (null: the step the net was
    trained with, `DeformationModel.step`)."""
    step = _deform(cfg_def).step
    if step is None:
        return int(getattr(model, "step", 1))
    return int(step)


def far_steps(model, cfg_def) -> tuple[int, ...]:
    """``deform.far_steps``: wider token steps for part-frames the window does not reach
    (``auto``: the larger steps the net was trained with, `DeformationModel.steps`; a list;
    ``[]``: none)."""
    spec = _deform(cfg_def).far_steps
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


@dataclass
class Adjusting:
    """A session after its body model and (when it ran) its rigid adjustment: what a
    deformation mode adjusts.

    solve(config, observation, init_poses) -> an `adjust.lsq.AdjustmentResult` of this
    session; rigid: the rigid adjustment's (None when none ran); cons: the session's 3D
    observations (`adjust.estimate.Consensus`, None with ``consensus.estimate=false``);
    rigid_obs: the rigid observation with the parts' deformation moments (None without cons);
    few_var: (K, 3) torch, the spread of parts placed from their single views (else NaN);
    deform: the ``deform`` settings; adapt_cfg: the ``adapt`` block (`adjust.adapt`'s to read);
    consensus: the consensus triangulation's settings; timings: summary.json's time_s, added
    to."""

    det: Detections
    weight: np.ndarray
    cams: CameraTensors
    body: BodyModel
    cons: Any
    rigid_obs: Any
    few_var: Any
    solver_cfg: Any
    solve: Callable
    rigid: Any
    deform: DeformConfig
    adapt_cfg: Any
    consensus: ConsensusConfig
    where: str
    out: Path
    progress: bool
    timings: dict = field(default_factory=dict)

    @property
    def deform_solver_cfg(self):
        """The solver settings of the deformable adjustment (``deform.max_iterations`` where
        set)."""
        if self.deform.max_iterations is None:
            return self.solver_cfg
        return self.solver_cfg.replace(max_iterations=int(self.deform.max_iterations))

    def interp_observation(self) -> InterpObservation:
        """``deformation=interp``'s observation of this session."""
        c = self.cons
        obs = InterpObservation(
            torch.tensor(np.array(self.body.points)),
            torch.as_tensor(c.points),
            torch.as_tensor(c.observed),
            torch.as_tensor(c.noise_var),
            few_var=self.few_var,
        )
        obs.world_prior_on, obs.gate_pairs = self.deform.world_prior, self.deform.gate_pairs
        return obs

    def anchor_rays(self, res) -> tuple[np.ndarray, np.ndarray]:
        """The rays (T, K, 3) and across-ray variances (T, K) of the part-frames one camera
        saw in the adjustment ``res`` (`adjust.lsq.smoother.view_rays`)."""
        c = self.cams
        sig = np.asarray(self.cons.sigma_det_per_camera, dtype=np.float64)
        sig = np.where(np.isfinite(sig), sig, float(self.cons.sigma_det_px))
        _, rays, var = view_rays(
            np.asarray(res.points, dtype=np.float64),
            np.asarray(res.weights),
            c.centers.cpu().numpy(),
            c.focal.cpu().numpy(),
            sig,
            c.R.cpu().numpy(),
            c.t.cpu().numpy(),
            self.deform.ray_sd_factor,
        )
        return rays, var

    def interp_solve(self, cfg, init) -> tuple[Any, InterpObservation, dict]:
        """``deformation=interp``'s adjustment from the poses ``init`` with the solver settings
        ``cfg``: (the result, its observation, summary facts). With ``deform.single_views``
        it runs twice, the second time with the part-frames one camera saw among the
        observations its gaps are interpolated from (`InterpObservation.anchored`), read as
        ``deform.anchors`` says."""
        obs = self.interp_observation()
        res = self.solve(cfg, obs, init)
        facts = {}
        if self.deform.single_views:
            views = (np.asarray(res.weights) > 0).sum(-1)  # accepted views per part-frame
            rays = self.anchor_rays(res) if self.deform.anchors == "rays" else (None, None)
            obs = obs.anchored(
                res.points,
                res.point_sd,
                views,
                *rays,
                disagreement=self.deform.ray_disagreement,
                outliers=self.deform.ray_outliers,
            )
            res = self.solve(cfg, obs, res.poses)
            facts["single_view_anchors"] = int(obs.anchors.sum())
            if obs.ray_parts is not None:  # the parts the smoother predicts (anchors=rays)
                parts = self.body.parts
                facts["ray_parts"] = [p for p, u in zip(parts, obs.ray_parts) if u]
            if obs.ray_rejected is not None:  # observations the smoother contradicted
                facts["ray_rejected"] = int(obs.ray_rejected.sum())
        return res, obs, facts


class DeformationMode:
    """One choice of ``deformation=``. name: its summary.json ``mode``."""

    name = "rigid"
    #: needs the session's 3D observations (``consensus.estimate=true``)
    needs_consensus = False

    def checkpoint_body(self, body_cfg) -> BodyModel | None:
        """The body model the mode brings (a checkpoint's), else None (the ``body`` group's)."""
        return None

    def prepare(self, body: BodyModel) -> None:
        """Anything the mode needs once the session's body model is final."""

    def rigid_first(self, deform: DeformConfig, cons) -> bool:
        """Whether the rigid adjustment runs before `adjust`."""
        return True

    def start_cfg(self, solver_cfg, deform: DeformConfig):
        """The solver settings of the rigid adjustment the mode starts from: its robust kernel
        ``deform.rigid_robust`` (null: the solver's own)."""
        if deform.rigid_robust is None:
            return solver_cfg
        return solver_cfg.replace(robust=deform.rigid_robust)

    def adjust(self, a: Adjusting) -> tuple[Any, dict]:
        """(the session's result, summary.json's ``deformation`` block)."""
        raise NotImplementedError


class RigidMode(DeformationMode):
    """``deformation=rigid``: the rigid adjustment is the result."""

    name = "rigid"

    def start_cfg(self, solver_cfg, deform: DeformConfig):
        return solver_cfg  # the rigid adjustment is the result: the solver's own kernel

    def adjust(self, a: Adjusting) -> tuple[Any, dict]:
        return a.rigid, {"mode": self.name}


class InterpMode(DeformationMode):
    """``deformation=interp``: interpolated body-frame offsets, from the rigid poses."""

    name = "interp"
    needs_consensus = True

    def adjust(self, a: Adjusting) -> tuple[Any, dict]:
        res, obs, facts = a.interp_solve(a.deform_solver_cfg, a.rigid.poses)
        return res, {"mode": self.name, **interp_facts(obs, a.body), **facts}
