"""interp's world prior (``deform.world_prior``, `InterpObservation.world_prior`): a part no
camera pair sees is also held near where its 3D observations in the neighbouring frames put it
in the world; its prediction, its cost term's derivatives, and a recording where it matters."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from adjust.camera import CameraTensors
from adjust.lsq import SolverConfig, synthetic
from adjust.lsq.geometry import retract
from adjust.lsq.observation import InterpObservation, RigidObservation
from adjust.lsq.problem import Problem, evaluate, normal_equations, total_cost
from adjust.lsq.solver import isolated_pairs
from deformnet.body import default_mouse

F64 = torch.float64
pytestmark = pytest.mark.usefixtures("one_thread")


def test_the_world_prediction_interpolates_between_observations_only():
    """W is the straight line between the observations around a gap, its information > 0 in
    the gap only: not where the part is observed, not before its first or after its last
    observation."""
    T, K = 400, 2
    t = np.arange(T, dtype=np.float64)
    X = np.zeros((T, K, 3))
    X[:, 0, 0] = 2.0 * t  # part 0 walks along x at 2 mm per frame
    rng = np.random.default_rng(0)
    X[:, 1] = np.cumsum(rng.normal(0.0, 1.0, (T, 3)), 0)  # part 1 wanders (a random walk)
    three = np.ones((T, K), bool)
    three[20:30] = False  # a gap of both parts
    three[350:, 1] = False  # part 1 never seen again
    W, info = InterpObservation._world_prior(X, three, X, None, np.full((T, K), 1.0))
    assert W.shape == (T, K, 3) and info.shape == (T, K)
    np.testing.assert_allclose(W[20:30, 0], X[20:30, 0], atol=1e-6)  # exact on a straight walk
    lin = X[19, 1] + (X[30, 1] - X[19, 1]) * (t[20:30, None] - 19) / 11
    np.testing.assert_allclose(W[20:30, 1], lin, atol=1e-6)  # the line between the two ends
    assert (info[20:30] > 0).all()
    assert (info[three] == 0).all()
    assert (info[350:, 1] == 0).all()  # beyond the last observation: left to the body frame
    # a wandering part's information falls towards the middle of its gap
    assert info[20, 1] > info[24, 1] and info[29, 1] > info[25, 1]


class _WithPrior(RigidObservation):
    """The rigid model with a fixed world prior (W, info)."""

    def __init__(self, body, W, info):
        super().__init__(body)
        self._wp = (W, info)

    def world_prior(self, poses):
        return self._wp


def test_the_world_prior_term_has_the_cost_s_gradient_and_curvature():
    """normal_equations' right-hand side is minus the gradient of total_cost's world-prior
    term and its diagonal block the Gauss-Newton curvature (central differences, float64)."""
    body = torch.tensor(default_mouse().points, dtype=F64)
    K = body.shape[0]
    cams = CameraTensors.from_cameras(synthetic.ring_cameras(3)).to(F64)
    T, C = 3, cams.R.shape[0]
    g = torch.Generator().manual_seed(0)
    poses = torch.cat([0.3 * torch.randn(T, 3, generator=g, dtype=F64),
                       torch.randn(T, 3, generator=g, dtype=F64) * 20], -1)  # fmt: skip
    W = 10 * torch.randn(T, K, 3, generator=g, dtype=F64)
    info = torch.rand(T, K, generator=g, dtype=F64)
    info[0, :3] = 0.0
    cfg = SolverConfig(constraint="none", num_threads=1)
    xy = torch.zeros(T, K, C, 2, dtype=F64)
    none = torch.zeros(T, K, C, dtype=torch.bool)
    pb = Problem(xy, none.to(F64), none, cams, _WithPrior(body, W, info), cfg, 1.0, None,
                 cams.focal.to(F64))  # fmt: skip
    wmix = torch.ones(T, K, C, dtype=F64)

    def cost(delta: np.ndarray) -> float:
        p = retract(poses, torch.as_tensor(delta, dtype=F64))
        return total_cost(evaluate(p, pb, jacobian=False), pb, wmix)

    lin = evaluate(poses, pb, jacobian=True)
    blocks, rhs = normal_equations(lin, torch.zeros(T, K, C, dtype=F64), pb)
    h = 1e-6
    grad = np.zeros((T, 6))
    for i in range(T):
        for j in range(6):
            d = np.zeros((T, 6))
            d[i, j] = h
            grad[i, j] = (cost(d) - cost(-d)) / (2 * h)
    np.testing.assert_allclose(rhs, -grad, rtol=1e-5, atol=1e-6)
    expected = 0.5 * float((info * ((W - lin.X) ** 2).sum(-1)).sum())
    assert abs(cost(np.zeros((T, 6))) - expected) < 1e-9
    # a step along the Gauss-Newton direction of one frame lowers the cost as its model predicts
    step = np.zeros((T, 6))
    step[1] = np.linalg.solve(blocks[0][1], rhs[1]) * 1e-3
    predicted = -float(rhs[1] @ step[1]) + 0.5 * float(step[1] @ blocks[0][1] @ step[1])
    assert cost(step) - cost(np.zeros((T, 6))) == pytest.approx(predicted, rel=1e-3)


def test_isolated_pairs():
    """A rejected 3D observation loses its two views' trust only when no other rejection of the
    part lies within ISOLATED frames and exactly two views made it."""
    T, K, C = 12, 2, 3
    rejected = torch.zeros(T, K, dtype=torch.bool)
    rejected[3, 0] = rejected[7, 0] = rejected[8, 0] = rejected[0, 1] = rejected[10, 1] = True
    trusted = torch.zeros(T, K, C, dtype=torch.bool)
    trusted[..., :2] = True
    trusted[10, 1, 2] = True  # three views
    out = isolated_pairs(rejected, trusted)
    assert out.nonzero().tolist() == [[0, 1], [3, 0]]


def test_a_chunk_of_the_observation_keeps_its_settings():
    """`InterpObservation.window` (the solver's chunks, sessions over `solver.chunk_size`
    frames) carries every setting of the whole: the rays' disagreement and outlier check, the
    world prior, the gated pairs."""
    T, K = 40, 2
    body = torch.zeros(K, 3, dtype=F64)
    data = torch.randn(T, K, 3, dtype=F64)
    obs = InterpObservation(body, data, torch.ones(T, K, dtype=torch.bool))
    obs.world_prior_on, obs.gate_pairs = True, True
    rays = np.tile(np.array([0.0, 0.0, 1.0]), (T, K, 1))
    a = obs.anchored(data.numpy(), np.ones((T, K)), np.ones((T, K), int), rays,
                     np.ones((T, K)), disagreement=0.5, outliers=True)  # fmt: skip
    w = a.window(5, 30)
    assert w is not a and w.observed.shape == (25, K)
    for name in ("ray_disagreement", "ray_outliers", "world_prior_on", "gate_pairs"):
        assert getattr(w, name) == getattr(a, name), name
    assert (w.ray_disagreement, w.ray_outliers) == (0.5, True)
