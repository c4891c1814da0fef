"""`adjust-track` through Hydra's compose API: a small simulated scene, the real hand data,
the grid constraint, bad input, and a deformable run with a tiny checkpoint."""

from __future__ import annotations

import json
from pathlib import Path

import hydra
import numpy as np
import pytest
import torch

from adjust.apps.track import run
from adjust.camera import CameraTensors
from adjust.io import InputError, load_scene, read_points3d
from deformnet.behavior.tracks import POSE_COLUMNS
from deformnet.body import default_mouse
from deformnet.paths import CONF_DIR, real_hand_dir

REAL = real_hand_dir()
FIELDS = ("x", "y", "z", "error", "ncams", "score")
FAST = ["progress=false", "solver.max_iterations=8"]


def _cfg(name: str, overrides: list[str]):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose(name, overrides=overrides)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A small simulated scene folder (default rig and detector), written by adjust-simulate."""
    from adjust.apps.simulate import run as simulate

    out = tmp_path_factory.mktemp("scene")
    simulate(_cfg("scene", [f"output.dir={out}", "num_frames=120", "seed=5"]))
    return out


def _track_cfg(calibration: Path, detections: Path, extra: list[str] = ()):
    """adjust-track's config for a calibration file and a detections folder, then `extra`."""
    ov = [f"input.calibration={calibration}", f"input.detections={detections}", *extra]
    return _cfg("track", ov)


def _track(scene: Path, out: Path, extra: list[str] = ()) -> dict:
    ov = [f"output.dir={out}", *FAST, *extra]
    return run(_track_cfg(scene / "calibration.toml", scene / "detections", ov))


def _columns(path: Path) -> list[str]:
    return path.read_text().splitlines()[0].split(",")


def _dlt(scene: Path) -> np.ndarray:
    from adjust.triangulate import triangulate

    cameras, det = load_scene(scene / "calibration.toml", scene / "detections", default_mouse())
    cams = CameraTensors.from_cameras(cameras, dtype=torch.float64)
    with torch.no_grad():
        res = triangulate(torch.as_tensor(det.xy), torch.as_tensor(det.weight()), cams)
    return res.points.numpy()


@pytest.fixture(scope="module")
def default_run(scene, tmp_path_factory):
    """adjust-track with its defaults (deformation=interp): (output folder, summary)."""
    out = tmp_path_factory.mktemp("track")
    return out, _track(scene, out)


@pytest.fixture(scope="module")
def rigid_run(scene, tmp_path_factory):
    """adjust-track deformation=rigid (the rigid body model only): (output folder, summary)."""
    out = tmp_path_factory.mktemp("rigid")
    return out, _track(scene, out, ["deformation=rigid"])


def test_default_track_complete_and_better_than_dlt(scene, default_run):
    out, summary = default_run
    parts = default_mouse().parts
    cols = _columns(out / "points3d.csv")
    want = [f"{p}_{f}" for p in parts for f in FIELDS]
    assert cols[: len(want)] == want and cols[-1] == "fnum"
    # the pose and sigma columns: in the sidecar points3d.extra.csv (anipose's columns only in
    # points3d.csv), joined back by read_points3d
    extra = (out / "points3d.extra.csv").read_text().splitlines()[1].split(",")  # after the sha
    assert set(POSE_COLUMNS) | {"pose_sigma_r", "pose_sigma_t"} <= set(extra)
    assert {f"{p}_sigma" for p in parts} <= set(extra)
    assert not set(extra) - {"fnum"} & set(cols)

    d = read_points3d(out / "points3d.csv")
    P = d["points"]
    assert P.shape == (120, 8, 3) and np.isfinite(P).all()  # every part in every frame
    assert summary["completeness"] == 1.0
    assert json.loads((out / "summary.json").read_text()) == summary
    for key in ("iterations", "final_cost", "reprojection_error_px_per_camera", "time_s"):
        assert key in summary
    assert set(summary["reprojection_error_px_per_camera"]) == {"top", "side", "front"}
    assert summary["settings"]["solver"]["constraint"] == "grid"  # conf/solver/default.yaml

    # _ncams / _score / _error semantics
    truth = np.load(scene / "truth.npz")
    cameras, det = load_scene(scene / "calibration.toml", scene / "detections", default_mouse())
    observed = det.observed.sum(-1)
    ncams = d["ncams"]  # the accepted detections: gated against the other cameras and the track
    assert (ncams <= observed).all() and (ncams == 0).any()
    assert 0.9 < ncams.sum() / observed.sum() < 1.0  # a few mis-detections rejected, not more
    assert np.isnan(d["score"][ncams == 0]).all() and np.isnan(d["error"][ncams == 0]).all()
    assert (d["score"][ncams > 0] >= det.threshold).all()
    assert np.isfinite(d["error"][ncams > 0]).all()
    sig = np.stack([d["extra"][f"{p}_sigma"] for p in parts], 1)
    assert np.isfinite(sig).all() and (sig > 0).all()
    assert np.median(sig[ncams == 0]) > np.median(sig[ncams >= 2])  # unseen parts less certain

    # accuracy: better than DLT triangulation on the part-frames DLT can do
    dlt = _dlt(scene)
    can = np.isfinite(dlt).all(-1)
    assert 0.3 < can.mean() < 0.95
    err_adj = np.linalg.norm(P - truth["points"], axis=-1)
    err_dlt = np.linalg.norm(dlt - truth["points"], axis=-1)
    rmse_adj = np.sqrt(np.mean(err_adj[can] ** 2))
    rmse_dlt = np.sqrt(np.mean(err_dlt[can] ** 2))
    assert rmse_adj < rmse_dlt, (rmse_adj, rmse_dlt)
    # and the parts DLT cannot do are tracked about as well (measured 3.8 mm rms)
    assert np.sqrt(np.mean(err_adj[~can] ** 2)) < 6.0


