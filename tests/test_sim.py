"""Deformable-mouse simulator: kinematics of gait, head and behaviors, arena, determinism,
config, masks, file format."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import yaml
from scipy.spatial.transform import Rotation

from deformnet.body import BodyModel, default_mouse
from deformnet.paths import CONF_DIR
from deformnet.sim import BEHAVIORS, MECHANISMS, SimConfig, SimData, load_sim, save_sim, simulate
from deformnet.so3 import kabsch

FPS = 30.0
PAIR_A = ("right_front_paw", "left_hind_paw")  # the paper: stance together
PAIR_B = ("left_front_paw", "right_hind_paw")


@pytest.fixture(scope="module")
def cfg() -> SimConfig:
    return SimConfig()


@pytest.fixture(scope="module")
def long_run(cfg) -> SimData:
    return simulate(cfg, num_frames=60000, seed=11)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of the True runs of a 1-D bool array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def _interior(mask: np.ndarray, pad: int) -> np.ndarray:
    """mask, shrunk by `pad` frames at each run's ends."""
    out = np.zeros_like(mask)
    for a, b in _runs(mask):
        if b - a > 2 * pad:
            out[a + pad : b - pad] = True
    return out


def _rot(data: SimData) -> np.ndarray:
    return Rotation.from_rotvec(data.poses[:, :3]).as_matrix()


def _idx(data: SimData, *names: str) -> list[int]:
    return [data.parts.index(n) for n in names]


def _head_angles(data: SimData) -> np.ndarray:
    """(T, 3) yaw, pitch, roll (deg) of the deformed head triangle relative to the body."""
    R, tau = _rot(data), data.poses[:, 3:]
    h = _idx(data, "nose_tip", "left_ear", "right_ear")
    local = np.einsum("tji,tkj->tki", R, data.deformed[:, h] - tau[:, None])  # R^T (X - tau)
    Rh, _ = kabsch(torch.as_tensor(local), torch.as_tensor(data.model[h]))  # ref -> local
    Rh = Rh.numpy()
    return Rotation.from_matrix(Rh).as_euler("ZXY", degrees=True)


# --- contract ----------------------------------------------------------------------------------
def test_contract_shapes_and_dtypes(long_run):
    d = long_run
    T, K = 60000, 8
    assert d.time.shape == (T,) and d.time.dtype == np.float64
    assert np.allclose(np.diff(d.time), 1 / FPS)
    assert d.poses.shape == (T, 6) and d.poses.dtype == np.float64
    assert d.rigid.shape == d.deformed.shape == (T, K, 3)
    assert d.labels.shape == (T,) and d.labels.dtype == np.int64
    assert (
        d.behaviors
        == BEHAVIORS
        == ("walk", "scan", "rear", "groom", "lever", "splint", "ball", "slider")
    )
    assert d.observed.shape == (T, K) and d.observed.dtype == np.bool_
    assert d.parts == default_mouse().parts and d.model.shape == (K, 3)
    assert d.fps == FPS and d.seed == 11
    assert d.lockbox_corners.shape == (8, 3)
    assert d.mechanisms[0] == MECHANISMS and d.mechanisms[1].shape == (4, 3)
    assert d.arena_size.tolist() == [300.0, 300.0]
    assert dataclasses.is_dataclass(d)
    with pytest.raises(dataclasses.FrozenInstanceError):
        d.fps = 1.0  # type: ignore[misc]


def test_rigid_is_model_moved_by_pose(long_run):
    d = long_run
    X = np.einsum("tij,kj->tki", _rot(d), d.model) + d.poses[:, None, 3:]
    np.testing.assert_allclose(d.rigid, X, atol=1e-9)


