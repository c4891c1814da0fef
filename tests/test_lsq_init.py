"""`kalman_smooth` and `unwrap_rotations` (adjust/lsq/init.py): exact on what their models
describe (constant velocity; a turn through pi)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from adjust.lsq.geometry import so3_exp, so3_log
from adjust.lsq.init import consistent_fits, kalman_smooth, unwrap_rotations
from deformnet.so3 import matrix_to_rodrigues, rodrigues_to_matrix

T = 50
LINE = np.stack([3 + 2.0 * np.arange(T), -1 - 0.5 * np.arange(T)], -1)


@pytest.mark.parametrize(("meas", "accel"), [(1.0, 0.1), (2.0, 50.0), (0.01, 1.0)])
def test_kalman_constant_velocity_is_exact(meas, accel):
    out = kalman_smooth(LINE, np.ones(T, bool), np.full(2, meas), np.full(2, accel))
    np.testing.assert_allclose(out, LINE, rtol=0, atol=1e-6)


def test_kalman_bridges_gaps_and_leading_frames():
    ok = np.ones(T, bool)
    ok[:5] = False  # before the first measurement: extrapolated back
    ok[20:35] = False  # a gap: bridged along the line
    out = kalman_smooth(LINE, ok, np.ones(2), np.full(2, 0.1))
    np.testing.assert_allclose(out, LINE, rtol=0, atol=1e-4)


def test_kalman_smooths_noise_and_bridges_a_gap():
    """What holds today: noise is reduced, a gap is bridged close to the line."""
    rng = np.random.default_rng(0)
    z = LINE + rng.normal(0, 1.0, LINE.shape)
    ok = np.ones(T, bool)
    ok[20:30] = False
    out = kalman_smooth(z, ok, np.ones(2), np.full(2, 0.05))
    assert np.sqrt(np.mean((out - LINE) ** 2)) < 0.5 * np.sqrt(np.mean((z - LINE) ** 2))
    assert np.abs(out[20:30] - LINE[20:30]).max() < 1.0
    assert np.isfinite(kalman_smooth(z, np.zeros(T, bool), np.ones(2), np.ones(2))).all()


def test_unwrap_rotations_through_pi():
    """A steady turn through pi: the rotation vectors of the matrices jump (|r| <= pi, the
    axis flips); unwrapped they are the continuous angle times the axis, to rounding."""
    axis = np.array([0.3, -0.2, 0.93])
    axis /= np.linalg.norm(axis)
    angle = np.linspace(0.0, 1.8 * np.pi, 60)
    truth = angle[:, None] * axis
    wrapped = matrix_to_rodrigues(rodrigues_to_matrix(torch.as_tensor(truth))).numpy()
    assert np.abs(wrapped - truth).max() > 5.0  # the wrap is there
    np.testing.assert_allclose(unwrap_rotations(wrapped), truth, rtol=0, atol=1e-9)
    # continuous input is left as it is; a zero rotation too
    np.testing.assert_allclose(unwrap_rotations(truth[:30]), truth[:30], rtol=0, atol=1e-12)
    assert np.array_equal(unwrap_rotations(np.zeros((3, 3))), np.zeros((3, 3)))


def test_consistent_fits_drop_flipped_fits():
    """Fits that turn by > 45 degrees from their neighbours in time are dropped (strong ones by
    their strong neighbours' vote, weak ones against the kept strong fits' interpolation); the
    others, a real turn included, are kept."""
    T = 200
    t = torch.arange(T, dtype=torch.float64)
    poses = torch.zeros(T, 6, dtype=torch.float64)
    poses[:, 2] = 0.02 * t  # a steady turn about z: 230 degrees over the track
    poses[:, 3] = t
    flipped = poses.clone()
    bad = [20, 21, 90, 151]
    for f in bad:  # the same frames flipped by 180 degrees about the body's long axis
        R = so3_exp(poses[f, :3]) @ so3_exp(torch.tensor([0.0, torch.pi, 0.0], dtype=torch.float64))
        flipped[f, :3] = so3_log(R)
    ok = torch.ones(T, dtype=torch.bool)
    strong = torch.ones(T, dtype=torch.bool)
    strong[1::2] = False  # every other fit weak
    keep, facts = consistent_fits(flipped, ok, strong)
    assert sorted(torch.nonzero(~keep).ravel().tolist()) == bad
    assert facts == {"dropped_strong": 2, "dropped_weak": 2}
    keep, _ = consistent_fits(poses, ok, strong)
    assert bool(keep.all())
