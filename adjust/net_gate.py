"""Does a deformation net beat interpolation on this recording? The checks behind
``deform.require_better`` (a net not trained on the recording) and ``adapt.require_better``
(``deformation=self``'s adapted net), on the recording's own held-out parts: the net against
the interpolation the tracks would otherwise get, ``deformation=interp``'s kriging of body-frame
offsets from the 3D observations and the single-view anchors (`kriged_mid`, `Anchors`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from adjust.io import InputError
from adjust.lsq.observation import InterpObservation, with_single_views
from adjust.lsq.stochastic import OffsetCovariance, count_within, krige_offsets
from adjust.tokenize import session_tokens
from deformnet.heldout import MIN_TARGETS, WINDOWS, rmse_by_part, summed_over, window_sums
from deformnet.so3 import kabsch
from deformnet.windows import FixedWindowBatches, MaskConfig, WindowBank

log = logging.getLogger(__name__)

__all__ = ["REQUIRE_BETTER", "Anchors", "heldout_check", "kriged_mid", "net_vs_kriging"]


REQUIRE_BETTER = ("auto", "parts", "all", "report", "false")


@dataclass(frozen=True)
class Anchors:
    """A recording's single-view anchors (`InterpObservation.anchored`): the part-frames without
    a 3D observation whose one accepted view was fused with the interp prior. points (T, K, 3)
    global mm, mask (T, K) bool, var (T, K) mm^2 per body axis."""

    points: Tensor
    mask: Tensor
    var: Tensor

    @classmethod
    def of(cls, obs: InterpObservation | None) -> Anchors | None:
        """The anchors of an interp observation; None without any (``deform.single_views``
        off, or no observation)."""
        if obs is None or obs.anchors is None:
            return None
        m = obs.anchors.cpu().bool()
        return cls(obs.data.detach().cpu().double(), m, obs.anchor_var.detach().cpu().double())

    def window(self, frames: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Each window token's anchor: frames (B, W) recording frames -> points (B, W, K, 3),
        mask (B, W, K), var (B, W, K)."""
        f = frames.long()
        return self.points[f], self.mask[f], self.var[f]


def heldout_check(
    model,
    poses,
    body,
    cons,
    require_better,
    where: str,
    mode: str = "default",
    step=None,
    interp: InterpObservation | None = None,
    net_anchors: bool = False,
):
    """``deform.require_better``: a net not trained on this recording (``deformation=default``
    or a checkpoint) against the interpolation the tracks would otherwise get (`net_vs_kriging`:
    interp's kriging with the session's offset covariance and single-view anchors, from
    ``interp``, the interp stage's prepared observation) on the recording's own held-out parts
    (masked windows of its tokens from the interp poses (T, 6)).
    ``parts``: the net predicts only the parts it predicts better (a part with too few
    held-out targets follows the verdict over all parts); ``all``: every part if it is better
    over all parts, else none; ``report``: every part, the figures computed and a worse part
    logged; ``false``: every part, unchecked; ``auto`` (default): ``parts`` for the shipped
    net (`mode` ``default``), ``report`` for a checkpoint (the user's own net, used as given:
    a ``deformation=self`` run's checkpoint reproduces its tracks).
    Returns (net_parts (K,) bool numpy or None for all, facts); all False: the tracks are
    ``deformation=interp``'s (the net modes start from interp's own adjustment; logged
    loudly). step: frames between the
    net's tokens (`adjust.deformation_modes.deform_step`; None: the net's)."""
    spec = str(require_better).lower()
    if spec not in REQUIRE_BETTER:
        raise InputError(
            f"deform.require_better must be one of {', '.join(REQUIRE_BETTER)}, got {spec!r}"
        )
    if spec == "auto":
        spec = "parts" if mode == "default" else "report"
    if spec == "false" or cons is None or interp is None or interp.cov is None:
        return None, {"require_better": spec, "checked": False}
    tokens = session_tokens(poses, body.points, cons, body.parts, body.name, source=where)
    try:
        h = net_vs_kriging(
            model,
            tokens,
            interp.cov,
            step=step,
            windows=WINDOWS,
            anchors=Anchors.of(interp),
            net_anchors=net_anchors,
        )
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
        **{k: h[k] for k in ("baseline", "windows", "targets", "net_all_mm", "interp_all_mm")},
        "net_mm": dict(zip(body.parts, map(float, net_mm))),
        "interp_mm": dict(zip(body.parts, map(float, int_mm))),
        "net_parts": [p for p, k in zip(body.parts, keep) if k],
    }
    for k in ("beyond_share", "net_beyond_mm", "interp_beyond_mm"):  # the windows beyond reach
        if k in h:
            facts[k] = dict(zip(body.parts, map(float, h[k])))
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


