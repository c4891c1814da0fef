"""Real mice I: body models from occluded data, the stochastic model estimated from the data,
fusion never worse than triangulation, deformation=interp, calibrated uncertainty."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from adjust.camera import CameraTensors, project_cameras
from adjust.io import read_points3d, save_calibration
from adjust.io.dlc import write_dlc_csv
from adjust.lsq.stochastic import OffsetCovariance, detector_sigma, krige_offsets
from adjust.lsq.synthetic import ring_cameras, smooth_trajectory
from adjust.triangulate import triangulate
from deformnet.body import BodyModel, default_mouse
from deformnet.confutil import compose
from deformnet.shape import real_paper_parts, rigid_floor
from deformnet.so3 import transform_points
from deformnet.tables import read_points3d_table


def track(session: Path, out: Path, overrides: list[str] = ()) -> dict:
    from adjust.apps.track import run

    return run(
        compose(
            "track",
            [
                f"input.calibration={session / 'calibration.toml'}",
                f"input.detections={session / 'detections'}",
                f"output.dir={out}",
                "progress=false",
                *overrides,
            ],
        )
    )


def write_session(path: Path, cams, xy: np.ndarray, lik: np.ndarray, parts) -> Path:
    """A session folder (calibration.toml + one DeepLabCut CSV per camera) from arrays."""
    (path / "detections").mkdir(parents=True)
    save_calibration(path / "calibration.toml", cams)
    for c, cam in enumerate(cams):
        write_dlc_csv(
            path / "detections" / f"{cam.name}.csv", list(parts), xy[:, :, c], lik[:, :, c]
        )
    return path


def film(points: np.ndarray, cams, noise_px: float, rng, drop: np.ndarray | None = None):
    """Detections (T, K, C, 2) and likelihoods of points (T, K, 3) by cameras, with noise."""
    ct = CameraTensors.from_cameras(cams, dtype=torch.float64)
    uv = project_cameras(torch.as_tensor(points), ct).numpy()
    uv = uv + rng.normal(size=uv.shape) * noise_px
    lik = np.full(uv.shape[:-1], 0.95)
    if drop is not None:
        uv[drop] = np.nan
        lik[drop] = 0.01
    return uv, lik


# ---------------------------------------------------------------------------------------------
# the stochastic model's pieces
# ---------------------------------------------------------------------------------------------
def test_detector_sigma_recovers_noise_despite_outliers():
    rng = np.random.default_rng(0)
    cams = ring_cameras(3)
    ct = CameraTensors.from_cameras(cams, dtype=torch.float64)
    X = rng.normal(size=(2000, 4, 3)) * 60.0
    uv = project_cameras(torch.as_tensor(X), ct).numpy() + rng.normal(size=(2000, 4, 3, 2)) * 1.5
    bad = rng.random((2000, 4, 3)) < 0.02
    uv[bad] += 40.0
    tri = triangulate(torch.as_tensor(uv), torch.ones(2000, 4, 3, dtype=torch.float64), ct, True, 8)
    sig, per = detector_sigma(tri.view_error.numpy(), tri.used.numpy())
    assert abs(sig - 1.5) < 0.08, sig
    assert np.allclose(per, 1.5, atol=0.15), per


def test_offset_covariance_orders_parts_and_krige_is_calibrated():
    rng = np.random.default_rng(1)
    T, sd, phi, noise = 20000, np.array([1.0, 8.0, 3.0]), 0.97, 0.4
    o = np.zeros((T, 3, 3))
    for t in range(1, T):
        o[t] = phi * o[t - 1] + rng.normal(size=(3, 3)) * sd[:, None] * np.sqrt(1 - phi**2)
    obs = o + rng.normal(size=o.shape) * noise
    m = rng.random((T, 3)) > 0.2
    for s in rng.integers(0, T - 60, 200):
        m[s : s + rng.integers(2, 50)] = False
    cov = OffsetCovariance.estimate(obs, m, nugget=np.full((3, 3), noise**2))
    assert list(np.argsort(cov.sigma_mm)) == [0, 2, 1]  # the ordering of the true spreads
    assert np.allclose(cov.sigma_mm, sd * np.sqrt(3), rtol=0.1)
    pred, var = krige_offsets(obs, m, cov)
    for mask in (m, ~m):  # observed frames (predicted from neighbours) and gaps
        err2 = ((pred - o) ** 2)[mask].mean()
        assert 0.85 < np.sqrt(err2 / var[mask].mean()) < 1.15


def test_krige_exact_for_linear_motion_across_a_gap_and_held_at_the_ends():
    T = 200
    t = np.arange(T, dtype=float)
    o = np.zeros((T, 2, 3))
    o[:, 0] = np.stack([0.1 * t, -0.05 * t + 2, 3.0 + 0 * t], -1)  # linear in body coordinates
    o[:, 1] = np.sin(t / 7.0)[:, None]  # something that varies, for the covariance
    m = np.ones((T, 2), dtype=bool)
    m[80:130, 0] = False  # a 50-frame gap
    m[185:, 0] = False  # the end
    cov = OffsetCovariance.estimate(o + 1e-3 * np.random.default_rng(0).normal(size=o.shape), m)
    pred, _ = krige_offsets(o, m, cov, skip_self=True)
    assert np.allclose(pred[80:130, 0], o[80:130, 0], atol=1e-9)
    assert np.allclose(pred[190:, 0], o[184, 0], atol=1e-9)  # held at the last observation
    assert np.allclose(pred[10:70, 0], o[10:70, 0], atol=1e-9)  # observed: from t-1 and t+1


# ---------------------------------------------------------------------------------------------
# body models from occluded data, in the user's size
# ---------------------------------------------------------------------------------------------
def test_scaled_body_recovers_a_known_scale():
    rng = np.random.default_rng(2)
    body = default_mouse()
    poses = smooth_trajectory(300, seed=2)
    X = transform_points(poses, torch.as_tensor(body.points * 1.17)).numpy()
    X = X + rng.normal(size=X.shape) * 0.5
    X[rng.random(X.shape[:2]) < 0.4] = np.nan  # no frame needs all parts
    s, n = body.estimate_scale(X)
    assert n > 100 and abs(s - 1.17) < 0.01, s


def test_body_auto_from_partial_frames():
    rng = np.random.default_rng(3)
    body = default_mouse()
    poses = smooth_trajectory(400, seed=3)
    X = transform_points(poses, torch.tensor(body.points)).numpy()
    seen = rng.random(X.shape[:2]) < 0.55
    seen[np.arange(400), rng.integers(0, 8, 400)] = False  # every frame misses a part
    Xo = np.where(seen[..., None], X + rng.normal(size=X.shape) * 0.3, np.nan)
    est = BodyModel.from_observations(Xo, parts=body.parts)
    f = rigid_floor(X, parts=body.parts)  # the true shape's Procrustes body (same frame rule)
    d = np.linalg.norm(
        np.sort(np.linalg.norm(est.points - est.points.mean(0), axis=1))
        - np.sort(np.linalg.norm(f.body.points - f.body.points.mean(0), axis=1))
    )
    assert d < 0.5, d


def test_body_models_on_real_poses_filmed_by_simulated_cameras(tmp_path):
    """The 91 hand-labelled real poses (8 paper parts), filmed by a simulated 3-camera ring:
    body=auto recovers the real mouse's Procrustes shape, and the scaled Table 1 is closer to
    the real parts than Table 1 as is."""
    names, P = real_paper_parts()
    parts = default_mouse().parts
    P = P[:, [list(names).index(p) for p in parts]]  # in the model's part order
    assert P.shape[1:] == (8, 3)
    rng = np.random.default_rng(4)
    P = P - np.nanmean(P.reshape(-1, 3), 0) + np.array([0.0, 0.0, 30.0])
    cams = ring_cameras(3, radius=600.0, height=450.0)
    xy, _ = film(np.nan_to_num(P), cams, 1.0, rng)
    xy[~np.isfinite(P).all(-1)] = np.nan
    ct = CameraTensors.from_cameras(cams, dtype=torch.float64)
    tri = triangulate(torch.as_tensor(xy), torch.ones(xy.shape[:-1], dtype=torch.float64), ct)
    X = tri.points.numpy()
    est = BodyModel.from_observations(X, parts=parts)
    ref = rigid_floor(P, parts=parts).body
    radii = [np.sort(np.linalg.norm(b.points - b.points.mean(0), axis=1)) for b in (est, ref)]
    assert np.abs(radii[0] - radii[1]).max() < 1.0
    table = default_mouse()
    s, n = table.estimate_scale(X)
    assert n > 80 and 1.0 < s < 1.4, s  # the real mouse is larger than Table 1
    fit = {}  # distance of the models' radial profiles from the real Procrustes body's
    for name, b in (("table", table), ("scaled", table.scaled(s))):
        r = np.sort(np.linalg.norm(b.points - b.points.mean(0), axis=1))
        fit[name] = float(np.linalg.norm(r - radii[1]))
    assert fit["scaled"] < 0.6 * fit["table"], fit


# ---------------------------------------------------------------------------------------------
# adjust-track end to end on synthetic sessions
# ---------------------------------------------------------------------------------------------
def _deforming_session(
    tmp_path: Path, n_cams: int, deform: np.ndarray, drop_rate: float, seed=0, no_full=False
):
    """A mouse-sized rigid body on a smooth track, each part deforming smoothly (AR(1) in body
    coordinates, per-part rms `deform` mm), filmed with 1 px noise and dropped detections."""
    rng = np.random.default_rng(seed)
    body = default_mouse()
    T, K = 600, body.num_parts
    poses = smooth_trajectory(T, seed=seed, speed=0.5)
    off = np.zeros((T, K, 3))
    phi = 0.97
    for t in range(1, T):
        off[t] = phi * off[t - 1] + rng.normal(size=(K, 3)) * (
            deform[:, None] / np.sqrt(3)
        ) * np.sqrt(1 - phi**2)
    B = torch.tensor(body.points)
    X = transform_points(poses, B + torch.as_tensor(off)).numpy()
    cams = ring_cameras(n_cams, radius=600.0, height=450.0)
    drop = rng.random((T, K, n_cams)) < drop_rate
    for _ in range(40):  # occlusion episodes
        t0, k, c = rng.integers(0, T - 30), rng.integers(0, K), rng.integers(0, n_cams)
        drop[t0 : t0 + rng.integers(5, 30), k, c] = True
    if no_full:  # in every frame some part is missed by some camera
        drop[np.arange(T), rng.integers(0, K, T), rng.integers(0, n_cams, T)] = True
    xy, lik = film(X, cams, 1.0, rng, drop)
    session = write_session(tmp_path / "session", cams, xy, lik, body.parts)
    nviews = (~drop).sum(-1)
    return session, X, nviews


def test_body_auto_on_two_cameras_without_any_complete_frame(tmp_path):
    session, X, nviews = _deforming_session(
        tmp_path, 2, np.full(8, 1.0), 0.25, seed=5, no_full=True
    )
    assert not (nviews == 2).all(-1).any()  # no frame has every part seen by both cameras
    summary = track(session, tmp_path / "out", ["body=auto"])
    P = read_points3d(tmp_path / "out" / "points3d.csv")["points"]
    assert summary["completeness"] == 1.0
    err = np.linalg.norm(P - X, axis=-1)
    assert np.sqrt(np.mean(err[nviews == 2] ** 2)) < 1.5


def test_per_part_variances_order_the_parts(tmp_path):
    deform = np.array([1.0, 1.0, 1.0, 3.0, 3.0, 12.0, 3.0, 1.0])  # left hind paw deforms most
    session, _, _ = _deforming_session(tmp_path, 3, deform, 0.2, seed=6)
    summary = track(session, tmp_path / "out")
    parts = summary["parts"]
    sig = np.array([summary["deformation"]["deformation_sigma_mm_per_part"][p] for p in parts])
    rig = np.array([summary["body"]["rigid_rms_mm_per_part"][p] for p in parts])
    assert int(np.argmax(sig)) == 5 and int(np.argmax(rig)) == 5
    assert sig[5] > 2.5 * np.median(sig)
    assert abs(summary["stochastic"]["sigma_det_px"] - 1.0) < 0.1  # estimated, not the 2 px default


def test_fusion_at_least_as_accurate_as_triangulation_without_deformation(tmp_path):
    session, X, nviews = _deforming_session(tmp_path, 3, np.zeros(8), 0.25, seed=7)
    from adjust.io import load_scene

    cameras, det = load_scene(session / "calibration.toml", session / "detections", default_mouse())
    ct = CameraTensors.from_cameras(cameras, dtype=torch.float64)
    tri = triangulate(torch.as_tensor(det.xy), torch.as_tensor(det.weight()), ct, robust=True)
    e_tri = np.linalg.norm(tri.points.numpy() - X, axis=-1)
    seen = nviews >= 2
    rmse_tri = np.sqrt(np.mean(e_tri[seen] ** 2))
    for mode in ("rigid", "interp"):
        track(session, tmp_path / mode, [f"deformation={mode}", "body.scale=1"])
        P = read_points3d(tmp_path / mode / "points3d.csv")["points"]
        rmse = np.sqrt(np.mean(np.linalg.norm(P - X, axis=-1)[seen] ** 2))
        assert rmse <= rmse_tri, (mode, rmse, rmse_tri)


def test_interp_beats_rigid_and_is_calibrated_on_a_deforming_mouse(tmp_path):
    from adjust.apps.simulate import run

    scene = tmp_path / "scene"
    run(compose("scene", [f"output.dir={scene}", "num_frames=600", "seed=93001", "sim=mouse_b"]))
    truth = np.load(scene / "truth.npz")
    T, nv = truth["points"], truth["nviews"]
    res = {}
    for mode in ("rigid", "interp"):
        s = track(scene, tmp_path / mode, [f"deformation={mode}"])
        d = read_points3d(tmp_path / mode / "points3d.csv")
        df = read_points3d_table(tmp_path / mode / "points3d.csv")  # with points3d.extra.csv
        sig = np.stack([df[f"{p}_sigma"].to_numpy(float) for p in d["parts"]], 1)
        err = np.linalg.norm(d["points"] - T, axis=-1)
        res[mode] = {
            g: (np.sqrt(np.mean(err[m] ** 2)), np.sqrt(np.mean(sig[m] ** 2)))
            for g, m in (("seen", nv >= 2), ("occ", nv < 2))
        }
        if mode == "interp":
            # the shape estimated from the data has the size of the truth's mean shape
            # (generalized Procrustes of the true points; mouse_b's paws and spine move, so it
            # is not exactly 1.2x Table 1)
            mean_shape = BodyModel.from_observations(T, parts=d["parts"])
            size = 1 / mean_shape.in_frame_of(default_mouse())[1]["scale"]
            assert abs(1 / s["body"]["frame"]["scale"] / size - 1) < 0.05, (s["body"], size)
    assert res["interp"]["occ"][0] < 0.85 * res["rigid"]["occ"][0], res
    assert res["interp"]["seen"][0] < res["rigid"]["seen"][0], res
    for g in ("seen", "occ"):  # rms error / rms sigma: calibrated within a margin
        ratio = res["interp"][g][0] / res["interp"][g][1]
        assert 0.7 < ratio < 1.5, (g, ratio)


def test_body_auto_places_parts_only_seen_with_few_others(caplog):
    """A part never seen together with >= 3 placed parts is placed by translation, loudly; a
    part never seen in 3D with any other is put at the centre, loudly; no error either way."""
    rng = np.random.default_rng(8)
    body = default_mouse()
    poses = smooth_trajectory(200, seed=8)
    X = transform_points(poses, torch.tensor(body.points)).numpy()
    X[:, 7] = np.nan  # tail root ...
    X[::10, 7] = transform_points(poses, torch.tensor(body.points)).numpy()[::10, 7]
    X[::10, 2:7] = np.nan  # ... seen only with nose and left ear
    X[:, 6] = np.nan  # right hind paw: never together with another part
    X[5::10, :6] = np.nan
    X[5::10, 6] = 1.0
    with caplog.at_level("WARNING"):
        est = BodyModel.from_observations(X + rng.normal(size=X.shape) * 0.1, parts=body.parts)
    assert "translation only" in caplog.text and "right_hind_paw" in caplog.text
    d = est.points - est.points[:6].mean(0)
    assert np.isfinite(est.points).all()
    assert np.linalg.norm(d[6]) < np.linalg.norm(d[:6], axis=1).max()  # at the centre


def test_body_auto_on_every_real_hand_leave_out(tmp_path):
    """body=auto on the real hand data with each camera left out (2 of 4 used to fail)."""
    from adjust.io import load_calibration
    from deformnet.paths import real_hand_dir

    src = real_hand_dir()
    cams = load_calibration(src / "calibration.toml")
    for left in cams:
        sess = tmp_path / f"without_{left.name}"
        (sess / "detections").mkdir(parents=True)
        keep = [c for c in cams if c.name != left.name]
        save_calibration(sess / "calibration.toml", keep)
        for c in keep:
            lines = (src / "trial_000" / f"{c.name}.csv").read_text().splitlines()
            (sess / "detections" / f"{c.name}.csv").write_text("\n".join(lines[:103]) + "\n")
        s = track(sess, sess / "out", ["body=auto"])
        assert s["completeness"] == 1.0 and s["num_frames"] == 100
        assert s["reprojection_error_px"]["median"] < 6.0


def test_body_auto_with_22_real_keypoints_on_three_cameras(tmp_path):
    """The real 22-keypoint skeleton, filmed by 3 simulated cameras with parts dropped: no frame
    has all 22, body=auto (adjust-track) still estimates the model and tracks every part."""
    from deformnet.shape import load_real_poses

    names, P = load_real_poses()
    rng = np.random.default_rng(9)
    P = P - np.nanmean(P.reshape(-1, 3), 0) + np.array([0.0, 0.0, 40.0])
    cams = ring_cameras(3, radius=600.0, height=450.0)
    drop = rng.random((*P.shape[:2], 3)) < 0.3
    drop[np.arange(P.shape[0]), rng.integers(0, 22, P.shape[0]), :] = True  # never all 22
    drop |= ~np.isfinite(P).all(-1)[..., None]  # parts not labelled are not detected
    xy, lik = film(np.nan_to_num(P), cams, 1.0, rng, drop)
    session = write_session(tmp_path / "s", cams, xy, lik, names)
    s = track(session, tmp_path / "out", ["body=auto", "deformation=rigid"])
    assert s["completeness"] == 1.0 and len(s["parts"]) == 22
    assert s["body"]["frames_used"] >= 80


def test_summary_says_how_much_rests_on_no_detection(tmp_path):
    session, _, nviews = _deforming_session(tmp_path, 3, np.full(8, 1.0), 0.6, seed=10)
    s = track(session, tmp_path / "out")
    d = read_points3d(tmp_path / "out" / "points3d.csv")
    alone = s["from_model_only"]
    assert alone["fraction"] == pytest.approx(float((d["ncams"] == 0).mean()))
    assert set(alone["per_part"]) == set(s["parts"]) and 0 < alone["fraction"] < 1


def test_accepted_npz_says_which_detections_the_track_used(tmp_path):
    from adjust.plot import classify_detections, load_accepted

    session, _, _ = _deforming_session(tmp_path, 3, np.full(8, 1.0), 0.2, seed=11)
    track(session, tmp_path / "out")
    d = read_points3d(tmp_path / "out" / "points3d.csv")
    cams = [c.name for c in ring_cameras(3, radius=600.0, height=450.0)]
    acc = load_accepted(tmp_path / "out" / "points3d.csv", list(d["parts"]), cams)
    assert acc is not None and acc.dtype == bool and acc.shape == (*d["ncams"].shape, 3)
    assert (acc.sum(-1) == d["ncams"]).all()  # the same detections _ncams counts
    xy = np.zeros((*acc.shape, 2))
    codes = classify_detections(xy, np.ones(acc.shape), 0.5, xy, acc)
    assert ((codes == 1) == acc).all() and ((codes == 2) == ~acc).all()


def test_chunked_long_session_matches_one_piece(tmp_path):
    """Long sessions run in overlapping chunks (solver.chunk_size) with the same result."""
    session, X, _ = _deforming_session(tmp_path, 3, np.full(8, 2.0), 0.2, seed=12)
    track(session, tmp_path / "one")
    track(session, tmp_path / "chunks", ["solver.chunk_size=150", "solver.overlap=32"])
    a = read_points3d(tmp_path / "one" / "points3d.csv")["points"]
    b = read_points3d(tmp_path / "chunks" / "points3d.csv")["points"]
    ea, eb = (np.sqrt(np.mean(np.sum((p - X) ** 2, -1))) for p in (a, b))
    assert eb < 1.1 * ea + 0.05, (ea, eb)
