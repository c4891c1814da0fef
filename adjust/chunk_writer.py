"""A long session's outputs, chunk by chunk (`adjust.chunks`, issue 46): the chunks' interiors
appended, in order, to points3d.csv in the run's staged output set (`deformnet.outputs.OutputSet`)
and to raw arrays on disk, from which the sidecar, accepted.npz and tokens.npz are written at
the end, member by member (`npz_from_raw`), never whole in memory."""

from __future__ import annotations

import logging
import shutil
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from adjust.io import write_points3d
from adjust.tokenize import session_tokens
from deformnet.outputs import OutputSet
from deformnet.sessions import VERSION as TOKENS_VERSION
from deformnet.tables import extra_header, extra_path

log = logging.getLogger(__name__)

__all__ = ["ChunkWriter", "TracksOnDisk", "append_lines", "npz_from_raw"]


class TracksOnDisk:
    """points3d.csv's numbers, appended block by block to raw float64 files under `folder`;
    `tracks` reads them back memory-mapped, as `adjust.io.read_points3d` reads the CSV (the
    CSV's floats round-trip exactly), for an NWB file written block by block
    (`adjust.export.write_nwb`'s ``table``)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.rows = 0
        self.K = 0
        self.extra: list[str] = []

    def append(self, parts, points, error, ncams, score, extra: dict) -> None:
        """Rows: points (n, K, 3), error, ncams, score (n, K), extra {name: (n,) or (n, K)}
        (a name with ``{part}``: one column per part, as `write_points3d` writes them)."""
        cols = []
        for name, v in extra.items():
            v = _as_written(v)
            if "{part}" in name:
                cols += [(name.format(part=p), v[:, k]) for k, p in enumerate(parts)]
            else:
                cols.append((name, v))
        self.extra, self.K = [n for n, _ in cols], len(parts)
        for name, v in (
            ("points", points),
            ("error", error),
            ("ncams", ncams),
            ("score", score),
            ("extra", np.stack([v for _, v in cols], -1)),
        ):
            with open(self.folder / f"tracks.{name}", "ab") as fh:
                np.ascontiguousarray(_as_written(v)).tofile(fh)
        self.rows += len(points)

    def tracks(self, parts, fnum: np.ndarray) -> dict:
        """`read_points3d`'s dict of the rows appended, its arrays memory-mapped."""
        T, K = self.rows, self.K

        def mm(name, shape):
            return np.memmap(self.folder / f"tracks.{name}", np.float64, "r", shape=shape)

        extra = mm("extra", (T, len(self.extra)))
        return {
            "parts": tuple(parts),
            "points": mm("points", (T, K, 3)),
            "error": mm("error", (T, K)),
            "ncams": mm("ncams", (T, K)),
            "score": mm("score", (T, K)),
            "fnum": np.asarray(fnum),
            "M": np.eye(3),
            "center": np.zeros(3),
            "extra": {n: extra[:, e] for e, n in enumerate(self.extra)},
        }


def _as_written(v) -> np.ndarray:
    """float64 values as the CSV gives them back: float32 ones through their shortest decimal
    (as pandas writes them), others as they are (float64 decimals round-trip exactly)."""
    v = np.asarray(v)
    if v.dtype == np.float32:
        return v.astype(str).astype(np.float64)
    return v.astype(np.float64)