def kriged_mid(
    batch: dict,
    body_points,
    cov: OffsetCovariance,
    mid: int,
    step: int = 1,
    anchors: tuple[Tensor, Tensor, Tensor] | None = None,
) -> Tensor:
    """``deformation=interp``'s prediction of each window's mid frame: every part's offset from
    the rigid model, in body axes, kriged from the window's observed frames
    (`adjust.lsq.stochastic.krige_offsets` with the session's `OffsetCovariance`, as
    `InterpObservation` does over the whole session), the mid frame itself not used.

    batch: rigid, deformed (B, W, K, 3) mm, observed (B, W, K) (a `deformnet.windows` batch);
    body_points (K, 3) mm, the model whose points ``rigid`` moves; step: frames between the
    window's tokens (the covariance's lags are in frames); anchors: the window's single-view
    anchors (`Anchors.window`: points (B, W, K, 3) mm, mask (B, W, K), var (B, W, K) mm^2),
    kriged from with their own noise where the window has no 3D observation (as
    `InterpObservation.anchored`); None: the 3D observations only. Returns (B, K, 3) mm,
    global."""
    rigid = batch["rigid"].double()
    deformed = batch["deformed"].double()
    observed = batch["observed"].bool()
    Bw, W, K, _ = rigid.shape
    noise = None
    if anchors is not None:
        a_pts, a_mask, a_var = anchors
        if tuple(a_pts.shape) != (Bw, W, K, 3) or tuple(a_mask.shape) != (Bw, W, K):
            raise ValueError(
                f"anchors must be (B, W, K, 3) / (B, W, K) for windows {(Bw, W, K)}, "
                f"got {tuple(a_pts.shape)} / {tuple(a_mask.shape)}"
            )
        deformed, observed, a_mask = with_single_views(deformed, observed, a_pts, a_mask)
        own = torch.as_tensor(np.tile(cov.nugget, (Bw, 1))).reshape(Bw, 1, K, 3)
        noise = torch.where(a_mask[..., None], a_var.double()[..., None], own)
        noise = noise.permute(1, 0, 2, 3).reshape(W, Bw * K, 3).numpy()
    R, _ = kabsch(rigid, torch.tensor(np.asarray(body_points), dtype=torch.float64))
    # o = R^T (X - t) - B = R^T (X - rigid): (B, W, K, 3) in body axes
    off = torch.einsum("bwji,bwkj->bwki", R, deformed - rigid)
    # windows side by side along the parts axis: each (window, part) one kriged series
    o = off.permute(1, 0, 2, 3).reshape(W, Bw * K, 3).numpy()
    m = observed.permute(1, 0, 2).reshape(W, Bw * K).numpy()
    tiled = OffsetCovariance(
        mean=np.tile(cov.mean, (Bw, 1)),
        sill=np.tile(cov.sill, (Bw, 1)),
        nugget=np.tile(cov.nugget, (Bw, 1)),
        lags=np.asarray(cov.lags, dtype=np.float64) / float(step),  # in tokens
        gamma=np.tile(cov.gamma, (Bw, 1, 1)),
        counts=np.tile(cov.counts, Bw),
    )
    pred, _ = krige_offsets(o, m, tiled, skip_self=True, noise=noise)
    p = torch.as_tensor(pred[mid]).reshape(Bw, K, 3)
    return rigid[:, mid] + torch.einsum("bij,bkj->bki", R[:, mid], p)


