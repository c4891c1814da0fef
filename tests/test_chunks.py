"""Long sessions in chunks (`adjust.chunks`, issue 46): the plan, the streamed CSV reader, a
session no longer than one chunk tracked exactly as before, a longer one tracked in chunks in
agreement with the whole run (measured on this 1,500-frame scene with 500-frame chunks: points
0.050 mm apart at the median, 0.26 mm at the 99th percentile, 7.4 mm at most (a part seen by one
camera); 2.061 mm rms from the truth both; rigid 0.001 / 0.12 / 7.6 mm), its outputs whole (the net
modes in chunks: tests/test_chunks_net.py)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from adjust.chunks import (
    MAX_OVERLAP,
    MIN_OVERLAP,
    SAMPLE_FRAMES,
    ChunkConfig,
    merge_summaries,
    overlap_frames,
    plan_chunks,
    sample_rows,
)
from adjust.io import (
    InputError,
    load_calibration,
    read_dlc,
    read_points3d,
    save_calibration,
    write_dlc_csv,
)
from adjust.io.dlc import iter_dlc
from adjust.lsq import synthetic
from adjust.moves import unrotate
from adjust.pipeline import run
from deformnet.body import default_mouse
from deformnet.paths import CONF_DIR
from deformnet.sessions import SessionTokens

FRAMES = 1500
CHUNK = 500


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 1,500-frame synthetic session (8 parts, 3 cameras, 2 px noise, 20% missing, 2 mm
    per-part deformation) as DeepLabCut CSVs, and its true points."""
    root = tmp_path_factory.mktemp("long")
    body = default_mouse()
    cams = synthetic.ring_cameras(3)
    poses = synthetic.smooth_trajectory(FRAMES, seed=7)
    xy, _, X = synthetic.simulate(
        poses,
        torch.tensor(np.array(body.points)),
        synthetic.CameraTensors.from_cameras(cams),
        noise_px=2.0,
        drop=0.2,
        deform_mm=2.0,
        seed=7,
    )
    save_calibration(root / "calibration.toml", cams)
    (root / "detections").mkdir()
    xy = xy.numpy()
    lik = np.where(np.isfinite(xy).all(-1), 0.9, 0.05)
    for c, cam in enumerate(cams):
        write_dlc_csv(
            root / "detections" / f"{cam.name}.csv", body.parts, xy[:, :, c], lik[:, :, c]
        )
    return root, X.numpy()


def _cfg(root, out, *extra):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return compose(
            "track",
            [
                f"input.calibration={root / 'calibration.toml'}",
                f"input.detections={root / 'detections'}",
                f"output.dir={out}",
                "body=auto",
                "progress=false",
                *extra,
            ],
        )


@pytest.fixture(scope="module")
def runs(scene, tmp_path_factory):
    """The scene tracked whole (chunk_frames=0) and in 500-frame chunks (interp)."""
    root, _ = scene
    tmp = tmp_path_factory.mktemp("runs")
    whole = run(_cfg(root, tmp / "whole", "chunk_frames=0"))
    chunked = run(_cfg(root, tmp / "chunked", f"chunk_frames={CHUNK}"))
    return tmp, whole, chunked


def test_plan_tiles_the_session_with_overlap():
    plan = plan_chunks(1250, 500)
    assert [(a, b) for a, b, _, _ in plan] == [(0, 500), (500, 1000), (1000, 1250)]
    over = overlap_frames(500)
    assert over == max(MIN_OVERLAP, 50)
    assert plan[1][2:] == (500 - over, 1000 + over) and plan[0][2] == 0 and plan[-1][3] == 1250
    assert overlap_frames(10**7) == MAX_OVERLAP
    rows = sample_rows(10**6)
    assert len(rows) == SAMPLE_FRAMES and rows[0] == 0 and rows[-1] == 10**6 - 1
    assert np.all(np.diff(rows) > 0)
    np.testing.assert_array_equal(sample_rows(300), np.arange(300))


