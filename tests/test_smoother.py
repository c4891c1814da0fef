"""The offsets' smoother (`adjust.lsq.smoother`, ``deform.anchors=rays``): leave-one-out
predictions equal to the dense Gaussian process's, the Matern length read off a semivariogram,
a single view as its ray, and a part that only single views see found where their rays meet."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from adjust.io import InputError
from adjust.lsq.observation import InterpObservation
from adjust.lsq.smoother import (
    _inv3_general,
    across_ray_rms,
    matern32_semivariogram,
    matern_lengths,
    ray_information,
    smooth_offsets,
    view_rays,
)
from adjust.lsq.stochastic import OffsetCovariance, krige_offsets
from adjust.track_config import DeformConfig


def _cov(mean, sill, length, lags=(1, 2, 4, 8, 16, 32)) -> OffsetCovariance:
    lags = np.asarray(lags)
    K = sill.shape[0]
    gamma = matern32_semivariogram(lags, sill[..., None], length[..., None])
    return OffsetCovariance(mean, sill, np.full((K, 3), 0.1), lags, gamma, np.full(K, 100))


@pytest.mark.parametrize("T", [1, 2, 40, 300])
def test_leave_one_out_equals_the_dense_gaussian_process(T):
    """Every frame's prediction and covariance, its own observation left out, equal the dense
    GP posterior with that observation removed (3D observations and single views alike), from
    one frame to several levels of the blocked scan (300 frames: blocks of 8, then of 8 blocks)."""
    rng = np.random.default_rng(T)
    K = 2
    sill = np.array([[4.0, 9.0, 1.0], [2.0, 2.0, 5.0]])
    length = np.array([[5.0, 10.0, 3.0], [20.0, 7.0, 2.0]])
    mean = rng.normal(size=(K, 3))
    cov = _cov(mean, sill, length)
    o = rng.normal(size=(T, K, 3)) * 2 + mean
    J = np.zeros((T, K, 3, 3))
    three = rng.random((T, K)) < 0.3
    one = (rng.random((T, K)) < 0.3) & ~three
    J[three] = np.eye(3) / 0.1
    J[one] = ray_information(rng.normal(size=(int(one.sum()), 3)), np.full(int(one.sum()), 0.2))
    pred, var = smooth_offsets(o, J, cov, lengths=length)
    assert pred.shape == (T, K, 3) and var.shape == (T, K, 3, 3)
    t = np.arange(T)
    for k in range(K):
        C = np.zeros((3 * T, 3 * T))
        for a in range(3):
            h = math.sqrt(3) * np.abs(t[:, None] - t[None]) / length[k, a]
            C[a::3, a::3] = sill[k, a] * (1 + h) * np.exp(-h)
        Pinv = np.linalg.inv(C)
        for f in sorted({0, min(7, T - 1), min(19, T - 1), T // 2, T - 1}):
            Jl, hl = np.zeros_like(C), np.zeros(3 * T)
            for s in range(T):
                if s != f:
                    Jl[3 * s : 3 * s + 3, 3 * s : 3 * s + 3] = J[s, k]
                    hl[3 * s : 3 * s + 3] = J[s, k] @ (o[s, k] - mean[k])
            S = np.linalg.inv(Pinv + Jl)
            m = S @ hl
            np.testing.assert_allclose(pred[f, k], m[3 * f : 3 * f + 3] + mean[k], atol=1e-4)
            np.testing.assert_allclose(
                var[f, k], S[3 * f : 3 * f + 3, 3 * f : 3 * f + 3], atol=1e-4
            )
    with pytest.raises(ValueError, match="info must be"):
        smooth_offsets(o, J[:, :1], cov)


def test_matern_lengths_read_the_semivariogram():
    sill = np.array([[4.0, 9.0, 1.0]])
    length = np.array([[3.0, 30.0, 300.0]])
    got = matern_lengths(_cov(np.zeros((1, 3)), sill, length, lags=(1, 2, 4, 8, 16, 64, 256)))
    np.testing.assert_allclose(got, length, rtol=0.1)


def test_a_view_is_its_ray():
    """A ray's information has no component along the ray and 1 / var across it; `view_rays`
    finds the part-frames one view was accepted for, their ray through the camera's centre and
    their across-ray variance (sd_factor x sigma_px x depth / focal)^2."""
    u = np.array([[0.0, 0.0, 2.0]])
    J = ray_information(u, np.array([0.25]))
    np.testing.assert_allclose(J[0] @ np.array([0.0, 0.0, 1.0]), 0.0)
    np.testing.assert_allclose(J[0] @ np.array([1.0, 0.0, 0.0]), [4.0, 0.0, 0.0])
    points = np.array([[[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]])  # (T=1, K=2, 3)
    weights = np.array([[[1.0, 0.0], [1.0, 1.0]]])  # part 0: camera 0 only; part 1: both
    centers = np.array([[0.0, 0.0, -500.0], [500.0, 0.0, 0.0]])
    R = np.stack([np.eye(3), np.eye(3)])
    t = -np.einsum("cij,cj->ci", R, centers)
    one, rays, var = view_rays(
        points, weights, centers, np.array([1000.0, 1000.0]), np.array([2.0, 2.0]), R, t, 3.0
    )
    assert one.tolist() == [[True, False]]
    np.testing.assert_allclose(rays[0, 0], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(var[0, 0], (3.0 * 2.0 * 500.0 / 1000.0) ** 2)


def _rays_scene():
    """One part whose offset holds at (12, -8, 5) mm, far from its mean (0), for 300 frames
    (10 at each end 3D-observed at the mean); in between one camera sees it every frame from a
    direction that turns with the body (in body axes, rays sweeping 180 deg: a half turn in 3 s
    at 100 fps). A view's fused point lies on its ray at the depth a first pass guessed (the
    mean's)."""
    T, K = 300, 1
    true = np.array([12.0, -8.0, 5.0])
    X = np.broadcast_to(true, (T, K, 3)).copy()
    observed = np.zeros((T, K), dtype=bool)
    observed[:10] = observed[-10:] = True
    X[:10] = X[-10:] = 0.0
    ang = np.linspace(-np.pi / 2, np.pi / 2, T)
    rays = np.stack([np.cos(ang), np.sin(ang), np.zeros(T)], -1)[:, None, :]
    fused = X - rays * (X * rays).sum(-1, keepdims=True)
    fused = np.where(observed[..., None], X, fused)
    return X, observed, rays, fused, true


