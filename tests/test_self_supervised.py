"""Real mice II: self-supervised tokens from a session, deformnet-train data=sessions,
adjust-track deformation=self|default and the shipped pretrained net."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from deformnet.confutil import compose
from deformnet.sessions import SessionTokens, split_sessions


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A deforming mouse_b scene (1.2x Table 1, 100 fps, spine bending, free head)."""
    from adjust.apps.simulate import run

    out = tmp_path_factory.mktemp("self") / "scene"
    run(compose("scene", [f"output.dir={out}", "num_frames=900", "seed=31", "sim=mouse_b"]))
    return out


def _track(scene: Path, out: Path, overrides: list[str]) -> dict:
    from helpers import track_session

    return track_session(scene, out, overrides)


def _points(out: Path) -> np.ndarray:
    from adjust.io import read_points3d

    return read_points3d(out / "points3d.csv")["points"]


@pytest.fixture(scope="module")
def tracked(scene, tmp_path_factory) -> dict:
    """rigid, interp and deformation=self (fine-tuning capped at 60 s; it stops earlier, by
    adapt.max_steps / adapt.patience: measured 75 steps, 7 s) on the scene: ``self`` with its
    adapted net used whatever its gate says (``adapt.require_better=false``), ``self_gated``
    as a user runs it."""
    root = tmp_path_factory.mktemp("tracks")
    runs = {}
    adapt = ["deformation=self", "adapt.max_time=00:00:01:00", "adapt.tensorboard=false"]
    for name, ov in (
        ("rigid", ["deformation=rigid"]),
        ("interp", ["deformation=interp"]),
        ("self", [*adapt, "adapt.require_better=false"]),
        ("self_gated", adapt),
    ):
        runs[name] = (_track(scene, root / name, ov), root / name)
    return runs


def test_tokens_mask_only_gated_two_view_measurements(scene, tracked):
    """tokens.npz: targets are only part-frames >= 2 cameras saw, gated (no mis-detection
    survives), and the rigid points are the adjusted poses' model points."""
    summary, out = tracked["rigid"]
    tok = SessionTokens.load(out / "tokens.npz")
    truth = np.load(scene / "truth.npz")
    nviews = truth["nviews"]
    T, K = tok.observed.shape
    assert (T, K) == nviews.shape
    assert tok.observed.any() and not tok.observed.all()
    # never a target without two cameras' detections (likelihood >= the threshold)
    from adjust.io import load_scene
    from deformnet.body import default_mouse

    _, det = load_scene(scene / "calibration.toml", scene / "detections", default_mouse())
    assert not (tok.observed & (det.observed.sum(-1) < 2)).any()
    # and almost never where fewer than two cameras truly saw the part
    assert (tok.observed & (nviews < 2)).sum() <= 0.01 * tok.observed.sum()
    # gated: measured targets are within a few mm of the truth (mis-detections are ~tens of mm)
    err = np.linalg.norm(tok.deformed - truth["points"], axis=-1)[tok.observed]
    # (measured: median 0.8, 99.5% 2.6 mm; 0.3% beyond 8 mm, two cameras agreeing on the same
    # wrong point, which no reprojection gate can catch)
    assert np.quantile(err, 0.995) < 4.0, np.quantile(err, 0.995)
    assert (err > 8.0).mean() < 0.006, (err > 8.0).mean()
    # unmeasured deformed values are NaN on disk; rigid points are finite everywhere
    assert np.isnan(tok.deformed[~tok.observed]).all()
    assert np.isfinite(tok.rigid).all()
    # windows cut from them: the mid frame's target mask is exactly the token mask
    import torch

    from deformnet.data import WindowBank

    bank = WindowBank([tok.to_sequence()], half_window=4)
    idx = torch.arange(len(bank))
    hide = torch.zeros(len(bank), bank.W, K, dtype=torch.bool)
    b = bank.batch(idx, hide)
    assert torch.equal(b["target_mask"], torch.as_tensor(tok.observed[4 : T - 4]))
    frames = bank.mids[:, None] + torch.arange(-4, 5)
    assert not (b["observed"] & ~torch.as_tensor(tok.observed)[frames]).any()


