"""Sessions of any length in bounded memory: `adjust-track` in chunks of frames (issue 46).

A session longer than ``chunk_frames`` frames (``conf/track.yaml``; 0 or null: never chunked)
whose deformation mode needs no net (``deformation=rigid``, ``interp``) is tracked in chunks,
its peak memory independent of its length:

1. Each camera's file is read once, in blocks of rows (`adjust.io.dlc.iter_dlc`; H5 and SLEAP
   files whole, one camera at a time), into a disk cache (`SessionCache`: float64 as read, and
   the frame numbers, 8 bytes a frame and camera, kept in memory).
2. The session-wide quantities are estimated once, from a sample of `SAMPLE_BLOCKS` evenly
   spaced blocks of frames (`SAMPLE_FRAMES` in all, as many as the body's shape uses,
   `adjust.body_fit.SHAPE_FRAMES`), by the recipe itself (`adjust.pipeline.track` with a
   `ChunkHooks`): the cameras' check (cameras excluded), the detector noise, the body model
   (shape, size, refinement from the rays, the parts' deformation moments) and the solver's
   sigmas (`SessionModel`).
3. Each chunk of ``chunk_frames`` frames runs the recipe with that model, read with
   `overlap_frames` more frames on either side, so the motion-track constraint and interp's
   kriging see across its borders; the chunk's interior is kept (`take`). Its offset
   covariance (``deformation=interp``) is estimated within the chunk.
4. The interiors' outputs are streamed into the run's output set (`deformnet.outputs.OutputSet`:
   the folder gets every file at once at the end, or keeps the previous run's): points3d.csv
   and its sidecar (byte for byte what `write_points3d` writes), accepted.npz and tokens.npz
   (written member by member from the disk, `_npz`); summary.json merges the chunks' figures
   (`merge_summaries`: counts summed, fractions and means weighted by frames, maxima taken;
   the medians and p90 of the error statistics are the chunks' count-weighted means of them,
   an approximation) and lists every chunk (``chunked``).

A session no longer than one chunk runs the recipe unchanged (identical results). The net
modes (``deformation=default``, ``self``, a checkpoint) run whole, their memory growing with the
session; a long session says so in the log (`track_long` returns None). ``output.nwb=true``
writes the NWB file from the whole points3d.csv (not bounded). A chunk in which fewer than two
cameras have a usable detection (e.g. the animal away for a whole chunk) stops the run with an
error naming the chunk's frames (unchunked, such frames are tracked from the model alone): a
larger ``chunk_frames``, or 0, tracks such a session.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import shutil
import tempfile
import time
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
from omegaconf import DictConfig

from adjust.body_fit import SHAPE_FRAMES
from adjust.camera import Camera
from adjust.camera_check import check_from_config, drop_cameras
from adjust.deformation_modes import CheckpointNet, NetMode, load_deformation, mode_from_config
from adjust.export import write_nwb
from adjust.io import InputError, load_calibration, load_detections, match_files, write_points3d
from adjust.io.dlc import DLCTable, iter_dlc
from adjust.io.scene import read_table
from adjust.io.sleap import is_sleap_file
from adjust.lsq.solver import RESULT_ARRAYS
from adjust.session import with_session
from adjust.settings import load_kwargs, required
from adjust.summary import report_result, result_summary, track_health
from adjust.tokenize import session_tokens
from deformnet.confutil import to_plain
from deformnet.outputs import OutputSet
from deformnet.paths import output_dir
from deformnet.sessions import VERSION as TOKENS_VERSION
from deformnet.tables import extra_header, extra_path

log = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_CHUNK_FRAMES",
    "ChunkConfig",
    "ChunkHooks",
    "SessionCache",
    "SessionModel",
    "merge_summaries",
    "overlap_frames",
    "plan_chunks",
    "sample_rows",
    "track_long",
]

#: ``chunk_frames``'s default: frames tracked at a time (conf/track.yaml)
DEFAULT_CHUNK_FRAMES = 50_000
#: the sample the session-wide quantities come from: this many frames in `SAMPLE_BLOCKS` blocks
SAMPLE_FRAMES = SHAPE_FRAMES
SAMPLE_BLOCKS = 20
#: rows of a CSV parsed at a time while the cache is built
READ_BLOCK_ROWS = 50_000
#: frames read on either side of a chunk: a tenth of it, within these bounds
MIN_OVERLAP, MAX_OVERLAP = 64, 1000


@dataclass(frozen=True)
class ChunkConfig:
    """``chunk_frames``: a session longer than this many frames is tracked in chunks of it
    (None or 0: never)."""

    chunk_frames: int | None = DEFAULT_CHUNK_FRAMES

    @classmethod
    def from_config(cls, cfg) -> ChunkConfig:
        value = cfg.get("chunk_frames", DEFAULT_CHUNK_FRAMES)
        if value is None:
            return cls(None)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(
                f"chunk_frames must be a whole number of frames >= 0 (0 or null: never chunk), "
                f"got {value!r}"
            )
        if 0 < value < 2 * MIN_OVERLAP:
            raise ValueError(f"chunk_frames must be 0 or at least {2 * MIN_OVERLAP}, got {value}")
        return cls(int(value) or None)


def overlap_frames(chunk_frames: int) -> int:
    """Frames read on either side of a chunk of `chunk_frames` (its tenth, within
    [`MIN_OVERLAP`, `MAX_OVERLAP`])."""
    return int(min(MAX_OVERLAP, max(MIN_OVERLAP, chunk_frames // 10)))


def plan_chunks(num_frames: int, chunk_frames: int) -> list[tuple[int, int, int, int]]:
    """The chunks of a session of `num_frames` frames: (start, stop, read_start, read_stop)
    row ranges, [start, stop) the chunk's own frames (they tile the session), [read_start,
    read_stop) the rows read (`overlap_frames` more on either side, within the session)."""
    over = overlap_frames(chunk_frames)
    plan = []
    for a in range(0, num_frames, chunk_frames):
        b = min(num_frames, a + chunk_frames)
        plan.append((a, b, max(0, a - over), min(num_frames, b + over)))
    return plan


def sample_rows(num_frames: int) -> np.ndarray:
    """(n,) the rows of the sample the session-wide quantities come from: `SAMPLE_BLOCKS`
    evenly spaced blocks of consecutive frames, `SAMPLE_FRAMES` in all (every row when the
    session is no longer)."""
    if num_frames <= SAMPLE_FRAMES:
        return np.arange(num_frames)
    block = SAMPLE_FRAMES // SAMPLE_BLOCKS
    starts = np.linspace(0, num_frames - block, SAMPLE_BLOCKS).astype(np.int64)
    return np.unique((starts[:, None] + np.arange(block)[None]).reshape(-1))


# --- the detections' cache ---------------------------------------------------------------


class _NotChunked(Exception):
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

    def tables(self, lo: int, hi: int, only: np.ndarray | None = None) -> list[DLCTable]:
        """The cameras' tables of session rows [lo, hi) (`only`: and in these rows)."""
        want = None if only is None else self.frames[only]
        return [c.table(int(self.frames[lo]), int(self.frames[hi - 1]), want) for c in self.cams]


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
                raise _NotChunked(f"{path}: frames are named (labelled images), not numbered")
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