def net_vs_kriging(
    model,
    tokens,
    cov: OffsetCovariance,
    blocks=None,
    step: int | None = None,
    windows: int = 1024,
    batch_size: int = 256,
    seed: int = 0,
    anchors: Anchors | None = None,
    net_anchors: bool = False,
    beyond: bool = True,
) -> dict:
    """RMSE (mm) of the net and of `kriged_mid` (what ``deformation=interp`` predicts) on the
    same masked windows (`deformnet.windows`, training-like masks) of the recording's tokens
    (`deformnet.sessions.SessionTokens`), over all parts and per part.

    blocks: [[start, stop], ...] frames to draw the windows from (the fine-tuning's held-out
    blocks; None: the whole recording); step: frames between tokens (None: the net's);
    anchors: the recording's single-view anchors, which the kriging uses as interp does
    (None: none); net_anchors: the net's window inputs include them too (as observed tokens,
    ``deform.net_anchors``). beyond: also judge the windows in which the part is alone, hidden
    in every frame with its anchors (`_alone`), where the tracks take the net's prediction
    beyond its window's reach of any observation (``deform.beyond_window``): each part's mean
    squared errors near and beyond mixed by the share of its unobserved frames that lie that
    far (`beyond_share`); False: the training-like windows only (before stop 53, when a net
    that passed could make tracks worse in long gaps). Returns {"net_mm", "interp_mm" (per part
    lists), "targets", "net_all_mm", "interp_all_mm", "windows", "baseline"} and, with
    beyond, "beyond_share", "net_near_mm", "interp_near_mm", "net_beyond_mm",
    "interp_beyond_mm" (per part). ValueError when no block holds a window."""
    step = int(model.step if step is None else step)
    spans = [(0, tokens.num_frames)] if blocks is None else [(int(a), int(b)) for a, b in blocks]
    bank = WindowBank([tokens.to_sequence(a, b) for a, b in spans], model.half_window, step)
    # each bank frame's recording frame (the kept blocks laid end to end)
    recording = torch.cat([torch.arange(*spans[i]) for i in bank.kept])
    data = FixedWindowBatches.build(bank, int(windows), int(batch_size), int(seed), MaskConfig())

    def sums(b: dict) -> dict[str, Tensor]:
        a = None if anchors is None else anchors.window(recording[b["frames"]])
        if a is not None and "alone" in b:  # the part alone in its window: no anchor either
            a = (a[0], a[1] & ~b["alone"][:, None, :], a[2])
        nb = b
        if net_anchors and a is not None:
            deformed, observed, _ = with_single_views(b["deformed"], b["observed"], *a[:2])
            nb = {**b, "deformed": deformed, "observed": observed}
        s = window_sums(model, nb, model.half_window)
        pred = kriged_mid(b, tokens.body_points, cov, model.half_window, step, a)
        m = b["target_mask"].double()
        krig = (((pred - b["target"].double()) ** 2).sum(-1) * m).sum(0)
        return {"net": s["net"], "interp": krig, "count": s["count"]}

    total = summed_over(model, data.batches, sums)
    count = total.pop("count")
    rmse = rmse_by_part(total, count)
    out = {
        "net_mm": rmse["net"][0],
        "interp_mm": rmse["interp"][0],
        "targets": [int(c) for c in count],
        "net_all_mm": rmse["net"][1],
        "interp_all_mm": rmse["interp"][1],
        "windows": sum(int(b["rigid"].shape[0]) for b in data.batches),
        "baseline": "interp's kriging" + ("" if anchors is None else " with single-view anchors"),
    }
    if not beyond:
        return out
    # beyond the window: where no 3D observation and no anchor of a part lies within the
    # net's reach, the tracks take the net's prediction from a window without that part
    # (``deform.beyond_window``); the same windows with one part hidden throughout, weighed by
    # the share of the part's unobserved frames that lie so far from any observation (over the
    # whole recording: the held-out blocks are windows to judge by, not where the net is used)
    far = beyond_share(tokens.observed, None if anchors is None else anchors.mask,
                       model.half_window * step, [(0, tokens.num_frames)])  # fmt: skip
    t_far = summed_over(model, [_alone(b) for b in data.batches], sums)
    c_far = t_far.pop("count")
    near_n, far_n = count.double(), c_far.double()
    mixed = {}
    for k in ("net", "interp"):
        mse_near = total[k] / near_n.clamp_min(1)
        mse_far = torch.where(far_n > 0, t_far[k] / far_n.clamp_min(1), mse_near)
        mixed[k] = (1.0 - far) * mse_near + far * mse_far  # (K,) mm^2
    w = near_n / near_n.sum().clamp_min(1)
    out.update(
        net_mm=[float(v) for v in mixed["net"].sqrt()],
        interp_mm=[float(v) for v in mixed["interp"].sqrt()],
        net_all_mm=float((w * mixed["net"]).sum().sqrt()),
        interp_all_mm=float((w * mixed["interp"]).sum().sqrt()),
        beyond_share=[round(float(v), 4) for v in far],
        net_near_mm=rmse["net"][0],
        interp_near_mm=rmse["interp"][0],
        net_beyond_mm=[float(v) for v in (t_far["net"] / far_n.clamp_min(1)).sqrt()],
        interp_beyond_mm=[float(v) for v in (t_far["interp"] / far_n.clamp_min(1)).sqrt()],
    )
    return out


def _alone(b: dict) -> dict:
    """A copy of window batch b with one part per window (in turn) hidden in every frame and
    the only target: the windows in which the net predicts a part from the others alone."""
    B, W, K = b["observed"].shape
    k = torch.arange(B) % K
    alone = torch.nn.functional.one_hot(k, K).bool()  # (B, K)
    observed = b["observed"] & ~alone[:, None, :]
    deformed = torch.where(observed[..., None], b["deformed"], torch.zeros_like(b["deformed"]))
    return {**b, "observed": observed, "deformed": deformed, "alone": alone,
            "target_mask": b["target_mask"] & alone}  # fmt: skip


def beyond_share(observed, anchors, reach: int, spans) -> Tensor:
    """(K,) the share of each part's frames without a 3D observation (in the recording's
    ``spans``) that have neither a 3D observation nor an anchor (mask (T, K) or None) within
    ``reach`` frames: where the tracks take the net's prediction from a window without it."""
    obs = np.asarray(observed, dtype=bool)
    seen = obs if anchors is None else obs | np.asarray(anchors, dtype=bool)
    keep = np.zeros(obs.shape[0], dtype=bool)
    for a, b in spans:
        keep[a:b] = True
    unobs = ~obs & keep[:, None]
    far = unobs & (count_within(seen, reach) == 0)
    return torch.as_tensor(far.sum(0) / np.maximum(unobs.sum(0), 1), dtype=torch.float64)