# --- gait --------------------------------------------------------------------------------------
def _swing_ratio(d: SimData, band_deg: float, window: int) -> tuple[np.ndarray, dict]:
    """Swing paw / body horizontal speed on steady, straight walking frames (heading within
    `band_deg` for +-window frames, no rest within +-1.5 s, no pair swap at t-1 .. t+1), and
    stance statistics over all moving walk frames."""
    from scipy.ndimage import maximum_filter1d, minimum_filter1d

    walk = (d.labels[:-1] == 0) & (d.labels[1:] == 0)
    body_v = np.hypot(*np.diff(d.poses[:, 3:5], axis=0).T) * FPS
    moving = walk & (body_v > 15.0)
    paw_v = np.linalg.norm(np.diff(d.deformed, axis=0), axis=-1) * FPS  # (T-1, K), 3D
    a, b = _idx(d, *PAIR_A), _idx(d, *PAIR_B)
    planted = np.stack([(paw_v[:, a] < 1e-9).all(1), (paw_v[:, b] < 1e-9).all(1)], 1)
    any_still = np.stack([(paw_v[:, a] < 1e-9).any(1), (paw_v[:, b] < 1e-9).any(1)], 1)
    stats = {
        "moving": int(moving.sum()),
        "one_pair_planted": float(np.mean(planted[moving].any(1))),
        "both_planted": int(np.sum(planted[moving].all(1))),
        "split_pairs": int(np.sum(any_still[moving] & ~planted[moving])),
        "share_a": float(planted[moving, 0].sum() / max(1, planted[moving].any(1).sum())),
    }
    R = _rot(d)
    yaw = np.unwrap(np.arctan2(R[:, 1, 1], R[:, 0, 1]))
    band = maximum_filter1d(yaw, 2 * window + 1) - minimum_filter1d(yaw, 2 * window + 1)
    ok = (band[:-1] < np.radians(band_deg)) & (minimum_filter1d(body_v, 91) > 10.0) & moving
    steady = np.zeros_like(ok)
    steady[1:-1] = (planted[1:-1] == planted[:-2]).all(1) & (planted[1:-1] == planted[2:]).all(1)
    sel = ok & steady & planted.any(1)
    hv = np.linalg.norm(np.diff(d.deformed[..., :2], axis=0), axis=-1) * FPS
    swing = np.where(planted[:, :1], hv[:, b], hv[:, a])  # the pair that is not planted
    return (swing[sel] / body_v[sel, None]).ravel(), stats


def test_pace_gait_stance_still_and_swing_twice_body_speed(long_run):
    ratio, st = _swing_ratio(long_run, band_deg=5.0, window=15)
    assert st["moving"] > 5000
    # a diagonal pair is planted (both paws exactly still) in almost every moving frame; the
    # rest are the frames in which the pairs swap
    assert st["one_pair_planted"] > 0.85
    assert st["both_planted"] == 0
    assert st["split_pairs"] == 0  # the paws of a pair are planted together
    assert 0.3 < st["share_a"] < 0.7  # both pairs take turns
    # swing pair: twice the body's speed. Footfalls are placed by gait distance, so where the
    # path bends within a stride this holds to a few per cent only (exact test below)
    assert len(ratio) > 200
    err = np.abs(ratio - 2.0)
    assert abs(np.median(ratio) - 2.0) < 0.03
    assert np.mean(err < 0.1) > 0.7, np.percentile(err, [50, 80, 95])


def test_swing_exactly_twice_body_speed_on_straight_paths():
    cfg = SimConfig.from_config({"walk": {"curvature_std": 0.0, "stop_rate": 0.0}})
    ratio, st = _swing_ratio(simulate(cfg, num_frames=20000, seed=2), band_deg=0.5, window=30)
    assert len(ratio) > 200 and st["split_pairs"] == 0
    np.testing.assert_allclose(ratio, 2.0, atol=0.01)


def test_paws_on_the_ground_in_stance(long_run):
    d = long_run
    walk = d.labels == 0
    paws = _idx(d, *PAIR_A, *PAIR_B)
    z = d.deformed[walk][:, paws, 2]
    assert z.min() >= -1e-9
    assert np.mean(z < 1e-9) > 0.4  # stance half of the time
    assert z.max() <= SimConfig().gait.swing_height + 1e-9