def test_self_lowers_the_occluded_error_against_rigid(scene, tracked):
    """deformation=self end to end on a deforming scene: completeness 1, an adapted checkpoint,
    and the occluded (< 2 cameras) RMSE at most 0.6x the rigid adjustment's."""
    from adjust.metrics import point_errors

    truth = np.load(scene / "truth.npz")
    m = {
        k: point_errors(_points(out), truth["points"], truth["nviews"])
        for k, (_, out) in tracked.items()
    }
    summary, out = tracked["self"]
    assert summary["deformation"]["mode"] == "self"
    assert (out / "deformation.ckpt").is_file()
    assert summary["deformation"]["adapt"]["pretrained"] == "default"
    assert summary["time_s"]["adapt_s"] > 0
    # the measured part-frames' prior, chosen by held-out cameras (3 cameras here)
    mp = summary["deformation"]["measured_prior"]
    assert mp["choice"] in ("rigid", "interp") and mp["held_out_detections"] > 1000, mp
    assert set(mp["per_camera"]) == set(summary["cameras"])
    assert m["self"]["completeness"] == 1.0
    # trained on windows of token steps 1, 2 and 3 (augmented); the wider ones reach parts the
    # step-1 window misses
    used = summary["deformation"]["net_used_by_step"]
    assert set(used) == {1, 2, 3} and used[1] > 0.5 and used[2] + used[3] > 0, used
    # measured: occluded rigid 7.46, interp 3.66, self 4.32 mm (0.58x rigid) on this scene
    assert m["self"]["rmse_occluded"] < 0.6 * m["rigid"]["rmse_occluded"], m
    assert m["self"]["rmse_seen"] < 1.2 * m["interp"]["rmse_seen"], m


def test_self_falls_back_to_interp_where_its_net_is_worse(scene, tracked):
    """On this scene the adapted net is no better than interp (forced, its tracks' occluded
    RMSE is 3.32 mm against interp's 3.33, measured at stop 48; 3.72 before it fine-tuned
    with the single views among its inputs), and its gate, against interp's kriging with the
    single-view anchors, says so (the kriging without the anchors had passed a worse net,
    3.17 vs 4.17 mm on the benchmark's mouse_b scene): summary.json says interp, with the
    reason, and the tracks are interp's (3.36 mm)."""
    from adjust.metrics import point_errors

    summary, out = tracked["self_gated"]
    d = summary["deformation"]
    assert d["mode"] == "interp" and d["requested"] == "self", d
    assert "does not beat interp's kriging" in d["reason"]
    h = d["heldout"]
    assert h["baseline"] == "interp's kriging with single-view anchors"
    assert h["net_all_mm"] >= 0.98 * h["interp_all_mm"], h
    truth = np.load(scene / "truth.npz")
    occ = {
        k: point_errors(_points(tracked[k][1]), truth["points"], truth["nviews"])["rmse_occluded"]
        for k in ("interp", "self", "self_gated")
    }
    assert occ["self_gated"] < 1.03 * occ["interp"], occ
    assert occ["self"] > 0.97 * occ["interp"], occ  # the net it refused was no better


@pytest.mark.xfail(
    strict=True,
    reason="issue 50: measured self/interp occluded RMSE 1.18 on this scene (4.32 vs 3.66 mm; "
    "0.99 and 1.00 on seeds 32 and 33) since adjust.adapt's step-budgeted fine-tuning "
    "(the Lightning 60 s one measured 0.93)",
)
def test_self_beats_interp_on_the_occluded_parts(scene, tracked):
    """What deformation=self is for: the adapted net predicts the occluded parts better than
    interp's kriging, by at least 3% (interp alone cannot pass this)."""
    from adjust.metrics import point_errors

    truth = np.load(scene / "truth.npz")
    occluded = {
        k: point_errors(_points(tracked[k][1]), truth["points"], truth["nviews"])["rmse_occluded"]
        for k in ("interp", "self")
    }
    assert occluded["self"] < 0.97 * occluded["interp"], occluded


def test_adapted_checkpoint_reproduces_the_track(scene, tracked, tmp_path):
    """deformation=OUT/deformation.ckpt tracks the recording as the self run did: the same net
    on the same body (the checkpoint carries the body the self run estimated). Only the rigid
    start differs (the self run estimated that body in two steps, the checkpoint's run starts
    from it), so the points agree closely and the accuracy is the same within 2%."""
    summary, out = tracked["self"]
    again = _track(scene, tmp_path / "again", [f"deformation={out / 'deformation.ckpt'}"])
    assert again["deformation"]["mode"] == "net"
    a, b = _points(tmp_path / "again"), _points(out)
    assert np.median(np.linalg.norm(a - b, axis=-1)) < 0.05
    truth = np.load(scene / "truth.npz")["points"]
    rmse = [np.sqrt(np.mean(np.sum((p - truth) ** 2, -1))) for p in (a, b)]
    assert abs(rmse[0] / rmse[1] - 1) < 0.02, rmse


