"""adjust-track's default deformable Jacobian ("frozen"): exact for the frozen-prediction
function, the same points as the finite-difference modes, and close to the full Jacobian."""

import torch
from helpers import tiny_deformation_model

from adjust.lsq.geometry import retract
from deformnet.body import default_mouse
from deformnet.deformation import DeformationModel
from deformnet.so3 import rodrigues_to_matrix


def _model(perturb: bool = True) -> DeformationModel:
    model = tiny_deformation_model()
    for p in model.parameters():  # an untrained net predicts the rigid model: perturb it
        p.requires_grad_(False)
        if perturb:
            p.add_(0.3 * torch.randn_like(p))
    return model.double().eval()


def _problem(T: int = 12):
    gen = torch.Generator().manual_seed(3)
    body = torch.tensor(default_mouse().points)
    poses = torch.cat(
        (
            0.3 * torch.randn(T, 3, generator=gen, dtype=torch.float64),
            50 * torch.randn(T, 3, generator=gen, dtype=torch.float64),
        ),
        -1,
    )
    data = (
        body[None]
        + poses[:, None, 3:]
        + 2 * torch.randn(T, 8, 3, generator=gen, dtype=torch.float64)
    )
    observed = torch.rand(T, 8, generator=gen) > 0.3
    return body, poses, data, observed


def test_frozen_jacobian_is_exact_for_the_frozen_prediction():
    from adjust.track import _measured_observation_class

    model = _model()
    body, poses, data, observed = _problem()
    cls = _measured_observation_class()
    frozen = cls(model, body, model.window, data, observed, 30.0, 4096, "frozen")
    central = cls(model, body, model.window, data, observed, 30.0, 4096, "central")
    frozen.prepare(poses)
    central.prepare(poses)
    X, J = frozen.points(poses)
    Xc, Jc = central.points(poses)
    torch.testing.assert_close(X, Xc)  # same observation function value
    # the prediction in body coordinates, held fixed, moved by perturbed poses
    R = (
        torch.stack([torch.linalg.matrix_exp(torch.zeros(3, 3, dtype=X.dtype))] * 0)
        if False
        else None
    )
    R = rodrigues_to_matrix(poses[:, :3])
    c = torch.einsum("tji,tkj->tki", R, X - poses[:, None, 3:])
    h = 1e-6
    for j in range(6):
        d = torch.zeros_like(poses)
        d[:, j] = h
        pp, pm = retract(poses, d), retract(poses, -d)
        Xp = torch.einsum("tij,tkj->tki", rodrigues_to_matrix(pp[:, :3]), c) + pp[:, None, 3:]
        Xm = torch.einsum("tij,tkj->tki", rodrigues_to_matrix(pm[:, :3]), c) + pm[:, None, 3:]
        torch.testing.assert_close(J[..., j], (Xp - Xm) / (2 * h), atol=1e-6, rtol=1e-6)
    # the neglected part is the prediction's change with the pose relative to the neighbours
    assert (J - Jc).norm() > 1e-3 * Jc.norm()


def test_frozen_jacobian_equals_full_one_for_a_rigid_prediction():
    """An untrained net (zero-initialised head) predicts the rigid model: nothing is neglected."""
    from adjust.track import _measured_observation_class

    model = _model(perturb=False)
    body, poses, data, observed = _problem()
    cls = _measured_observation_class()
    frozen = cls(model, body, model.window, data, observed, 30.0, 4096, "frozen")
    central = cls(model, body, model.window, data, observed, 30.0, 4096, "central")
    frozen.prepare(poses)
    central.prepare(poses)
    torch.testing.assert_close(
        frozen.points(poses)[1], central.points(poses)[1], atol=1e-5, rtol=1e-5
    )


def test_unknown_jacobian_mode_is_refused():
    import pytest

    from adjust.track import _measured_observation_class

    model = _model()
    body, _, data, observed = _problem()
    with pytest.raises(ValueError, match="deform.jacobian"):
        _measured_observation_class()(model, body, model.window, data, observed, 30.0, 64, "exact")
