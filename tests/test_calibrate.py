"""adjust-calibrate: cameras resected from known lock-box points recover the simulated rig."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import hydra
import numpy as np
import pytest
import torch

from adjust.apps.calibrate import run
from adjust.camera import CameraTensors, project_cameras
from adjust.io import InputError, load_calibration, save_calibration, write_dlc_csv
from adjust.scene import default_rig
from deformnet.paths import CONF_DIR

torch.set_num_threads(1)


def _box_points() -> dict[str, np.ndarray]:
    """Lock-box-like known points: the corners of two boxes and a lever, 3 heights (mm)."""
    pts = {}
    for i, (x, y) in enumerate([(100, 100), (200, 100), (200, 200), (100, 200)]):
        for j, z in enumerate((0.0, 40.0)):
            pts[f"box_{i}_{j}"] = np.array([x, y, z], float)
    for i, (x, y, z) in enumerate([(150, 150, 70), (130, 170, 20), (180, 120, 55), (160, 90, 10)]):
        pts[f"lever_{i}"] = np.array([x, y, z], float)
    for i, (x, y) in enumerate([(60, 150), (240, 150), (150, 60), (150, 240)]):
        pts[f"floor_{i}"] = np.array([x, y, 0.0], float)
    return pts


def _write(tmp_path: Path, pts, cams, noise=0.3, seed=0, drop=(), coplanar=False) -> tuple:
    rng = np.random.default_rng(seed)
    names = [n for n in pts if not coplanar or pts[n][2] == 0.0]
    X = np.array([pts[n] for n in names])
    p3 = tmp_path / "lockbox.csv"
    p3.write_text("name,x,y,z\n" + "".join(f"{n},{x},{y},{z}\n" for n, (x, y, z) in pts.items()))
    folder = tmp_path / "labels"
    folder.mkdir(exist_ok=True)
    uv = project_cameras(torch.as_tensor(X), CameraTensors.from_cameras(cams, torch.float64))
    uv = uv.numpy() + rng.normal(0, noise, uv.shape)
    for c, cam in enumerate(cams):
        lines = ["name,u,v"]
        for k, n in enumerate(names):
            vis = n not in drop
            lines.append(f"{n},{uv[k, c, 0]},{uv[k, c, 1]}" if vis else f"{n},,")
        (folder / f"{cam.name}.csv").write_text("\n".join(lines) + "\n")
    return p3, folder


def _cfg(tmp_path, p3, folder, *extra):
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra.compose(
            "calibrate",
            [
                f"input.points3d={p3}",
                f"input.points2d={folder}",
                f"output.dir={tmp_path / 'out'}",
                "input.size=[1280,1024]",
                *extra,
            ],
        )


def test_calibrate_recovers_the_rig(tmp_path):
    cams = default_rig()
    p3, folder = _write(tmp_path, _box_points(), cams)
    summary = run(_cfg(tmp_path, p3, folder))
    got = {c.name: c for c in load_calibration(tmp_path / "out" / "calibration.toml")}
    assert set(got) == {c.name for c in cams}
    for cam in cams:
        rep = summary["cameras"][cam.name]
        assert rep["points"] == 16
        assert 0.15 < rep["rms_px"] < 0.5  # 0.3 px noise, 16 points, 10 unknowns
        # unknown focal length: the distance along the axis trades against it; 0.3 px noise on
        # a 100 mm box seen from 800 mm gives 2-16 mm (seeds 0-2), i.e. up to 2% of the range
        assert np.linalg.norm(np.array(rep["center_mm"]) - cam.center) < 25.0, rep
        assert abs(got[cam.name].K[0, 0] / cam.K[0, 0] - 1) < 0.03
    on_disk = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert on_disk["cameras"]["top"]["rms_px"] == summary["cameras"]["top"]["rms_px"]


def test_calibrate_with_known_intrinsics_and_dlc_labels(tmp_path):
    cams = default_rig()
    pts = _box_points()
    p3, folder = _write(tmp_path, pts, cams, drop=("lever_0", "box_0_1"))
    save_calibration(tmp_path / "intr.toml", cams)
    # the top camera's labels as a DeepLabCut labels file (one image)
    rows = [ln.split(",") for ln in (folder / "top.csv").read_text().splitlines()[1:]]
    names = [r[0] for r in rows]
    xy = np.array(
        [[float(r[1]) if r[1] else np.nan, float(r[2]) if r[2] else np.nan] for r in rows]
    )
    (folder / "top.csv").unlink()
    write_dlc_csv(
        folder / "top.csv", names, xy[None], np.ones((1, len(names))), frames=["img0.png"]
    )
    summary = run(_cfg(tmp_path, p3, folder, f"input.intrinsics={tmp_path / 'intr.toml'}"))
    assert summary["intrinsics"] == "given"
    for cam in cams:
        rep = summary["cameras"][cam.name]
        assert rep["points"] == 14
        # known intrinsics: measured 0.3-1.5 mm (seeds 0-2)
        assert np.linalg.norm(np.array(rep["center_mm"]) - cam.center) < 3.0, rep


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("coplanar", "coplanar"),
        ("few", "needs >= 6 points"),
        ("stray", "are not in"),
        ("size", "set input.size"),
    ],
)
def test_calibrate_refuses(tmp_path, case, message):
    cams = default_rig()
    pts = _box_points()
    if case == "few":
        pts = dict(list(pts.items())[:5])
    p3, folder = _write(tmp_path, pts, cams, coplanar=case == "coplanar")
    if case == "stray":
        with open(folder / "side.csv", "a") as fh:
            fh.write("door,10,20\n")
    extra = ["input.size=null"] if case == "size" else []
    with pytest.raises(InputError, match=message) as exc:
        run(_cfg(tmp_path, p3, folder, *extra))
    assert "\n" not in str(exc.value)
    assert not (tmp_path / "out" / "calibration.toml").exists()


def test_calibrate_fisheye_cameras_with_known_intrinsics(tmp_path):
    """Known intrinsics from a fisheye calibration (``fisheye = true``): the poses are resected
    through the fisheye model and the written calibration keeps it."""
    d = np.array([0.05, -0.02, 0.004, 0.0, 0.0])
    cams = [replace(c, dist=d, fisheye=True) for c in default_rig()]
    p3, folder = _write(tmp_path, _box_points(), cams, noise=0.1)
    save_calibration(tmp_path / "intr.toml", cams)
    summary = run(_cfg(tmp_path, p3, folder, f"input.intrinsics={tmp_path / 'intr.toml'}"))
    got = {c.name: c for c in load_calibration(tmp_path / "out" / "calibration.toml")}
    for cam in cams:
        assert got[cam.name].fisheye and np.allclose(got[cam.name].dist, d)
        rep = summary["cameras"][cam.name]
        assert rep["rms_px"] < 0.3, rep
        assert np.linalg.norm(np.array(rep["center_mm"]) - cam.center) < 3.0, rep
