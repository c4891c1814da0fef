"""Validation at load time: impossible calibrations, absurd detections, likelihoods, frames."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from adjust.camera import Camera
from adjust.io import InputError, load_calibration, load_detections, save_calibration, write_dlc_csv


def _cam(name="A", K=None, dist=None, rvec=(0.0, 0.0, 0.0), tvec=(0.0, 0.0, 500.0)):
    K = np.array([[800.0, 0, 639.5], [0, 800.0, 511.5], [0, 0, 1]]) if K is None else K
    return Camera(name, np.asarray(K, float), np.zeros(5) if dist is None else np.asarray(dist),
                  np.asarray(rvec), np.asarray(tvec), (1280, 1024))  # fmt: skip


def _rig():
    return [_cam("A"), _cam("B", rvec=(0, 0.5, 0), tvec=(-200.0, 0, 520.0))]


def _load(tmp_path, cams):
    return load_calibration(save_calibration(tmp_path / "calibration.toml", cams))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"K": [[-800.0, 0, 639.5], [0, 800, 511.5], [0, 0, 1]]}, "focal lengths must be > 0"),
        ({"K": [[0.0, 0, 639.5], [0, 0, 511.5], [0, 0, 1]]}, "focal lengths must be > 0"),
        ({"K": [[800.0, 0, 639.5], [0, 800, 511.5], [0, 0.1, 1]]}, "'matrix' must be"),
        ({"K": [[800.0, 0, 639.5], [0, 800, 511.5], [0, 0, 2]]}, "'matrix' must be"),
        ({"dist": [1e6, 0, 0, 0, 0]}, "is not a real lens"),
        ({"dist": [-3.0, 0, 0, 0, 0]}, "is not a real lens"),
        ({"dist": [0, 0, 2.0, 0, 0]}, "tangential distortion"),
        ({"K": [[800.0, 0, 1e5], [0, 800, 511.5], [0, 0, 1]]}, "principal point"),
    ],
)
def test_impossible_intrinsics_name_the_camera(tmp_path, change, message):
    cams = _rig()
    cams[1] = _cam("B", **change)
    with pytest.raises(InputError, match=message) as exc:
        _load(tmp_path, cams)
    assert "calibration.toml: camera [cam_1] ('B')" in str(exc.value)


def test_real_lenses_accepted(tmp_path):
    cams = _rig()
    cams[0] = _cam("A", dist=[-0.3, 0.1, 0.001, -0.001, 0.0])
    assert [c.name for c in _load(tmp_path, cams)] == ["A", "B"]


def test_all_cameras_at_one_pose(tmp_path, caplog):
    with pytest.raises(InputError, match=r"all cameras \['A', 'B'\] are at one position"):
        _load(tmp_path, [_cam("A"), _cam("B")])
    with caplog.at_level(logging.WARNING):
        _load(tmp_path, [*_rig(), _cam("C")])  # C copies A's pose: loud, not fatal
    assert "cameras ['A', 'C'] are at the same position" in caplog.text


def test_binary_file_and_directory_as_calibration(tmp_path):
    (tmp_path / "calib.toml").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(InputError, match=r"calib.toml: not a text \(TOML\) file"):
        load_calibration(tmp_path / "calib.toml")
    with pytest.raises(InputError, match="is a directory"):
        load_calibration(tmp_path)


# --- detections ----------------------------------------------------------------------------


def _detections(tmp_path, T=20, K=3, seed=0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(100, 900, (2, T, K, 2))
    lik = rng.uniform(0.6, 1.0, (2, T, K))
    return xy, lik


def _write(tmp_path, xy, lik, frames=(None, None)):
    for c, name in enumerate("AB"):
        write_dlc_csv(tmp_path / f"{name}.csv", ["p0", "p1", "p2"], xy[c], lik[c],
                      frames=frames[c])  # fmt: skip


def test_absurd_values_are_missing_and_counted(tmp_path, caplog):
    xy, lik = _detections(tmp_path)
    xy[0, 5, 1, 0] = 1e200  # one cell
    xy[1, :, 2] = 1e160  # one part in every frame of camera B
    _write(tmp_path, xy, lik)
    with caplog.at_level(logging.WARNING):
        det = load_detections(tmp_path, _rig(), None)
    assert det.notes["absurd_or_nonfinite"] == {"A": 1, "B": 20}
    assert (
        "camera 'A'" in caplog.text and "1 detections are non-finite or far outside" in caplog.text
    )
    assert "20 detections" in caplog.text
    obs = det.observed
    assert not obs[5, 1, 0] and not obs[:, 2, 1].any()
    assert obs.sum() == 2 * 20 * 3 - 21  # nothing else lost
    np.testing.assert_array_equal(det.xy[4, 1, 0], xy[0, 4, 1])


def test_likelihood_outside_unit_interval_refused(tmp_path):
    xy, lik = _detections(tmp_path)
    lik[1, 7, 2] = 50.0
    lik[1, 9, 0] = -1.0
    _write(tmp_path, xy, lik)
    with pytest.raises(InputError) as exc:
        load_detections(tmp_path, _rig(), None)
    msg = str(exc.value)
    assert "B.csv (camera 'B'): likelihood 50.0 of part 'p2' at frame 7 is outside [0, 1]" in msg
    assert "1 more outside" in msg


@pytest.mark.parametrize("threshold", [0.99999, 1.0])
def test_no_usable_detection_is_an_error(tmp_path, threshold):
    xy, lik = _detections(tmp_path)
    _write(tmp_path, xy, lik * 0.9)
    with pytest.raises(InputError, match="no usable detection in any file"):
        load_detections(tmp_path, _rig(), None, threshold)


@pytest.mark.parametrize("threshold", [2, -0.1, "abc", float("nan")])
def test_threshold_out_of_range(tmp_path, threshold):
    xy, lik = _detections(tmp_path)
    _write(tmp_path, xy, lik)
    with pytest.raises(InputError, match="input.likelihood_threshold must be a number from 0 to 1"):
        load_detections(tmp_path, _rig(), None, threshold)


def test_rows_matched_by_frame_number(tmp_path):
    xy, lik = _detections(tmp_path, T=6)
    # camera B's file lists the same frames in reverse order: matched by number, not position
    frames_b = list(range(5, -1, -1))
    _write(tmp_path, np.stack([xy[0], xy[1][::-1]]), np.stack([lik[0], lik[1][::-1]]),
           frames=(None, frames_b))  # fmt: skip
    det = load_detections(tmp_path, _rig(), None)
    assert det.frames.tolist() == list(range(6))
    np.testing.assert_array_equal(det.xy[:, :, 1], xy[1])
    # labelled images with different names cannot be matched
    _write(tmp_path, xy, lik, frames=([f"img{i}.png" for i in range(6)],
                                     [f"img{i + 1}.png" for i in range(6)]))  # fmt: skip
    with pytest.raises(InputError, match="label different frames"):
        load_detections(tmp_path, _rig(), None)


# --- checkpoints are data, not code ------------------------------------------------------


class _Payload:
    """Unpickling this creates a file: what a malicious checkpoint would do."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        import builtins

        return (builtins.open, (self.marker, "w"))