def test_rigid_track_accuracy(scene, rigid_run, default_run):
    """deformation=rigid: complete, reported as rigid, accurate where the
    parts are seen; interp's deformation model beats it on the occluded parts."""
    out, summary = rigid_run
    assert summary["deformation"]["mode"] == "rigid" and summary["completeness"] == 1.0
    truth = np.load(scene / "truth.npz")
    seen = truth["nviews"] >= 2
    P = read_points3d(out / "points3d.csv")["points"]
    assert np.isfinite(P).all()
    err = np.linalg.norm(P - truth["points"], axis=-1)
    rms = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    # measured: 4.50 mm overall, 0.85 seen by >= 2 cameras, 6.50 occluded
    assert rms(err) < 5.5 and rms(err[seen]) < 1.1 and rms(err[~seen]) < 8.0, (
        rms(err),
        rms(err[seen]),
        rms(err[~seen]),
    )
    # better than DLT triangulation where DLT can triangulate
    dlt = _dlt(scene)
    can = np.isfinite(dlt).all(-1)
    assert rms(err[can]) < rms(np.linalg.norm(dlt - truth["points"], axis=-1)[can])
    # the default (interp) run: 4.62 mm occluded, 0.71x rigid's
    P_interp = read_points3d(default_run[0] / "points3d.csv")["points"]
    err_interp = np.linalg.norm(P_interp - truth["points"], axis=-1)
    assert rms(err_interp[~seen]) < 0.85 * rms(err[~seen]), (
        rms(err_interp[~seen]),
        rms(err[~seen]),
    )


def test_grid_and_spline_constraints(scene, default_run, tmp_path):
    _, grid = default_run
    spline = _track(scene, tmp_path, ["solver.constraint=spline"])
    assert spline["settings"]["solver"]["constraint"] == "spline"
    assert spline["completeness"] == 1.0
    a = read_points3d(default_run[0] / "points3d.csv")["points"]
    b = read_points3d(tmp_path / "points3d.csv")["points"]
    # two forms of the same constraint: close, not identical (measured 0.056 mm rms)
    assert 0 < np.sqrt(np.mean(np.sum((a - b) ** 2, -1))) < 0.5
    assert grid["iterations"] >= 1 and spline["iterations"] >= 1


def _hand_subset(tmp_path: Path, start: int = 240, frames: int = 60) -> Path:
    """Frames start .. start + frames - 1 of the real hand data (the CSV files cut; in these
    frames every part is triangulated in some well-observed frame, as body=auto needs)."""
    det = tmp_path / "trial"
    det.mkdir()
    for f in sorted((REAL / "trial_000").glob("*.csv")):
        lines = f.read_text().splitlines()
        rows = lines[:3] + lines[3 + start : 3 + start + frames]
        (det / f.name).write_text("\n".join(rows) + "\n")
    return det


