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
    from adjust.lsq.net_observation import NetObservation

    model = _model()
    body, poses, data, observed = _problem()
    frozen = NetObservation(model, body, model.window, data, observed, 30.0, 4096, "frozen")
    central = NetObservation(model, body, model.window, data, observed, 30.0, 4096, "central")
    frozen.prepare(poses)
    central.prepare(poses)
    X, J = frozen.points(poses)
    Xc, Jc = central.points(poses)
    torch.testing.assert_close(X, Xc)  # same observation function value
    # the prediction in body coordinates, held fixed, moved by perturbed poses
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
    from adjust.lsq.net_observation import NetObservation

    model = _model(perturb=False)
    body, poses, data, observed = _problem()
    frozen = NetObservation(model, body, model.window, data, observed, 30.0, 4096, "frozen")
    central = NetObservation(model, body, model.window, data, observed, 30.0, 4096, "central")
    frozen.prepare(poses)
    central.prepare(poses)
    torch.testing.assert_close(
        frozen.points(poses)[1], central.points(poses)[1], atol=1e-5, rtol=1e-5
    )


def test_unknown_jacobian_mode_is_refused():
    import pytest

    from adjust.lsq.net_observation import NetObservation

    model = _model()
    body, _, data, observed = _problem()
    with pytest.raises(ValueError, match="deform.jacobian"):
        NetObservation(model, body, model.window, data, observed, 30.0, 64, "exact")


def test_frozen_solve_reaches_the_central_difference_solution(tmp_path):
    """adjust-track with a net that deforms: the default frozen-Jacobian solve ends at the same
    points as the full central-difference one, and both differ from the rigid track."""
    import hydra
    import numpy as np

    from adjust.apps.simulate import run as simulate
    from adjust.apps.track import run as track
    from adjust.io import read_points3d
    from deformnet.paths import CONF_DIR

    def compose(name, overrides):
        with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
            return hydra.compose(name, overrides=overrides)

    scene = tmp_path / "scene"
    simulate(compose("scene", [f"output.dir={scene}", "num_frames=80", "seed=5"]))
    model = tiny_deformation_model(seed=1)
    gen = torch.Generator().manual_seed(2)
    with torch.no_grad():  # a fixed, non-trivial function of its inputs: it deforms
        for p in model.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=gen))
    ckpt = tmp_path / "net.ckpt"
    model.save(ckpt)
    pts = {}
    for name, ov in (
        ("rigid", ["deformation=rigid"]),
        (
            "frozen",
            [
                f"deformation={ckpt}",
                "deform.jacobian=frozen",
                "deform.max_iterations=30",
                "deform.refresh=30",  # the fixed point of the frozen iteration
            ],
        ),
        ("central", [f"deformation={ckpt}", "deform.jacobian=central", "deform.max_iterations=30"]),
    ):
        out = tmp_path / name
        track(
            compose(
                "track",
                [
                    f"input.calibration={scene / 'calibration.toml'}",
                    f"input.detections={scene / 'detections'}",
                    f"output.dir={out}",
                    "progress=false",
                    # the net's Jacobian is the subject: interp's single views as fused points
                    # (as rays, interp's own prediction turns with the pose too, which neither
                    # the frozen nor the central Jacobian of the net is about)
                    "deform.anchors=fused",
                    *ov,
                ],
            )
        )
        pts[name] = read_points3d(out / "points3d.csv")["points"]

    def rms(a, b):
        return float(np.sqrt(np.mean(np.sum((a - b) ** 2, -1))))

    moved = rms(pts["frozen"], pts["rigid"])
    assert moved > 0.5, moved  # the net deforms the track
    # measured: moved 1.16 mm, frozen vs central 0.017 mm. (The frozen Jacobian neglects how the
    # prediction changes with the frame's pose relative to its neighbours; with a net 3x as
    # pose-dependent, moving points by 11 mm, its fixed point is 3.4 mm from the full one.)
    assert rms(pts["frozen"], pts["central"]) < 0.05 * moved, (
        rms(pts["frozen"], pts["central"]),
        moved,
    )