def test_checkpoint_with_pickle_payload_refused_unexecuted(tmp_path):
    import torch
    from helpers import tiny_deformation_model

    from deformnet.deformation import CHECKPOINT_KEY, DeformationModel

    path = tmp_path / "shared_by_another_lab.ckpt"
    tiny_deformation_model().save(path)
    good = DeformationModel.from_checkpoint(path)  # a plain checkpoint loads
    assert good.window == tiny_deformation_model().window
    blob = torch.load(path, weights_only=True)
    marker = tmp_path / "pwned"
    blob[CHECKPOINT_KEY]["extra"] = _Payload(marker)
    torch.save(blob, path)
    with pytest.raises(ValueError, match=r"refused: the checkpoint holds pickled Python objects"):
        DeformationModel.from_checkpoint(path)
    assert not marker.exists()  # never executed


@pytest.mark.parametrize("content", ["passwd", "garbage", "empty", "pickle"])
def test_garbage_checkpoint_is_one_clear_error(tmp_path, content):
    import pickle

    from adjust.deformation_modes import load_deformation

    path = tmp_path / "model.ckpt"
    if content == "passwd":
        path.write_text("root:x:0:0:root:/root:/bin/bash\n")
    elif content == "garbage":
        path.write_bytes(bytes(range(256)) * 8)
    elif content == "empty":
        path.write_bytes(b"")
    else:
        path.write_bytes(pickle.dumps({"a": 1}))  # a legacy (non-zip) pickle
    with pytest.raises(InputError) as exc:
        load_deformation(str(path))
    msg = str(exc.value)
    assert "model.ckpt" in msg and "\n" not in msg
    assert "not a PyTorch checkpoint" in msg
    with pytest.raises(InputError, match="not found"):
        load_deformation(str(tmp_path / "missing.ckpt"))


