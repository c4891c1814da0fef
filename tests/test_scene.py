"""Simulated multi-camera scenes: rig, self-occlusion, detector model, `adjust-simulate`."""

from __future__ import annotations

from dataclasses import fields
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch
from omegaconf import OmegaConf

from adjust.camera import CameraTensors, project_cameras
from adjust.scene import (
    DetectorConfig,
    Ellipsoid,
    arena_in_view,
    camera_look_at,
    default_rig,
    detector_config,
    occluded_by_boxes,
    occluded_by_ellipsoids,
    simulate_scene,
)
from adjust.scene.rig import RigConfig
from deformnet.body import default_mouse
from deformnet.paths import CONF_DIR
from deformnet.so3 import matrix_to_rodrigues


def standin_sim(T: int = 600, seed: int = 0, arena: float = 300.0) -> SimpleNamespace:
    """A small stand-in for `deformnet.sim.simulate`: the rigid mouse wandering on the ground
    (smooth random path, heading along the velocity, slight pitch) plus part jitter."""
    rng = np.random.default_rng(seed)
    body = default_mouse()
    t = np.arange(T) / 30.0
    pos = np.zeros((T, 2))
    for d in range(2):
        f, ph, a = rng.uniform(0.02, 0.2, 5), rng.uniform(0, 2 * np.pi, 5), rng.uniform(15, 40, 5)
        pos[:, d] = arena / 2 + (a[:, None] * np.sin(2 * np.pi * f[:, None] * t + ph[:, None])).sum(
            0
        )
    pos = np.clip(pos, 45.0, arena - 45.0)
    vel = np.gradient(pos, axis=0)
    yaw = np.arctan2(vel[:, 1], vel[:, 0]) - np.pi / 2  # model +Y along the velocity
    pitch = 0.15 * np.sin(2 * np.pi * 0.3 * t)
    cz, sz, cx, sx = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    o, i = np.zeros(T), np.ones(T)
    Rz = np.stack(
        [np.stack([cz, -sz, o], -1), np.stack([sz, cz, o], -1), np.stack([o, o, i], -1)], 1
    )
    Rx = np.stack(
        [np.stack([i, o, o], -1), np.stack([o, cx, -sx], -1), np.stack([o, sx, cx], -1)], 1
    )
    R = Rz @ Rx
    tau = np.concatenate([pos, np.full((T, 1), 8.0)], 1)
    rigid = np.einsum("tij,kj->tki", R, body.points) + tau[:, None]
    return SimpleNamespace(
        time=t,
        poses=np.concatenate([matrix_to_rodrigues(torch.as_tensor(R)).numpy(), tau], 1),
        rigid=rigid,
        deformed=rigid + rng.normal(0.0, 1.0, rigid.shape),
        labels=np.zeros(T, dtype=np.int64),
        behaviors=("walk",),
        parts=body.parts,
        model=body.points,
        fps=30.0,
        seed=seed,
        lockbox_corners=np.array([[60.0, 260, 0], [240, 260, 0], [240, 300, 45], [60, 300, 45]]),
        arena_size=np.array([arena, arena]),
    )


@pytest.fixture(scope="module")
def rig():
    return default_rig(None)


@pytest.fixture(scope="module")
def sim():
    return standin_sim(1500)


# --- rig ------------------------------------------------------------------------------------
def test_look_at_camera_geometry():
    cam = camera_look_at("c", [0, -500, 0], [0, 0, 0], up=[0, 0, 1], focal_px=1000, size=[641, 481])
    assert np.allclose(cam.K[:2, 2], [320.0, 240.0])  # pixel origin at the top-left pixel centre
    assert np.allclose(cam.center, [0, -500, 0])
    R = cam.R
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    X = torch.tensor([[0.0, 0, 0], [0, 0, 10], [10, 0, 0]], dtype=torch.float64)
    uv = project_cameras(X, CameraTensors.from_cameras([cam]))[:, 0].numpy()
    assert np.allclose(uv[0], [320, 240])  # the look-at point at the principal point
    assert uv[1, 1] < 240 and np.isclose(uv[1, 0], 320)  # world up -> image up
    assert uv[2, 0] > 320  # +X is to the right when looking along +Y with Z up
    with pytest.raises(ValueError, match="parallel"):
        camera_look_at("top", [0, 0, 500], [0, 0, 0], up=[0, 0, 1])
    with pytest.raises(ValueError, match="coincide"):
        camera_look_at("c", [1, 2, 3], [1, 2, 3])


