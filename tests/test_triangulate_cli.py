"""`adjust-triangulate` through Hydra's compose API: the real hand data and a synthetic mouse."""

from __future__ import annotations

import dataclasses
import json

import hydra
import numpy as np
import pytest
import torch

from adjust.apps.triangulate import run
from adjust.camera import Camera, CameraTensors, project_cameras
from adjust.io import read_points3d, save_calibration, write_dlc_csv
from adjust.settings import TriangulateConfig
from deformnet.body import default_mouse
from deformnet.paths import CONF_DIR, real_hand_dir

REAL = real_hand_dir()


def _cfg(overrides):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose("triangulate", overrides=overrides)


def test_the_triangulate_block_is_typed_and_its_yaml_defaults_are_the_dataclass_s():
    """conf/triangulate.yaml's ``triangulate`` block holds exactly `TriangulateConfig`'s
    fields and defaults (the one copy in the code); a bad value names its setting."""
    cfg = _cfg([])
    assert dict(cfg.triangulate) == dataclasses.asdict(TriangulateConfig())
    assert TriangulateConfig.from_config(cfg.triangulate) == TriangulateConfig()
    given = TriangulateConfig.from_config({"weight": "uniform", "min_views": 3})
    assert given == TriangulateConfig(weight="uniform", min_views=3)  # the others: defaults
    with pytest.raises(ValueError, match="triangulate.weight must be one of"):
        TriangulateConfig.from_config({"weight": "equal"})
    with pytest.raises(ValueError, match="triangulate.min_views=1"):
        TriangulateConfig.from_config({"min_views": 1})
    with pytest.raises(ValueError, match="triangulate.typo"):
        TriangulateConfig.from_config({"typo": 1})


def test_cli_on_real_hand_data(tmp_path):
    cfg = _cfg(
        [
            f"input.calibration={REAL / 'calibration.toml'}",
            f"input.detections={REAL / 'trial_000'}",
            f"output.dir={tmp_path}",
        ]
    )
    assert cfg.get("body") is None  # default: the files' own part names
    summary = run(cfg)
    # README: ~85% of keypoint-frames; median reprojection ~3.9 px for plain DLT (this
    # triangulation's depth reweighting gives ~3.3 px)
    assert 0.80 < summary["completeness"] < 0.90
    err = summary["reprojection_error_px"]
    assert 2.5 < err["median"] < 4.5 and 5.0 < err["p90"] < 9.0
    assert summary["cameras"] == ["08150951", "08151951", "08152151", "08154551"]
    assert len(summary["parts"]) == 21 and summary["num_frames"] == 513
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    d = read_points3d(tmp_path / "points3d.csv")
    assert d["parts"][:2] == ("elbow", "wrist") and d["points"].shape == (513, 21, 3)
    done = np.isfinite(d["points"]).all(-1)
    assert done.mean() == pytest.approx(summary["completeness"])
    assert np.nanmedian(d["error"]) == pytest.approx(err["median"])
    assert (d["ncams"][done] >= 2).all() and (d["ncams"][~done] == 0).all()
    assert (d["score"][done] >= 0.5).all() and np.isnan(d["score"][~done]).all()
    assert d["fnum"].tolist() == list(range(513))


def test_cli_synthetic_mouse_with_body_aliases(tmp_path):
    """Exact projections of a known mouse -> the CLI recovers the 3D points (body=mouse)."""
    mouse = default_mouse()
    rng = np.random.default_rng(0)
    T, K = 10, mouse.num_parts
    truth = mouse.points[None] + rng.normal(0, 20, (T, 1, 3)) + np.array([0, 0, 50.0])
    K_ = np.array([[800.0, 0, 640], [0, 800, 512], [0, 0, 1]])
    cams = []
    for i, ang in enumerate(np.deg2rad([0, 90, 180, 270])):
        # cameras on a circle 600 mm out, 300 mm up, looking at the origin
        c = np.array([600 * np.sin(ang), -600 * np.cos(ang), 300.0])
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        rvec = _rodrigues(R)
        dist = np.array([-0.05, 0.01, 0, 0, 0])
        cams.append(Camera(f"cam{i}", K_, dist, rvec, -R @ c, (1280, 1024)))
    save_calibration(tmp_path / "calibration.toml", cams)
    uv = project_cameras(torch.as_tensor(truth), CameraTensors.from_cameras(cams)).numpy()
    lik = np.full((T, K, 4), 0.9)
    lik[3, 0, :3] = 0.1  # nose tip seen by one camera only in frame 3
    file_parts = ["snout", "leftear", "rightear", "left_forepaw", "right_forepaw"]
    file_parts += ["left_hindpaw", "right_hindpaw", "tailbase"]
    for i, cam in enumerate(cams):
        write_dlc_csv(tmp_path / "det" / f"{cam.name}DLC.csv", file_parts, uv[:, :, i], lik[..., i])
    out = tmp_path / "out"
    cfg = _cfg(
        [
            f"input.calibration={tmp_path / 'calibration.toml'}",
            f"input.detections={tmp_path / 'det'}",
            f"output.dir={out}",
            "body=mouse",
        ]
    )
    summary = run(cfg)
    assert summary["body"] == "mouse" and summary["parts"] == list(mouse.parts)
    assert summary["completeness"] == pytest.approx(1 - 1 / (T * K))
    d = read_points3d(out / "points3d.csv")
    assert d["parts"] == mouse.parts
    ok = np.ones((T, K), bool)
    ok[3, 0] = False
    assert np.isnan(d["points"][3, 0]).all() and d["ncams"][3, 0] == 0
    np.testing.assert_allclose(d["points"][ok], truth[ok], atol=1e-3)
    assert np.nanmax(d["error"]) < 1e-3 and (d["score"][ok] == 0.9).all()


def _rodrigues(R: np.ndarray) -> np.ndarray:
    angle = np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return axis / (2 * np.sin(angle)) * angle


def test_cli_requires_inputs(tmp_path):
    with pytest.raises(ValueError, match="input.calibration"):
        run(_cfg([f"output.dir={tmp_path}"]))