# --- solver and settings -------------------------------------------------------------------


def test_nan_cost_is_never_converged():
    from adjust.lsq.lm import levenberg_marquardt

    def linearise(x):
        return np.ones((1, 1, 1, 1)), np.zeros((1, 1)), float("nan"), None

    res = levenberg_marquardt(np.zeros(1), linearise, lambda x, ctx: float("nan"), lambda x, d: x)
    assert not res.converged and res.iterations == 1

    def finite(x):  # cost x^2 - 2x + 2 at 1 row: converges
        return np.full((1, 1, 1, 1), 2.0), np.array([[2.0 - 2.0 * x[0]]]), (x[0] - 1) ** 2 + 1, None

    res = levenberg_marquardt(np.zeros(1), finite, lambda x, c: (x[0] - 1) ** 2 + 1,
                              lambda x, d: x + d.reshape(-1))  # fmt: skip
    assert res.converged and abs(res.x[0] - 1) < 1e-6


@pytest.mark.parametrize(
    ("key", "value", "accepts"),
    [
        ("solver.max_iterations", "abc", "an integer >= 0"),
        ("solver.max_iterations", 2.5, "an integer >= 0"),
        ("solver.max_iterations", -3, "an integer >= 0"),
        ("solver.chunk_size", "abc", "an integer >= 0"),
        ("solver.sigma_det_px", "wide", "a number from 0.01 to 1000"),
        ("threads", "abc", "an integer from 1 to {MAX_THREADS}"),
        ("triangulate.min_views", "abc", "an integer >= 2"),
        ("input.likelihood_threshold", "abc", "a number from 0 to 1"),
        ("input.likelihood_threshold", 2, "a number from 0 to 1"),
        ("progress", "maybe", "true or false"),
        # physically meaningless values (issue 46): not only the wrong type
        ("stochastic.sigma_det_px", 1e-9, "a number from 0.01 to 1000"),
        ("stochastic.sigma_det_px", 0, "a number from 0.01 to 1000"),
        ("stochastic.sigma_det_px", -2.0, "a number from 0.01 to 1000"),
        ("solver.sigma_det_px", 1e-9, "a number from 0.01 to 1000"),
        ("solver.sigma_def_mm", -1.0, "a number >= 0"),
        ("solver.min_weight", 1.5, "a number from 0 to 1"),
        ("stochastic.gate_sigmas", 0, "a number >= 0.1"),
        ("threads", 100000, "an integer from 1 to {MAX_THREADS}"),
        ("threads", 0, "an integer from 1 to {MAX_THREADS}"),
        ("threads", -1, "an integer from 1 to {MAX_THREADS}"),
        ("deform.threads", 0, "an integer from 1 to {MAX_THREADS}"),
        ("solver.num_threads", 100000, "an integer from 0 to {MAX_THREADS}"),
        ("adapt.val_fraction", 1.5, "a number from 0.01 to 0.9"),
        ("adapt.augment.mirror", 2, "a number from 0 to 1"),
        ("inferred.below", -0.5, "a number from 0 to 1"),
    ],
)
def test_settings_of_wrong_type_or_range(key, value, accepts):
    from omegaconf import OmegaConf

    from adjust.settings import MAX_THREADS, check_settings

    accepts = accepts.format(MAX_THREADS=MAX_THREADS)
    cfg = OmegaConf.create({"solver": {"max_iterations": 30}, "threads": 1})
    OmegaConf.update(cfg, key, value, force_add=True)
    with pytest.raises(ValueError) as exc:
        check_settings(cfg)
    assert str(exc.value) == f"{key}={value!r} is not valid: {key} accepts {accepts}"
    fractions = ("threshold", "fraction", "mirror", "below", "weight")
    good = 0.5 if any(w in key for w in fractions) else 3
    OmegaConf.update(cfg, key, good, force_add=True)
    if key != "progress":
        check_settings(cfg)  # a good value passes