def test_chunk_frames_setting():
    assert ChunkConfig.from_config({}).chunk_frames == 50_000
    assert ChunkConfig.from_config({"chunk_frames": 0}).chunk_frames is None
    assert ChunkConfig.from_config({"chunk_frames": None}).chunk_frames is None
    for bad in (-1, "many", 2.5, True, 10):
        with pytest.raises(ValueError, match="chunk_frames"):
            ChunkConfig.from_config({"chunk_frames": bad})


def test_streamed_csv_equals_the_whole_file(tmp_path):
    rng = np.random.default_rng(0)
    xy = rng.normal(500, 50, (23, 3, 2))
    xy[rng.random((23, 3)) < 0.3] = np.nan
    lik = rng.random((23, 3))
    path = write_dlc_csv(tmp_path / "cam0.csv", ["a", "b", "c"], xy, lik, frames=range(5, 28))
    whole = read_dlc(path)
    blocks = list(iter_dlc(path, block_rows=7))
    assert [b.num_frames for b in blocks] == [7, 7, 7, 2]
    np.testing.assert_array_equal(np.concatenate([b.xy for b in blocks]), whole.xy)
    np.testing.assert_array_equal(np.concatenate([b.likelihood for b in blocks]), whole.likelihood)
    np.testing.assert_array_equal(np.concatenate([b.frames for b in blocks]), whole.frames)
    # an error in a later block names the same line as the whole file's reading
    lines = path.read_text().splitlines()
    lines[20] = lines[20].replace(lines[20].split(",")[2], "oops", 1)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as whole_err:
        read_dlc(path)
    with pytest.raises(InputError) as block_err:
        list(iter_dlc(path, block_rows=7))
    assert "line 21" in str(whole_err.value) and str(block_err.value) == str(whole_err.value)


def test_a_session_within_one_chunk_is_tracked_as_before(scene, runs, tmp_path):
    root, _ = scene
    tmp, whole, _ = runs
    same = run(_cfg(root, tmp_path / "one", f"chunk_frames={FRAMES}"))
    assert "chunked" not in same and "chunked" not in whole
    for name in ("points3d.csv", "points3d.extra.csv", "accepted.npz", "tokens.npz"):
        assert (tmp_path / "one" / name).read_bytes() == (tmp / "whole" / name).read_bytes(), name


def test_chunked_run_agrees_with_the_whole_run(scene, runs):
    root, truth = scene
    tmp, whole, chunked = runs
    facts = chunked["chunked"]
    assert facts["chunk_frames"] == CHUNK and len(facts["chunks"]) == 3
    assert [c["frames"] for c in facts["chunks"]] == [[0, 499], [500, 999], [1000, 1499]]
    a = read_points3d(tmp / "whole" / "points3d.csv")
    b = read_points3d(tmp / "chunked" / "points3d.csv")
    np.testing.assert_array_equal(a["fnum"], b["fnum"])
    # the sidecar belongs to the chunked file's bytes; `tracked`: every frame was
    assert set(b["extra"]) == set(a["extra"]) | {"tracked"} and (b["extra"]["tracked"] == 1).all()
    d = np.linalg.norm(a["points"] - b["points"], axis=-1)
    assert np.median(d) < 0.2 and np.percentile(d, 99) < 1.0, (np.median(d), d.max())
    err_a = np.sqrt(np.mean(np.sum((a["points"] - truth) ** 2, -1)))
    err_b = np.sqrt(np.mean(np.sum((b["points"] - truth) ** 2, -1)))
    assert err_b < 1.05 * err_a, (err_a, err_b)
    # the summary: the chunks' figures merged
    T, K = FRAMES, 8
    assert chunked["num_frames"] == T and chunked["counts"]["part_frames"] == T * K
    assert chunked["completeness"] == 1.0 and chunked["health"]["status"] == "ok"
    assert chunked["iterations"] == max(c["iterations"] for c in facts["chunks"])
    assert chunked["converged"] == all(c["converged"] for c in facts["chunks"])
    n_a, n_b = whole["counts"]["detections"], chunked["counts"]["detections"]
    assert abs(n_a - n_b) <= 0.01 * n_a
    assert chunked["body"]["source"] == "auto" and chunked["body"]["points"]
    # the npz outputs: whole arrays of every frame, readable as the unchunked ones
    tok = SessionTokens.load(tmp / "chunked" / "tokens.npz")
    ref = SessionTokens.load(tmp / "whole" / "tokens.npz")
    assert tok.rigid.shape == ref.rigid.shape == (T, K, 3)
    np.testing.assert_array_equal(tok.observed, ref.observed)
    with (
        np.load(tmp / "chunked" / "accepted.npz") as z,
        np.load(tmp / "whole" / "accepted.npz") as w,
    ):
        assert z["accepted"].shape == w["accepted"].shape
        assert (z["accepted"] == w["accepted"]).mean() > 0.99
    files = chunked["outputs"]["files"]
    assert {"points3d.csv", "points3d.extra.csv", "accepted.npz", "tokens.npz"} <= set(files)


