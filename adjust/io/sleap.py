"""SLEAP files as 2D detections: analysis HDF5 (``*.analysis.h5``, h5py) and ``.slp`` (sleap-io).

SLEAP's analysis export (``sleap-convert --format analysis``, or File > Export Analysis HDF5)
holds, as read by h5py (SLEAP writes the arrays transposed, MATLAB style):

- ``tracks`` (n_tracks, 2, n_nodes, n_frames): x, y in px, NaN where a node is missing;
- ``point_scores`` (n_tracks, n_nodes, n_frames): the confidence-map peak of each node;
- ``node_names`` (n_nodes,) and ``track_names`` (n_tracks,) byte strings.

Frame ``i`` of the arrays is frame ``i`` of the video (SLEAP writes every frame from 0 up to the
last labelled one). A file written without the transpose (n_frames, n_nodes, 2, n_tracks) is
recognised by its shape and read the same way.

Point scores are not probabilities: SLEAP's confidence maps peak slightly above 1 (up to ~1.2)
for sharp detections. Scores in (1, 2] are clipped to 1 (logged); a score below 0 or above 2 is
not a SLEAP score and is an error naming the file, part and frame. A node present in ``tracks``
whose score is NaN (a hand-placed, proofread point) gets score 1. The result is a `DLCTable`
(the files' own node names, in file order), so the rest of `adjust.io` treats SLEAP and
DeepLabCut files alike.

SLEAP's own project / predictions files (``*.slp``) are read with sleap-io (`read_slp`; ``pip
install sleap-io``, part of the ``sleap`` and ``test`` extras): one skeleton and one video per
file; rows 0 .. the last labelled frame, as the analysis export writes them; user (hand-placed)
instances preferred over predictions of the same track, their points scored 1. Both readers
choose a track of a multi-animal file by name or by index (``input.individual=mouse2`` or
``input.individual=1``; a name wins over an index). `sleap_edges` reads either file's skeleton
edges (by node name).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import h5py
import numpy as np

from adjust.io.dlc import DLCTable
from adjust.io.errors import InputError

log = logging.getLogger(__name__)

SUFFIX = ".analysis.h5"
SLP_SUFFIX = ".slp"
#: the largest point score accepted (clipped to 1); SLEAP's peaks stay well below it
MAX_SCORE = 2.0


def _strings(arr) -> list[str]:
    out = []
    for v in np.asarray(arr).reshape(-1):
        out.append(v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v))
    return out


def is_sleap_file(path: str | os.PathLike) -> bool:
    """True if `path` is a SLEAP ``.slp`` file or an HDF5 file with SLEAP's ``tracks`` and
    ``node_names`` datasets."""
    path = Path(path)
    if path.name.lower().endswith(SUFFIX) or path.suffix.lower() == SLP_SUFFIX:
        return True
    if path.suffix.lower() not in (".h5", ".hdf5") or not path.is_file():
        return False
    try:
        with h5py.File(path, "r") as f:
            return "tracks" in f and "node_names" in f
    except (OSError, ValueError):
        return False


def read_sleap(path: str | os.PathLike, individual: str | None = None) -> DLCTable:
    """Read a SLEAP analysis HDF5 file into a `DLCTable` (see the module doc).

    individual: the track to take, by name or index (`choose_track`); required when the file
    has several tracks (the error lists them), ignored (with a warning) for a single-track file
    when it names no track. A ``.slp`` file is read by `read_slp`.
    """
    path = Path(path)
    if path.suffix.lower() == SLP_SUFFIX:
        return read_slp(path, individual)
    if not path.is_file():
        raise InputError(f"SLEAP analysis file not found: {path}")
    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in ("tracks", "node_names") if k not in f]
            if missing:
                raise InputError(
                    f"{path}: not a SLEAP analysis file: no {missing} dataset(s); it holds "
                    f"{sorted(f.keys())}"
                )
            tracks = np.asarray(f["tracks"][()], dtype=np.float64)
            nodes = _strings(f["node_names"][()])
            scores = (
                np.asarray(f["point_scores"][()], dtype=np.float64) if "point_scores" in f else None
            )
            names = _strings(f["track_names"][()]) if "track_names" in f else []
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - h5py raises OSError, KeyError, TypeError, ...
        raise InputError(f"{path}: cannot read SLEAP HDF5: {type(exc).__name__}: {exc}") from None
    K = len(nodes)
    if K == 0:
        raise InputError(f"{path}: 'node_names' is empty")
    if len(set(nodes)) != K:
        raise InputError(f"{path}: duplicate node names {nodes}")
    # to (n_tracks, 2, n_nodes, n_frames)
    if tracks.ndim == 4 and tracks.shape[1] == 2 and tracks.shape[2] == K:
        pass
    elif tracks.ndim == 4 and tracks.shape[2] == 2 and tracks.shape[1] == K:
        tracks = tracks.transpose(3, 2, 1, 0)  # untransposed (frames, nodes, 2, tracks)
        if scores is not None:
            scores = scores.T
    else:
        raise InputError(
            f"{path}: 'tracks' has shape {tracks.shape}; expected (n_tracks, 2, {K}, n_frames) "
            f"for {K} nodes"
        )
    n_tracks, _, _, T = tracks.shape
    if scores is not None and scores.shape != (n_tracks, K, T):
        raise InputError(
            f"{path}: 'point_scores' has shape {scores.shape}, expected {(n_tracks, K, T)}"
        )
    if len(names) != n_tracks:
        names = [f"track_{i}" for i in range(n_tracks)]
    i = choose_track(path, names, individual)
    xy = np.ascontiguousarray(tracks[i].transpose(2, 1, 0))  # (T, K, 2)
    lik = None if scores is None else np.ascontiguousarray(scores[i].T)  # (T, K)
    return _table(path, nodes, xy, lik, names, i)


def choose_track(path: Path, names: list[str], individual) -> int:
    """The index of the track to read: by name, else by index (an integer or a string of
    digits); None for a single-track file. A multi-track file without a choice, or an unknown
    choice, is an InputError listing the tracks."""
    n = len(names)
    if n == 0:
        raise InputError(f"{path}: the file has no tracks")
    if individual is None:
        if n > 1:
            raise InputError(
                f"{path}: multi-animal SLEAP file with tracks {names}; choose one by name or "
                "index (input.individual=NAME or input.individual=0)"
            )
        return 0
    key = str(individual)
    if key in names:
        return names.index(key)
    if key.lstrip("-").isdigit() and -n <= int(key) < n:
        return int(key) % n
    if n == 1:
        log.warning("%s: single-track file; individual '%s' ignored", path, individual)
        return 0
    raise InputError(
        f"{path}: individual '{individual}' is not in the file; it has {names} (a name, or an "
        f"index 0..{n - 1})"
    )


def _table(
    path: Path,
    nodes: list[str],
    xy: np.ndarray,
    lik: np.ndarray | None,
    names: list[str],
    i: int,
) -> DLCTable:
    """One track's (T, K, 2) positions and (T, K) scores (None: no scores) -> `DLCTable`,
    with the module doc's score rules."""
    T, K = xy.shape[:2]
    present = np.isfinite(xy).all(-1)
    unusable = ~present & ~np.isnan(xy).all(-1)  # inf, or x without y
    xy[~present] = np.nan
    no_scores = lik is None
    if lik is None:  # said as a warning naming the camera by adjust.io.scene
        lik = np.where(present, 1.0, np.nan)
        log.debug("%s: no point_scores; score 1 where a node is present", path)
    else:
        lik = np.where(present & np.isnan(lik), 1.0, lik)  # hand-placed points
        bad = present & np.isfinite(lik) & ((lik < 0) | (lik > MAX_SCORE))
        if bad.any():
            t, k = np.argwhere(bad)[0]
            raise InputError(
                f"{path}: point score {float(lik[t, k])} of part '{nodes[k]}' at frame {t} is "
                f"not a SLEAP score (expected 0 to ~1.2)"
                + (f"; {int(bad.sum()) - 1} more such scores" if bad.sum() > 1 else "")
            )
        over = present & (lik > 1.0)
        if over.any():
            log.info("%s: %d point scores above 1 clipped to 1", path, int(over.sum()))
            lik = np.where(over, 1.0, lik)
    frames = np.arange(T, dtype=np.int64)
    log.debug("read %s: %d frames, %d nodes, track '%s'", path, T, K, names[i])
    chosen = names[i] if len(names) > 1 else None
    return DLCTable(
        tuple(nodes),
        xy,
        lik,
        "SLEAP",
        frames,
        chosen,
        path,
        tuple(nodes) if no_scores else (),
        unusable if unusable.any() else None,
    )