def _count_rows(path: Path, individual) -> int:
    """A camera file's data rows, about (a CSV: its lines less its header; else read)."""
    if path.suffix.lower() == ".csv" and not is_sleap_file(path):
        n = 0
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 24), b""):
                n += block.count(b"\n")
        return max(0, n - 3)
    return read_table(path, individual).num_frames


# --- the recipe's hooks --------------------------------------------------------------------


@dataclass
class SessionModel:
    """What a long session's sample estimated once, for every chunk: its body model, the
    solver's settings (``sigma_det_px``, ``sigma_def_mm`` set), the rigid observation (the
    parts' deformation moments), few_var (the spread of parts placed from single views, or
    None), the cameras excluded and the camera check's report, and the sample's summary."""

    body: Any
    solver_cfg: Any
    rigid_obs: Any
    few_var: Any
    excluded: tuple[str, ...]
    camera_report: dict
    summary: dict
    mode: Any = None

    @property
    def sigma_det_px(self) -> float:
        return float(self.solver_cfg.sigma_det_px)


class ChunkHooks:
    """One pass of `adjust.pipeline.track` over part of a long session: rows [lo, hi) of the
    `SessionCache` (`only`: those of them in this set, the sample). Without a `model` (the
    sample's pass) the recipe estimates the session's quantities and `take` keeps them as
    `learned`; with one (a chunk's pass) the recipe uses them, and `take` hands the interior
    [keep_lo, keep_hi) (rows of the pass) to `writer`."""

    def __init__(
        self,
        cache: SessionCache,
        lo: int,
        hi: int,
        *,
        only: np.ndarray | None = None,
        model: SessionModel | None = None,
        keep: tuple[int, int] | None = None,
        writer: _ChunkWriter | None = None,
    ) -> None:
        self.cache, self.lo, self.hi, self.only = cache, lo, hi, only
        self.model, self.keep, self.writer = model, keep, writer
        self.learned: SessionModel | None = None
        self.mode = None

    def deformation_mode(self, mode):
        """The recipe's deformation mode: the sample's own (its choice of net, a
        `NetDecision`, made there once) in every chunk."""
        if self.model is None:
            self.mode = mode
            return mode
        return self.model.mode

    def load_scene(
        self, calibration, detections, body, likelihood_threshold=0.5, individual=None, **kw
    ):
        """`adjust.io.load_scene` of this pass's rows."""
        cameras = load_calibration(calibration)
        tables = self.cache.tables(self.lo, self.hi, self.only)
        det = load_detections(
            detections, cameras, body, likelihood_threshold, individual, tables=tables, **kw
        )
        return cameras, det

    def check_cameras(self, cameras, det, input_cfg):
        """`adjust.camera_check.check_from_config` on the sample; the chunks drop the cameras
        it excluded and report it."""
        if self.model is None:
            return check_from_config(cameras, det, input_cfg)
        cams, det = drop_cameras(cameras, det, self.model.excluded)
        return cams, det, self.model.camera_report

    def take(self, summary: dict, *, res, cols, det, cons, body, solver_cfg, rigid_obs, few_var):
        """The recipe's result of this pass (instead of its outputs): kept as the session's
        model (the sample), or its interior written (a chunk); returns the pass's summary."""
        if self.model is None:
            report = summary.get("camera_check") or {}
            excluded = [*report.get("excluded_by_hand", []), *(report.get("excluded") or {})]
            self.learned = SessionModel(
                body, solver_cfg, rigid_obs, few_var, tuple(excluded), report, summary, self.mode
            )
            return summary
        a, b = self.keep
        part = _interior(res, a, b)
        det_i = dataclasses.replace(
            det,
            xy=det.xy[a:b],
            likelihood=det.likelihood[a:b],
            frames=None if det.frames is None else det.frames[a:b],
        )
        cons_i = None
        if cons is not None:
            cons_i = SimpleNamespace(points=cons.points[a:b], observed=cons.observed[a:b])
            summary["stochastic"].update(
                observed_3d_fraction=float(cons.observed[a:b].mean()),
                outvoted_detections=int(cons.dropped[a:b].sum()),
            )
        summary.update(result_summary(part, det_i, cols.error[a:b], cols.view_err[a:b]))
        summary["health"] = track_health(
            cols.points[a:b],
            cols.view_err[a:b],
            solver_cfg.sigma_det_px,
            poses=part.poses,
        )
        summary["num_frames"] = b - a
        self.writer.add(det_i, cols, a, b, part, body, cons_i)
        return summary


