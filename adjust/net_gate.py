"""Does a deformation net beat interpolation on this recording? The checks behind
``deform.require_better`` (a net not trained on the recording) and ``adapt.require_better``
(``deformation=self``'s adapted net), on the recording's own held-out parts.
"""

from __future__ import annotations

import logging

import numpy as np

from adjust.io import InputError
from adjust.tokens import session_tokens
from deformnet.heldout import MIN_TARGETS, heldout_errors

log = logging.getLogger(__name__)

__all__ = ["REQUIRE_BETTER", "heldout_check"]


REQUIRE_BETTER = ("auto", "parts", "all", "report", "false")


def heldout_check(
    model, poses, body, cons, cfg_def, where: str, mode: str = "default", step: int | None = None
):
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
    iterations, not ``deform.max_iterations``; logged loudly). step: frames between the
    net's tokens (`adjust.deformation_modes.deform_step`; None: the net's)."""
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
        h = heldout_errors(model, tokens, step=step)
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
