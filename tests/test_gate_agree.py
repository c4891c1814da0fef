"""The fusion's innovation gate: which cameras may outvote a part's prediction (issue 45).

Two detections of one part-frame that both fail the gate used to be kept as "cameras that
agree with each other" without any check that they do: a correct view and a far outlier, or
two unrelated far outliers, were fused into a point tens of mm off (real motion, validation
segment, 3 cameras: 10-13 part-frames in 8,000 with a far outlier fused carried 12-21% of the
squared error). With a consensus triangulation (`trusted` / ``agree``) only the views it found
to agree outvote.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from adjust.camera import CameraTensors, project_cameras
from adjust.lsq import SolverConfig, adjust_poses, synthetic
from adjust.lsq.fusion import innovation_gate
from adjust.lsq.observation import RigidObservation
from deformnet.body import default_mouse

F64 = torch.float64

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def cams():
    return CameraTensors.from_cameras(synthetic.ring_cameras(3), dtype=F64)


def _frame(cams, X: torch.Tensor, offsets) -> tuple[torch.Tensor, torch.Tensor]:
    """One part-frame's detections of X (3,) in the 3 cameras, moved by offsets (3, 2) px
    (NaN: no detection), and the valid mask, as (1, 1, C, ...) tensors."""
    xy = project_cameras(X[None, None], cams) + torch.as_tensor(offsets, dtype=F64)[None, None]
    return xy, torch.isfinite(xy).all(-1)


def test_gate_keeps_failing_views_only_where_they_agree(cams):
    prior = torch.tensor([0.0, 0.0, 20.0], dtype=F64)
    P = torch.eye(3, dtype=F64)[None, None]  # 1 mm^2: a confident prediction
    nan = float("nan")
    # two unrelated far outliers (the third camera saw nothing)
    xy, valid = _frame(cams, prior, [[120.0, 40.0], [-60.0, 150.0], [nan, nan]])
    old, d2 = innovation_gate(prior[None, None], P, xy, valid, cams, 1.0)
    assert old[0, 0, :2].all() and (d2[0, 0, :2] > 100).all()  # without a say: outvoted
    none_agree = torch.zeros_like(valid)
    ok, _ = innovation_gate(prior[None, None], P, xy, valid, cams, 1.0, agree=none_agree)
    assert not ok.any()
    # two correct views of a point 25 mm from the prediction: they agree and outvote it
    moved = prior + torch.tensor([25.0, 0.0, 0.0], dtype=F64)
    xy, valid = _frame(cams, moved, [[0.0, 0.0], [0.0, 0.0], [nan, nan]])
    ok, d2 = innovation_gate(prior[None, None], P, xy, valid, cams, 1.0, agree=valid)
    assert (d2[0, 0, :2] > 100).all() and ok[0, 0, :2].all()


def test_solver_fuses_no_far_outlier_pair_the_consensus_did_not_trust(cams):
    """adjust_poses with a consensus (``trusted``): a part-frame whose two detections are
    unrelated far outliers falls back to the model instead of their fused point."""
    body = torch.tensor(default_mouse().points, dtype=F64)
    T, K = 30, body.shape[0]
    truth = synthetic.smooth_trajectory(T, seed=3)
    xy, w, X = synthetic.simulate(truth, body, cams, noise_px=0.5, seed=2)
    t, k = 15, 2
    xy[t, k, 0] += torch.tensor([120.0, 40.0], dtype=F64)
    xy[t, k, 1] += torch.tensor([-60.0, 150.0], dtype=F64)
    xy[t, k, 2] = float("nan")
    valid = torch.isfinite(xy).all(-1)
    trusted = valid.clone()
    trusted[t, k] = False  # two views that disagree: no consensus
    obs = RigidObservation(body, torch.ones(K, 3, dtype=F64))
    cfg = SolverConfig(num_threads=1, sigma_det_px=0.5, max_iterations=10)
    res = adjust_poses(xy, w, cams, body, cfg, observation=obs, progress=False, trusted=trusted)
    assert np.all(np.asarray(res.weights)[t, k] == 0)
    err = float(np.linalg.norm(np.asarray(res.points)[t, k] - X[t, k].numpy()))
    assert err < 5.0, err  # both outliers fused: tens of mm