class ChunkWriter:
    """The chunks' interiors appended, in order, to points3d.csv in the staged output set and
    to raw arrays under `tmp` (its sidecar's rows, accepted.npz's and tokens.npz's arrays);
    `finish` writes the sidecar and the npz files from them; with `nwb`, the numbers also to a
    `TracksOnDisk` (`table`) for the NWB file."""

    def __init__(self, staged: OutputSet, tmp: Path, nwb: bool = False) -> None:
        self.staged, self.tmp = staged, tmp
        self.points = staged.path("points3d.csv")
        self.extra_rows = tmp / "extra.rows"
        self.rows = 0
        self.shape: tuple[int, int] | None = None
        self.tokens = False
        self.body = None
        self.empty = 0  # frames left untracked (add_empty)
        self.table = TracksOnDisk(tmp) if nwb else None  # for the NWB file (output.nwb)

    def add(self, det, cols, a: int, b: int, res, body, cons) -> None:
        part = self.tmp / "chunk.csv"
        extra = {n: np.asarray(v)[a:b] for n, v in cols.extra.items()}
        extra["tracked"] = np.ones(b - a, dtype=np.int64)
        write_points3d(
            part,
            det.parts,
            cols.points[a:b],
            cols.error[a:b],
            cols.ncams[a:b],
            cols.score[a:b],
            extra=extra,
            fnum=det.frames,
        )
        self._append(part, cols.observed[a:b])
        if self.table is not None:
            self.table.append(
                det.parts,
                cols.points[a:b],
                cols.error[a:b],
                cols.ncams[a:b],
                cols.score[a:b],
                extra,
            )
        if cons is not None:
            t = session_tokens(res.poses, body.points, cons, body.parts, body.name)
            deformed = np.where(t.observed[..., None], t.deformed, np.nan)
            for name, v in (
                ("rigid", t.rigid.astype(np.float32)),
                ("deformed", deformed.astype(np.float32)),
                ("observed", t.observed.astype(bool)),
            ):
                with open(self.tmp / f"tokens.{name}", "ab") as fh:
                    np.ascontiguousarray(v).tofile(fh)
            self.tokens = True
        self.body = body
        self.rows += b - a

    def add_empty(self, fnum: np.ndarray, model) -> None:
        """Frames `fnum` (n,) left untracked: empty points (NaN, ``_ncams`` 0), empty extra
        columns (``tracked`` 0), no accepted detection; model: the session's `SessionModel`
        (its parts, cameras and extra columns)."""
        n, parts, C = len(fnum), model.summary["parts"], len(model.summary["cameras"])
        K = len(parts)
        part = self.tmp / "chunk.csv"
        extra = {name: np.full((n, *shape), np.nan) for name, shape in model.columns.items()}
        extra["tracked"] = np.zeros(n, dtype=np.int64)
        nan = np.full((n, K), np.nan)
        write_points3d(
            part,
            parts,
            np.full((n, K, 3), np.nan),
            nan,
            np.zeros((n, K), dtype=np.int64),
            nan,
            extra=extra,
            fnum=np.asarray(fnum),
        )
        self._append(part, np.zeros((n, K, C), dtype=bool))
        if self.table is not None:
            self.table.append(parts, np.full((n, K, 3), np.nan), nan, np.zeros((n, K)), nan, extra)
        self.rows += n
        self.empty += n

    def _append(self, part: Path, observed: np.ndarray) -> None:
        """A chunk's points3d.csv `part` (and its sidecar) and accepted detections appended."""
        first = self.rows == 0
        append_lines(part, self.points, skip=0 if first else 1)
        append_lines(extra_path(part), self.extra_rows, skip=1 if first else 2)
        self.shape = observed.shape[1:]
        with open(self.tmp / "accepted", "ab") as fh:
            np.ascontiguousarray(observed, dtype=bool).tofile(fh)

    def finish(self, parts, cameras, summary: dict) -> None:
        """The sidecar (its first line names points3d.csv's bytes), accepted.npz, tokens.npz
        (not with frames left untracked: its rows are consecutive frames)."""
        out = self.staged
        side = out.path(extra_path(self.points).name)
        with open(side, "w", encoding="utf-8", newline="") as fh:
            fh.write(extra_header(self.points, "points3d.csv"))
        append_lines(self.extra_rows, side, skip=0)
        T, (K, C) = self.rows, self.shape
        npz_from_raw(
            out.path("accepted.npz"),
            [("accepted", self.tmp / "accepted", np.bool_, (T, K, C))],
            {"parts": np.asarray(parts), "cameras": np.asarray(cameras)},
        )
        final = summary["outputs"]
        final["accepted"] = str(out.final("accepted.npz"))
        if self.tokens and self.empty:
            log.warning(
                "tokens.npz is not written: %d frames were left untracked (a gap the tokens' "
                "windows cannot see)",
                self.empty,
            )
        elif self.tokens:
            npz_from_raw(
                out.path("tokens.npz"),
                [
                    ("rigid", self.tmp / "tokens.rigid", np.float32, (T, K, 3)),
                    ("deformed", self.tmp / "tokens.deformed", np.float32, (T, K, 3)),
                    ("observed", self.tmp / "tokens.observed", np.bool_, (T, K)),
                ],
                {  # deformnet.sessions.SessionTokens.save's other members
                    "parts": np.asarray(self.body.parts),
                    "body_points": np.asarray(self.body.points, dtype=np.float64),
                    "body_name": np.asarray(self.body.name),
                    "fps": np.asarray(float("nan")),
                    "version": np.asarray(TOKENS_VERSION),
                },
            )
            final["tokens"] = str(out.final("tokens.npz"))
        final["extra"] = str(out.final(side.name))


def append_lines(src: Path, dst: Path, skip: int) -> None:
    """Append `src`'s bytes after its first `skip` lines to `dst`."""
    with open(src, "rb") as fi, open(dst, "ab") as fo:
        for _ in range(skip):
            fi.readline()
        shutil.copyfileobj(fi, fo, 1 << 20)


def npz_from_raw(path: Path, raw: list[tuple[str, Path, Any, tuple]], small: dict) -> None:
    """A compressed .npz (as `np.savez_compressed` writes it) whose large members are copied
    from raw C-order files in blocks (never whole in memory), then the `small` arrays."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
        for name, src, dtype, shape in raw:
            header = {
                "descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                "fortran_order": False,
                "shape": tuple(int(s) for s in shape),
            }
            with zf.open(f"{name}.npy", "w", force_zip64=True) as fo, open(src, "rb") as fi:
                np.lib.format.write_array_header_2_0(fo, header)
                shutil.copyfileobj(fi, fo, 1 << 22)
        for name, value in small.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as fo:
                np.lib.format.write_array(fo, np.asanyarray(value), allow_pickle=False)
