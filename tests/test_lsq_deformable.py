"""adjust.lsq pluggable observation: the deformable path with a stand-in DeformationModel."""

from __future__ import annotations

import torch
from torch import nn

from adjust.camera import CameraTensors, project_cameras
from adjust.lsq import DeformableObservation, SolverConfig, adjust_poses, synthetic
from adjust.lsq.geometry import pose_difference, retract
from deformnet.body import default_mouse

F64 = torch.float64


class _Bend(nn.Module):
    """Stand-in with the DeformationModel call: mid-frame rigid points pulled towards the window
    mean, plus a pose-dependent bend (differentiable in `rigid`)."""

    def __init__(self, window: int) -> None:
        super().__init__()
        self.n = window // 2
        self.scale = nn.Parameter(torch.tensor(0.2, dtype=F64))

    def forward(self, rigid, deformed, observed):
        mid = rigid[..., self.n, :, :]
        bend = (
            torch.tanh(mid[..., :1] / 50.0) * self.scale * torch.tensor([0.0, 0.0, 5.0], dtype=F64)
        )
        return mid + 0.1 * (rigid.mean(-3) - mid) + bend


def test_deformable_observation_jacobian_and_noiseless_recovery(one_thread):
    body = torch.tensor(default_mouse().points)
    cams = CameraTensors.from_cameras(synthetic.ring_cameras(3))
    T, W = 16, 5
    truth = synthetic.smooth_trajectory(T, seed=7)
    model = _Bend(W)
    obs = DeformableObservation(model, body, W)
    obs.prepare(truth)
    X, J = obs.points(truth, jacobian=True)
    eps = 1e-6
    for i in range(6):
        d = torch.zeros(T, 6, dtype=F64)
        d[:, i] = eps
        fd = (
            obs.points(retract(truth, d), False)[0] - obs.points(retract(truth, -d), False)[0]
        ) / (2 * eps)
        torch.testing.assert_close(J[..., i], fd, rtol=1e-5, atol=1e-6)
    # detections of the deformed points; the adjustment with the model recovers the poses
    xy = project_cameras(X.detach(), cams)
    cfg = SolverConfig(num_threads=1, robust="none", sigma_def_mm=0.0, constraint="grid")
    res = adjust_poses(
        xy, None, cams, body, cfg, observation=DeformableObservation(model, body, W), progress=False
    )
    d = pose_difference(torch.as_tensor(res.poses), truth)
    # measured: 2.7e-6 mm, 4.1e-8 rad, model points 3.0e-6 mm (the solver's stopping rules)
    assert float(d[:, 3:].abs().max()) < 1e-5 and float(d[:, :3].abs().max()) < 2e-7
    torch.testing.assert_close(torch.as_tensor(res.model_points), X, atol=1e-5, rtol=0)
    # the rigid model alone cannot explain these detections as well
    rigid = adjust_poses(xy, None, cams, body, cfg, progress=False)
    assert abs(rigid.residuals).max() > 10 * abs(res.residuals).max()