def test_default_rig_sees_the_arena(rig):
    assert [c.name for c in rig] == ["top", "side", "front"]
    assert all(arena_in_view(rig, [300.0, 300.0], height=80.0).values())
    # about 90 degrees between the viewing directions
    d = np.stack([c.R[2] for c in rig])
    ang = np.degrees(np.arccos(np.clip(d @ d.T, -1, 1)))
    assert 50 < ang[0, 1] < 130 and 50 < ang[0, 2] < 130 and 60 < ang[1, 2] < 120


def test_the_rig_settings_are_typed_and_their_yaml_defaults_are_the_dataclass_s():
    """conf/rig/default.yaml's ``up`` and ``arena_view_height`` are `RigConfig`'s defaults (the
    one copy in the code); a rig without them keeps those."""
    yaml = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "rig" / "default.yaml"))
    assert tuple(yaml["up"]) == tuple(RigConfig().up)
    assert yaml["arena_view_height"] == RigConfig().arena_view_height
    assert RigConfig.from_config({"cameras": {}}) == RigConfig()
    given = RigConfig.from_config({"up": [0, 1, 0], "arena_view_height": 50})
    assert list(given.up) == [0, 1, 0] and given.arena_view_height == 50.0


def test_bad_rig_config():
    with pytest.raises(ValueError, match="cameras"):
        default_rig({"cameras": {}})
    with pytest.raises(ValueError, match="missing keys"):
        default_rig({"cameras": {"a": {"position": [0, 0, 1]}}})
    with pytest.raises(ValueError, match="unknown keys"):
        default_rig(
            {
                "cameras": {
                    "a": {
                        "position": [0, 0, 1],
                        "look_at": [0, 1, 0],
                        "focal_px": 10,
                        "size": [10, 10],
                        "fov": 3,
                    }
                }
            }
        )


# --- occlusion ------------------------------------------------------------------------------
def test_point_in_front_visible_behind_hidden():
    ell = [Ellipsoid("trunk", [0, 0, 0], [10, 20, 5])]
    pose = np.zeros((1, 6))
    cam = np.array([[0.0, 0, 500]])  # above
    pts = np.array([[[0.0, 0, 8], [0, 0, -8], [15, 0, -8], [0, 5, 4.0], [0, 0, -2], [0, 0, 2]]])
    hid = occluded_by_ellipsoids(pts, pose, cam, ell, surface_margin=2.0)[0, :, 0]
    # above (in front of) it; below (behind) it; beside it; just under its surface (the part's
    # own surface vicinity); inside, in the lower half (stands for the bottom surface: hidden
    # from above); inside, upper half (the top surface: seen)
    assert hid.tolist() == [False, True, False, False, True, False]
    # the same from the side camera: the point above is seen, one beyond the body is not
    side = np.array([[500.0, 0, 0]])
    pts_s = np.array([[[0.0, 0, 8], [-15, 0, 0], [15, 0, 0]]])
    assert occluded_by_ellipsoids(pts_s, pose, side, ell, 2.0)[0, :, 0].tolist() == [
        False,
        True,
        False,
    ]
    # moved with the pose: turn the body 90 degrees about Z and shift it
    pose2 = np.array([[0, 0, np.pi / 2, 100, 50, 0]])
    pts2 = np.array([[[100.0 - 15, 50, -8], [100 + 15, 50, -8], [100, 50 + 15, -8]]])
    hid2 = occluded_by_ellipsoids(pts2, pose2, np.array([[100.0, 50, 500]]), ell, 2.0)[0, :, 0]
    assert hid2.tolist() == [True, True, False]