def test_body_auto_on_real_hand_data(tmp_path):
    det = _hand_subset(tmp_path)
    out = tmp_path / "out"
    summary = run(
        _track_cfg(REAL / "calibration.toml", det, [f"output.dir={out}", "body=auto", *FAST])
    )
    assert summary["body"]["source"] == "auto" and len(summary["parts"]) == 21
    assert summary["completeness"] == 1.0
    d = read_points3d(out / "points3d.csv")
    assert d["parts"][:2] == ("elbow", "wrist") and d["points"].shape == (60, 21, 3)
    assert np.isfinite(d["points"]).all()
    # the reported points agree with the detections as well as DLT's (median ~3.3-3.9 px;
    # measured 3.15)
    assert summary["reprojection_error_px"]["median"] < 3.5, summary["reprojection_error_px"]
    assert summary["settings"]["solver"]["sigma_def_mm"] == pytest.approx(
        max(summary["body"]["rms_deviation_mm"], 0.5)
    )


def test_default_body_on_hand_data_tracks_the_files_parts(tmp_path):
    """Files whose parts are not the mouse's: the default body is estimated from them and every
    part is tracked; body.other_parts=error stops, naming the unknown parts and body=auto."""
    assert REAL.exists(), f"shared data missing: {REAL}"
    cfg = _track_cfg(
        REAL / "calibration.toml", REAL / "trial_000", [f"output.dir={tmp_path / 'a'}", *FAST]
    )
    summary = run(cfg)
    assert "elbow" in summary["parts"] and len(summary["parts"]) > 8
    assert summary["body"]["source"] == "auto"
    assert "elbow" in summary["body"]["other_parts"]
    assert summary["completeness"] == 1.0
    cfg = _track_cfg(
        REAL / "calibration.toml",
        REAL / "trial_000",
        [f"output.dir={tmp_path / 'b'}", "body.other_parts=error", *FAST],
    )
    with pytest.raises(InputError, match="elbow.*body=auto"):
        run(cfg)


def test_bad_input(scene, tmp_path):
    base = [f"output.dir={tmp_path / 'out'}", *FAST]
    cfg = _track_cfg(tmp_path / "nope.toml", scene / "detections", base)
    with pytest.raises(InputError, match="calibration file not found: .*nope.toml"):
        run(cfg)
    # a detections folder without the file of one camera
    partial = tmp_path / "partial"
    partial.mkdir()
    for cam in ("top", "side"):
        (partial / f"{cam}.csv").write_bytes((scene / "detections" / f"{cam}.csv").read_bytes())
    cfg = _track_cfg(scene / "calibration.toml", partial, base)
    with pytest.raises(InputError, match=r"cameras without a file: \['front'\]"):
        run(cfg)
    cfg = _track_cfg(
        scene / "calibration.toml",
        scene / "detections",
        [f"deformation={tmp_path / 'missing.ckpt'}", *base],
    )
    with pytest.raises(InputError, match="deformation checkpoint not found"):
        run(cfg)
    with pytest.raises(ValueError, match="input.calibration"):
        run(_cfg("track", [f"input.detections={scene / 'detections'}", *base]))
    assert not (tmp_path / "out" / "points3d.csv").exists()


def _tiny_checkpoint(path: Path) -> Path:
    """An untrained tiny LSTM deformation model saved as a checkpoint (DeformationModel.save)."""
    from helpers import tiny_deformation_model

    tiny_deformation_model().save(path)
    return path


def test_deformable_run_with_tiny_checkpoint(scene, rigid_run, tmp_path):
    ckpt = _tiny_checkpoint(tmp_path / "tiny.ckpt")
    out = tmp_path / "out"
    summary = _track(scene, out, [f"deformation={ckpt}", "deform.max_iterations=2"])
    assert summary["deformation"]["window"] == 5
    # a checkpoint is the user's own net: checked and reported, used as given
    assert summary["deformation"]["heldout"]["require_better"] == "report"
    assert summary["body"]["source"] == "checkpoint"
    assert summary["completeness"] == 1.0
    d = read_points3d(out / "points3d.csv")
    assert np.isfinite(d["points"]).all()
    # an untrained net predicts the rigid model where it is used (4% of the part-frames), the
    # rest is interp's (the net modes run rigid -> interp -> net): better than the rigid track
    # (measured 3.51 vs 4.50 mm; interp 3.20)
    rigid = read_points3d(rigid_run[0] / "points3d.csv")["points"]
    truth = np.load(scene / "truth.npz")["points"]
    rmse = np.sqrt(np.mean(np.sum((d["points"] - truth) ** 2, -1)))
    rmse_rigid = np.sqrt(np.mean(np.sum((rigid - truth) ** 2, -1)))
    assert rmse < rmse_rigid, (rmse, rmse_rigid)