def _interior(res, a: int, b: int):
    """The adjustment result `res` restricted to rows [a, b)."""
    names = (*RESULT_ARRAYS, "poses", "pose_cov", "fitted")
    arrays = {n: getattr(res, n) for n in names}
    return dataclasses.replace(res, **{n: v[a:b] for n, v in arrays.items() if v is not None})


# --- the outputs, chunk by chunk ----------------------------------------------------------


class _ChunkWriter:
    """The chunks' interiors appended, in order, to points3d.csv in the staged output set and
    to raw arrays under `tmp` (its sidecar's rows, accepted.npz's and tokens.npz's arrays);
    `finish` writes the sidecar and the npz files from them."""

    def __init__(self, staged: OutputSet, tmp: Path) -> None:
        self.staged, self.tmp = staged, tmp
        self.points = staged.path("points3d.csv")
        self.extra_rows = tmp / "extra.rows"
        self.rows = 0
        self.shape: tuple[int, int] | None = None
        self.tokens = False
        self.body = None
        self.hash = hashlib.sha256()

    def add(self, det, cols, a: int, b: int, res, body, cons) -> None:
        part = self.tmp / "chunk.csv"
        extra = {n: np.asarray(v)[a:b] for n, v in cols.extra.items()}
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
        first = self.rows == 0
        _append_lines(part, self.points, skip=0 if first else 1)
        _append_lines(extra_path(part), self.extra_rows, skip=1 if first else 2)
        observed = cols.observed[a:b]
        self.shape = observed.shape[1:]
        with open(self.tmp / "accepted", "ab") as fh:
            np.ascontiguousarray(observed, dtype=bool).tofile(fh)
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

    def finish(self, parts, cameras, summary: dict) -> None:
        """The sidecar (its first line names points3d.csv's bytes), accepted.npz, tokens.npz."""
        out = self.staged
        side = out.path(extra_path(self.points).name)
        with open(side, "w", encoding="utf-8", newline="") as fh:
            fh.write(extra_header(self.points, "points3d.csv"))
        _append_lines(self.extra_rows, side, skip=0)
        T, (K, C) = self.rows, self.shape
        _npz(
            out.path("accepted.npz"),
            [("accepted", self.tmp / "accepted", np.bool_, (T, K, C))],
            {"parts": np.asarray(parts), "cameras": np.asarray(cameras)},
        )
        final = summary["outputs"]
        final["accepted"] = str(out.final("accepted.npz"))
        if self.tokens:
            _npz(
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


def _append_lines(src: Path, dst: Path, skip: int) -> None:
    """Append `src`'s bytes after its first `skip` lines to `dst`."""
    with open(src, "rb") as fi, open(dst, "ab") as fo:
        for _ in range(skip):
            fi.readline()
        shutil.copyfileobj(fi, fo, 1 << 20)


def _npz(path: Path, raw: list[tuple[str, Path, Any, tuple]], small: dict) -> None:
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


# --- the summary ---------------------------------------------------------------------------

#: summary keys merged by their maximum (iterations are the most any chunk took)
_MAX_KEYS = frozenset({"iterations", "rigid_iterations", "max", "limit_px"})
_STATS_KEYS = frozenset({"count", "median", "mean", "p90", "max"})


def merge_summaries(parts: Sequence[dict], frames: Sequence[int]) -> dict:
    """One summary of the chunks' summaries `parts` (each of its own `frames`, the interior):
    booleans all true, ``iterations`` the largest, other whole numbers summed, costs summed,
    other numbers weighted by frames; error statistics (count, median, mean, p90, max): counts
    summed, means weighted by count, maxima taken, median and p90 the count-weighted means of
    the chunks' (an approximation); ``health`` the worst status with its frames (rows of the
    session); lists of numbers element by element; anything else the first chunk's."""
    return _merge(list(parts), [float(f) for f in frames], "")


def _merge(values: list, weights: list[float], key: str):
    pairs = [(v, w) for v, w in zip(values, weights) if v is not None]
    if not pairs:
        return None
    values, weights = [v for v, _ in pairs], [w for _, w in pairs]
    first = values[0]
    if key == "health":
        return _merge_health(values)
    if key == "cost_history":
        return list(values)
    if isinstance(first, dict):
        if set(first) == _STATS_KEYS:
            return _merge_stats(values)
        keys = dict.fromkeys(k for v in values if isinstance(v, dict) for k in v)
        return {
            k: _merge([v.get(k) for v in values], weights, k)
            for k in keys
            if all(isinstance(v, dict) for v in values)
        }
    if isinstance(first, bool):
        return all(bool(v) for v in values)
    if isinstance(first, (int, float)) and all(isinstance(v, (int, float)) for v in values):
        if key in _MAX_KEYS:
            return max(values)
        if isinstance(first, int) or "cost" in str(key):
            return sum(values)
        finite = [(v, w) for v, w in zip(values, weights) if math.isfinite(v)]
        if not finite:
            return first
        return float(sum(v * w for v, w in finite) / max(sum(w for _, w in finite), 1e-300))
    if (
        isinstance(first, list)
        and first
        and all(isinstance(v, list) and len(v) == len(first) for v in values)
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) for v in values for x in v)
    ):
        columns = [list(c) for c in zip(*values)]
        return [_merge(c, weights, key) for c in columns]
    return first


