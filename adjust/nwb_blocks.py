"""An NWB file's per-frame data written block by block of rows (issue 46): a long session's
tracks (memory-mapped, `adjust.chunk_writer.TracksOnDisk`) go into the file without ever being
whole in memory. Needs hdmf (the ``nwb`` extra); imported by `adjust.export.write_nwb` only."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from hdmf.backends.hdf5.h5_utils import H5DataIO
from hdmf.data_utils import GenericDataChunkIterator

__all__ = ["BLOCK_ROWS", "BlockData", "nanmax_rows", "rows_data"]

#: rows computed and written at a time
BLOCK_ROWS = 50_000


class BlockData(GenericDataChunkIterator):
    """(T, ...) data of `dtype` made block by block: ``fn(a, b)`` returns rows a..b-1 whole."""

    def __init__(self, fn: Callable[[int, int], np.ndarray], shape: tuple, dtype) -> None:
        self._fn, self._shape, self._dtype = fn, tuple(int(s) for s in shape), np.dtype(dtype)
        rows = max(1, min(BLOCK_ROWS, self._shape[0]))
        block = (rows, *self._shape[1:])
        super().__init__(buffer_shape=block, chunk_shape=block, display_progress=False)

    def _get_data(self, selection: tuple[slice, ...]) -> np.ndarray:
        rows = selection[0]
        block = np.asarray(self._fn(int(rows.start), int(rows.stop)), dtype=self._dtype)
        return block[(slice(None), *selection[1:])]

    def _get_maxshape(self) -> tuple:
        return self._shape

    def _get_dtype(self) -> np.dtype:
        return self._dtype


def rows_data(fn: Callable[[int, int], np.ndarray], shape: tuple, dtype, blocks: bool):
    """A dataset's data, rows ``fn(a, b)`` of `shape`: with `blocks` written block by block
    (gzip, as the whole arrays are), else `fn(0, T)` whole (small data stays uncompressed)."""
    if not blocks:
        data = np.ascontiguousarray(np.asarray(fn(0, shape[0]), dtype=dtype))
        if data.size < 4096:
            return data
        return H5DataIO(data=data, compression="gzip", compression_opts=4, shuffle=True)
    return H5DataIO(
        data=BlockData(fn, shape, dtype), compression="gzip", compression_opts=4, shuffle=True
    )


def nanmax_rows(a: np.ndarray) -> float:
    """np.nanmax(a, initial=0), block by block of rows (a memory-mapped array stays on disk)."""
    m = 0.0
    for i in range(0, len(a), BLOCK_ROWS):
        m = max(m, float(np.nanmax(np.asarray(a[i : i + BLOCK_ROWS]), initial=0)))
    return m