def test_absurd_thread_count_refused_before_torch():
    """threads=100000 segfaulted torch; every app's thread setting goes through check_threads."""
    from deformnet.threads import MAX_THREADS, set_torch_threads, torch_threads

    accepts = f"threads=100000 is not valid: .* from 1 to {MAX_THREADS}"
    with pytest.raises(ValueError, match=accepts):
        set_torch_threads(100000)
    with pytest.raises(ValueError, match="threads='many' is not valid"):
        with torch_threads("many"):
            pass


@pytest.mark.parametrize("frames", [list(range(100, 120)), [f"img{i:03d}.png" for i in range(20)]])
def test_triangulate_fnum_is_the_files_frame_number(tmp_path, frames):
    import hydra
    import torch

    from adjust.apps.triangulate import run
    from adjust.camera import CameraTensors, project_cameras
    from adjust.io import read_points3d
    from deformnet.paths import CONF_DIR

    cams = _rig()
    X = np.random.default_rng(0).uniform(-50, 50, (20, 3, 3))
    uv = project_cameras(torch.as_tensor(X), CameraTensors.from_cameras(cams, torch.float64))
    det = tmp_path / "det"
    det.mkdir()
    for c, cam in enumerate(cams):
        write_dlc_csv(det / f"{cam.name}.csv", ["p0", "p1", "p2"], uv[:, :, c].numpy(),
                      np.ones((20, 3)), frames=frames)  # fmt: skip
    save_calibration(tmp_path / "calibration.toml", cams)
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cal = tmp_path / "calibration.toml"
        cfg = hydra.compose("triangulate", [f"input.calibration={cal}", f"input.detections={det}",
                                            f"output.dir={tmp_path / 'out'}"])  # fmt: skip
    summary = run(cfg)
    d = read_points3d(tmp_path / "out" / "points3d.csv")
    assert [str(f) for f in d["fnum"]] == [str(f) for f in frames]
    assert summary["frames"] == [frames[0], frames[-1]]
    np.testing.assert_allclose(d["points"], X, atol=1e-6)


# --- issue 46: inputs that could fool the tracker, files that are not files ----------------


def test_fifo_and_device_as_calibration_refused_unopened(tmp_path):
    """A FIFO blocked and /dev/zero read until memory ran out: refused before opening."""
    import os

    fifo = tmp_path / "calibration.toml"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match=r"calibration.toml is a named pipe \(FIFO\), not a"):
        load_calibration(fifo)  # would block forever if opened
    with pytest.raises(InputError, match="/dev/zero is a device, not a regular file"):
        load_calibration("/dev/zero")
    from adjust.io import read_points3d

    with pytest.raises(InputError, match="/dev/zero is a device"):
        read_points3d("/dev/zero")


def test_usable_detections_per_camera_and_one_camera_refused(tmp_path, caplog):
    from adjust.io import check_cameras_usable

    xy, lik = _detections(tmp_path)
    lik[1] = 0.1  # camera B: every detection below the threshold
    _write(tmp_path, xy, lik)
    with caplog.at_level(logging.WARNING):
        det = load_detections(tmp_path, _rig(), None)
    assert det.usable_per_camera() == {"A": 60, "B": 0}
    # B loses all its detections on reading: it says why
    assert (
        "camera 'B'" in caplog.text and "60 of its 60 detections (100%) are not used" in caplog.text
    )
    assert "60 below input.likelihood_threshold=0.5" in caplog.text
    with pytest.raises(InputError) as exc:
        check_cameras_usable(det, "session1")
    msg = str(exc.value)
    assert msg.startswith("session1: only 1 of 2 cameras have a usable detection")
    assert "'A' 60 (A.csv), 'B' 0 (B.csv)" in msg
    lik[1] = 0.9
    _write(tmp_path, xy, lik)
    check_cameras_usable(load_detections(tmp_path, _rig(), None), "session1")  # two: fine