def _chunk_summary(iterations, converged, completeness, detections, ncams, cost, err, frames):
    """A chunk's summary (the fields `merge_summaries` combines): err = (count, median, mean,
    p90, max); frames: its bad frames (health failed when any)."""
    return {
        "iterations": iterations,
        "converged": converged,
        "completeness": completeness,
        "counts": {"detections": detections, "ncams_histogram": ncams},
        "final_cost": cost,
        "err": dict(zip(("count", "median", "mean", "p90", "max"), err)),
        "health": {
            "status": "failed" if frames else "ok",
            "limit_px": 100.0,
            "bad_frames": len(frames),
            "frames": frames,
        },
    }


def test_merge_summaries_rules():
    s1 = _chunk_summary(4, True, 1.0, 10, [1, 2], 2.0, (1, 1.0, 1.0, 1.0, 1.0), [])
    s2 = _chunk_summary(9, False, 0.5, 5, [3, 4], 3.0, (3, 3.0, 2.0, 5.0, 7.0), [12, 13])
    m = merge_summaries([s1, s2], [100, 300])
    assert m["iterations"] == 9 and m["converged"] is False and m["final_cost"] == 5.0
    assert m["completeness"] == pytest.approx(0.625)
    assert m["counts"] == {"detections": 15, "ncams_histogram": [4, 6]}
    assert m["err"] == {"count": 4, "median": 2.5, "mean": 1.75, "p90": 4.0, "max": 7.0}
    assert m["health"]["status"] == "failed" and m["health"]["frames"] == [12, 13]