def test_ellipsoid_following_parts():
    # a proxy attached to three parts moves with their rigid fit, not with the body pose
    model = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [5, 5, -30]])
    parts = ("a", "b", "c", "paw")
    ell = [Ellipsoid("head", [5, 5, -10], [6, 6, 6], ("a", "b", "c"))]
    shift = np.array([100.0, 0, 0])
    pts = (model + shift)[None]  # the whole body shifted, the pose left at the identity
    pose = np.zeros((1, 6))
    cam = np.array([[105.0, 5, 500]])
    hid = occluded_by_ellipsoids(pts, pose, cam, ell, 2.0, model=model, parts=parts)
    assert hid[0, :, 0].tolist() == [False, False, False, True]
    with pytest.raises(ValueError, match="model and parts"):
        occluded_by_ellipsoids(pts, pose, cam, ell, 2.0)
    with pytest.raises(ValueError, match=">= 3 distinct parts"):
        Ellipsoid("x", [0, 0, 0], [1, 1, 1], ("a", "b"))


def test_box_occlusion():
    box = np.array([[[0.0, 0, 0], [10, 10, 10]]])
    cam = np.array([[5.0, -100, 5]])
    pts = np.array([[[5.0, -5, 5], [5, 20, 5], [5, 1, 5], [30, 20, 5]]])
    # in front; behind; touching its near face (surface vicinity); beside
    assert occluded_by_boxes(pts, cam, box, 2.0)[0, :, 0].tolist() == [False, True, False, False]


def test_paws_under_trunk_hidden_from_top_more_than_side(rig, sim):
    det = simulate_scene(sim, rig, None, seed=0)
    top, side = [c.name for c in rig].index("top"), [c.name for c in rig].index("side")
    paws = [det.parts.index(p) for p in ("left_front_paw", "right_front_paw")]
    occ = det.occluded[:, paws]
    assert occ[..., top].mean() > occ[..., side].mean() + 0.2
    assert occ[..., top].mean() > 0.6
    # the ears, on top of the head, are always seen from the top
    ears = [det.parts.index(p) for p in ("left_ear", "right_ear")]
    assert det.occluded[:, ears, top].mean() < 0.05


# --- detector model -------------------------------------------------------------------------
def test_detector_rates_roughly_as_configured(rig, sim):
    cfg = detector_config(
        {"dropout_rate": 0.2, "outlier_rate": 0.05, "swap_rate": 0.03, "noise_px": 2.0}
    )
    det = simulate_scene(sim, rig, cfg, seed=3)
    f = det.fractions()
    assert abs(f["dropout_given_visible"] - 0.2) < 0.03
    assert abs(f["outlier"] - 0.05) < 0.01
    T, K, C = det.likelihood.shape
    assert det.xy.shape == (T, K, C, 2) and det.visible.shape == (T, K, C)
    found = det.visible & ~det.dropped & ~det.outlier
    assert (det.likelihood[found] >= 0.9).all()
    hidden = ~det.visible & ~det.outlier & det.in_image
    assert (det.likelihood[hidden] <= 0.3).all() and (det.likelihood[hidden] >= 0.01).all()
    assert np.isfinite(det.xy).all()  # DLC always reports a position (out_of_image: clip)
    err = np.linalg.norm(det.xy - det.truth_xy, axis=-1)
    assert 1.5 < np.median(err[found]) < 3.5  # Rayleigh median of sigma 2: 2.35
    far = det.outlier & ~det.swapped
    assert (det.likelihood[far] >= 0.6).all() and np.median(err[far]) > 40
    # swaps: a left/right pair, both visible, each reported at the other's place
    assert det.swapped.any()
    t, k, c = np.argwhere(det.swapped)[0]
    j = det.parts.index(
        det.parts[k].replace("left", "@").replace("right", "left").replace("@", "right")
    )
    assert det.swapped[t, j, c]
    assert np.linalg.norm(det.xy[t, k, c] - det.truth_xy[t, j, c]) < 15


def test_distorted_camera(sim):
    cam = camera_look_at(
        "wide",
        [150, 150, 700],
        [150, 150, 0],
        up=[0, 1, 0],
        focal_px=1500,
        size=[1280, 1024],
        dist=[-0.2, 0.05, 0.0, 0.0, 0.0],
    )
    assert np.allclose(cam.dist, [-0.2, 0.05, 0, 0, 0])
    det = simulate_scene(sim, [cam], None, seed=0)
    assert det.in_image.all() and np.isfinite(det.xy).all()