def test_triangulate_refuses_a_one_camera_session(tmp_path):
    """It exited 0 with 0% triangulated; now one error naming the cameras and their counts."""
    import hydra

    from adjust.apps.triangulate import run
    from deformnet.paths import CONF_DIR

    det = tmp_path / "det"
    det.mkdir()
    xy, lik = _detections(tmp_path)
    xy[1] = np.nan  # camera B: no detection at all
    for c, name in enumerate("AB"):
        write_dlc_csv(det / f"{name}.csv", ["p0", "p1", "p2"], xy[c], lik[c])
    save_calibration(tmp_path / "calibration.toml", _rig())
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra.compose("triangulate", [f"input.calibration={tmp_path / 'calibration.toml'}",
                                            f"input.detections={det}",
                                            f"output.dir={tmp_path / 'out'}"])  # fmt: skip
    with pytest.raises(InputError, match=r"only 1 of 2 cameras .*'A' 60 \(A.csv\), 'B' 0"):
        run(cfg)
    assert not (tmp_path / "out" / "points3d.csv").exists()


def test_empty_likelihood_cells_read_as_one_with_a_warning(tmp_path, caplog):
    xy, lik = _detections(tmp_path)
    lik[0, :5, 1] = np.nan  # x and y given, likelihood cell empty
    _write(tmp_path, xy, lik)
    with caplog.at_level(logging.WARNING):
        det = load_detections(tmp_path, _rig(), None)
    assert det.observed[:5, 1, 0].all()  # not dropped
    np.testing.assert_array_equal(det.likelihood[:5, 1, 0], 1.0)
    assert (
        "camera 'A'" in caplog.text
        and "5 detections have x and y but an empty likelihood cell" in caplog.text
        and "read as likelihood 1" in caplog.text
    )


def test_missing_likelihood_column_is_stated(tmp_path, caplog):
    xy, lik = _detections(tmp_path)
    _write(tmp_path, xy, lik)
    p = tmp_path / "B.csv"
    rows = [ln.split(",") for ln in p.read_text().splitlines()]
    keep = [j for j, c in enumerate(rows[2]) if c != "likelihood"]  # the coords row
    p.write_text("\n".join(",".join(r[j] for j in keep) for r in rows) + "\n")
    with caplog.at_level(logging.WARNING):
        det = load_detections(tmp_path, _rig(), None)
    assert det.observed[:, :, 1].all()
    assert (
        "camera 'B'" in caplog.text and "B.csv): no likelihood column for any part" in caplog.text
    )
    assert "taken at likelihood 1" in caplog.text


def test_a_file_losing_most_detections_says_why(tmp_path, caplog):
    xy, lik = _detections(tmp_path)
    xy[1, :12, :, 0] = np.inf  # 36 of B's 60 detections not finite
    _write(tmp_path, xy, lik)
    with caplog.at_level(logging.WARNING):
        load_detections(tmp_path, _rig(), None)
    assert (
        "camera 'B'" in caplog.text and "36 of its 60 detections (60%) are not used" in caplog.text
    )
    assert "36 not finite numbers" in caplog.text
    caplog.clear()
    xy, lik = _detections(tmp_path)
    _write(tmp_path, xy, lik)
    with caplog.at_level(logging.WARNING):
        load_detections(tmp_path, _rig(), None)
    assert "are not used" not in caplog.text  # a clean file: no warning


def test_frame_numbers_beyond_int64(tmp_path):
    from adjust.io import read_points3d, write_points3d

    xy, lik = _detections(tmp_path, T=3)
    _write(tmp_path, xy, lik, frames=([0, 1, 99999999999999999999999], None))
    with pytest.raises(InputError, match="frame number 99999999999999999999999 is beyond"):
        load_detections(tmp_path, _rig(), None)
    p = write_points3d(tmp_path / "p.csv", ["a"], np.zeros((3, 1, 3)), np.zeros((3, 1)),
                       np.ones((3, 1)), np.ones((3, 1)))  # fmt: skip
    text = p.read_text().rstrip("\n").rsplit(",", 1)[0] + ",99999999999999999999999\n"
    p.write_text(text)
    with pytest.raises(InputError, match="fnum 99999999999999999999999 at row 2 is beyond"):
        read_points3d(p)
    p.write_text(p.read_text().splitlines()[0] + "\n")  # the header only
    with pytest.raises(InputError, match="no rows"):
        read_points3d(p)