def test_rays_find_a_part_only_single_views_see():
    """Smoothed with each view as its ray, the offset between the ends is found where the rays
    meet; the two-neighbour kriging of the views' fused points keeps the first pass's depth."""
    X, observed, rays, fused, true = _rays_scene()
    T, K = observed.shape
    cov = _cov(np.zeros((K, 3)), np.full((K, 3), 400.0), np.full((K, 3), 100.0))
    J = np.zeros((T, K, 3, 3))
    J[observed] = np.eye(3) / 0.25
    J[~observed] = ray_information(rays[~observed], np.full(int((~observed).sum()), 0.25))
    pred, var = smooth_offsets(fused, J, cov, lengths=np.full((K, 3), 100.0))
    mid = slice(110, 190)
    assert np.linalg.norm(pred[mid, 0] - true, axis=-1).max() < 4.0
    sd = np.sqrt(np.diagonal(var[mid, 0], axis1=-2, axis2=-1))
    assert np.all(np.abs(pred[mid, 0] - true) < 3 * sd)  # the covariance covers the error
    kriged, _ = krige_offsets(fused, np.ones((T, K), bool), cov)
    assert np.linalg.norm(kriged[150, 0] - true) > 5.0


def test_anchored_with_rays_uses_the_smoother():
    """`InterpObservation.anchored` with rays: where no 3D observation is, the prediction is the
    smoother's from the session's own covariance (the 3D observations with the nugget, the
    views as rays), its full covariance (rotated by `deformation_cov`) floored at the
    kriging's variance, the rays kept through `window`; without rays the fused points'
    kriging, which differs there."""
    X, observed, rays, fused, true = _rays_scene()
    T, K = observed.shape
    body = np.zeros((K, 3))
    noise = torch.full((T, K), 0.25, dtype=torch.float64)
    data = torch.tensor(np.where(observed[..., None], X, np.nan))
    obs = InterpObservation(torch.tensor(body), data, torch.tensor(observed), noise)
    poses = torch.zeros(T, 6, dtype=torch.float64)
    ncams = torch.tensor(np.where(observed, 2, 1))
    sd = torch.full((T, K), 20.0, dtype=torch.float64)
    rv = torch.full((T, K), 0.25, dtype=torch.float64)
    as_rays = obs.anchored(torch.tensor(fused), sd, ncams, torch.tensor(rays), rv)
    as_rays.prepare(poses)
    J = np.zeros((T, K, 3, 3))
    J[observed] = np.eye(3) / np.maximum(as_rays.cov.nugget[0], 1e-6)
    J[~observed] = ray_information(rays[~observed], np.full(int((~observed).sum()), 0.25))
    want, want_var = smooth_offsets(fused, J, as_rays.cov)
    gap = ~observed
    np.testing.assert_allclose(as_rays._M.numpy()[gap], want[gap], atol=1e-9)
    # its covariance scaled up to at least the two-neighbour kriging's variance (the trace)
    assert int(as_rays.outliers.sum()) == 0
    noise = np.where(observed[..., None], as_rays.cov.nugget[None], 400.0)  # anchors: sd^2
    _, kv = krige_offsets(fused, np.ones((T, K), bool), as_rays.cov, noise=noise)
    tr = np.trace(want_var, axis1=-2, axis2=-1)
    scale = np.maximum(1.0, kv.sum(-1) / tr)
    assert (scale[gap] > 1.01).any()  # the floor binds
    got = as_rays._var.numpy()[gap]
    np.testing.assert_allclose(got, want_var[gap] * scale[gap][:, None, None], rtol=1e-9)
    assert as_rays.deformation_cov(poses).shape == (T, K, 3, 3)
    w = as_rays.window(10, 50)
    assert w.rays.shape == (40, K, 3) and w.ray_var.shape == (40, K)
    as_fused = obs.anchored(torch.tensor(fused), sd, ncams)
    as_fused.prepare(poses)
    assert as_fused._var.shape == (T, K, 3)
    assert np.abs(as_fused._M.numpy()[gap] - want[gap]).max() > 1.0
    # a 3D-observed frame keeps the kriging from its neighbours, as without rays
    np.testing.assert_allclose(as_rays._M.numpy()[observed], as_fused._M.numpy()[observed])
    v = as_fused._var.numpy()[observed]
    np.testing.assert_allclose(as_rays._var.numpy()[observed], v[..., None] * np.eye(3))