def test_a_chunk_without_two_cameras_is_left_empty_and_named(scene, tmp_path, caplog):
    """Cameras 1 and 2 out for the middle chunk (frames 500..999): those frames are left empty
    and named (points3d.extra.csv tracked 0, summary.json untracked, per-chunk camera counts),
    the run exits normally and its other frames are tracked as with every camera."""
    root, truth = scene
    gap = tmp_path / "gap"
    (gap / "detections").mkdir(parents=True)
    (gap / "calibration.toml").write_bytes((root / "calibration.toml").read_bytes())
    for c, f in enumerate(sorted((root / "detections").iterdir())):
        t = read_dlc(f)
        xy, lik = t.xy.copy(), t.likelihood.copy()
        if c > 0:
            xy[CHUNK : 2 * CHUNK], lik[CHUNK : 2 * CHUNK] = np.nan, 0.0
        write_dlc_csv(gap / "detections" / f.name, t.parts, xy, lik, frames=t.frames)
    with caplog.at_level(logging.WARNING, logger="adjust"):
        s = run(_cfg(gap, tmp_path / "out", f"chunk_frames={CHUNK}"))
    assert "left EMPTY" in caplog.text and "frames 500..999" in caplog.text
    u = s["untracked"]
    assert u["frames"] == CHUNK and u["ranges"] == [[CHUNK, 2 * CHUNK - 1]]
    assert s["health"]["untracked_frames"] == CHUNK and s["health"]["status"] == "ok"
    chunks = s["chunked"]["chunks"]
    assert [c["tracked"] for c in chunks] == [True, False, True]
    middle = chunks[1]["usable_per_camera"]
    assert sorted(middle.values())[:2] == [0, 0] and max(middle.values()) > 0
    assert all(min(c["usable_per_camera"].values()) > 0 for c in (chunks[0], chunks[2]))
    d = read_points3d(tmp_path / "out" / "points3d.csv")
    gap_rows = slice(CHUNK, 2 * CHUNK)
    assert np.isnan(d["points"][gap_rows]).all() and (d["ncams"][gap_rows] == 0).all()
    np.testing.assert_array_equal(d["extra"]["tracked"], np.repeat([1, 0, 1], CHUNK))
    assert np.isnan(d["extra"]["pose_rx"][gap_rows]).all()
    kept = np.r_[0:CHUNK, 2 * CHUNK : FRAMES]
    assert np.isfinite(d["points"][kept]).all()
    rms = np.sqrt(np.mean(np.sum((d["points"][kept] - truth[kept]) ** 2, -1)))
    assert rms < 3.0, rms  # 2.06 mm with every camera
    assert s["completeness"] == pytest.approx(2 / 3, abs=0.01)
    assert not (tmp_path / "out" / "tokens.npz").exists() and "tokens" not in s["outputs"]
    with np.load(tmp_path / "out" / "accepted.npz") as z:
        assert z["accepted"].shape[0] == FRAMES and not z["accepted"][gap_rows].any()


def _spoil_camera_1(root, out, edit) -> str:
    """A copy of the scene at `out` with camera 1's (xy, likelihood) replaced by
    ``edit(table)`` (its file's frames kept where the row count is); returns its file's
    stem."""
    (out / "detections").mkdir(parents=True)
    (out / "calibration.toml").write_bytes((root / "calibration.toml").read_bytes())
    name = None
    for c, f in enumerate(sorted((root / "detections").iterdir())):
        t = read_dlc(f)
        xy, lik = t.xy, t.likelihood
        if c == 1:
            name = f.stem
            xy, lik = edit(t)
        frames = t.frames if len(xy) == len(t.xy) else None
        write_dlc_csv(out / "detections" / f.name, t.parts, xy, lik, frames=frames)
    return name


def test_a_camera_out_of_step_is_shifted_back_in_every_chunk(scene, runs, tmp_path):
    """Camera 1's file starts 4 frames early: the sample finds the offset and every chunk reads
    the camera shifted back (the chunks' frames beyond their own come from the overlap)."""
    root, truth = scene
    tmp, _, chunked = runs
    late = tmp_path / "late"

    def early(t):
        xy = np.concatenate([np.full((4, *t.xy.shape[1:]), np.nan), t.xy[:-4]])
        return xy, np.concatenate([np.zeros((4, t.xy.shape[1])), t.likelihood[:-4]])

    name = _spoil_camera_1(root, late, early)
    s = run(_cfg(late, tmp_path / "out", f"chunk_frames={CHUNK}"))
    assert len(s["chunked"]["chunks"]) == 3
    assert s["camera_check"]["sync"]["offsets"] == {name: 4}
    b = read_points3d(tmp_path / "out" / "points3d.csv")["points"]
    a = read_points3d(tmp / "chunked" / "points3d.csv")["points"]
    err_a = np.sqrt(np.mean(np.sum((a - truth) ** 2, -1)))
    err_b = np.sqrt(np.mean(np.sum((b - truth) ** 2, -1)))
    assert err_b < 1.05 * err_a, (err_a, err_b)


