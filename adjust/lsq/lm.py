"""Generic banded Levenberg-Marquardt (Gauss-Newton with damping and accept/reject).

The problem supplies `linearise(x) -> (blocks (b+1, T, n, n), g (T, n), cost, ctx)` (the
normal matrix J^T W J in block-band form, the right-hand side -J^T W r and the cost at x, plus
any context such as IRLS weights that must stay fixed while steps are tried), `cost(x, ctx)`
and `retract(x, delta (T, n)) -> x`. Steps solve (N + lambda diag(N)) delta = g by banded
Cholesky in O(T); a step is accepted if it does not increase the cost.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from adjust.lsq import banded

log = logging.getLogger(__name__)


@dataclass
class LMResult:
    x: Any
    iterations: int
    history: list[float] = field(default_factory=list)
    converged: bool = False
    blocks: np.ndarray | None = (
        None  # undamped normal matrix (with ridge) of the last linearisation
    )


def add_ridge(blocks: np.ndarray, ridge: float) -> float:
    """Add ridge * mean(diagonal) to the diagonal (keeps N definite); returns the amount."""
    d = np.diagonal(blocks[0], axis1=-2, axis2=-1)
    scale = float(np.mean(d)) if d.size else 1.0
    eps = ridge * (scale if math.isfinite(scale) and scale > 0 else 1.0) + 1e-300
    idx = np.arange(blocks.shape[-1])
    blocks[0][:, idx, idx] += eps
    return eps


def levenberg_marquardt(
    x0: Any,
    linearise: Callable[[Any], tuple[np.ndarray, np.ndarray, float, Any]],
    cost: Callable[[Any, Any], float],
    retract: Callable[[Any, np.ndarray], Any],
    *,
    max_iterations: int = 30,
    min_iterations: int = 1,
    ftol: float = 1e-10,
    xtol: float = 1e-12,
    wtol: float = 0.0,
    atol: float = 0.0,
    stol: float = 0.0,
    lam: float = 1e-6,
    lam_up: float = 10.0,
    lam_down: float = 0.3,
    ridge: float = 0.0,
    tick: Callable[[str], None] | None = None,
    max_tries: int = 12,
) -> LMResult:
    """Minimise a sum of squares whose normal matrix is block-banded.

    Stops when an accepted step decreases the cost by less than `ftol` (relative) or by less
    than `atol` (absolute) while also by less than 1e-3 (relative), moves less than `xtol` (max
    abs), the cost at successive linearisation points changes by less than `wtol` (relative;
    for reweighted problems), or no damping gives a decrease.
    A run stopped by `max_iterations` still counts as converged when its last accepted step was
    settled: the rms of the step over all parameters below `stol` (in the parameters' own
    units; 0 = never). Reweighted problems (IRLS, kriged offsets refreshed every iteration)
    can creep on along a flat valley long after the solution has settled.
    """
    x = x0
    history: list[float] = []
    converged = False
    it = 0
    settled = False
    for it in range(1, max_iterations + 1):
        blocks, g, c, ctx = linearise(x)
        history.append(c)
        if not math.isfinite(c):  # a NaN/inf cost is never "converged"
            log.warning("Levenberg-Marquardt: the cost is %s at iteration %d; stopped", c, it)
            break
        if ridge > 0:
            add_ridge(blocks, ridge)
        n = blocks.shape[-1]
        idx = np.arange(n)
        diag0 = blocks[0][:, idx, idx].copy()
        floor = 1e-12 * float(diag0.max(initial=1.0))
        accepted = stop = False
        for _ in range(max_tries):
            blocks[0][:, idx, idx] = diag0 + lam * np.maximum(diag0, floor)
            try:
                delta = banded.solve(blocks, g)
            except np.linalg.LinAlgError:
                lam = max(lam * lam_up, 1e-8)
                continue
            trial = retract(x, delta)
            new = cost(trial, ctx)
            if math.isfinite(new) and new <= c:
                accepted = True
                rel = (c - new) / max(c, 1e-300)
                step = float(np.abs(delta).max()) if delta.size else 0.0
                settled = bool(delta.size) and float(np.sqrt(np.mean(delta**2))) < stol
                x = trial
                lam = max(lam * lam_down, 1e-12)
                change = abs(history[-2] - c) / max(c, 1e-300) if it > 1 else math.inf
                small = (c - new) < atol and rel < 1e-3
                if it >= min_iterations and (rel < ftol or small or step < xtol or change < wtol):
                    stop = True
                break
            lam = max(lam * lam_up, 1e-8)
        if tick is not None:
            tick(f"cost {c:.6g} lambda {lam:.1e}")
        blocks[0][:, idx, idx] = diag0
        if not accepted:  # no decrease at any damping: at a minimum (to machine precision)
            stop = it >= min_iterations or c == 0.0
        if stop:
            converged = True
            break
    else:  # the iteration cap: converged if the last step had settled
        converged = settled
    return LMResult(x, it, history, converged, blocks if max_iterations > 0 else None)