def test_the_anchor_settings_are_checked():
    assert DeformConfig().anchors == "rays"
    with pytest.raises(InputError, match="deform.anchors"):
        DeformConfig(anchors="ray")
    with pytest.raises(InputError, match="ray_sd_factor"):
        DeformConfig(ray_sd_factor=0.5)


def test_the_smoother_is_used_only_for_the_parts_it_predicts_better():
    """Per part, the smoother replaces the kriging only where it predicts the left-out views
    better across their rays (`across_ray_rms`); a part with too few views to tell (here 10,
    under its 20) keeps the fused kriging."""
    X, observed, rays, fused, true = _rays_scene()
    T = X.shape[0]
    few = np.zeros((T, 1), bool)
    few[100:110] = True  # part 1: ten single views, no view elsewhere in the gap
    Xa = np.concatenate([X, X], 1)
    Fa = np.concatenate([fused, fused], 1)
    Oa = np.concatenate([observed, observed], 1)
    ncams = np.where(Oa, 2, 1)
    ncams[:, 1] = np.where(observed[:, 0], 2, np.where(few[:, 0], 1, 0))
    K = 2
    data = torch.tensor(np.where(Oa[..., None], Xa, np.nan))
    noise = torch.full((T, K), 0.25, dtype=torch.float64)
    obs = InterpObservation(torch.zeros(K, 3, dtype=torch.float64), data, torch.tensor(Oa), noise)
    args = (torch.tensor(Fa), torch.full((T, K), 20.0, dtype=torch.float64), torch.tensor(ncams))
    poses = torch.zeros(T, 6, dtype=torch.float64)
    as_rays = obs.anchored(*args, torch.tensor(np.concatenate([rays, rays], 1)),
                           torch.full((T, K), 0.25, dtype=torch.float64))  # fmt: skip
    as_rays.prepare(poses)
    as_fused = obs.anchored(*args)
    as_fused.prepare(poses)
    assert as_rays.ray_parts.tolist() == [True, False]
    np.testing.assert_allclose(as_rays._M.numpy()[:, 1], as_fused._M.numpy()[:, 1])
    assert np.abs(as_rays._M.numpy()[:, 0] - as_fused._M.numpy()[:, 0]).max() > 1.0
    r = np.zeros((4, 2, 3))
    r[..., 0] = 1.0  # rays along x: only y and z count
    resid = np.tile(np.array([5.0, 3.0, 4.0]), (4, 2, 1))
    np.testing.assert_allclose(across_ray_rms(resid, r, np.ones((4, 2), bool), 4), [5.0, 5.0])
    assert np.isnan(across_ray_rms(resid, r, np.ones((4, 2), bool), 5)).all()