# --- head --------------------------------------------------------------------------------------
def test_head_angles_in_configured_intervals(long_run, cfg):
    d = long_run
    ang = _head_angles(d)
    keys = ("yaw", "pitch", "roll")
    lo = np.array([min(getattr(cfg.head, k)[0], getattr(cfg.scan, k)[0]) for k in keys])
    hi = np.array([max(getattr(cfg.head, k)[1], getattr(cfg.scan, k)[1]) for k in keys])
    assert np.all(ang >= lo - 1e-6) and np.all(ang <= hi + 1e-6)
    pad = int(4 * cfg.head.blend * FPS) + 1
    walk = _interior(d.labels == 0, pad)
    wl = np.array([getattr(cfg.head, k)[0] for k in keys])
    wh = np.array([getattr(cfg.head, k)[1] for k in keys])
    aw = ang[walk]
    assert np.all(aw >= wl - 1e-6) and np.all(aw <= wh + 1e-6)
    # the whole interval is used, back and forth linearly (constant rate between turns)
    assert np.all(aw.min(0) < wl * 0.9) and np.all(aw.max(0) > wh * 0.9)
    rate = np.diff(aw, axis=0)
    curv = np.abs(np.diff(rate, axis=0))
    assert np.mean(curv < 1e-6) > 0.8
    scan = _interior(d.labels == 1, pad)
    sl = np.array([getattr(cfg.scan, k)[0] for k in keys])
    sh = np.array([getattr(cfg.scan, k)[1] for k in keys])
    assert np.all(ang[scan] >= sl - 1e-6) and np.all(ang[scan] <= sh + 1e-6)
    assert ang[scan, 0].max() > 0.8 * sh[0] and ang[scan, 0].min() < 0.8 * sl[0]


def test_head_triangle_stays_rigid(long_run):
    d = long_run
    h = _idx(d, "nose_tip", "left_ear", "right_ear")
    X = d.deformed[:, h]
    m = d.model[h]
    for i, j in ((0, 1), (0, 2), (1, 2)):
        dist = np.linalg.norm(X[:, i] - X[:, j], axis=-1)
        np.testing.assert_allclose(dist, np.linalg.norm(m[i] - m[j]), atol=1e-9)


# --- behaviors ---------------------------------------------------------------------------------
def _peak(a: int, b: int) -> int:
    return (a + b) // 2


def test_every_behavior_occurs(long_run):
    counts = np.bincount(long_run.labels, minlength=len(BEHAVIORS))
    assert np.all(counts > 0), dict(zip(BEHAVIORS, counts))
    assert counts[0] == counts.max()  # walking dominates


def test_rear_signature(long_run, cfg):
    d = long_run
    R = _rot(d)
    body_pitch = np.degrees(np.arcsin(np.clip(R[:, 2, 1], -1, 1)))  # model Y's elevation
    front = _idx(d, "left_front_paw", "right_front_paw")
    hind = _idx(d, "left_hind_paw", "right_hind_paw")
    runs = _runs(d.labels == 2)
    assert len(runs) >= 3
    for a, b in runs:
        if b - a < 10 or b == len(d.labels):
            continue
        t = _peak(a, b)
        assert body_pitch[t] >= cfg.rear.pitch[0] - 1.0
        assert np.all(d.deformed[t, front, 2] > 12.0)
        assert np.all(d.deformed[t, hind, 2] < 1e-9)  # still standing on the hind paws
    assert np.all(np.abs(body_pitch[d.labels == 0]) < 1e-9)  # walking: level


def test_groom_signature(long_run, cfg):
    d = long_run
    nose = d.part_index("nose_tip")
    front = _idx(d, "left_front_paw", "right_front_paw")
    pad = int(cfg.reach.ramp * FPS) + 1
    groom = _interior(d.labels == 3, pad)
    assert groom.sum() > 100
    dist = np.linalg.norm(d.deformed[groom][:, front] - d.deformed[groom][:, [nose]], axis=-1)
    assert dist.max() < 9.0
    # not so while walking
    walk = d.labels == 0
    dist_w = np.linalg.norm(d.deformed[walk][:, front] - d.deformed[walk][:, [nose]], axis=-1)
    assert np.median(dist_w) > 15.0


