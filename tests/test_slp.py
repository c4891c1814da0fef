"""SLEAP's native .slp files (adjust.io.sleap.read_slp, through sleap-io): a file made with
sleap-io from the shared analysis file's data reads back as the analysis reader reads it; tracks
chosen by name or index; the skeleton's edges; a session folder of .slp files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sleap_io as sio

from adjust.io import InputError, load_scene
from adjust.io.skeleton import detection_edges, resolve_skeleton
from adjust.io.sleap import read_sleap, read_slp, sleap_edges
from deformnet.paths import shared_dir

SLEAP_MOUSE = shared_dir() / "data" / "real-mouse-sleap-4cam"
FRAMES = 12
needs_data = pytest.mark.skipif(
    not (SLEAP_MOUSE / "top.analysis.h5").is_file(), reason="shared SLEAP data not present"
)


def _slp_from_analysis(src: Path, dst: Path, frames: int = FRAMES, copies: int = 1) -> Path:
    """A .slp file (sleap-io) holding the first `frames` frames of an analysis file; with
    copies > 1 further tracks (``mouse{i}``) shifted by 100 i px, scores scaled by 0.5."""
    t = read_sleap(src)
    edges = sleap_edges(src)
    skeleton = sio.Skeleton(nodes=list(t.parts), edges=edges)
    video = sio.Video(filename=f"{src.stem}.mp4", open_backend=False)
    tracks = [sio.Track(f"mouse{i}") for i in range(copies)]
    lik = np.where(np.isfinite(t.likelihood), t.likelihood, 0.0)
    lfs = []
    for f in range(frames):
        if not np.isfinite(t.xy[f]).any():
            continue
        insts = [
            sio.PredictedInstance.from_numpy(
                t.xy[f] + 100.0 * i,
                skeleton,
                point_scores=lik[f] * (0.5 if i else 1.0),
                score=1.0,
                track=tr,
            )
            for i, tr in enumerate(tracks)
        ]
        lfs.append(sio.LabeledFrame(video=video, frame_idx=f, instances=insts))
    labels = sio.Labels(labeled_frames=lfs, videos=[video], skeletons=[skeleton], tracks=tracks)
    sio.save_slp(labels, str(dst))
    return dst


@needs_data
def test_slp_reads_as_the_analysis_file(tmp_path):
    src = SLEAP_MOUSE / "back.analysis.h5"  # 78% present: missing nodes and frames
    want = read_sleap(src)
    path = _slp_from_analysis(src, tmp_path / "back.slp")
    got = read_slp(path)
    assert got.parts == want.parts
    np.testing.assert_array_equal(got.xy, want.xy[:FRAMES])
    np.testing.assert_array_equal(got.likelihood, want.likelihood[:FRAMES])
    np.testing.assert_array_equal(got.frames, np.arange(FRAMES))
    # read_sleap dispatches on the suffix; the skeleton's edges come through
    np.testing.assert_array_equal(read_sleap(path).xy, got.xy)
    assert sleap_edges(path) == sleap_edges(src) and len(sleap_edges(src)) == 14


@needs_data
def test_slp_track_by_name_or_index(tmp_path):
    src = SLEAP_MOUSE / "top.analysis.h5"
    want = read_sleap(src)
    path = _slp_from_analysis(src, tmp_path / "top.slp", copies=2)
    with pytest.raises(InputError, match=r"mouse0.*mouse1.*input.individual"):
        read_slp(path)
    by_name = read_slp(path, "mouse1")
    by_index = read_slp(path, 1)
    shifted = (want.xy[:FRAMES] + 100.0).astype(np.float32)  # .slp stores float32
    np.testing.assert_array_equal(by_name.xy, shifted)
    np.testing.assert_array_equal(by_index.xy, by_name.xy)
    np.testing.assert_array_equal(read_slp(path, "0").xy, want.xy[:FRAMES])
    assert by_name.individual == "mouse1"
    with pytest.raises(InputError, match="index 0..1"):
        read_slp(path, "mouse7")
    # the analysis reader takes an index too
    np.testing.assert_array_equal(read_sleap(src, 0).xy, want.xy)


@needs_data
def test_session_of_slp_files(tmp_path):
    det = tmp_path / "detections"
    det.mkdir()
    for cam in ("back", "mid", "side", "top"):
        _slp_from_analysis(SLEAP_MOUSE / f"{cam}.analysis.h5", det / f"{cam}.predictions.slp")
    _, d = load_scene(SLEAP_MOUSE / "calibration.toml", det, None, 0.0)
    _, ref = load_scene(
        SLEAP_MOUSE / "calibration.toml", SLEAP_MOUSE, None, 0.0, pattern="*.analysis.h5"
    )
    assert d.parts == ref.parts
    np.testing.assert_array_equal(d.xy, ref.xy[:FRAMES])
    # the session's skeleton for NWB and figures: SLEAP's edges, by node name
    edges, source = detection_edges(det)
    assert len(edges) == 14 and source.endswith(".slp")
    pairs, source = resolve_skeleton(d.parts, detections=det)
    assert len(pairs) == 14 and source.endswith(".slp")


def test_slp_without_sleap_tracks_and_errors(tmp_path):
    skeleton = sio.Skeleton(nodes=["a", "b"], edges=[("a", "b")])
    video = sio.Video(filename="cam.mp4", open_backend=False)
    inst = sio.Instance.from_numpy(np.array([[1.0, 2.0], [3.0, 4.0]]), skeleton)
    lf = sio.LabeledFrame(video=video, frame_idx=2, instances=[inst])
    path = tmp_path / "cam.slp"
    sio.save_slp(sio.Labels(labeled_frames=[lf], videos=[video], skeletons=[skeleton]), str(path))
    t = read_slp(path)  # one untracked user instance per frame: a single animal
    assert t.xy.shape == (3, 2, 2) and np.isnan(t.xy[:2]).all()
    np.testing.assert_array_equal(t.xy[2], [[1.0, 2.0], [3.0, 4.0]])
    np.testing.assert_array_equal(t.likelihood[2], [1.0, 1.0])  # hand-placed: score 1
    bad = tmp_path / "bad.slp"
    bad.write_bytes(b"not hdf5")
    with pytest.raises(InputError, match="cannot read SLEAP .slp"):
        read_slp(bad)