def _one_part_observation(X, observed, rays, fused):
    """`_rays_scene`'s part as an `InterpObservation` (3D observations of noise 0.25 mm^2) and
    the arguments of its `anchored` (the views' fused points with a view's whole sd, 20 mm; each
    view also as its ray, 0.25 mm^2 across it), with zero poses."""
    T, K = observed.shape
    data = torch.tensor(np.where(observed[..., None], X, np.nan))
    noise = torch.full((T, K), 0.25, dtype=torch.float64)
    obs = InterpObservation(torch.zeros(K, 3, dtype=torch.float64), data, torch.tensor(observed),
                            noise)  # fmt: skip
    args = (torch.tensor(fused), torch.full((T, K), 20.0, dtype=torch.float64),
            torch.tensor(np.where(observed, 2, 1)))  # fmt: skip
    ray_args = (torch.tensor(rays), torch.full((T, K), 0.25, dtype=torch.float64))
    return obs, args, ray_args, torch.zeros(T, 6, dtype=torch.float64)


def test_the_smoothed_gaps_covariance_counts_the_two_predictions_disagreement():
    """With ``disagreement`` w, a smoothed part-frame's prior covariance is the smoother's own
    plus w d d^T, d the smoother's prediction minus the kriging's (where the kriging keeps the
    first pass's depth along the rays, the two disagree along them); 3D-observed frames keep
    the kriging's covariance unchanged."""
    X, observed, rays, fused, true = _rays_scene()
    obs, args, ray_args, poses = _one_part_observation(X, observed, rays, fused)
    out = {}
    for w in (0.0, 1.0):
        o = obs.anchored(*args, *ray_args, disagreement=w)
        o.prepare(poses)
        assert o.ray_parts.tolist() == [True]
        out[w] = (o._M.numpy()[:, 0], o._var.numpy()[:, 0])
    np.testing.assert_array_equal(out[0.0][0], out[1.0][0])  # the prediction is the smoother's
    krig = obs.anchored(*args)  # the fused anchors' kriging: the other prediction
    krig.prepare(poses)
    d = out[0.0][0] - krig._M.numpy()[:, 0]
    extra = out[1.0][1] - out[0.0][1]  # (T, 3, 3)
    gap = ~observed[:, 0]
    np.testing.assert_allclose(extra[gap], d[gap, :, None] * d[gap, None, :], atol=1e-9)
    assert np.median(np.linalg.norm(d[gap], axis=-1)) > 1.0  # the two do disagree here
    assert np.abs(extra[~gap]).max() == 0.0
    with pytest.raises(ValueError, match="disagreement must be >= 0"):
        obs.anchored(*args, *ray_args, disagreement=-1.0)