def test_a_camera_turned_mid_session_is_mapped_back_in_every_chunk(scene, runs, tmp_path):
    """Camera 1 turned by 1 deg (a pan, about 35 px) from frame 750 on, its calibration as it
    was: the sample finds the move and every chunk maps that camera's detections back by frame
    number, so the tracks are those of the unmoved session."""
    root, truth = scene
    tmp, _, chunked = runs
    moved = tmp_path / "moved"
    (moved / "detections").mkdir(parents=True)
    (moved / "calibration.toml").write_bytes((root / "calibration.toml").read_bytes())
    cams = load_calibration(root / "calibration.toml")
    a = np.deg2rad(1.0)
    turn = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    name = None
    for c, f in enumerate(sorted((root / "detections").iterdir())):
        t = read_dlc(f)
        xy = t.xy.copy()
        if c == 1:
            name = f.stem
            cam = next(k for k in cams if k.name in name)
            xy[750:] = unrotate(t.xy[750:], cam, turn)
        write_dlc_csv(moved / "detections" / f.name, t.parts, xy, t.likelihood, frames=t.frames)
    s = run(_cfg(moved, tmp_path / "out", f"chunk_frames={CHUNK}"))
    assert len(s["chunked"]["chunks"]) == 3
    found = s["camera_check"]["moved"]["moves"]
    assert [m["camera"] for m in found] == [cam.name] and abs(found[0]["first_frame"] - 750) <= 5
    assert s["camera_check"]["excluded"] == {}
    b = read_points3d(tmp_path / "out" / "points3d.csv")["points"]
    a = read_points3d(tmp / "chunked" / "points3d.csv")["points"]
    err_a = np.sqrt(np.mean(np.sum((a - truth) ** 2, -1)))
    err_b = np.sqrt(np.mean(np.sum((b - truth) ** 2, -1)))
    assert err_b < 1.05 * err_a, (err_a, err_b)


def test_a_camera_on_its_own_clock_is_read_at_the_others_times_in_every_chunk(
    scene, runs, tmp_path
):
    """Camera 1's clock runs 0.5% slow (its frame g shows frame g / 0.995: 7 frames behind by
    the end; its detections interpolated in time from the scene's): the sample finds its
    rate and every chunk reads it at the others' times from its rows over the frames the map
    reads (beyond the chunk's own): the chunks track as the whole session does (0.08 mm apart
    at the median), close to the session in step."""
    root, truth = scene
    tmp, _, chunked = runs
    slow = tmp_path / "slow"

    def slower(t):
        when = np.arange(int((FRAMES - 1) * 0.995) + 1) / 0.995
        i = np.floor(when).astype(int)
        w = (when - i)[:, None, None]
        j = np.minimum(i + 1, FRAMES - 1)
        return (1 - w) * t.xy[i] + w * t.xy[j], np.minimum(t.likelihood[i], t.likelihood[j])

    name = _spoil_camera_1(root, slow, slower)
    s = run(_cfg(slow, tmp_path / "out", f"chunk_frames={CHUNK}"))
    assert len(s["chunked"]["chunks"]) == 3
    got = s["camera_check"]["clocks"]["retimed"]
    assert set(got) == {name} and abs(got[name]["rate"] - 0.995) < 5e-4, got
    assert s["camera_check"]["excluded"] == {}
    b = read_points3d(tmp_path / "out" / "points3d.csv")["points"]
    run(_cfg(slow, tmp_path / "whole", "chunk_frames=0"))
    w = read_points3d(tmp_path / "whole" / "points3d.csv")["points"]
    assert b.shape == w.shape
    assert np.nanmedian(np.linalg.norm(b - w, axis=-1)) < 0.2  # the chunks as the whole run
    a = read_points3d(tmp / "chunked" / "points3d.csv")["points"]
    err_a = np.sqrt(np.mean(np.sum((a - truth) ** 2, -1)))
    err_b = np.sqrt(np.mean(np.sum((b - truth) ** 2, -1)))
    # within 15% of the session in step (its detections interpolated twice: a missing one
    # takes its neighbour's frame with it; measured 2.29 against 2.08 mm)
    assert err_b < 1.15 * err_a, (err_a, err_b)