def _merge_stats(values: list[dict]) -> dict:
    have = [v for v in values if v.get("count")]
    if not have:
        return values[0]
    n = sum(v["count"] for v in have)
    out = {"count": n, "max": max(v["max"] for v in have)}
    for k in ("median", "mean", "p90"):
        out[k] = float(sum(v[k] * v["count"] for v in have) / n)
    return {k: out[k] for k in ("count", "median", "mean", "p90", "max")}


def _merge_health(values: list[dict]) -> dict:
    order = {"ok": 0, "suspect": 1, "failed": 2}
    worst = max(values, key=lambda h: order.get(h.get("status"), 0))
    out = dict(worst)
    for k in ("bad_frames", "nonfinite_frames", "turn_frames_count"):
        out[k] = int(sum(h.get(k, 0) for h in values))
    for k in ("frames", "turn_frames"):
        out[k] = [f for h in values for f in h.get(k, [])][:20]
    out["limit_px"] = max(h["limit_px"] for h in values)
    return out


# --- the run -------------------------------------------------------------------------------


def track_long(cfg: DictConfig, track: Callable[..., dict]) -> dict | None:
    """Track the session of `cfg` in chunks (see the module doc) and return its summary; None
    when the recipe is to run it whole: ``chunk_frames`` 0 or null, a session no longer than
    one chunk, a deformation mode that needs a net (said in the log), frames named rather
    than numbered. track: the recipe, `adjust.pipeline.track` (``track(cfg, chunk=hooks)``)."""
    chunk = ChunkConfig.from_config(cfg).chunk_frames
    if not chunk:
        return None
    mode = mode_from_config(cfg.get("deformation"))
    if isinstance(mode, CheckpointNet):  # a user's checkpoint is checked before any input
        load_deformation(mode.path)
    cfg = with_session(cfg)
    calibration = required(cfg, "input.calibration", "track")
    detections = required(cfg, "input.detections", "track")
    kwargs = load_kwargs(cfg.input)
    cameras = load_calibration(calibration)
    paths = match_files(detections, [c.name for c in cameras], kwargs["pattern"])
    rows = max(_count_rows(Path(p), kwargs["individual"]) for p in paths.values())
    if rows <= chunk:
        return None
    t_start = time.perf_counter()
    out = output_dir(cfg)
    with tempfile.TemporaryDirectory(prefix="mousetrack-chunks-") as tmp_name:
        tmp = Path(tmp_name)
        t0 = time.perf_counter()
        try:
            cache = SessionCache(cameras, paths, kwargs["individual"], tmp / "cache")
        except _NotChunked as exc:
            log.info("%s: tracked whole", exc)
            return None
        T = cache.num_frames
        if T <= chunk:
            return None
        read_s = time.perf_counter() - t0
        plan = plan_chunks(T, chunk)
        log.info(
            "a long session: %d frames in %d chunks of %d (chunk_frames; %d frames of overlap "
            "each side); the body model, detector noise and cameras from a sample of %d frames",
            T,
            len(plan),
            chunk,
            overlap_frames(chunk),
            min(T, SAMPLE_FRAMES),
        )
        t0 = time.perf_counter()
        sample = ChunkHooks(cache, 0, T, only=sample_rows(T))
        track(cfg, chunk=sample)
        model = sample.learned
        sample_s = time.perf_counter() - t0
        summaries, frames, chunks_facts = [], [], []
        with OutputSet(out) as staged:
            writer = _ChunkWriter(staged, tmp)
            for i, (a, b, ra, rb) in enumerate(plan):
                log.info(
                    "chunk %d/%d: frames %d..%d",
                    i + 1,
                    len(plan),
                    cache.frames[a],
                    cache.frames[b - 1],
                )
                hooks = ChunkHooks(cache, ra, rb, model=model, keep=(a - ra, b - ra), writer=writer)
                try:
                    s = track(cfg, chunk=hooks)
                except InputError as exc:  # e.g. a chunk without two cameras' detections
                    raise InputError(
                        f"chunk {i + 1}/{len(plan)} (frames {cache.frames[ra]}.."
                        f"{cache.frames[rb - 1]}): {exc}"
                    ) from None
                s["health"] = _offset_health(s["health"], a)
                summaries.append(s)
                frames.append(b - a)
                chunks_facts.append(
                    {
                        "frames": [int(cache.frames[a]), int(cache.frames[b - 1])],
                        "rows_read": [int(cache.frames[ra]), int(cache.frames[rb - 1])],
                        "iterations": s.get("iterations"),
                        "rigid_iterations": s.get("rigid_iterations"),
                        "converged": s.get("converged"),
                        "health": s["health"]["status"],
                        "time_s": s["time_s"].get("total_s"),
                    }
                )
            summary = _session_summary(summaries, frames, model, T)
            summary["chunked"] = {
                "chunk_frames": chunk,
                "overlap_frames": overlap_frames(chunk),
                "sample_frames": int(len(sample_rows(T))),
                "chunks": chunks_facts,
            }
            writer.finish(summary["parts"], summary["cameras"], summary)
            if cfg.output.get("nwb", False):
                log.warning("output.nwb=true: the NWB file is written from the whole points3d.csv")
                write_nwb(
                    staged.path("tracks.nwb"),
                    staged.path("points3d.csv"),
                    calibration,
                    fps=cfg.output.get("fps"),
                    session_start_time=cfg.output.get("session_start_time"),
                    subject=to_plain(cfg.output.get("subject")) or None,
                    detections=detections,
                )
                summary["outputs"]["nwb"] = str(staged.final("tracks.nwb"))
            summary["time_s"]["read_s"] = round(read_s, 3)
            summary["time_s"]["sample_s"] = round(sample_s, 3)
            summary["time_s"]["total_s"] = round(time.perf_counter() - t_start, 3)
            summary = staged.commit(summary)
        report_result(summary, str(detections), out, cache.frames)
        return summary


