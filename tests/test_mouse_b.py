"""The second simulated mouse (`sim=mouse_b`) and the shape helpers (`deformnet.shape`)."""

from __future__ import annotations

import numpy as np
import pytest

from deformnet.body import default_mouse
from deformnet.paths import CONF_DIR, real_mouse_poses_dir
from deformnet.shape import load_real_poses, pair_distances, real_paper_parts, rigid_floor
from deformnet.sim import SimConfig, simulate

FRAMES = 3000  # 30 s at mouse_b's 100 fps


@pytest.fixture(scope="module")
def cfg() -> SimConfig:
    return SimConfig.from_name("mouse_b")


@pytest.fixture(scope="module")
def run(cfg):
    return simulate(cfg, num_frames=FRAMES, seed=0)


def _idx(data, names):
    return [data.parts.index(n) for n in names]


# --- the config ------------------------------------------------------------------------------
def test_config_loads_with_its_defaults(cfg):
    assert SimConfig.from_name("default") == SimConfig()
    assert cfg.fps == 100.0 and cfg.body_scale == 1.2
    assert cfg.lockbox == SimConfig().lockbox  # inherited from default.yaml
    with pytest.raises(ValueError, match="sim config 'nope' not found"):
        SimConfig.from_name("nope")
    with pytest.raises(ValueError, match="sim.deform.head_yaw"):
        SimConfig.from_config({"deform": {"head_yaw": -1.0}})
    with pytest.raises(ValueError, match="sim.body_scale"):
        SimConfig.from_config({"body_scale": 0.0})


def test_from_name_matches_hydra_composition(cfg):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        app = compose("simulate", overrides=["sim=mouse_b"])
    assert SimConfig.from_config(app.sim) == cfg


def test_deterministic_per_seed(cfg, run):
    again = simulate(cfg, num_frames=FRAMES, seed=0)
    np.testing.assert_array_equal(run.deformed, again.deformed)
    np.testing.assert_array_equal(run.poses, again.poses)
    other = simulate(cfg, num_frames=FRAMES, seed=1)
    assert not np.allclose(run.deformed, other.deformed)


# --- size, floor, gait -------------------------------------------------------------------------
def test_size_is_1_2_times_table_1(run):
    mouse = default_mouse()
    np.testing.assert_allclose(run.model, 1.2 * mouse.points, atol=1e-12)  # the truth body
    floor = rigid_floor(run.deformed, parts=run.parts)

    def centroid_size(p):
        return np.sqrt(((p - p.mean(0)) ** 2).sum(1).mean())

    ratio = centroid_size(floor.body.points) / centroid_size(mouse.points)
    assert 1.14 < ratio < 1.26, ratio
    tail = pair_distances(run.deformed, run.parts, [("nose_tip", "tail_root")])
    assert 70.0 < np.median(tail) < 90.0  # a real mouse: 81 +- 10 mm


def test_rigid_floor_at_least_8_mm(run):
    floor = rigid_floor(run.deformed, parts=run.parts)
    assert floor.rms >= 8.0, floor.as_dict()
    per = dict(zip(run.parts, floor.per_part))
    # a hind paw and the snout stray from any rigid body far more than an ear
    assert per["left_hind_paw"] > per["left_ear"] and per["nose_tip"] > per["right_ear"]
    default = simulate(num_frames=1000, seed=0)
    assert rigid_floor(default.deformed).rms < floor.rms - 3.0


def test_trot_diagonal_paws_swing_together(run):
    names = ["left_front_paw", "right_front_paw", "left_hind_paw", "right_hind_paw"]
    paws = run.deformed[:, _idx(run, names)]
    body_v = np.hypot(*np.diff(run.poses[:, 3:5], axis=0).T) * run.fps
    paw_v = np.linalg.norm(np.diff(paws, axis=0), axis=-1) * run.fps  # (T-1, 4)
    walk = (run.labels[1:] == 0) & (body_v > 40.0)
    assert walk.sum() > 300
    swing = paw_v[walk] > 1.0 * body_v[walk, None]  # swinging paws move at ~2x body speed
    lf, rf, lh, rh = swing.T
    assert swing.mean() == pytest.approx(0.5, abs=0.1)
    assert (lf == rh).mean() > 0.9 and (rf == lh).mean() > 0.9  # diagonal pairs together
    assert (lf != rf).mean() > 0.9  # the pairs alternate
    # stride: a stance paw goes from about +11 to -11 mm about its rigid position
    k = _idx(run, ["left_front_paw"])[0]
    off = np.einsum(
        "tji,tj->ti", _rot(run)[1:][walk], (run.deformed - run.rigid)[1:, k][walk]
    )  # body frame
    assert 8.0 < np.percentile(np.abs(off[:, 1]), 95) < 20.0


def _rot(data):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(data.poses[:, :3]).as_matrix()


def test_spine_bends_with_turns_and_head_moves_on_its_own(run):
    R = _rot(run)
    local = np.einsum("tji,tkj->tki", R, run.deformed - run.poses[:, None, 3:])  # body frame
    tail = local[:, run.parts.index("tail_root"), 0] - run.model[run.parts.index("tail_root"), 0]
    yaw_rate = np.gradient(_yaw(R)) * run.fps
    walk = run.labels == 0
    # the rear lags behind a turn: turning left (yaw increasing) swings the tail root to the
    # outside of the curve, -X of the rigid body
    c = np.corrcoef(yaw_rate[walk], tail[walk])[0, 1]
    assert c < -0.3, c
    # the head triangle turns relative to the trunk by tens of degrees
    head = _idx(run, ["nose_tip", "left_ear", "right_ear"])
    nose_dir = local[:, head[0], :2] - local[:, head[1:], :2].mean(1)
    ang = np.degrees(np.arctan2(-nose_dir[:, 0], nose_dir[:, 1]))
    assert np.percentile(np.abs(ang), 90) > 15.0