def test_heading_frame_net_needs_the_worlds_up(scene, tmp_path):
    """A net trained in the heading frame of world up z tracks the (z-up) scene and reports how
    far the mouse's up was from z; one that assumes x is up is refused, naming the input."""
    from helpers import tiny_deformation_model

    tiny_deformation_model(up=(0, 0, 1)).save(tmp_path / "z.ckpt")
    summary = _track(
        scene, tmp_path / "z", [f"deformation={tmp_path / 'z.ckpt'}", "deform.max_iterations=2"]
    )
    facts = summary["deformation"]["world_up"]
    assert facts["up"] == [0.0, 0.0, 1.0] and facts["median_body_up_deg"] < 20.0
    assert summary["completeness"] == 1.0
    tiny_deformation_model(up=(1, 0, 0)).save(tmp_path / "x.ckpt")
    with pytest.raises(InputError, match=r"detections: the deformation net reads .* world up "
                       r"\[1.0, 0.0, 0.0\].* median \d+ deg"):  # fmt: skip
        _track(scene, tmp_path / "x", [f"deformation={tmp_path / 'x.ckpt'}"])


@pytest.mark.slow
def test_deformable_run_with_trained_tiny_checkpoint(scene, tmp_path):
    """Train a tiny net with deformnet-train's run() (toy data), then track with it."""
    from deformnet.train import run as train

    res = train(
        _cfg(
            "train",
            [
                f"output.dir={tmp_path / 'net'}",
                "data=toy",
                "data.num_frames=200",
                "data.steps_per_epoch=2",
                "data.val_windows=64",
                "trainer.max_epochs=1",
                "trainer.num_sanity_val_steps=0",
                "net.hidden=8",
                "net.embed=8",
                "net.layers=1",
                "half_window=2",
                "logger=none",
                "progress_bar=none",
            ],
        )
    )
    assert res["best_checkpoint"]
    ckpt = res["best_checkpoint"]
    summary = _track(scene, tmp_path / "out", [f"deformation={ckpt}", "deform.max_iterations=2"])
    assert summary["completeness"] == 1.0


def _deforming_model(scale: float = 0.1):
    """The tiny net (float64, frozen) with its weights perturbed: an untrained one predicts
    the rigid model; this one moves the parts (measured on the problem below: 3.8 mm median,
    14 mm at most where its prediction is used)."""
    from helpers import tiny_deformation_model

    model = tiny_deformation_model()
    gen = torch.Generator().manual_seed(2)
    with torch.no_grad():
        for p in model.parameters():
            p.requires_grad_(False)
            p.add_(scale * torch.randn(p.shape, generator=gen))
    return model.double().eval()


def _central_difference(obs, poses: torch.Tensor) -> torch.Tensor:
    """dX/d(delta) (T, K, 3, 6) of ``obs.points`` by central differences of the pose
    increment (1e-5 rad, 1e-3 mm)."""
    from adjust.lsq.geometry import retract

    cols = []
    for j in range(6):
        h = 1e-5 if j < 3 else 1e-3
        d = torch.zeros_like(poses)
        d[:, j] = h
        plus, minus = (
            obs.points(retract(poses, d), False)[0],
            obs.points(retract(poses, -d), False)[0],
        )
        cols.append((plus - minus) / (2 * h))
    return torch.stack(cols, -1)