def test_shipped_net_loads_without_lightning():
    code = (
        "import sys; sys.modules['lightning'] = None; sys.modules['pytorch_lightning'] = None\n"
        "from deformnet.pretrained import load_default\n"
        "m = load_default(); import torch\n"
        "W, K = m.window, m.num_parts\n"
        "r = torch.zeros(2, W, K, 3) + torch.tensor(m.body.points, dtype=torch.float32)\n"
        "print(tuple(m(r, r, torch.ones(2, W, K, dtype=torch.bool)).shape), K)\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    shape, K = res.stdout.strip().rsplit(" ", 1)
    assert shape == f"(2, {K}, 3)" and int(K) >= 8


@pytest.mark.slow  # the fast check: test_heldout's test_the_shipped_net_is_checked_part_by_part...
def test_default_mode_uses_the_shipped_net(scene, tmp_path):
    s = _track(scene, tmp_path / "d", ["deformation=default"])
    assert s["deformation"]["mode"] == "default"
    assert s["deformation"]["net_passes"] >= 1
    assert s["completeness"] == 1.0


def _tokens(T: int, seed: int, source: str) -> SessionTokens:
    rng = np.random.default_rng(seed)
    rigid = rng.normal(size=(T, 3, 3)).astype(np.float32)
    obs = rng.random((T, 3)) > 0.3
    return SessionTokens(
        rigid, rigid + 1, obs, ("a", "b", "c"), np.eye(3), "b", float("nan"), source
    )


def test_split_by_session_and_by_time_blocks():
    toks = [_tokens(200, i, f"s{i}") for i in range(4)]
    train, val, facts = split_sessions(toks, 0.25, 50, min_frames=9)
    assert facts["split"] == "by session"
    assert facts["val_sessions"] == ["s3"] and facts["train_sessions"] == ["s0", "s1", "s2"]
    assert len(train) == 3 and len(val) == 1
    train, val, facts = split_sessions(toks[:1], 0.2, 50, min_frames=9)
    assert facts["split"] == "by time blocks"
    # blocks 4 and 9 (of 50 frames... shortened to keep two val blocks) validate, the rest train
    assert facts["train_frames"] + facts["val_frames"] == 200
    assert all(s.rigid.shape[0] >= 9 for s in train + val)
    # a session only a few windows long still splits, no piece shorter than a window
    train, val, facts = split_sessions([_tokens(150, 9, "short")], 0.2, 500, min_frames=33)
    assert facts["train_frames"] + facts["val_frames"] == 150 and len(val) >= 1
    assert all(s.rigid.shape[0] >= 33 for s in train + val)
    with pytest.raises(ValueError, match="parts"):
        from deformnet.sessions import check_compatible

        bad = SessionTokens(
            toks[0].rigid, toks[0].deformed, toks[0].observed, ("x", "b", "c"), np.eye(3)
        )
        check_compatible([toks[0], bad])


def test_train_on_sessions_splits_by_session(tracked, tmp_path):
    """deformnet-train data=sessions on three adjust-track folders (fine-tuning the shipped
    net): split by session, the validation metrics of simulated training, a checkpoint."""
    from deformnet.train import run

    folders = [str(tracked[k][1]) for k in ("interp", "rigid", "self")]
    res = run(
        compose(
            "train",
            [
                "data=sessions",
                f"data.sessions=[{','.join(folders)}]",
                "pretrained=default",
                "logger=none",
                "progress_bar=none",
                "trainer.max_time=null",
                "trainer.max_steps=20",
                "trainer.max_epochs=2",
                "data.steps_per_epoch=10",
                "data.val_windows=256",
                f"output.dir={tmp_path / 'train'}",
            ],
        )
    )
    assert res["data"]["split"] == "by session"
    assert len(res["data"]["val_sessions"]) == 1
    assert set(res["data"]["train_sessions"]).isdisjoint(res["data"]["val_sessions"])
    for k in ("val/rmse_mm", "val/rmse_mm_rigid", "val/rmse_mm_linear"):
        assert np.isfinite(res["metrics"][k])
    assert res["best_checkpoint"] and Path(res["best_checkpoint"]).is_file()
    meta = json.loads((tmp_path / "train" / "metrics.json").read_text())
    assert meta["pretrained"] == "default"
    # a lab's tokens are augmented by default (as deformation=self's): windows at token steps
    # 1, 2 and 3, which the checkpoint keeps for the tracker's wider passes
    from deformnet.deformation import DeformationModel

    assert DeformationModel.from_checkpoint(res["best_checkpoint"]).steps == (1, 2, 3)


def test_heading_frame_training_on_sessions_checks_their_worlds_up(tracked, tmp_path):
    """data=sessions with up: each session's mouse must stand on that up (the simulated scene's
    z), else a clear error naming the session before any training."""
    from deformnet.train import run

    folder = str(tracked["interp"][1])
    base = ["data=sessions", f"data.sessions=[{folder}]", "pretrained=null", "net=lstm_small",
            "logger=none", "progress_bar=none", "trainer.fast_dev_run=true",
            "data.val_windows=64"]  # fmt: skip
    res = run(compose("train", [*base, "up=[0,0,1]", f"output.dir={tmp_path / 'z'}"]))
    assert np.isfinite(res["metrics"]["train/loss"])
    with pytest.raises(ValueError, match=r"interp.*heading frame of world up \[0.0, 1.0, 0.0\]"):
        run(compose("train", [*base, "up=[0,1,0]", f"output.dir={tmp_path / 'y'}"]))


def test_sessions_glob_that_matches_nothing_is_a_clear_error(tmp_path):
    from deformnet.sessions import resolve_sessions

    with pytest.raises(ValueError, match="names no session"):
        resolve_sessions([str(tmp_path / "nothing*")])


def test_pretrained_build_is_reproducible(tmp_path):
    """The shipped net's build script gives the same weights for the same seed."""
    from deformnet.pretrained.build import build

    a = build(steps=4, seed=3, out=tmp_path / "a.pt")
    b = build(steps=4, seed=3, out=tmp_path / "b.pt")
    c = build(steps=4, seed=4, out=tmp_path / "c.pt")
    assert a["sha256"] == b["sha256"] != c["sha256"]


@pytest.mark.slow
def test_shipped_net_is_the_build_scripts_output(tmp_path):
    """`python -m adjust.pretrain_real` (make pretrained) reproduces the shipped file: bit for
    bit on the kind of CPU that built it; elsewhere (other float kernels: 3000 steps of
    rounding apart) a net as good as the shipped one on the build's tracks' tokens of the
    validation segment, within 5% of its RMSE (about 15 minutes on 2 cores)."""
    from adjust.pretrain_real import (
        DATA,
        SCENES,
        TRAIN_FRAMES,
        build,
        evaluate,
        scene_tokens,
        token_slice,
    )
    from deformnet.deformation import DeformationModel
    from deformnet.pretrained import load_default
    from deformnet.pretrained.build import weights_sha256

    shipped = load_default()
    res = build(out=tmp_path / "rebuilt.pt", work=tmp_path / "work")
    if res["sha256"] == weights_sha256(shipped):
        return
    tokens = scene_tokens(DATA, TRAIN_FRAMES, SCENES, tmp_path / "work")
    held = [token_slice(t, 1200, 2200, TRAIN_FRAMES[0]) for t in tokens]
    rebuilt = DeformationModel.from_checkpoint(res["checkpoint"])
    a = np.mean([r["net_mm"] for r in evaluate(shipped, held, SCENES)])
    b = np.mean([r["net_mm"] for r in evaluate(rebuilt, held, SCENES)])
    assert b <= 1.05 * a, (a, b)


def test_self_falls_back_to_interp_when_the_net_does_not_beat_interpolation(scene, tmp_path):
    """An adapted net that does not beat the interpolation the run would fall back to (interp's
    kriging) by ``adapt.min_gain`` on held-out parts (here: a net trained from scratch for 20
    steps, a step budget rather than a time one so the test does not depend on the machine's
    load) is not used: the tracks are the interp adjustment's, and the summary says so, with
    the figures."""
    s = _track(
        scene,
        tmp_path / "fb",
        [
            "deformation=self",
            "adapt.pretrained=null",
            "adapt.max_steps=20",
            "adapt.max_time=null",
            "adapt.tensorboard=false",
        ],
    )
    d = s["deformation"]
    assert d["mode"] == "interp" and d["requested"] == "self", d
    assert d["adapt"]["used"] is False
    h = d["heldout"]  # not better than kriging by adapt.min_gain
    assert h["net_all_mm"] >= (1 - h["min_gain"]) * h["interp_all_mm"], h
    assert "deformation_sigma_mm_per_part" in s["deformation"]  # interp's facts
    assert s["completeness"] == 1.0


def test_train_on_a_raw_session_folder_tracks_it_first(scene, tmp_path):
    """data.sessions may name raw session folders (calibration.toml + detections), in
    adjust-track's batch syntax: the builder tracks each (adjust-track, interp) into the
    training folder, then trains on its tokens (one session: split by time blocks)."""
    from deformnet.train import run

    res = run(
        compose(
            "train",
            [
                "data=sessions",
                f"data.sessions=[glob({scene})]",
                "logger=none",
                "progress_bar=none",
                "trainer.max_time=null",
                "trainer.max_steps=10",
                "trainer.max_epochs=1",
                "data.steps_per_epoch=10",
                "data.val_windows=128",
                f"output.dir={tmp_path / 'train'}",
            ],
        )
    )
    assert (tmp_path / "train" / "sessions" / scene.name / "tokens.npz").is_file()
    assert res["data"]["split"] == "by time blocks"
    assert np.isfinite(res["metrics"]["val/rmse_mm"])
