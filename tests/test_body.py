"""BodyModel: estimation by generalized Procrustes, aliases, config round trip."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from deformnet.body import BodyModel, default_mouse
from deformnet.so3 import kabsch


def _pairwise(P: np.ndarray) -> np.ndarray:
    return np.linalg.norm(P[:, None] - P[None], axis=-1)


def _observe(model: np.ndarray, T: int, noise: float, missing: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    R = Rotation.random(T, random_state=seed).as_matrix()
    t = rng.uniform(-200, 200, (T, 3))
    X = np.einsum("tij,kj->tki", R, model) + t[:, None] + rng.normal(0, noise, (T, len(model), 3))
    X[rng.random((T, len(model))) < missing] = np.nan
    return X


def test_from_observations_recovers_rigid_model_up_to_rigid_transform():
    truth = default_mouse()
    X = _observe(truth.points, T=400, noise=0.5, missing=0.2, seed=0)
    est = BodyModel.from_observations(X, parts=truth.parts, name="est")
    assert est.parts == truth.parts and est.name == "est"
    err = np.abs(_pairwise(est.points) - _pairwise(truth.points))
    assert err.max() < 0.15, err.max()  # measured 0.103 (0.074-0.103 over seeds 0-5)
    # a proper rigid transform maps the estimate onto the truth (not a mirror image)
    a, b = est.points - est.points.mean(0), truth.points - truth.points.mean(0)
    R = kabsch(torch.as_tensor(b), torch.as_tensor(a))[0].numpy()  # b ~ a R^T, det R = +1
    rms = np.sqrt(np.mean(np.sum((a @ R.T - b) ** 2, -1)))
    assert rms < 0.08, rms  # measured 0.055 (0.036-0.055 over seeds 0-5)
    # model frame conventions: centroid at the origin, largest spread along Y
    np.testing.assert_allclose(est.points.mean(0), 0.0, atol=1e-9)
    assert np.ptp(est.points[:, 1]) >= np.ptp(est.points[:, 0]) >= np.ptp(est.points[:, 2])


def test_from_observations_noise_free_is_exact():
    truth = default_mouse()
    X = _observe(truth.points, T=50, noise=0.0, missing=0.3, seed=1)
    est = BodyModel.from_observations(X, parts=truth.parts)
    np.testing.assert_allclose(_pairwise(est.points), _pairwise(truth.points), atol=1e-6)


def test_from_observations_errors():
    X = np.full((10, 8, 3), np.nan)
    with pytest.raises(ValueError, match="frames"):
        BodyModel.from_observations(X)
    with pytest.raises(ValueError, match="shape"):
        BodyModel.from_observations(np.zeros((10, 8)))
    with pytest.raises(ValueError, match="part names"):
        BodyModel.from_observations(np.zeros((10, 8, 3)), parts=["a", "b"])
    Y = _observe(default_mouse().points, 20, 0.1, 0.0, 2)
    Y[:, 3] = np.nan


def test_from_observations_part_never_observed_is_placed_loudly(caplog):
    Y = _observe(default_mouse().points, 20, 0.1, 0.0, 2)
    Y[:, 3] = np.nan  # never observed in 3D: at the body's centre, with a warning naming it
    with caplog.at_level("WARNING"):
        body = BodyModel.from_observations(Y, min_parts=6)
    assert "part3" in caplog.text and "unknown" in caplog.text
    others = np.delete(body.points, 3, axis=0)
    assert np.allclose(body.points[3], others.mean(0), atol=1e-6)


def test_alias_lookup():
    body = default_mouse()
    assert body.index("snout") == body.index("nose_tip") == 0
    assert body.resolve("tailbase") == "tail_root"
    assert body.resolve("left_forepaw") == "left_front_paw"
    assert body.resolve("wing") is None
    with pytest.raises(KeyError, match="wing"):
        body.index("wing")
    with pytest.raises(ValueError, match="unknown part"):
        BodyModel(("a", "b", "c"), np.zeros((3, 3)), {"x": "d"})


def test_loose_part_names_and_added_aliases():
    body = default_mouse()
    # case and the separators _ - . and spaces ignored, for part names and aliases alike
    for name, part in [("Nose", "nose_tip"), ("Left_Ear", "left_ear"), ("Ear_R", "right_ear"),
                       ("TailBase", "tail_root"), ("right-front paw", "right_front_paw"),
                       ("LEFT.HIND.PAW", "left_hind_paw")]:  # fmt: skip
        assert body.resolve(name) == part, name
        assert body.index(name) == body.parts.index(part)
    assert body.resolve("Trunk") is None and body.resolve("Ear") is None
    # a loose name that would match two parts matches none
    two = BodyModel(("ab", "a_b"), np.eye(2, 3), name="two")
    assert two.resolve("a_b") == "a_b" and two.resolve("A-B") is None
    mine = body.with_aliases({"LFP": "left_front_paw", "TTI": "TailBase"})
    assert mine.resolve("LFP") == "left_front_paw" and mine.resolve("tti") == "tail_root"
    assert body.resolve("LFP") is None  # the original is unchanged
    assert body.with_aliases(None) is body
    with pytest.raises(ValueError, match=r"aliases: \{'Trunk': 'torso'\} name\(s\) no part"):
        body.with_aliases({"Trunk": "torso"})


def test_default_mouse_left_is_minus_x_and_round_trip():
    body = default_mouse()
    for part in ("ear", "front_paw", "hind_paw"):
        assert body.points[body.index(f"left_{part}"), 0] < 0
        assert body.points[body.index(f"right_{part}"), 0] > 0
    again = BodyModel.from_config(body.to_mapping())
    assert again.parts == body.parts and again.aliases == body.aliases
    np.testing.assert_array_equal(again.points, body.points)


def test_from_observations_places_a_part_seen_only_in_sparse_frames():
    """A part never seen together with most others (e.g. an elbow out of view whenever the
    fingers are visible) is placed from the frames with >= 3 parts that do see it."""
    truth = default_mouse()
    X = _observe(truth.points, T=200, noise=0.0, missing=0.0, seed=4)
    X[:150, 7] = np.nan  # tail root missing where everything else is seen ...
    X[150:, 3:7] = np.nan  # ... and seen only with 3 other parts
    est = BodyModel.from_observations(X, parts=truth.parts)
    np.testing.assert_allclose(_pairwise(est.points), _pairwise(truth.points), atol=1e-6)
