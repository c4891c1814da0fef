"""``deformation=`` with a deformation net (`adjust.lsq.net_observation.NetObservation`) after
rigid -> interp: `NetMode` and its three sources, `CheckpointNet` (a deformnet-train checkpoint),
`DefaultNet` (the shipped pretrained net) and `SelfNet` (that net fine-tuned on this recording's
own tokens, `adjust.adapt`); the choice made once per session (`NetDecision`), the held-out check
(`adjust.net_gate`) and the summary's facts of the net's use."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from adjust import adapt
from adjust.body_fit import check_world_up, triangulate_points
from adjust.deformation_modes.base import (
    Adjusting,
    DeformationMode,
    deform_step,
    far_steps,
    interp_facts,
)
from adjust.io import Detections, InputError
from adjust.lsq.net_observation import NetObservation
from adjust.lsq.observation import with_single_views
from adjust.net_gate import Anchors, heldout_check, net_vs_kriging
from adjust.tokenize import session_tokens
from adjust.track_config import DeformConfig
from adjust.validate import choose_measured_prior
from deformnet import pretrained
from deformnet.body import BodyModel
from deformnet.deformation import DeformationModel

log = logging.getLogger(__name__)


def load_deformation(path: str):
    """`DeformationModel.from_checkpoint`, with a clear error for a missing/unreadable file."""
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
    cfg_def: DeformConfig,
    cons=None,
    few_var=None,
    net_parts=None,
    max_error_px: float = 20.0,
    interp=None,
):
    """The solver's deformable observation for this data: the net's ``deformed`` inputs for
    observed tokens are the parts triangulated (robustly) from the detections (the session's
    gated 3D observations `cons` when given), gated by their distance from the rigid model
    (`deform.gate_mm`). few_var: (K, 3) torch, the spread of parts with too few 3D observations
    (`refine_body`; NaN: unknown). net_parts: (K,) bool, the parts that take the net's
    prediction (`heldout_check`; None: all); max_error_px: ``consensus.max_error_px`` (the
    robust triangulation without `cons`); interp: the interp stage's observation (its
    single-view anchors), used with ``deform.beyond_window=anchored``."""
    if cons is not None:
        X = torch.as_tensor(cons.points, dtype=torch.float64)
    else:
        tri = triangulate_points(det, cams, True, float(max_error_px))
        X = tri.points.to(torch.float64)
    observed = torch.isfinite(X).all(-1)
    jac = str(cfg_def.jacobian)
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
        float(cfg_def.gate_mm),
        int(cfg_def.batch_size),
        jac,
        noise_var=noise,
        refresh=int(cfg_def.refresh),
        beyond_window=str(cfg_def.beyond_window),
        measured="net" if cfg_def.measured == "net" else "interp",
        few_var=few_var,
        step=deform_step(model, cfg_def),
        far_steps=far_steps(model, cfg_def),
        net_parts=None if net_parts is None else torch.as_tensor(net_parts, dtype=torch.bool),
        interp=interp if str(cfg_def.beyond_window) == "anchored" or cfg_def.net_anchors else None,
        net_anchors=bool(cfg_def.net_anchors),
    )
    return obs, {"observed_fraction": float(observed.double().mean()) if observed.numel() else 0.0}


@dataclass
class NetDecision:
    """A net mode's choice for a session, made once: model, the net the tracks use (None: the
    interpolation's tracks), net_facts (`NetMode.net`'s), net_parts, heldout and reason
    (`NetMode.check`'s), up_deg (`check_world_up`'s, or None). A long session's is made on its
    sample and used in every chunk (`adjust.chunks`)."""

    model: Any
    net_facts: dict
    net_parts: Any
    heldout: dict | None
    reason: str | None
    up_deg: float | None


class NetMode(DeformationMode):
    """A deformation net: rigid -> interp (with the session's 3D observations) -> the net.
    Subclasses say where the net comes from (`net`) and how it is checked (`check`); the
    choice is kept as `decision` (`NetDecision`): a mode that already holds one (a long
    session's chunk, `adjust.chunks`) uses it instead of choosing again."""

    needs_consensus = True
    decision: NetDecision | None = None

    def net(self, a: Adjusting, poses, interp_obs=None) -> tuple[Any, dict]:
        """(the net, facts about it) for this session; poses (T, 6): the interp poses;
        interp_obs: the interp stage's observation (its single-view anchors), or None."""
        raise NotImplementedError

    def check(self, a: Adjusting, model, poses, interp_obs) -> tuple[Any, dict | None, str | None]:
        """(net_parts (K,) bool or None for all, summary facts under ``heldout``, the reason
        the net is not used or None); interp_obs: the interp stage's observation (its
        offset covariance), None without the session's 3D observations."""
        return None, None, None

    def checkpoint(self, a: Adjusting) -> str:
        """summary.json's ``deformation.checkpoint``."""
        raise NotImplementedError

    def rigid_first(self, deform: DeformConfig, cons) -> bool:
        return cons is not None or bool(deform.rigid_first)

    def adjust(self, a: Adjusting) -> tuple[Any, dict]:
        res, interp_obs, interp_extra = a.rigid, None, {}
        init = None if res is None else res.poses
        if a.cons is not None:  # the net starts from the interp poses: deformation=interp's
            # own adjustment (its iterations too), so a net the check refuses leaves its tracks
            t1 = time.perf_counter()
            res, interp_obs, interp_extra = a.interp_solve(a.deform_solver_cfg, init)
            init = res.poses
            a.timings["interp_s"] = time.perf_counter() - t1
        if self.decision is None:
            self.decision = self.decide(a, init, interp_obs)
        d = self.decision
        model, net_facts, net_parts = d.model, d.net_facts, d.net_parts
        heldout, reason, up_deg = d.heldout, d.reason, d.up_deg
        observation, def_facts, dcfg = None, {}, a.solver_cfg
        if model is not None:
            observation, def_facts = make_deformable_observation(
                model,
                a.body.points,
                a.det,
                a.cams,
                a.deform,
                cons=a.cons,
                few_var=a.few_var,
                net_parts=net_parts,
                max_error_px=a.consensus.max_error_px,
                interp=interp_obs,
            )
            def_facts.update(net_facts)
            if up_deg is not None:  # a heading-frame net: how far the mouse's up is from its up
                def_facts["world_up"] = {
                    "up": list(model.up),
                    "median_body_up_deg": round(up_deg, 1),
                }
            t_net = time.perf_counter()
            dcfg = a.deform_solver_cfg
            res = a.solve(dcfg, observation, init)
        measured_facts = None
        if a.rigid_obs is not None and (observation is not None or self.prior_without_net):
            res, measured_facts = self.measured_prior(
                a, res, observation if observation is not None else interp_obs, dcfg
            )
        if model is None:  # the interpolation's tracks
            facts = {
                "mode": "interp",
                **interp_facts(interp_obs, a.body),
                **interp_extra,
                **net_facts,
            }
            if reason is not None:
                facts.update({"requested": self.name, "reason": reason})
        else:
            a.timings["net_s"] = time.perf_counter() - t_net
            facts = {
                "mode": self.name,
                "checkpoint": self.checkpoint(a),
                "window": int(model.window),
                "step": int(observation.step),
                **def_facts,
                **net_use_facts(observation, a.body),
            }
        if measured_facts is not None:
            facts["measured_prior"] = measured_facts
        if heldout is not None:
            facts["heldout"] = heldout
        return res, facts

    def decide(self, a: Adjusting, init, interp_obs) -> NetDecision:
        """The net for this session (`net`), its world up and its check (`check`); a net the
        check refuses leaves the tracks to the interpolation (model None)."""
        model, net_facts = self.net(a, init, interp_obs)
        up_deg = None
        if model is not None and init is not None:
            up_deg = check_world_up(model, init, a.where)
        net_parts, heldout, reason = None, None, None
        if model is not None and init is not None:
            net_parts, heldout, reason = self.check(a, model, init, interp_obs)
            if reason is not None:
                model = None  # `res`: the interp adjustment's, outputs complete
        return NetDecision(model, net_facts, net_parts, heldout, reason, up_deg)

    #: the measured prior is chosen also when the net is not used
    prior_without_net = False

    def measured_prior(self, a: Adjusting, res, target, dcfg) -> tuple[Any, dict | None]:
        """``deform.measured`` (cv, rigid): a measured part-frame's prior, the rigid model
        point where it predicts held-out cameras better (``cv``, `adjust.validate`) or always
        (``rigid``); interp and net: no change here (the observation's own)."""
        measured = a.deform.measured
        if measured not in ("cv", "rigid"):
            return res, None
        t1 = time.perf_counter()
        choice, facts = measured, {"choice": measured, "reason": "deform.measured"}
        if measured == "cv":
            choice, facts = choose_measured_prior(
                res.poses,
                a.det.xy,
                a.weight,
                res.weights > 0,
                a.cams,
                np.array(a.body.points),
                a.rigid_obs.var.numpy(),
                a.solver_cfg.sigma_det_px,
                consensus_kwargs={
                    "max_error_px": float(a.consensus.max_error_px),
                    "gate_sigmas": float(a.consensus.gate_sigmas),
                },
                few_var=a.few_var,
            )
        if choice == "rigid":  # the shape prior where a part has its own 3D observation
            target.set_measured_var(a.rigid_obs.var)
            res = a.solve(dcfg, target, res.poses)
        a.timings["measured_prior_s"] = time.perf_counter() - t1
        return res, facts


class CheckpointNet(NetMode):
    """``deformation=PATH``: a deformnet-train checkpoint; its body model replaces the
    ``body`` group's points (the config's aliases still apply)."""

    name = "net"
    needs_consensus = False  # without them: the rigid start (deform.rigid_first), no check

    def __init__(self, path: str) -> None:
        self.path = str(path)
        self.model = None
        self._said_body = False  # the body's replacement is logged once per session

    def checkpoint_body(self, body_cfg) -> BodyModel:
        if self.model is None:  # (a long session's chunks reuse the sample's mode: loaded once)
            self.model = load_deformation(self.path)
        model = self.model
        given = BodyModel.from_config(body_cfg)
        body = model.body
        differs = given.parts != body.parts or not np.allclose(given.points, body.points)
        if differs and not self._said_body:
            self._said_body = True
            log.warning(
                "deformation: using the checkpoint's body model '%s' (the net was trained with "
                "it), not body=%s",
                body.name,
                given.name,
            )
        # the checkpoint's model may lack the config's aliases: merge them
        aliases = {k: v for k, v in given.aliases.items() if v in body.parts}
        return BodyModel(body.parts, body.points, {**aliases, **body.aliases}, body.name)

    def net(self, a: Adjusting, poses, interp_obs=None) -> tuple[Any, dict]:
        return self.model, {}

    def check(self, a: Adjusting, model, poses, interp_obs):
        return _require_better(a, model, poses, "net", interp_obs)

    def checkpoint(self, a: Adjusting) -> str:
        return str(Path(self.path).resolve())


class DefaultNet(NetMode):
    """``deformation=default``: the pretrained net shipped with the package, on this session's
    (scaled) body; checked part by part against the interpolation (``deform.require_better``)."""

    name = "default"

    def __init__(self) -> None:
        self.model = None

    def prepare(self, body: BodyModel) -> None:
        if self.decision is not None:  # a long session's chunk: the sample's net
            return
        model = pretrained.load_default()  # (the module's: tests replace it)
        # the net predicts in canonical coordinates; it runs on this session's (scaled) body
        # (a part-agnostic net on any skeleton; a net that knows parts by index on its own)
        try:
            self.model = model.for_body(body, "deformation=default")
        except ValueError as exc:
            raise InputError(f"{exc}; or use deformation=self") from None

    def net(self, a: Adjusting, poses, interp_obs=None) -> tuple[Any, dict]:
        return self.model, {}

    def check(self, a: Adjusting, model, poses, interp_obs):
        return _require_better(a, model, poses, "default", interp_obs)

    def checkpoint(self, a: Adjusting) -> str:
        return "default"


class SelfNet(NetMode):
    """``deformation=self``: the shipped net fine-tuned on this recording's own tokens
    (`adjust.adapt.adapt_net`, ``adapt.*``), used if it beats the interpolation on held-out
    tokens (``adapt.require_better``)."""

    name = "self"
    prior_without_net = True

    def net(self, a: Adjusting, poses, interp_obs=None) -> tuple[Any, dict]:
        """The shipped net fine-tuned on the recording's tokens; with ``deform.net_anchors``
        the windows also observe interp's single-view anchors as inputs (never as targets),
        as the tracker's net does."""
        t1 = time.perf_counter()
        tokens = session_tokens(
            poses, a.body.points, a.cons, a.body.parts, a.body.name, source=a.where
        )
        anchors = Anchors.of(interp_obs) if a.deform.net_anchors else None
        train = tokens
        if anchors is not None:
            deformed, _, one = with_single_views(
                torch.as_tensor(tokens.deformed), torch.as_tensor(tokens.observed),
                anchors.points, anchors.mask,
            )  # fmt: skip
            train = replace(tokens, deformed=deformed.numpy(), inputs=one.numpy())
        model, facts = adapt.adapt_net(train, a.out, a.adapt_cfg, a.progress)
        a.timings["adapt_s"] = time.perf_counter() - t1
        self.tokens, self.adapt_facts = tokens, facts
        return model, {"adapt": facts}

    def check(self, a: Adjusting, model, poses, interp_obs):
        """``adapt.require_better``: the adapted net against the interpolation the tracks would
        otherwise get (`InterpMode`'s kriging, with this session's offset covariance and
        single-view anchors) on the same masked windows of the fine-tuning's held-out blocks
        (`net_vs_kriging`)."""
        facts = self.adapt_facts
        settings = adapt.AdaptConfig.from_any(a.adapt_cfg)
        if not settings.require_better:
            facts["used"] = True
            return None, {"require_better": False, "checked": False}, None
        blocks = (facts.get("data") or {}).get("val_blocks")
        step = deform_step(model, a.deform)
        anchors, na = Anchors.of(interp_obs), bool(a.deform.net_anchors)
        try:
            h = net_vs_kriging(
                model, self.tokens, interp_obs.cov, blocks, step, anchors=anchors, net_anchors=na
            )
        except ValueError as exc:  # held-out blocks shorter than a window
            log.warning("adapt.require_better: the held-out blocks hold no window (%s)", exc)
            h = net_vs_kriging(
                model, self.tokens, interp_obs.cov, None, step, anchors=anchors, net_anchors=na
            )
            blocks = None
        h = {"require_better": True, "checked": True, "blocks": blocks or "all frames", **h}
        h["net_mm"] = dict(zip(a.body.parts, h["net_mm"]))
        h["interp_mm"] = dict(zip(a.body.parts, h["interp_mm"]))
        figures = (h["net_all_mm"], h["interp_all_mm"], h["windows"])
        gain = settings.min_gain
        h["min_gain"] = gain
        if h["net_all_mm"] < (1.0 - gain) * h["interp_all_mm"]:
            log.info(
                "deformation=self: the adapted net beats interp's kriging on held-out tokens "
                "(RMSE %.2f vs %.2f mm over %d windows)",
                *figures,
            )
            facts["used"] = True
            return None, h, None
        reason = (
            f"the adapted net does not beat interp's kriging by {100 * gain:g}% on held-out "
            f"tokens (RMSE {h['net_all_mm']:.2f} vs {h['interp_all_mm']:.2f} mm over "
            f"{h['windows']} windows; adapt.min_gain)"
        )
        log.warning(
            "deformation=self: %s; too little data or time? The tracks are interpolated "
            "(deformation=interp's tracks; summary.json says "
            "deformation.mode: interp; adapt.require_better=false uses the net anyway; its "
            "checkpoint is %s)",
            reason,
            facts["checkpoint"],
        )
        facts["used"] = False
        return None, h, reason

    def checkpoint(self, a: Adjusting) -> str:
        return str(a.out / "deformation.ckpt")


def _require_better(a: Adjusting, model, poses, mode: str, interp_obs):
    """``deform.require_better`` (`adjust.net_gate.heldout_check`, against interp_obs's
    kriging) as `NetMode.check`."""
    t1 = time.perf_counter()
    net_parts, facts = heldout_check(
        model,
        poses,
        a.body,
        a.cons,
        a.deform.require_better,
        a.where,
        mode,
        step=deform_step(model, a.deform),
        interp=interp_obs,
        net_anchors=bool(a.deform.net_anchors),
    )
    a.timings["heldout_check_s"] = time.perf_counter() - t1
    reason = None
    if net_parts is not None and not bool(net_parts.any()):
        reason = (
            f"the net predicts the recording's held-out parts no better than interpolation "
            f"(RMSE {facts['net_all_mm']:.2f} vs {facts['interp_all_mm']:.2f} mm)"
        )
    return net_parts, facts, reason


def net_use_facts(observation: NetObservation, body: BodyModel) -> dict:
    """How much of the tracks the net made (summary.json ``deformation``)."""
    used = observation.step_used[observation.use_net.to(observation.step_used.device)]
    return {
        "net_passes": int(observation.evaluations),
        "held_out_ratio_net_over_interp": {
            p: float(v) for p, v in zip(body.parts, observation.factor)
        },
        "net_reach_fraction": float(observation.reach.double().mean()),
        "net_used_fraction": float(observation.use_net.double().mean()),
        "net_used_by_step": {
            int(s): float((used == s).double().sum() / max(used.numel(), 1))
            for s in (observation.step, *observation.far_steps)
        },
    }
