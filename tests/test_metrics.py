"""adjust.metrics: hand-computed values, NaN handling, seen/occluded split, reprojection stats."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from test_triangulate import rig

from adjust.camera import project_cameras
from adjust.metrics import (
    completeness,
    error_summary,
    point_errors,
    reprojection_errors,
    reprojection_stats,
)


def test_completeness():
    est = np.zeros((2, 3, 3))
    est[0, 0, 1] = np.nan
    est[1, 2] = np.nan
    assert completeness(est) == pytest.approx(4 / 6)
    mask = np.array([[True, False, False], [False, False, True]])
    assert completeness(est, mask) == 0.0
    assert math.isnan(completeness(est, np.zeros((2, 3), bool)))
    with pytest.raises(ValueError):
        completeness(est, mask[:1])
    with pytest.raises(ValueError):
        completeness(est[..., :2])


def test_point_errors_values_and_split():
    T, K = 2, 2
    truth = np.zeros((T, K, 3))
    est = np.zeros((T, K, 3))
    est[0, 0] = [3.0, 4.0, 0.0]  # 5 mm, seen
    est[0, 1] = [0.0, 0.0, 1.0]  # 1 mm, seen
    est[1, 0] = [0.0, 12.0, 0.0]  # 12 mm, occluded
    est[1, 1] = np.nan  # missing, occluded
    nviews = np.array([[3, 2], [1, 0]])
    m = point_errors(est, truth, nviews, part_names=["snout", "tail"])
    assert m["completeness"] == pytest.approx(0.75)
    assert m["rmse_all"] == pytest.approx(math.sqrt((25 + 1 + 144) / 3))
    assert m["median_all"] == pytest.approx(5.0)
    assert m["within5_all"] == pytest.approx(2 / 3)  # 5 mm counts as within
    assert m["rmse_seen"] == pytest.approx(math.sqrt(13))
    assert m["within5_seen"] == 1.0 and m["n_seen"] == 2
    assert m["rmse_occluded"] == pytest.approx(12.0) and m["n_occluded"] == 1
    assert m["completeness_seen"] == 1.0 and m["completeness_occluded"] == 0.5
    assert m["within5_strict_all"] == pytest.approx(2 / 4)
    assert m["within5_strict_occluded"] == 0.0 and m["within5_strict_seen"] == 1.0
    assert m["frac_occluded"] == 0.5
    assert m["per_part"]["snout"]["rmse"] == pytest.approx(math.sqrt((25 + 144) / 2))
    assert m["per_part"]["tail"]["completeness"] == 0.5
    json.dumps(m)  # JSON-ready
    # without the split, and with missing truth (not counted anywhere)
    truth[0, 0] = np.nan
    m = point_errors(est, truth)
    assert "rmse_seen" not in m and m["n_all"] == 2
    assert m["completeness_all"] == pytest.approx(2 / 3)


def test_point_errors_empty_groups_and_shapes():
    est = np.full((3, 2, 3), np.nan)
    m = point_errors(est, np.zeros((3, 2, 3)), np.full((3, 2), 3))
    assert m["completeness"] == 0.0 and m["n_all"] == 0
    assert math.isnan(m["rmse_all"]) and math.isnan(m["within5_all"])
    assert math.isnan(m["rmse_occluded"]) and math.isnan(m["completeness_occluded"])
    with pytest.raises(ValueError):
        point_errors(est, np.zeros((3, 2, 2)))
    with pytest.raises(ValueError):
        point_errors(est, est, np.zeros((3, 3)))
    with pytest.raises(ValueError):
        point_errors(est, est, part_names=["a"])


def test_error_summary():
    s = error_summary(np.array([1.0, np.nan, 2.0, 3.0, 10.0]))
    assert s["n"] == 4 and s["mean"] == 4.0 and s["median"] == 2.5 and s["max"] == 10.0
    assert s["p90"] == pytest.approx(np.percentile([1, 2, 3, 10], 90))
    assert s["rmse"] == pytest.approx(math.sqrt((1 + 4 + 9 + 100) / 4))
    assert error_summary(np.array([np.nan]))["n"] == 0


def test_reprojection_errors_and_stats():
    cams = rig(3)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-100, 100, size=(10, 4, 3))

    xy = project_cameras(torch.as_tensor(pts), cams).numpy()
    xy[..., 1, 0] += 3.0  # camera 1: 3 px off in x
    xy[0, 0, 2] = np.nan
    e = reprojection_errors(pts, xy, cams)
    assert e.shape == (10, 4, 3)
    assert np.isnan(e[0, 0, 2]) and np.allclose(e[..., 1], 3.0)
    s = reprojection_stats(e, camera_names=["front", "top", "side"], part_names="abcd")
    assert s["per_camera"]["top"]["median"] == pytest.approx(3.0)
    assert s["per_camera"]["front"]["max"] < 1e-9
    assert s["per_camera"]["side"]["n"] == 39
    assert s["per_part"]["a"]["n"] == 29
    assert s["all"]["n"] == 119 and s["all"]["p90"] == pytest.approx(3.0)
    json.dumps(s)
    with pytest.raises(ValueError):
        reprojection_stats(e[..., 0])
    with pytest.raises(ValueError):
        reprojection_stats(e, camera_names=["x"])