def test_observations_the_smoother_contradicts_are_rejected():
    """``outliers=True`` (``deform.ray_outliers``; the kriging's own outlier rounds off here): a
    3D observation 25 mm off in a stretch the rays pin down (two views fused, one wrong along
    the epipolar line), and a single view 20 mm off across its ray, are rejected once at the
    first poses (``ray_rejected``); the prediction around them follows the rays again.
    Without it the wrong point pulls its neighbours."""
    X, observed, rays, fused, true = _rays_scene()
    obs3 = observed.copy()
    obs3[150] = True  # a wrong 3D observation in the single views' stretch
    X3 = X.copy()
    X3[150, 0] = true + np.array([0.0, 0.0, 25.0])
    fused = fused.copy()
    side = np.cross(rays[100, 0], [0.0, 0.0, 1.0])
    fused[100, 0] += 20.0 * side / np.linalg.norm(side)  # a wrong single view, across its ray
    obs, args, ray_args, poses = _one_part_observation(X3, obs3, rays, fused)
    err = {}
    for flag in (False, True):
        o = obs.anchored(*args, *ray_args, outliers=flag)
        o.outlier_rounds = 0  # the kriging's own rounds off: this check alone
        o.prepare(poses)
        err[flag] = np.linalg.norm(o._M.numpy()[:, 0] - true, axis=-1)
        if flag:
            rej = o.ray_rejected.numpy()[:, 0]
            assert rej[150] and rej[100]
            assert rej[20:280].sum() == 2  # the rest of the stretch kept
            assert o.outliers.numpy()[[100, 150], 0].all()
        else:
            assert o.ray_rejected is None
            assert not o.outliers.numpy()[[100, 150], 0].any()
    near = slice(140, 161)
    assert err[True][near].max() < 0.5 * err[False][near].max()


def _interp_covariance(cov: OffsetCovariance, h: np.ndarray) -> np.ndarray:
    """The definition `OffsetCovariance.covariance` vectorises: per part and axis, the sill
    minus np.interp of the semivariogram (0 at lag 0, the sill beyond the last lag)."""
    lag = np.concatenate(([0.0], cov.lags.astype(np.float64)))
    out = np.empty((*h.shape, 3))
    for k in range(h.shape[1]):
        for a in range(3):
            g = np.concatenate(([0.0], cov.gamma[k, a]))
            out[:, k, a] = cov.sill[k, a] - np.interp(h[:, k], lag, g, right=cov.sill[k, a])
    return np.maximum(out, 0.0)


def test_the_vectorised_covariance_is_np_interps_to_the_bit():
    rng = np.random.default_rng(1)
    T, K = 1500, 5
    o = np.cumsum(rng.standard_normal((T, K, 3)), 0) * 0.3
    cov = OffsetCovariance.estimate(o, rng.random((T, K)) < 0.6)
    top = int(cov.lags[-1])
    for h in (
        rng.integers(0, 3 * top, (T, K)).astype(float),  # whole lags: the tabulated path
        rng.integers(0, 10, (T, K)).astype(float),
        rng.random((T, K)) * 1.5 * top,  # between lags
        np.array([[0.0] * K, [float(top)] * K, [top + 0.5] * K]),  # the ends, few frames
    ):
        assert np.array_equal(cov.covariance(h), _interp_covariance(cov, h))
    hi = rng.integers(0, 3 * top, (T, K))
    assert np.array_equal(cov.lag_covariance(hi), _interp_covariance(cov, hi.astype(float)))


def test_the_elementwise_inverse_is_numpys():
    """The cofactor 3 x 3 inverse of general matrices (the Kalman update's) equals
    np.linalg.inv's."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(200, 3, 3)) + 2 * np.eye(3)
    np.testing.assert_allclose(_inv3_general(A), np.linalg.inv(A), rtol=1e-9, atol=1e-12)
