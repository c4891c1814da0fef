"""A long session's detections on disk (`adjust.chunks`, issue 46): each camera's file read once,
in blocks of rows (`adjust.io.dlc.iter_dlc`; H5 and SLEAP files whole, one camera at a time),
into raw arrays (float64 as read; the frame numbers, 8 bytes a frame and camera, kept in
memory); `SessionCache.tables` hands back any range of rows as the cameras' `DLCTable`s."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from adjust.camera import Camera
from adjust.io.dlc import DLCTable, iter_dlc
from adjust.io.scene import read_table
from adjust.io.sleap import is_sleap_file

__all__ = ["READ_BLOCK_ROWS", "NotChunked", "SessionCache", "count_rows"]

#: rows of a CSV parsed at a time while the cache is built
READ_BLOCK_ROWS = 50_000


class NotChunked(Exception):
    """The session cannot be chunked (frames named, not numbered): it runs whole."""


@dataclass
class _CameraCache:
    """One camera's file on disk: parts, scorer, individual, path, no_likelihood (as its
    `DLCTable`), rows, frames (rows,) int64 and whether they increase; the arrays in `folder`
    (xy (rows, K, 2) float64, likelihood (rows, K) float64, unusable (rows, K) uint8)."""

    parts: tuple[str, ...]
    scorer: str
    individual: str | None
    path: Path
    no_likelihood: tuple[str, ...]
    rows: int
    frames: np.ndarray
    increasing: bool
    folder: Path

    def _read(self, name: str, dtype, shape: tuple, rows: np.ndarray | slice) -> np.ndarray:
        if self.rows == 0:
            return np.zeros((0, *shape), dtype=dtype)
        mm = np.memmap(self.folder / name, dtype=dtype, mode="r", shape=(self.rows, *shape))
        out = np.array(mm[rows])
        del mm
        return out

    def table(self, lo: int, hi: int, only: np.ndarray | None = None) -> DLCTable:
        """Its rows with frame numbers in [lo, hi] (`only`: and in that sorted set)."""
        if self.increasing:
            a = np.searchsorted(self.frames, lo, side="left")
            b = np.searchsorted(self.frames, hi, side="right")
            rows: np.ndarray | slice = slice(int(a), int(b))
            frames = self.frames[rows]
            if only is not None:
                keep = np.isin(frames, only)
                rows = np.arange(int(a), int(b))[keep]
                frames = frames[keep]
        else:
            keep = (self.frames >= lo) & (self.frames <= hi)
            if only is not None:
                keep &= np.isin(self.frames, only)
            rows = np.flatnonzero(keep)
            frames = self.frames[rows]
        K = len(self.parts)
        unusable = self._read("unusable", np.uint8, (K,), rows).astype(bool)
        return DLCTable(
            self.parts,
            self._read("xy", np.float64, (K, 2), rows),
            self._read("likelihood", np.float64, (K,), rows),
            self.scorer,
            frames,
            self.individual,
            self.path,
            self.no_likelihood,
            unusable if unusable.any() else None,
        )


class SessionCache:
    """Every camera's detections on disk under `folder` (one pass over each file, in blocks of
    `READ_BLOCK_ROWS` rows); `frames`: (T,) the session's frame numbers (the files' union,
    sorted). `tables(lo, hi)`: the cameras' `DLCTable`s of session rows [lo, hi)."""

    def __init__(self, cameras: Sequence[Camera], paths: dict, individual, folder: Path):
        self.cameras = [c.name for c in cameras]
        self.cams: list[_CameraCache] = []
        for i, name in enumerate(self.cameras):
            self.cams.append(_cache_camera(Path(paths[name]), individual, folder / f"cam{i}"))
        frames = [c.frames for c in self.cams]
        self.frames = np.unique(np.concatenate(frames)) if frames else np.zeros(0, np.int64)

    @property
    def num_frames(self) -> int:
        return int(len(self.frames))

    def tables(
        self, lo: int, hi: int, only: np.ndarray | None = None, windows: dict | None = None
    ) -> list[DLCTable]:
        """The cameras' tables of session rows [lo, hi) (`only`: and in these rows); camera i
        of `windows` ({i: (first frame, last frame)}) instead has its rows in that window of
        its own frame numbers (a camera read at other times: `adjust.clocks`)."""
        want = None if only is None else self.frames[only]
        first, last = int(self.frames[lo]), int(self.frames[hi - 1])
        windows = windows or {}
        return [
            c.table(*windows[i]) if i in windows else c.table(first, last, want)
            for i, c in enumerate(self.cams)
        ]


def _cache_camera(path: Path, individual, folder: Path) -> _CameraCache:
    """One camera's file into `folder` (see `_CameraCache`), read in blocks."""
    folder.mkdir(parents=True)
    if path.suffix.lower() == ".csv" and not is_sleap_file(path):
        blocks = iter_dlc(path, individual, READ_BLOCK_ROWS)
    else:  # H5 / SLEAP: the file whole (one camera at a time)
        blocks = iter([read_table(path, individual)])
    frames, first = [], None
    with (
        open(folder / "xy", "wb") as fxy,
        open(folder / "likelihood", "wb") as flik,
        open(folder / "unusable", "wb") as fbad,
    ):
        for t in blocks:
            if t.frames is not None and t.frames.dtype.kind not in "iu":
                raise NotChunked(f"{path}: frames are named (labelled images), not numbered")
            first = first or t
            np.ascontiguousarray(t.xy, dtype=np.float64).tofile(fxy)
            np.ascontiguousarray(t.likelihood, dtype=np.float64).tofile(flik)
            bad = t.unusable if t.unusable is not None else np.zeros(t.likelihood.shape, bool)
            bad.astype(np.uint8).tofile(fbad)
            n0 = sum(len(f) for f in frames)
            f = t.frames if t.frames is not None else np.arange(t.num_frames)
            frames.append(np.asarray(f, dtype=np.int64) + (0 if t.frames is not None else n0))
    f = np.concatenate(frames) if frames else np.zeros(0, np.int64)
    return _CameraCache(
        first.parts,
        first.scorer,
        first.individual,
        path,
        first.no_likelihood,
        len(f),
        f,
        bool(len(f) < 2 or (np.diff(f) > 0).all()),
        folder,
    )


def count_rows(path: Path, individual) -> int:
    """A camera file's data rows, about (a CSV: its lines less its header; else read)."""
    if path.suffix.lower() == ".csv" and not is_sleap_file(path):
        n = 0
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 24), b""):
                n += block.count(b"\n")
        return max(0, n - 3)
    return read_table(path, individual).num_frames
