"""SLEAP analysis HDF5 files (``*.analysis.h5``) as 2D detections, read with ``h5py``.

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
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from adjust.io.dlc import DLCTable
from adjust.io.errors import InputError

log = logging.getLogger(__name__)

SUFFIX = ".analysis.h5"
#: the largest point score accepted (clipped to 1); SLEAP's peaks stay well below it
MAX_SCORE = 2.0


def _strings(arr) -> list[str]:
    out = []
    for v in np.asarray(arr).reshape(-1):
        out.append(v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v))
    return out


def is_sleap_file(path: str | os.PathLike) -> bool:
    """True if `path` is an HDF5 file with SLEAP's ``tracks`` and ``node_names`` datasets."""
    path = Path(path)
    if path.name.lower().endswith(SUFFIX):
        return True
    if path.suffix.lower() not in (".h5", ".hdf5") or not path.is_file():
        return False
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return "tracks" in f and "node_names" in f
    except (OSError, ValueError):
        return False


def read_sleap(path: str | os.PathLike, individual: str | None = None) -> DLCTable:
    """Read a SLEAP analysis HDF5 file into a `DLCTable` (see the module doc).

    individual: the track name to take; required when the file has several tracks (the error
    lists them), ignored (with a warning) for a single-track file.
    """
    import h5py

    path = Path(path)
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
    if n_tracks == 0:
        raise InputError(f"{path}: the file has no tracks")
    if individual is None:
        if n_tracks > 1:
            raise InputError(
                f"{path}: multi-animal SLEAP file with tracks {names}; choose one "
                "(input.individual=NAME)"
            )
        i = 0
    else:
        if n_tracks == 1 and str(individual) not in names:
            log.warning("%s: single-track file; individual '%s' ignored", path, individual)
            i = 0
        elif str(individual) not in names:
            raise InputError(
                f"{path}: individual '{individual}' is not in the file; it has {names}"
            )
        else:
            i = names.index(str(individual))
    xy = np.ascontiguousarray(tracks[i].transpose(2, 1, 0))  # (T, K, 2)
    present = np.isfinite(xy).all(-1)
    xy[~present] = np.nan
    if scores is None:
        lik = np.where(present, 1.0, np.nan)
        log.info("%s: no point_scores; score 1 where a node is present", path)
    else:
        lik = np.ascontiguousarray(scores[i].T)  # (T, K)
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
    chosen = names[i] if n_tracks > 1 else None
    return DLCTable(tuple(nodes), xy, lik, "SLEAP", frames, chosen, path)
