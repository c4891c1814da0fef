"""What uncertainty ``deformation=interp``'s second pass reports on its gaps (issue 45).

With ``deform.single_views`` interp is solved twice, the second time with the part-frames one
camera saw as anchors of its gaps (`InterpObservation.anchored`). The solver calibrates a gap's
prior by a per-part inflation measured on the single views (`adjust.lsq.fusion.prior_inflation`),
but in the second pass the single views *are* the anchors: the prior agrees with them by
construction, the inflation falls to 1 and the reported sigma of the part-frames no camera sees
is too small (2 cameras, real motion: rms error / rms sigma 1.46). Measuring the inflation
otherwise moves the kriging weights and costs accuracy; these choices change only the reported
covariance (`InterpObservation.report_inflation`), never the points (``deform.gap_sigma``):

- `GapSigma` (``solver``): the second pass's own inflation (as before).
- `LeaveRunsOut` (``leave_runs_out``): a label-free check of the second pass's kriging: each
  run of consecutive anchors of a part is predicted from the observations outside it, as a gap
  is (`adjust.lsq.stochastic.runs_out_neighbours`), and the solver's inflation is measured on
  the single views against that prediction (`InterpObservation.held_out`) instead of the one
  their own anchors made; `AnchorsOut` (``anchors_out``): against the prediction from the 3D
  observations alone. Either inflates only the part-frames no view was fused into (their point
  is the prediction alone): a view's fusion is calibrated already, or underconfident at 3-4
  cameras (`benchmarks/interp_variants.py`, ``calib_one_view``).
"""

from __future__ import annotations

import numpy as np

from adjust.io import InputError
from adjust.lsq.stochastic import neighbours, runs_out_neighbours


class GapSigma:
    """The second pass's own inflation (``deform.gap_sigma=solver``)."""

    name = "solver"

    def held_out(self, good: np.ndarray, anchors: np.ndarray) -> tuple[np.ndarray, ...] | None:
        """good (T, K) the observations the second pass interpolates from, anchors (T, K) those
        of them seen by one camera -> the previous and next observation (T, K) (-1 / T where
        none) each part-frame is predicted from for the check of the gaps' reported inflation,
        or None (no check: the solver's own inflation)."""
        return None


class LeaveRunsOut(GapSigma):
    """Each run of consecutive anchors of a part predicted from the observations outside it,
    as a gap of that length is (``deform.gap_sigma=leave_runs_out``)."""

    name = "leave_runs_out"

    def held_out(self, good, anchors):
        return runs_out_neighbours(good, anchors)


class AnchorsOut(GapSigma):
    """Every anchor left out: the prediction from the 3D observations alone, as the first pass
    made it (with the second pass's covariance) (``deform.gap_sigma=anchors_out``)."""

    name = "anchors_out"

    def held_out(self, good, anchors):
        return neighbours(np.asarray(good) & ~np.asarray(anchors), True)


GAP_SIGMAS = {c.name: c for c in (GapSigma, LeaveRunsOut, AnchorsOut)}


def gap_sigma(name: str) -> GapSigma:
    """The `GapSigma` called ``name`` (``deform.gap_sigma``)."""
    try:
        return GAP_SIGMAS[str(name)]()
    except KeyError:
        raise InputError(
            f"deform.gap_sigma must be one of {', '.join(GAP_SIGMAS)}, got {name!r}"
        ) from None