def _require_sleap_io(path: Path):
    try:
        import sleap_io
    except ImportError:
        raise InputError(
            f"{path}: reading SLEAP .slp files needs sleap-io: pip install 'mousetrack[sleap]' "
            "(or export an analysis file: sleap-convert --format analysis)"
        ) from None
    return sleap_io


def _load_slp(path: Path):
    sio = _require_sleap_io(path)
    if not path.is_file():
        raise InputError(f"SLEAP file not found: {path}")
    try:
        return sio.load_slp(str(path), open_videos=False)
    except Exception as exc:  # noqa: BLE001 - sleap-io raises many kinds
        raise InputError(f"{path}: cannot read SLEAP .slp: {type(exc).__name__}: {exc}") from None


def read_slp(path: str | os.PathLike, individual: str | int | None = None) -> DLCTable:
    """Read a SLEAP ``.slp`` file (predictions or a labels project) into a `DLCTable`, with
    sleap-io: one skeleton, one video; rows 0 .. the last labelled frame; the track chosen by
    name or index (`choose_track`); without tracks, at most one instance per frame."""
    path = Path(path)
    labels = _load_slp(path)
    if len(labels.skeletons) != 1:
        raise InputError(
            f"{path}: {len(labels.skeletons)} skeletons; one is expected (one file per camera, "
            "one skeleton)"
        )
    if len(labels.videos) != 1:
        raise InputError(
            f"{path}: labels of {len(labels.videos)} videos {[v.filename for v in labels.videos]}; "
            "one file per camera is expected (split it: one .slp per video)"
        )
    video = labels.videos[0]
    nodes = [str(n) for n in labels.skeletons[0].node_names]
    if len(set(nodes)) != len(nodes):
        raise InputError(f"{path}: duplicate node names {nodes}")
    frames = [lf.frame_idx for lf in labels.labeled_frames if lf.video is video]
    if not frames:
        raise InputError(f"{path}: no labelled frame")
    T = int(max(frames)) + 1
    names = [str(t.name) for t in labels.tracks]
    if names:
        arr = labels.numpy(video=video, return_confidence=True, user_instances=True)
    else:  # a single-animal project without tracks
        arr = labels.numpy(video=video, untracked=True, return_confidence=True)
        if arr.shape[1] > 1:
            raise InputError(
                f"{path}: up to {arr.shape[1]} instances per frame but no tracks; track the "
                "animals in SLEAP first (one track per animal)"
            )
        names = ["untracked"] if arr.shape[1] else []
    arr = np.asarray(arr, dtype=np.float64)  # (frames, tracks, nodes, 3): x, y, score
    if arr.shape[0] < T:
        pad = np.full((T - arr.shape[0],) + arr.shape[1:], np.nan)
        arr = np.concatenate([arr, pad])
    arr = arr[:T]
    i = choose_track(path, names, individual)
    xy = np.ascontiguousarray(arr[:, i, :, :2])
    lik = np.ascontiguousarray(arr[:, i, :, 2])
    return _table(path, nodes, xy, lik, names, i)