def test_reach_signature(long_run, cfg):
    d = long_run
    names, pos = d.mechanisms
    eff = {m.effector for m in cfg.lockbox.mechanisms}
    cand = _idx(d, *sorted(eff))
    for m, name in enumerate(names):
        runs = _runs(d.labels == 4 + m)
        assert runs, name
        effector = d.part_index(cfg.lockbox.mechanisms[m].effector)
        for a, b in runs:
            if b == len(d.labels):
                continue
            t = _peak(a, b)
            dist = np.linalg.norm(d.deformed[t, cand] - pos[m], axis=-1)
            assert dist.min() < 4.0, (name, t, dist)
            assert np.linalg.norm(d.deformed[t, effector] - pos[m]) < 4.0
            # the mouse walked there: at the episode start it stands in front of the box
            assert np.linalg.norm(d.rigid[a, effector, :2] - pos[m, :2]) < 40.0
            # and before the first reach of a visit it was walking
            before = d.labels[a - 1] if a > 0 else 0
            assert before in (0, 4, 5, 6, 7) or np.allclose(d.poses[a - 1, 3:], d.poses[a, 3:])


def test_scan_signature(long_run):
    d = long_run
    ang = _head_angles(d)
    runs = [r for r in _runs(d.labels == 1) if r[1] - r[0] > 20]
    assert len(runs) >= 3
    for a, b in runs:
        assert np.ptp(d.poses[a:b, 3:], axis=0).max() < 1e-9  # body still
        assert np.ptp(d.deformed[a:b, _idx(d, "left_front_paw")], axis=0).max() < 1e-9
        assert np.ptp(ang[a:b, 0]) > 10.0  # head sweeps


def test_walk_has_speed_variation_and_stops(long_run, cfg):
    d = long_run
    v = np.hypot(*np.diff(d.poses[:, 3:5], axis=0).T) * FPS
    walk = (d.labels[:-1] == 0) & (d.labels[1:] == 0)
    vw = v[walk]
    assert 20.0 < vw.mean() < cfg.walk.speed_max
    assert vw.max() <= cfg.walk.speed_max * 1.05
    assert np.mean(vw < 2.0) > 0.05  # stops (and starts) within walks
    assert np.std(vw) > 10.0


def test_heading_follows_path(long_run):
    d = long_run
    R = _rot(d)
    fwd = R[:, :2, 1]  # model Y in the plane
    v = np.diff(d.poses[:, 3:5], axis=0)
    speed = np.hypot(*v.T) * FPS
    sel = (speed > 20.0) & (d.labels[1:] == 0)
    cosang = np.einsum("ti,ti->t", fwd[1:][sel], v[sel]) / np.hypot(*v[sel].T)
    assert np.median(cosang) > 0.999
    assert np.mean(cosang > 0.98) > 0.97


# --- arena -------------------------------------------------------------------------------------
def test_body_stays_in_arena_and_out_of_the_box(long_run):
    d = long_run
    W, H = d.arena_size
    for X in (d.rigid, d.deformed):
        assert X[..., 0].min() >= 0 and X[..., 0].max() <= W
        assert X[..., 1].min() >= 0 and X[..., 1].max() <= H
    assert d.deformed[..., 2].min() >= -1e-9
    c = d.lockbox_corners
    inside = (
        (d.deformed[..., 0] > c[:, 0].min())
        & (d.deformed[..., 0] < c[:, 0].max())
        & (d.deformed[..., 1] > c[:, 1].min() + 1e-6)
        & (d.deformed[..., 2] < c[:, 2].max())
    )
    assert not inside.any()


def test_small_arena_and_moved_box():
    cfg = SimConfig.from_config(
        {"arena": {"size": [240.0, 260.0]}, "lockbox": {"center": [120.0, 240.0]}}
    )
    d = simulate(cfg, num_frames=6000, seed=5)
    for X in (d.rigid, d.deformed):
        assert X[..., 0].min() >= 0 and X[..., 0].max() <= 240
        assert X[..., 1].min() >= 0 and X[..., 1].max() <= 260
    np.testing.assert_allclose(d.mechanisms[1][:, 1], 220.0 - np.array([15.0, 2.0, 12.0, 2.0]))
    assert d.lockbox_corners[:, 1].min() == 220.0