def test_spine_bend_is_a_rotation_about_the_pivot(cfg):
    import dataclasses

    still = cfg.replace(deform=dataclasses.replace(cfg.deform, jitter=0.0))
    d = simulate(still, num_frames=1500, seed=2)
    R = _rot(d)
    k = d.parts.index("tail_root")
    local = np.einsum("tji,tj->ti", R, d.deformed[:, k] - d.poses[:, 3:])
    pivot = np.array([0.0, cfg.deform.spine_pivot * cfg.body_scale])
    walk = d.labels == 0
    r = np.linalg.norm(local[walk, :2] - pivot, axis=1)
    np.testing.assert_allclose(r, np.linalg.norm(d.model[k, :2] - pivot), atol=1e-9)
    bend = np.degrees(np.arctan2(local[walk, 0], pivot[1] - local[walk, 1]))
    assert np.abs(bend).max() <= cfg.deform.spine_max + 4 * cfg.deform.spine_wiggle
    assert np.percentile(np.abs(bend), 90) > 5.0


def _yaw(R):
    return np.unwrap(np.arctan2(-R[:, 0, 1], R[:, 1, 1]))


def test_rearing_is_high_with_free_front_paws(run):
    rear = run.labels == 2
    assert rear.sum() > 100
    nose = run.deformed[:, run.parts.index("nose_tip"), 2]
    assert 90.0 < nose[rear].max() < 150.0  # a real mouse: snout up to 120 mm
    R = _rot(run)
    k = run.parts.index("left_front_paw")
    rel = np.einsum("tji,tj->ti", R, run.deformed[:, k] - run.rigid[:, k])
    peak = rear & (run.deformed[:, run.parts.index("nose_tip"), 2] > 60.0)
    # the reared front paw moves relative to the body (not a fixed tuck)
    assert np.std(rel[peak], axis=0).max() > 2.0


# --- the scene -------------------------------------------------------------------------------
@pytest.mark.parametrize("detector", ["default", "mouse_b"])
def test_adjust_simulate_mouse_b_scene(tmp_path, detector):
    from hydra import compose, initialize_config_dir

    from adjust.apps.simulate import run as scene_run

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose(
            "scene",
            overrides=[
                "sim=mouse_b",
                f"detector={detector}",
                "num_frames=1500",
                "seed=0",
                f"output.dir={tmp_path}",
            ],
        )
        res = scene_run(cfg)
    f = res["fractions"]
    assert 0.42 <= f["ge2_views"] <= (0.65 if detector == "default" else 0.58), f
    truth = np.load(tmp_path / "truth.npz")
    assert float(truth["fps"]) == 100.0
    assert truth["points"].shape == (1500, 8, 3)


# --- deformnet.shape -------------------------------------------------------------------------
def test_rigid_floor_is_zero_for_rigid_motion_and_exact_for_one_moving_part():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    body = default_mouse().points
    R = Rotation.random(200, random_state=1).as_matrix()
    X = np.einsum("tij,kj->tki", R, body) + rng.normal(0, 50, (200, 1, 3))
    assert rigid_floor(X).rms < 1e-6
    # one part of K moving +-5 mm: a rigid body that ignores it is 5 / sqrt(K) mm RMS away;
    # the best fit (which shifts and turns a little towards it) is closer, never farther
    Y = np.repeat(body[None], 400, 0).copy()
    Y[:, 0, 2] += np.where(np.arange(400) % 2 == 0, 5.0, -5.0)
    f = rigid_floor(Y)
    K = len(body)
    assert 0.8 * 5.0 / np.sqrt(K) < f.rms <= 5.0 / np.sqrt(K) + 1e-9
    assert f.per_part[0] == f.per_part.max()
    Xn = X.copy()
    Xn[::3, 4] = np.nan
    g = rigid_floor(Xn)
    assert np.isnan(g.residual[::3, 4]).all() and g.rms < 1e-6


@pytest.mark.skipif(
    not (real_mouse_poses_dir() / "poses3d.csv").is_file(), reason="shared real poses absent"
)
def test_real_poses_load():
    parts, pts = load_real_poses()
    assert len(parts) == 22 and pts.shape == (91, 22, 3)
    assert 0.0 < np.isnan(pts).mean() < 0.05
    names, eight = real_paper_parts()
    assert eight.shape == (91, 8, 3) and names[0] == "nose_tip"
    floor = rigid_floor(eight, parts=names)
    assert 8.0 < floor.rms < 12.0  # a real mouse is far from rigid


def test_load_real_poses_errors(tmp_path):
    bad = tmp_path / "poses3d.csv"
    bad.write_text("sample_ms,A_x,A_y,A_z\n0,1,2,x\n")
    with pytest.raises(ValueError, match=r"row 2, column A_z: not a number"):
        load_real_poses(bad)
    bad.write_text("sample_ms,A_x,A_y\n0,1,2\n")
    with pytest.raises(ValueError, match="columns"):
        load_real_poses(tmp_path)
    with pytest.raises(ValueError, match="not found"):
        load_real_poses(tmp_path / "missing.csv")