def test_out_of_image_and_behind(sim):
    cam = camera_look_at(
        "narrow", [150, 150, 400], [150, 150, 0], up=[0, 1, 0], focal_px=3000, size=[320, 240]
    )
    det = simulate_scene(sim, [cam], {"outlier_rate": 0.0}, seed=0)
    assert 0.0 < det.in_image.mean() < 1.0
    out = ~det.in_image
    assert (det.likelihood[out] <= 0.05).all() and not det.visible[out].any()
    assert (det.xy[out] >= -0.5).all() and (det.xy[out][:, 0] < 320).all()
    det_nan = simulate_scene(sim, [cam], {"out_of_image": "nan"}, seed=0)
    assert np.isnan(det_nan.xy[out]).all()
    # a camera in the arena looking along +X: what lies behind it is never visible
    inside = camera_look_at("in", [150, 150, 60], [300, 150, 0], focal_px=300, size=[1280, 1024])
    det_in = simulate_scene(sim, [inside], None, seed=0)
    behind = sim.deformed[..., 0] < 140
    assert behind.any() and not det_in.in_image[behind, 0].any()
    assert (det_in.likelihood[behind, 0] <= 0.05).all()


def test_deterministic(rig, sim):
    a = simulate_scene(sim, rig, None, seed=5)
    b = simulate_scene(sim, rig, None, seed=5)
    c = simulate_scene(sim, rig, None, seed=6)
    assert np.array_equal(a.xy, b.xy) and np.array_equal(a.likelihood, b.likelihood)
    assert not np.array_equal(a.xy, c.xy)


def test_bad_detector_config():
    with pytest.raises(ValueError, match="dropout_rate"):
        detector_config({"dropout_rate": 1.5})
    with pytest.raises(ValueError, match="unknown detector config keys"):
        detector_config({"dropout": 0.1})
    with pytest.raises(ValueError, match="hidden_likelihood"):
        DetectorConfig(hidden_likelihood=(0.5, 0.2))
    with pytest.raises(ValueError, match="radii"):
        detector_config({"occluders": {"trunk": {"center": [0, 0, 0], "radii": [1, 0, 1]}}})
    with pytest.raises(ValueError, match="out_of_image"):
        DetectorConfig(out_of_image="drop")


def test_shipped_detector_config_loads():
    from omegaconf import OmegaConf

    cfg = detector_config(OmegaConf.load(CONF_DIR / "detector" / "default.yaml"))
    assert [e.name for e in cfg.occluders] == ["trunk", "head"] and cfg.threshold == 0.5
    assert cfg.occluders[1].parts == ("nose_tip", "left_ear", "right_ear")


def test_standin_fractions_in_range(rig):
    det = simulate_scene(
        standin_sim(3000, seed=1),
        rig,
        detector_config(
            __import__("omegaconf").OmegaConf.load(CONF_DIR / "detector" / "default.yaml")
        ),
        seed=0,
    )
    f = det.fractions()
    assert 0.4 <= f["ge2_views"] <= 0.65, f
    assert 0.05 <= f["no_view"] <= 0.16, f


# --- scene folder and adjust-simulate -------------------------------------------------------
def test_write_scene_reads_back(tmp_path, rig, sim):
    from adjust.io import load_scene
    from adjust.scene import write_scene

    det = simulate_scene(sim, rig, None, seed=0)
    res = write_scene(tmp_path / "scene", sim, rig, det)
    body = default_mouse()
    cams, loaded = load_scene(res["calibration"], tmp_path / "scene" / "detections", body)
    assert [c.name for c in cams] == ["top", "side", "front"]
    assert loaded.parts == body.parts and loaded.cameras == ("top", "side", "front")
    assert loaded.xy.shape == det.xy.shape
    for a, b in zip(cams, rig):
        assert np.allclose(a.K, b.K) and np.allclose(a.R, b.R) and np.allclose(a.tvec, b.tvec)
        assert tuple(a.size) == tuple(b.size)
    np.testing.assert_allclose(loaded.likelihood, det.likelihood)
    # the in-memory twin equals what the loader reads back
    mem = det.to_detections()
    np.testing.assert_allclose(loaded.xy, mem.xy, equal_nan=True)
    assert np.array_equal(loaded.observed, mem.observed)
    truth = np.load(res["truth"])
    assert truth["points"].shape == sim.deformed.shape
    assert truth["nviews"].shape == det.likelihood.shape[:2]
    assert truth["visible"].shape == det.likelihood.shape
    assert list(truth["parts"]) == list(body.parts)