def test_deformable_jacobians_are_the_derivatives_of_their_observations():
    """With a net that deforms, each deformable observation's Jacobian is the derivative of its
    own points: NetObservation's by central and forward differences through the net,
    DeformableObservation's by reverse mode (both to rounding; forward to its truncation);
    measured inputs reach the net, gated by distance."""
    from adjust.lsq.net_observation import DeformableObservation, NetObservation

    model = _deforming_model()
    gen = torch.Generator().manual_seed(1)
    T, body = 20, torch.tensor(default_mouse().points)
    rand = lambda *shape: torch.randn(*shape, generator=gen, dtype=torch.float64)  # noqa: E731
    poses = torch.cat((0.3 * rand(T, 3), 50 * rand(T, 3)), -1)
    data = body[None] + poses[:, None, 3:] + 2 * rand(T, 8, 3)
    data[3, 2] += 100.0  # a mis-detection: gated out
    observed = torch.rand(T, 8, generator=gen) > 0.3

    def net_obs(jacobian, d=data):
        obs = NetObservation(model, body, model.window, d, observed, 30.0, 4096, jacobian)
        obs.prepare(poses)
        return obs

    central, forward = net_obs("central"), net_obs("forward")
    assert not central._observed_win[3, model.half_window, 2]  # gated
    ref = DeformableObservation(model, body, model.window, observed)
    ref.prepare(poses)
    ref._deformed_win, ref._observed_win = central._deformed_win, central._observed_win
    rigid_X, rigid_J = central.rigid_points(poses)[0], central.rigid.points(poses)[1]
    use = central.use_net
    assert use.sum() > 20  # the net predicts the unmeasured part-frames its window reaches
    for obs, atol in ((central, 2e-8), (ref, 2e-8), (forward, 1e-4)):
        X, J = obs.points(poses)
        # measured: central 1.4e-9, reverse mode 3.9e-9, forward 2.1e-5 (its O(h) error)
        torch.testing.assert_close(J, _central_difference(obs, poses), atol=atol, rtol=0)
        # the net deforms: neither its points nor its Jacobian are the rigid model's
        assert (X - rigid_X).norm(dim=-1)[use].median() > 1.0
        assert (J - rigid_J)[use].abs().max() > 1.0
    # the same net on the same inputs where NetObservation uses it
    torch.testing.assert_close(
        central.points(poses, False)[0][use], ref.points(poses, False)[0][use]
    )
    # an accepted measurement moved by 5 mm moves the net's predictions in its window; the
    # gated mis-detection moved does not change anything
    t, k = 10, int(observed[10].nonzero()[0])
    near = torch.zeros_like(use)
    near[t - model.half_window : t + model.half_window + 1] = True
    assert (use & near).any()
    for frame, part, changes in ((t, k, True), (3, 2, False)):
        moved = data.clone()
        moved[frame, part] += 5.0
        diff = net_obs("central", moved).points(poses, False)[0] - central.points(poses, False)[0]
        if changes:
            assert diff.norm(dim=-1)[use & near].max() > 1e-3
        else:
            assert diff.abs().max() == 0
    sub = central.window(5, 15)
    assert sub.data.shape[0] == 10 and type(sub) is type(central)


def test_nwb_without_a_frame_rate_stops_before_tracking(scene, tmp_path):
    """output.nwb=true with no output.fps and no fps in the calibration: one error naming
    output.fps, before any tracking (nothing written)."""
    with pytest.raises(InputError, match=r"output\.fps"):
        _track(scene, tmp_path / "nwb", ["output.nwb=true"])
    assert not (tmp_path / "nwb" / "points3d.csv").exists()


def test_nwb_without_a_session_start_stops_before_tracking(scene, tmp_path):
    """output.nwb=true with a frame rate but no session start (setting or calibration
    metadata): one error naming output.session_start_time, nothing written."""
    with pytest.raises(InputError, match=r"output\.session_start_time"):
        _track(scene, tmp_path / "nwb", ["output.nwb=true", "output.fps=30"])
    assert not (tmp_path / "nwb" / "points3d.csv").exists()


def test_body_shape_from_a_handful_of_frames_is_not_trusted(tmp_path):
    """body.shape=data on a 20-frame session (fewer than MIN_SHAPE_FRAMES frames with 3 parts
    in 3D): the named model's shape, scaled, said in summary.json."""
    from adjust.apps.simulate import run as simulate
    from adjust.body_fit import MIN_SHAPE_FRAMES

    simulate(_cfg("scene", [f"output.dir={tmp_path / 's'}", "num_frames=20", "seed=6"]))
    s = _track(tmp_path / "s", tmp_path / "out")
    assert s["body"]["source"] == "config" and str(MIN_SHAPE_FRAMES) in s["body"]["shape_fallback"]
    assert s["completeness"] == 1.0
