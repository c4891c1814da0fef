"""Skeletons (pairs of part names) for figures and NWB: from the input, the spanning tree last.

Sources, in the order `resolve_skeleton` tries them:

1. ``edges``: pairs given in a setting (``[[a, b], ...]``); a part the tracks lack is an error;
2. ``skeleton``: a file, ``skeleton.csv`` (columns ``part_a,part_b``, one edge per row), or a
   SLEAP file (``*.analysis.h5``: ``edge_names`` or ``edge_inds`` + ``node_names``; ``*.slp``:
   its skeleton, read with sleap-io);
3. ``detections``: the session's detection folder (or one file): the edges of its SLEAP files
   (DeepLabCut and Lightning Pose files carry none);
4. the minimum spanning tree of the parts' median distances (`spanning_edges`), logged.

Edges of a file (2, 3) that name a part the tracks lack are dropped with a warning (a SLEAP
skeleton often has nodes a session does not track); a file whose edges all miss falls through to
the next source.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from adjust.io.errors import InputError
from adjust.io.sleap import is_sleap_file, sleap_edges
from deformnet.tables import read_csv

log = logging.getLogger(__name__)

SKELETON_COLUMNS = ("part_a", "part_b")


def spanning_edges(points: np.ndarray) -> list[tuple[int, int]]:
    """Skeleton edges: the minimum spanning tree of the parts' median distances.

    points: (T, K, 3) mm (NaN allowed). Returns K - 1 index pairs (a < b), or fewer when some
    part has no finite frame (it stays unconnected)."""
    X = np.asarray(points, dtype=np.float64)
    if X.ndim != 3 or X.shape[-1] != 3:
        raise ValueError(f"points must be (T, K, 3), got {X.shape}")
    K = X.shape[1]
    D = np.full((K, K), np.inf)
    for a in range(K):
        for b in range(a + 1, K):
            d = np.linalg.norm(X[:, a] - X[:, b], axis=-1)
            d = d[np.isfinite(d)]
            if d.size:
                D[a, b] = D[b, a] = float(np.median(d))
    # Prim's algorithm from part 0 over the finite distances
    inside, edges = {0}, []
    while len(inside) < K:
        best = None
        for a in inside:
            for b in range(K):
                if b not in inside and math.isfinite(D[a, b]):
                    if best is None or D[a, b] < best[0]:
                        best = (D[a, b], min(a, b), max(a, b), b)
        if best is None:
            break
        edges.append((best[1], best[2]))
        inside.add(best[3])
    return sorted(edges)


def read_skeleton_csv(path: str | os.PathLike) -> list[tuple[str, str]]:
    """``skeleton.csv`` (``part_a,part_b``, one edge per row) -> [(a, b)]."""

    path = Path(path)
    df = read_csv(path, "skeleton file", InputError)
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in SKELETON_COLUMNS if c not in df.columns]
    if missing:
        raise InputError(
            f"{path}: a skeleton file has columns part_a,part_b; missing {missing} "
            f"(has {list(df.columns)})"
        )
    out = []
    for r, (a, b) in enumerate(zip(df["part_a"], df["part_b"])):
        if not isinstance(a, str) or not isinstance(b, str) or not a.strip() or not b.strip():
            raise InputError(f"{path}: row {r + 1}: two part names expected, got {a!r}, {b!r}")
        out.append((a.strip(), b.strip()))
    return out


def read_skeleton(path: str | os.PathLike) -> list[tuple[str, str]]:
    """The edges of a skeleton file: ``skeleton.csv`` or a SLEAP file (``.slp``,
    ``.analysis.h5`` / SLEAP HDF5)."""

    path = Path(path)
    if not path.is_file():
        raise InputError(f"skeleton file not found: {path}")
    if path.suffix.lower() == ".slp" or is_sleap_file(path):
        return sleap_edges(path)
    return read_skeleton_csv(path)


def detection_edges(detections: str | os.PathLike) -> tuple[list[tuple[str, str]], str] | None:
    """The SLEAP edges of a session's detection folder (or one file): (edges, source file), or
    None when it has no SLEAP file with edges. Files whose edges differ: the first (sorted by
    name) is used, with a warning."""

    path = Path(detections)
    files = sorted(path.iterdir()) if path.is_dir() else [path] if path.is_file() else []
    found: list[tuple[Path, list[tuple[str, str]]]] = []
    for f in files:
        if f.name.startswith(".") or not f.is_file():
            continue
        if f.suffix.lower() == ".slp" or is_sleap_file(f):
            edges = sleap_edges(f)
            if edges:
                found.append((f, edges))
    if not found:
        return None
    first, edges = found[0]
    differ = [f.name for f, e in found[1:] if sorted(e) != sorted(edges)]
    if differ:
        log.warning("%s: SLEAP skeletons differ from %s's; using %s's", differ, first.name, first)
    return edges, str(first)


def _indices(edges, parts: Sequence[str], where: str, strict: bool) -> list[tuple[int, int]]:
    index = {p: k for k, p in enumerate(parts)}
    out, dropped = [], []
    for e in edges:
        pair = list(e) if isinstance(e, Sequence) and not isinstance(e, str) else [e]
        if len(pair) != 2:
            raise InputError(f"{where}: skeleton edge {pair!r}: give two part names")
        a, b = (str(p) for p in pair)
        if a in index and b in index:
            if index[a] != index[b]:
                out.append((index[a], index[b]))
            continue
        if strict:
            unknown = a if a not in index else b
            raise InputError(
                f"{where}: skeleton edge {pair!r}: unknown part {unknown!r} (parts: {list(parts)})"
            )
        dropped.append((a, b))
    if dropped:
        log.warning(
            "%s: %d skeleton edge(s) name parts the tracks lack, dropped: %s",
            where,
            len(dropped),
            dropped,
        )
    return out


def resolve_skeleton(
    parts: Sequence[str],
    points: np.ndarray | None = None,
    edges=None,
    skeleton: str | os.PathLike | None = None,
    detections: str | os.PathLike | None = None,
) -> tuple[list[tuple[int, int]], str]:
    """The skeleton of tracks with these `parts`: (index pairs into `parts`, source), trying
    `edges`, the `skeleton` file, the SLEAP files of `detections`, then the minimum spanning
    tree of `points` (T, K, 3) (see the module doc). source: ``"edges"``, the file used, or
    ``"minimum spanning tree"`` (``"none"`` with no points)."""
    parts = [str(p) for p in parts]
    if edges is not None:
        return _indices(edges, parts, "edges", strict=True), "edges"
    if skeleton is not None:
        pairs = _indices(read_skeleton(skeleton), parts, str(skeleton), strict=False)
        if pairs:
            return pairs, str(skeleton)
        log.warning("%s: no edge between the tracks' parts %s", skeleton, parts)
    if detections is not None and Path(detections).exists():
        found = detection_edges(detections)
        if found is not None:
            pairs = _indices(found[0], parts, found[1], strict=False)
            if pairs:
                log.info("skeleton: %d edges from %s", len(pairs), found[1])
                return pairs, found[1]
    if points is None or len(parts) < 2:
        return [], "none"
    log.info(
        "skeleton: none given (edges, skeleton=skeleton.csv or a SLEAP file) or found in the "
        "detections; using the minimum spanning tree of the parts' median distances"
    )
    return spanning_edges(points), "minimum spanning tree"
