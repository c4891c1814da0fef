"""The rigid model from the detections themselves (`place_from_rays`, `body_fit.refine`) and the
held-out-camera choice of the measured part-frames' prior (`held_out_view_errors`,
`choose_measured_prior`, `deformation=self`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_real_mice import track, write_session

from adjust.camera import CameraTensors, project_cameras
from adjust.estimate import place_from_rays
from adjust.io import read_points3d
from adjust.lsq.fusion import held_out_view_errors
from adjust.lsq.synthetic import ring_cameras, smooth_trajectory
from adjust.validate import choose_measured_prior
from deformnet.body import default_mouse
from deformnet.so3 import transform_points


def _scene(T=300, n_cams=3, seed=0, deform_mm=0.0, bias_px=0.0, noise_px=0.5):
    """A mouse-sized body on a smooth track filmed by a camera ring: true points (T, K, 3),
    poses (T, 6), detections (T, K, C, 2) with noise, an optional smooth deformation (AR(1)
    body-frame offsets of ``deform_mm`` rms per axis) and a persistent per part and camera
    detector bias of ``bias_px`` rms per image axis."""
    rng = np.random.default_rng(seed)
    body = default_mouse()
    K = body.num_parts
    poses = smooth_trajectory(T, seed=seed, speed=0.5)
    off = np.zeros((T, K, 3))
    phi = 0.95
    for t in range(1, T):
        off[t] = phi * off[t - 1] + rng.normal(size=(K, 3)) * deform_mm * np.sqrt(1 - phi**2)
    X = transform_points(poses, torch.tensor(body.points) + torch.as_tensor(off)).numpy()
    cams = ring_cameras(n_cams, radius=600.0, height=450.0)
    ct = CameraTensors.from_cameras(cams, dtype=torch.float64)
    uv = project_cameras(torch.as_tensor(X), ct).numpy()
    uv = uv + rng.normal(size=uv.shape) * noise_px + rng.normal(size=(K, n_cams, 2)) * bias_px
    return body, poses.numpy(), X, cams, ct, uv


# ---------------------------------------------------------------------------------------------
# place_from_rays
# ---------------------------------------------------------------------------------------------
def test_place_from_rays_finds_a_part_that_one_camera_sees():
    """A part seen by one camera only (never triangulated), starting at the body's centre, is
    placed within a millimetre of its true body-frame point from 300 frames of 0.5 px noise;
    its spread is small (the body is rigid), the untouched parts keep point and variance."""
    body, poses, _, _, ct, uv = _scene()
    K = body.num_parts
    uv[:, 7, 1:] = np.nan  # tail root: camera 0 only
    B0 = np.array(body.points)
    B0[7] = B0.mean(0)
    var = np.full((K, 3), 4.0)
    which = np.zeros(K, bool)
    which[7] = True
    w = np.isfinite(uv).all(-1).astype(float)
    pl = place_from_rays(poses, uv, w, ct, B0, var, which, 0.5, prior_sd_mm=40.0)
    assert pl.placed.tolist() == which.tolist()
    assert np.linalg.norm(pl.points[7] - body.points[7]) < 1.0, pl.points[7]
    assert np.sqrt(pl.var[7].sum()) < 1.5
    assert np.array_equal(pl.points[:7], B0[:7]) and np.array_equal(pl.var[:7], var[:7])
    assert pl.rms_px[7] < 1.0 and pl.views[7] == 300


def test_place_from_rays_holds_what_the_rays_leave_open_at_the_prior():
    """A body that stands still is seen along one body-frame ray per camera: with one camera
    the point moves onto that ray but stays at the prior along it, and says so in its
    variance."""
    body, poses, _, _, ct, _ = _scene()
    poses[:, :3] = 0.0  # no motion: every ray of camera 0 is the same in the body frame
    poses[:, 3:] = poses[0, 3:]
    X = transform_points(torch.as_tensor(poses), torch.tensor(body.points)).numpy()
    uv = project_cameras(torch.as_tensor(X), ct).numpy()
    uv[:, :, 1:] = np.nan
    K = body.num_parts
    B0 = np.array(body.points)
    B0[7] = B0.mean(0)
    which = np.zeros(K, bool)
    which[7] = True
    pl = place_from_rays(
        poses,
        uv,
        np.isfinite(uv).all(-1).astype(float),
        ct,
        B0,
        np.ones((K, 3)),
        which,
        0.5,
        prior_sd_mm=40.0,
    )
    assert pl.placed[7]
    # camera 0 sees the placed point where it sees the true one ...
    ref = project_cameras(torch.as_tensor(X[:, 7]), ct).numpy()[:, 0]
    Xp = transform_points(torch.as_tensor(poses), torch.as_tensor(pl.points)).numpy()[:, 7]
    got = project_cameras(torch.as_tensor(Xp), ct).numpy()[:, 0]
    assert np.abs(got - ref).max() < 0.5
    # ... but the depth is the prior's, and the variance that large along some axis
    assert np.sqrt(pl.var[7].max()) > 10.0


def test_place_from_rays_refuses_bad_shapes():
    body, poses, _, _, ct, uv = _scene(T=20)
    K = body.num_parts
    with pytest.raises(ValueError, match="poses"):
        place_from_rays(
            poses[1:],
            uv,
            np.ones(uv.shape[:-1]),
            ct,
            body.points,
            np.ones((K, 3)),
            np.ones(K, bool),
            1.0,
            40.0,
        )


def test_body_auto_places_a_part_one_camera_sees_end_to_end(tmp_path):
    """adjust-track body=auto on two cameras, one part never seen by the second: the
    Procrustes model cannot place it (centre); body_fit.refine places it from its single views,
    says so in summary.json, and its tracked points are far closer to the truth."""
    body, _, X, cams, _, uv = _scene(T=400, n_cams=2, seed=3, deform_mm=0.5)
    uv[:, 7, 1] = np.nan
    lik = np.where(np.isfinite(uv).all(-1), 0.95, 0.01)
    session = write_session(tmp_path / "s", cams, uv, lik, body.parts)
    err = {}
    for mode in ("none", "views"):
        s = track(session, tmp_path / mode, ["body=auto", f"body_fit.refine={mode}"])
        P = read_points3d(tmp_path / mode / "points3d.csv")["points"]
        err[mode] = float(np.sqrt(np.mean(np.sum((P[:, 7] - X[:, 7]) ** 2, -1))))
        if mode == "views":
            assert list(s["body"]["refined"]["from_single_views"]) == ["tail_root"]
        else:
            assert "refined" not in s["body"]
    assert err["views"] < 3.0 and err["views"] < 0.3 * err["none"], err


# ---------------------------------------------------------------------------------------------
# held-out views
# ---------------------------------------------------------------------------------------------
def test_held_out_view_errors_exact_and_masked():
    """With the true points as the prior and noise-free detections every held-out view is
    predicted exactly; a view without two other views is not evaluated (NaN)."""
    body, poses, X, _, ct, _ = _scene(T=30)
    uv = project_cameras(torch.as_tensor(X), ct).numpy()
    acc = np.ones(uv.shape[:-1], bool)
    acc[:5, 0, 1] = False  # part 0, frames 0-4: two views only
    Xp = torch.as_tensor(X)
    P = torch.eye(3, dtype=torch.float64).expand(*X.shape[:2], 3, 3) * 4.0
    e = held_out_view_errors(Xp, P, torch.as_tensor(uv), torch.as_tensor(acc), ct, 1.0, 2)
    assert e.shape == acc.shape
    assert torch.isnan(e[:5, 0]).all()
    ok = torch.isfinite(e)
    assert int(ok.sum()) == acc.size - 5 * 3
    assert float(e[ok].max()) < 1e-6
    with pytest.raises(ValueError, match="shapes"):
        held_out_view_errors(Xp[1:], P, torch.as_tensor(uv), torch.as_tensor(acc), ct, 1.0)


def _choose(body, poses, ct, uv, var: float, **kw):
    """`choose_measured_prior` with every detection present and accepted."""
    ones = np.ones(uv.shape[:-1])
    rigid_var = np.full((body.num_parts, 3), var)
    return choose_measured_prior(
        poses, uv, ones, ones > 0, ct, np.array(body.points), rigid_var, 0.5, **kw
    )


@pytest.mark.parametrize("deform_mm, bias_px, want", [(0.0, 3.0, "rigid"), (4.0, 0.0, "interp")])
def test_measured_prior_chosen_by_held_out_cameras(deform_mm, bias_px, want):
    """A rigid body whose detections carry a persistent bias per part and camera: the
    neighbours' triangulations carry it too, the rigid model does not, and the held-out
    cameras say so. A smoothly deforming body filmed without bias: its neighbouring frames
    predict it better than the rigid model."""
    body, poses, _, _, ct, uv = _scene(
        T=300, n_cams=3, seed=5, deform_mm=deform_mm, bias_px=bias_px
    )
    choice, facts = _choose(body, poses, ct, uv, max(deform_mm, 0.5) ** 2)
    assert choice == want, facts
    assert facts["held_out_detections"] > 1000
    assert set(facts["per_camera"]) == {"cam0", "cam1", "cam2"}


def test_measured_prior_needs_three_cameras():
    body, poses, _, _, ct, uv = _scene(T=30, n_cams=2)
    choice, facts = _choose(body, poses, ct, uv, 1.0)
    assert choice == "rigid" and ">= 3" in facts["reason"]


def test_measured_prior_on_the_middle_block_of_a_long_session():
    body, poses, _, _, ct, uv = _scene(T=300, n_cams=3, seed=5, bias_px=3.0)
    choice, facts = _choose(body, poses, ct, uv, 0.25, max_frames=150)
    assert facts["frames"] == [75, 225] and choice == "rigid", facts
    assert facts["held_out_detections"] <= 150 * body.num_parts * 3