# --- determinism, body, left/right -------------------------------------------------------------
def test_deterministic_per_seed():
    a = simulate(num_frames=3000, seed=3)
    b = simulate(num_frames=3000, seed=3)
    c = simulate(num_frames=3000, seed=4)
    for f in ("poses", "rigid", "deformed", "labels", "observed"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert not np.allclose(a.deformed, c.deformed)


def test_body_model_round_trips_through_config():
    body = default_mouse()
    again = BodyModel.from_config(body.to_mapping())
    assert again.parts == body.parts and again.aliases == body.aliases
    np.testing.assert_array_equal(again.points, body.points)
    from omegaconf import OmegaConf

    again2 = BodyModel.from_config(OmegaConf.create(body.to_mapping()))
    np.testing.assert_array_equal(again2.points, body.points)
    a = simulate(num_frames=600, seed=1, body=body)
    b = simulate(num_frames=600, seed=1, body=again)
    np.testing.assert_array_equal(a.deformed, b.deformed)


def test_kabsch_fit_keeps_left_on_the_left(long_run):
    """Fit the rigid model to the simulated (deformed) mouse: a proper rotation, and the left
    parts end up on the mouse's left (forward x up points to its right)."""
    d = long_run
    walk = np.flatnonzero(d.labels == 0)[::50]
    X = d.deformed[walk]
    m = d.model - d.model.mean(0)
    R = kabsch(torch.as_tensor(X), torch.as_tensor(m))[0].numpy()  # model -> global
    assert np.allclose(np.linalg.det(R), 1.0)
    fit = np.einsum("tij,kj->tki", R, m) + X.mean(1, keepdims=True)
    assert (
        np.sqrt(np.mean(np.sum((fit - X) ** 2, -1))) < 6.0
    )  # deformation only, not a mirror image
    fwd, up = R[:, :, 1], R[:, :, 2]
    right = np.cross(fwd, up)
    np.testing.assert_allclose(right, R[:, :, 0], atol=1e-9)
    assert np.all(up[:, 2] > 0.9)  # the fitted model stands upright
    for part, share in (("ear", 1.0), ("hind_paw", 1.0), ("front_paw", 0.95)):
        # (front paws, 11 mm apart, may cross briefly in tight turns)
        left = X[:, d.part_index(f"left_{part}")]
        right_p = X[:, d.part_index(f"right_{part}")]
        assert np.mean(np.einsum("ti,ti->t", left - right_p, right) < 0) >= share, part
    # ... and the model itself: left parts at -X
    for part in ("ear", "front_paw", "hind_paw"):
        assert (
            d.model[d.part_index(f"left_{part}"), 0] < 0 < d.model[d.part_index(f"right_{part}"), 0]
        )
    # the fitted rotation agrees with the simulator's pose
    ang = np.degrees(Rotation.from_matrix(np.einsum("tji,tjk->tik", _rot(d)[walk], R)).magnitude())
    assert np.median(ang) < 5.0


# --- config ------------------------------------------------------------------------------------
def test_default_config_matches_yaml():
    with open(CONF_DIR / "sim" / "default.yaml", encoding="utf-8") as fh:
        node = yaml.safe_load(fh)
    assert SimConfig.from_config(node) == SimConfig()
    from omegaconf import OmegaConf

    assert SimConfig.from_config(OmegaConf.create(node)) == SimConfig()


def test_simulate_accepts_app_config_nodes():
    import hydra

    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        app = hydra.compose("simulate", overrides=["num_frames=300", "seed=2"])
    a = simulate(app)
    b = simulate(app.sim, num_frames=300, seed=2)
    assert a.num_frames == 300 and a.seed == 2
    np.testing.assert_array_equal(a.deformed, b.deformed)


@pytest.mark.parametrize(
    "override, key",
    [
        ({"fps": 0}, "sim.fps"),
        ({"walk": {"speed_mean": -1.0}}, "sim.walk.speed_mean"),
        ({"walk": {"speeed": 1.0}}, "sim.walk"),
        ({"head": {"yaw": [5.0, 20.0]}}, "sim.head.yaw"),
        ({"head": {"pitch": [10.0, -10.0]}}, "sim.head.pitch"),
        ({"scan": {"period": [1.0, 0.0, 1.0]}}, "sim.scan.period"),
        ({"behaviors": {"transitions": {"walk": [0.5] * 8}}}, "sim.behaviors.transitions.walk"),
        ({"behaviors": {"durations": {"jump": [1, 2]}}}, "sim.behaviors.durations"),
        ({"lockbox": {"center": [280.0, 280.0]}}, "sim.lockbox.center"),
        ({"lockbox": {"mechanisms": {"lever": {"effector": "tail_tip"}}}}, "lever.effector"),
        ({"missing": {"dropout": 1.5}}, "sim.missing.dropout"),
        ({"arena": {"size": [100.0, "x"]}}, "sim.arena.size"),
    ],
)
def test_bad_config_values_name_the_key(override, key):
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        simulate(SimConfig.from_config(override), num_frames=10)


def test_bad_num_frames():
    with pytest.raises(ValueError, match="num_frames"):
        simulate(num_frames=0)
    with pytest.raises(ValueError, match="num_frames"):
        simulate(num_frames=2.5)


def test_short_runs_work():
    for n in (1, 2, 7):
        d = simulate(num_frames=n, seed=0)
        assert d.num_frames == n and np.isfinite(d.deformed).all()


# --- masks -------------------------------------------------------------------------------------
def test_dropout_rate():
    cfg = SimConfig.from_config({"missing": {"dropout": 0.1, "occlusion_rate": 0.0}})
    d = simulate(cfg, num_frames=20000, seed=1)
    assert abs((~d.observed).mean() - 0.1) < 0.01


def test_occlusion_episodes_rate_and_length():
    cfg = SimConfig.from_config(
        {"missing": {"dropout": 0.0, "occlusion_rate": 0.2, "occlusion_duration": [0.5, 1.0]}}
    )
    d = simulate(cfg, num_frames=60000, seed=1)
    expected = 1.0 - np.exp(-0.2 * 0.75)  # coverage of a Poisson process of episodes
    assert abs((~d.observed).mean() - expected) < 0.02
    lengths = [b - a for k in range(d.num_parts) for a, b in _runs(~d.observed[:, k])]
    assert min(lengths) >= 1 and np.median(lengths) >= 0.5 * FPS


def test_no_missing_when_rates_are_zero():
    cfg = SimConfig.from_config({"missing": {"dropout": 0.0, "occlusion_rate": 0.0}})
    assert simulate(cfg, num_frames=500).observed.all()


def test_masks_do_not_change_the_motion():
    cfg = SimConfig.from_config({"missing": {"dropout": 0.3}})
    a, b = simulate(num_frames=900, seed=2), simulate(cfg, num_frames=900, seed=2)
    np.testing.assert_array_equal(a.deformed, b.deformed)
    assert not np.array_equal(a.observed, b.observed)


# --- file format -------------------------------------------------------------------------------
def test_save_load_round_trip(tmp_path):
    d = simulate(num_frames=400, seed=9)
    path = save_sim(tmp_path / "sim.npz", d)
    assert path.is_file() and not list(tmp_path.glob(".sim.npz*"))
    e = load_sim(path)
    for f in dataclasses.fields(SimData):
        a, b = getattr(d, f.name), getattr(e, f.name)
        if f.name == "mechanisms":
            assert a[0] == b[0]
            np.testing.assert_array_equal(a[1], b[1])
        elif isinstance(a, np.ndarray):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b
    with np.load(path, allow_pickle=False) as z:  # plain npz, no pickles
        assert str(z["format"]) == "mousetrack-sim"


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        load_sim(tmp_path / "nope.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    with pytest.raises(ValueError, match="bad.npz"):
        load_sim(bad)
    other = tmp_path / "other.npz"
    np.savez(other, x=np.zeros(3))
    with pytest.raises(ValueError, match="missing arrays"):
        load_sim(other)
    with pytest.raises(ValueError, match=r"\.npz"):
        save_sim(tmp_path / "sim.txt", simulate(num_frames=5))
