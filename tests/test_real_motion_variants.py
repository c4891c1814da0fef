"""Imputing parts no camera sees in 3D (issue 45): interp's gaps anchored by the part-frames one
camera saw (`InterpObservation.anchored`, the default); benchmarks/interp_variants.py's
estimators: the body's shape space as a conditional Gaussian (`PartCovariance`), the session's
gap lengths and the cross-validated calibration of a predictor's variance
(`calibrate_kriging`)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from adjust.lsq.observation import InterpObservation
from adjust.lsq.stochastic import OffsetCovariance, krige_offsets

ROOT = Path(__file__).resolve().parent.parent


def _load():
    spec = importlib.util.spec_from_file_location(
        "interp_variants", ROOT / "benchmarks" / "interp_variants.py"
    )
    mod = importlib.util.module_from_spec(spec)
    sys.modules["interp_variants"] = mod  # (its dataclasses look their module up)
    spec.loader.exec_module(mod)
    return mod


def test_shape_space_predicts_a_part_from_the_others():
    """Four parts driven by one shared latent (plus 0.3 mm noise each): a part is predicted
    from the others far better than by its mean, a hidden part as well as a seen one (whose own
    value is left out: changing it does not change its prediction), with a variance that
    matches the error."""
    iv = _load()
    rng = np.random.default_rng(0)
    T, K = 3000, 4
    z = rng.normal(size=(T, 1, 3))
    o = z * np.array([1.0, 2.0, 3.0, 0.5])[None, :, None] + 0.3 * rng.normal(size=(T, K, 3))
    m = rng.random((T, K)) > 0.3
    pc = iv.PartCovariance.estimate(o, m)
    pred, var = pc.condition(o, m)
    for k in range(K):
        e = np.sqrt(((o[:, k] - pred[:, k]) ** 2).sum(-1).mean())
        spread = np.sqrt(((o[:, k] - o[:, k].mean(0)) ** 2).sum(-1).mean())
        assert e < 0.6 * spread
        assert 0.7 < e / np.sqrt(var[:, k].sum(-1).mean()) < 1.3
    o2 = o.copy()
    o2[:, 2] += 5.0
    pred2, _ = pc.condition(o2, m)
    assert np.allclose(pred2[:, 2], pred[:, 2])  # a part's own value is left out


def test_gap_lengths():
    iv = _load()
    m = np.array([[1, 0], [0, 0], [0, 1], [1, 0], [0, 1], [1, 1]], dtype=bool)
    g = iv.gap_lengths(m)
    assert g[0].tolist() == [2, 1] and g[1].tolist() == [1]


def test_cross_validation_finds_a_variance_off_by_a_factor():
    """A smooth random walk of offsets with gaps: kriging's own variance gives factors near 1;
    the same kriging claiming a quarter of its variance gets factors near 4."""
    iv = _load()
    rng = np.random.default_rng(1)
    T, K = 2000, 3
    o = np.cumsum(rng.normal(size=(T, K, 3)) * 0.3, axis=0) + 0.2 * rng.normal(size=(T, K, 3))
    m = np.ones((T, K), dtype=bool)
    for k in range(K):  # gaps of 5-40 frames
        t = 10
        while t < T - 60:
            L = int(rng.integers(5, 40))
            m[t : t + L, k] = False
            t += L + int(rng.integers(20, 60))
    nug = np.full((K, 3), 0.04)

    def honest(oo, mm):
        return krige_offsets(oo, mm, OffsetCovariance.estimate(oo, mm, nugget=nug))

    def overconfident(oo, mm):
        p, v = honest(oo, mm)
        return p, v / 4.0

    f1 = iv.calibrate_kriging(o, m, honest, nug).factor
    f4 = iv.calibrate_kriging(o, m, overconfident, nug).factor
    assert np.all((f1 > 0.6) & (f1 < 1.6)), f1
    assert np.all((f4 > 2.5) & (f4 < 6.0)), f4


def _gap_scene(T=300, K=3, seed=0):
    """Offsets of K parts (identity poses, so global = body frame + rest points): small noise
    about 0, but part 0 sits 20 mm off along x through a 120-frame gap of its 3D observations
    (hidden away from its usual place)."""
    rng = np.random.default_rng(seed)
    body = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.0, 30.0, 0.0]])[:K]
    off = 0.5 * rng.normal(size=(T, K, 3))
    gap = slice(90, 210)
    off[gap, 0, 0] += 20.0
    X = body[None] + off
    observed = np.ones((T, K), dtype=bool)
    observed[gap, 0] = False
    return body, X, observed, gap


def test_single_view_anchors_pull_a_gap_off_the_mean():
    """Across a long gap the interpolation reverts to the part's mean (0); with the part-frames
    one camera saw in the gap as anchors (at their fused points, 3 mm sd) the prediction in the
    gap follows them, its variance no smaller than an anchor's own; the anchors, their noise
    and the 3D observations are kept apart."""
    body, X, observed, gap = _gap_scene()
    T, K = observed.shape
    noise = torch.full((T, K), 0.25, dtype=torch.float64)
    obs = InterpObservation(
        torch.tensor(body), torch.tensor(np.where(observed[..., None], X, np.nan)),
        torch.tensor(observed), noise,
    )  # fmt: skip
    poses = torch.zeros(T, 6, dtype=torch.float64)
    obs.prepare(poses)
    mid = (gap.start + gap.stop) // 2
    assert abs(float(obs._M[mid, 0, 0]) - body[0, 0]) < 5.0  # the mean, far from the truth
    ncams = np.where(observed, 2, 0)
    ncams[gap.start + 5 : gap.stop - 5 : 10, 0] = 1  # one view every 10 frames in the gap
    sd = np.full((T, K), 3.0)
    anchored = obs.anchored(torch.tensor(X), torch.tensor(sd), torch.tensor(ncams))
    assert int(anchored.anchors.sum()) == int((ncams == 1).sum())
    assert torch.equal(anchored.anchors | obs.observed, anchored.observed)
    anchored.prepare(poses)
    assert abs(float(anchored._M[mid, 0, 0]) - (body[0, 0] + 20.0)) < 4.0
    a = anchored.anchors.numpy()
    assert np.all(anchored._var.numpy()[a] >= 9.0 - 1e-9)  # an anchor's prior: >= its own
    with pytest.raises(ValueError, match="point_sd"):
        obs.anchored(torch.tensor(X), torch.tensor(sd[:, :2]), torch.tensor(ncams))