def _offset_health(health: dict, a: int) -> dict:
    """A chunk's health with its frames as rows of the session (the chunk starts at row a)."""
    return {
        **health,
        "frames": [f + a for f in health.get("frames", [])],
        "turn_frames": [f + a for f in health.get("turn_frames", [])],
    }


#: summary.json's ``deformation`` keys of a net mode's choice (`NetDecision`), the sample's
_DECISION_KEYS = frozenset(
    {"mode", "requested", "reason", "checkpoint", "window", "step", "adapt", "world_up", "heldout"}
)


def _session_summary(summaries: list[dict], frames: list[int], model: SessionModel, T: int):
    """The session's summary: the chunks' merged (`merge_summaries`), the sample's body model,
    camera check and detector noise."""
    merged = merge_summaries(summaries, frames)
    first = summaries[0]
    for key in ("inputs", "cameras", "parts", "settings", "outputs"):
        merged[key] = first[key]
    sample = model.summary
    merged["body"] = sample["body"]
    merged["camera_check"] = sample["camera_check"]
    if merged.get("stochastic") is not None and sample.get("stochastic") is not None:
        merged["stochastic"]["sigma_det_px"] = sample["stochastic"]["sigma_det_px"]
        merged["stochastic"]["sigma_det_px_per_camera"] = sample["stochastic"][
            "sigma_det_px_per_camera"
        ]
    if isinstance(model.mode, NetMode):  # the net's choice, made once on the sample
        chosen = {k: v for k, v in sample["deformation"].items() if k in _DECISION_KEYS}
        merged["deformation"] = {**merged["deformation"], **chosen, "decided_on": "sample"}
    merged["num_frames"] = T
    merged["time_s"] = {
        k: round(sum(s["time_s"].get(k, 0.0) for s in summaries), 3) for k in first["time_s"]
    }
    return merged