def sleap_edges(path: str | os.PathLike) -> list[tuple[str, str]]:
    """The skeleton edges (source node, destination node) of a SLEAP file: ``.slp`` (sleap-io)
    or an analysis HDF5 (``edge_names``, else ``edge_inds`` with ``node_names``; [] when it has
    neither)."""
    path = Path(path)
    if path.suffix.lower() == SLP_SUFFIX:
        labels = _load_slp(path)
        if not labels.skeletons:
            return []
        return [(str(a), str(b)) for a, b in labels.skeletons[0].edge_names]
    try:
        with h5py.File(path, "r") as f:
            if "edge_names" in f:
                names = _strings(f["edge_names"][()])
                return list(zip(names[0::2], names[1::2]))
            if "edge_inds" in f and "node_names" in f:
                nodes = _strings(f["node_names"][()])
                inds = np.asarray(f["edge_inds"][()], dtype=np.int64).reshape(-1, 2)
                if inds.size and (inds.min() < 0 or inds.max() >= len(nodes)):
                    raise InputError(f"{path}: 'edge_inds' outside the {len(nodes)} nodes")
                return [(nodes[a], nodes[b]) for a, b in inds]
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - h5py raises OSError, KeyError, TypeError, ...
        raise InputError(f"{path}: cannot read SLEAP HDF5: {type(exc).__name__}: {exc}") from None
    return []