def test_truth_labels_csv_is_what_classify_reads(tmp_path, rig, sim):
    from adjust.scene import write_scene, write_truth_labels
    from deformnet.behavior.labels import read_labels

    det = simulate_scene(sim, rig, None, seed=0)
    res = write_scene(tmp_path / "scene", sim, rig, det)
    path = write_truth_labels(res["dir"], tmp_path / "labels.csv")
    truth = np.load(res["truth"])
    names = [str(b) for b in truth["behaviors"]]
    assert (truth["labels"] >= 0).all()
    labels = read_labels(path, np.arange(len(truth["labels"])), names)  # the classifier's reader
    assert np.array_equal(labels, truth["labels"])
    df = pd.read_csv(path)
    assert list(df.columns) == ["fnum", "label"] and df["fnum"].tolist() == list(range(len(df)))
    # a scene without behavior labels: an error naming its truth file
    z = dict(truth)
    z["labels"] = np.full_like(truth["labels"], -1)
    (tmp_path / "nolabels").mkdir()
    np.savez(tmp_path / "nolabels" / "truth.npz", **z)
    with pytest.raises(ValueError, match=r"nolabels/truth.npz: the scene has no behavior labels"):
        write_truth_labels(tmp_path / "nolabels", tmp_path / "x.csv")
    assert not (tmp_path / "x.csv").exists()


def test_adjust_simulate_compose_run(tmp_path):
    from hydra import compose, initialize_config_dir

    from adjust.apps.simulate import run
    from adjust.io import load_scene

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose("scene", overrides=["num_frames=3000", "seed=0", f"output.dir={tmp_path}"])
    res = run(cfg)
    assert (tmp_path / "calibration.toml").is_file() and (tmp_path / "truth.npz").is_file()
    assert sorted(p.name for p in (tmp_path / "detections").iterdir()) == [
        "front.csv",
        "side.csv",
        "top.csv",
    ]
    body = default_mouse()
    cams, det = load_scene(tmp_path / "calibration.toml", tmp_path / "detections", body)
    assert [c.name for c in cams] == ["top", "side", "front"]
    assert det.parts == body.parts and det.xy.shape == (3000, body.num_parts, 3, 2)
    f = res["fractions"]
    assert 0.42 <= f["ge2_views"] <= 0.62, f
    assert 0.06 <= f["no_view"] <= 0.17, f
    truth = np.load(tmp_path / "truth.npz")
    assert truth["points"].shape == (3000, body.num_parts, 3)
    assert np.isclose((truth["nviews"] >= 2).mean(), f["ge2_views"])


def test_dataclass_defaults_match_shipped_config():
    from omegaconf import OmegaConf

    shipped = detector_config(OmegaConf.load(CONF_DIR / "detector" / "default.yaml"))
    plain = DetectorConfig()
    for f in fields(DetectorConfig):
        a, b = getattr(shipped, f.name), getattr(plain, f.name)
        if f.name == "occluders":
            assert [(e.name, e.center.tolist(), e.radii.tolist(), e.parts) for e in a] == [
                (e.name, e.center.tolist(), e.radii.tolist(), e.parts) for e in b
            ]
        else:
            assert a == b, f.name


def test_adjust_simulate_bad_config(tmp_path):
    from hydra import compose, initialize_config_dir

    from adjust.apps.simulate import run

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        for bad, match in (("num_frames=0", "num_frames"), ("seed=-1", "seed")):
            cfg = compose("scene", overrides=[bad, f"output.dir={tmp_path}"])
            with pytest.raises(ValueError, match=match):
                run(cfg)
        cfg = compose(
            "scene",
            overrides=["num_frames=10", "detector.dropout_rate=2", f"output.dir={tmp_path}"],
        )
        with pytest.raises(ValueError, match="dropout_rate"):
            run(cfg)
