"""Sessions of any length in bounded memory: `adjust-track` in chunks of frames (issue 46).

A session longer than ``chunk_frames`` frames (``conf/track.yaml``; 0 or null: never chunked)
is tracked in chunks, its peak memory independent of its length (in every deformation mode):

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
   covariance (``deformation=interp``) is estimated within the chunk. A camera the sample
   found on its own clock (`adjust.clocks`) is read at the others' times from its rows over
   the frames its map reads, which may lie beyond the chunk's (`ChunkHooks.load_scene`); a
   camera at a whole multiple of the others' rate (`adjust.rates`) stops the run.
4. The interiors' outputs are streamed into the run's output set (`deformnet.outputs.OutputSet`:
   the folder gets every file at once at the end, or keeps the previous run's): points3d.csv
   and its sidecar (byte for byte what `write_points3d` writes), accepted.npz and tokens.npz
   (written member by member from the disk, `adjust.chunk_writer.npz_from_raw`); summary.json
   merges the chunks' figures (`merge_summaries`: counts summed, fractions and means weighted
   by frames, maxima taken; the medians and p90 of the error statistics are the chunks'
   count-weighted means of them, an approximation) and lists every chunk (``chunked``).
   ``output.nwb=true``: the NWB file is written from the chunks' numbers on disk, block by
   block of rows (`adjust.chunk_writer.TracksOnDisk`, `adjust.export.write_nwb`'s ``table``).

A session no longer than one chunk runs the recipe unchanged (identical results). The net
modes (``deformation=default``, ``self``, a checkpoint) choose their net once, on the sample
(``self`` fine-tunes it there; the gate that may leave the tracks to the interpolation decides
and logs once: `adjust.deformation_modes.NetDecision`), and use it in every chunk.

A chunk in which fewer than two cameras have a usable detection (a camera out for an hour,
the animal away) is not tracked: its frames are left empty in points3d.csv (NaN points,
``_ncams`` 0; points3d.extra.csv's ``tracked`` column 0, 1 elsewhere), named in summary.json
(``untracked``: frames and ranges; ``health.untracked_frames``; every chunk's usable
detections per camera under ``chunked.chunks``) and in the log, and tokens.npz is not written
(its rows are consecutive frames). The run exits 0: the frames it gives are trustworthy, the
empty ones named. A session in which fewer than two cameras have any usable detection is
refused as before (its sample is).

The modules: `adjust.chunk_cache` (the detections on disk), `adjust.chunk_writer` (the outputs,
chunk by chunk), `adjust.chunk_summary` (summary.json).
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
from omegaconf import DictConfig

from adjust.body_fit import SHAPE_FRAMES
from adjust.camera_check import check_from_config, drop_cameras
from adjust.chunk_cache import NotChunked, SessionCache, count_rows
from adjust.chunk_summary import (
    merge_summaries,
    offset_health,
    session_summary,
    untracked_summary,
)
from adjust.chunk_writer import ChunkWriter
from adjust.clocks import read_clocked
from adjust.clocks import window as clock_window
from adjust.deformation_modes import CheckpointNet, NetMode, load_deformation, mode_from_config
from adjust.export import write_nwb
from adjust.io import InputError, load_calibration, load_detections, match_files
from adjust.io.scene import MIN_CAMERAS
from adjust.lens import apply_lens
from adjust.lsq.solver import RESULT_ARRAYS
from adjust.moves import apply_moves
from adjust.pixels import apply as apply_pixel_maps
from adjust.session import with_session
from adjust.settings import required
from adjust.sides import swap as swap_sides
from adjust.subframe import resample
from adjust.summary import report_result, result_summary, track_health
from adjust.sync import row_offsets, shift_cameras
from adjust.track_config import DEFAULT_CHUNK_FRAMES, MIN_CHUNK_FRAMES, ChunkConfig, TrackConfig
from deformnet.outputs import OutputSet
from deformnet.paths import output_dir

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

#: the sample the session-wide quantities come from: this many frames in `SAMPLE_BLOCKS` blocks
SAMPLE_FRAMES = SHAPE_FRAMES
SAMPLE_BLOCKS = 20
#: frames read on either side of a chunk: a tenth of it, within these bounds
MIN_OVERLAP, MAX_OVERLAP = MIN_CHUNK_FRAMES // 2, 1000  # (a chunk holds twice the least)


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


# --- the recipe's hooks --------------------------------------------------------------------


class Untracked(Exception):
    """A chunk in which fewer than two cameras have a usable detection (after the sample's
    camera check): its frames are left empty. usable: {camera: its usable detections}."""

    def __init__(self, usable: dict[str, int]) -> None:
        super().__init__(usable)
        self.usable = usable


@dataclass
class SessionModel:
    """What a long session's sample estimated once, for every chunk: its body model, the
    solver's settings (``sigma_det_px``, ``sigma_def_mm`` set), the rigid observation (the
    parts' deformation moments), few_var (the spread of parts placed from single views, or
    None), the cameras excluded and the camera check's report, the sample's summary, its
    deformation mode (with a net's `NetDecision`) and points3d's extra columns."""

    body: Any
    solver_cfg: Any
    rigid_obs: Any
    few_var: Any
    excluded: tuple[str, ...]
    camera_report: dict
    summary: dict
    mode: Any = None
    #: points3d's extra columns: name -> the shape of a frame's values (`ChunkWriter.add_empty`)
    columns: dict = field(default_factory=dict)

    @property
    def sigma_det_px(self) -> float:
        return float(self.solver_cfg.sigma_det_px)

    def clocks(self) -> dict:
        """{camera: (rate, offset)} of the cameras the sample's check retimed (`adjust.clocks`;
        excluded ones left out)."""
        got = (self.camera_report.get("clocks") or {}).get("retimed") or {}
        return {n: (v["rate"], v["offset"]) for n, v in got.items() if n not in self.excluded}


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
        writer: ChunkWriter | None = None,
    ) -> None:
        self.cache, self.lo, self.hi, self.only = cache, lo, hi, only
        self.model, self.keep, self.writer = model, keep, writer
        self.learned: SessionModel | None = None
        self.mode = None
        self.usable: dict[str, int] = {}

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
        """`adjust.io.load_scene` of this pass's rows; in a chunk, a camera the sample found
        on its own clock (`adjust.clocks`) read at the others' times from its rows over the
        frames its map reads (`adjust.clocks.read_clocked`)."""
        cameras = load_calibration(calibration)
        tables = self.cache.tables(self.lo, self.hi, self.only)
        det = load_detections(
            detections, cameras, body, likelihood_threshold, individual, tables=tables, **kw
        )
        retimed = {} if self.model is None else self.model.clocks()
        if retimed:
            names = [c.name for c in cameras]
            first, last = int(self.cache.frames[self.lo]), int(self.cache.frames[self.hi - 1])
            windows = {
                names.index(n): clock_window(r, o, first, last) for n, (r, o) in retimed.items()
            }
            quiet = logging.getLogger("adjust.io.scene")
            level = quiet.level
            quiet.setLevel(logging.ERROR)  # the chunk's own load said it
            try:
                wide = load_detections(
                    detections, cameras, body, likelihood_threshold, individual,
                    tables=self.cache.tables(self.lo, self.hi, None, windows), **kw,
                )  # fmt: skip
            finally:
                quiet.setLevel(level)
            det = read_clocked(det, wide, retimed)
        return cameras, det

    def check_cameras(self, cameras, det, input_cfg, reference=None):
        """`adjust.camera_check.check_from_config` on the sample; the chunks (read at the
        sample's clocks by `load_scene`) drop the cameras it excluded, map those whose
        detections were on scaled or cropped videos (`adjust.pixels`), swap the left and
        right parts of those labelled the other way round (`adjust.sides`), map those on
        undistorted videos (`adjust.lens`), shift those it
        found out of step (`adjust.sync`), map back those it found moved (`adjust.moves`),
        interpolate those a fraction of a frame out of step (`adjust.subframe`), and report
        it."""
        if self.model is None:
            cams, det, report = check_from_config(cameras, det, input_cfg, reference)
            renumbered = (report.get("rates") or {}).get("renumbered") or {}
            if renumbered:
                raise InputError(
                    f"cameras {sorted(renumbered)} were recorded at another frame rate than "
                    f"the others ({renumbered}); a session tracked in chunks (chunk_frames) is "
                    "cut by frame number and cannot renumber them: resample their files to the "
                    "others' rate, or track the session whole (chunk_frames=0)"
                )
            return cams, det, report
        cams, det = drop_cameras(cameras, det, self.model.excluded)
        mapped = (self.model.camera_report.get("pixels") or {}).get("mapped") or {}
        det = apply_pixel_maps(
            det, {n: (m["scale"], m["offset"]) for n, m in mapped.items() if n in det.cameras}
        )
        swapped = (self.model.camera_report.get("sides") or {}).get("swapped") or {}
        det = swap_sides(det, {n: v["pairs"] for n, v in swapped.items() if n in det.cameras})
        lens = (self.model.camera_report.get("lens") or {}).get("undistorted") or {}
        det = apply_lens(det, cams, lens)  # in the check's order: before the shifts and moves
        sync = self.model.camera_report.get("sync") or {}
        shifts: dict = {n: o for n, o in (sync.get("offsets") or {}).items()}
        shifts.update({n: row_offsets(det, st) for n, st in (sync.get("steps") or {}).items()})
        det = shift_cameras(det, {n: o for n, o in shifts.items() if n in det.cameras})
        det = apply_moves(det, cams, (self.model.camera_report.get("moved") or {}).get("moves"))
        sub = (self.model.camera_report.get("subframe") or {}).get("offsets") or {}
        det = resample(det, {n: o for n, o in sub.items() if n in det.cameras})
        a, b = self.keep
        counts = det.observed[a:b].sum(axis=(0, 1))
        self.usable = {c: int(n) for c, n in zip(det.cameras, counts)}
        if sum(n > 0 for n in self.usable.values()) < MIN_CAMERAS:
            raise Untracked(self.usable)
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
            self.learned.columns = {n: np.shape(v)[1:] for n, v in cols.extra.items()}
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
        summary["usable_per_camera"] = self.usable
        self.writer.add(det_i, cols, a, b, part, body, cons_i)
        return summary


def _interior(res, a: int, b: int):
    """The adjustment result `res` restricted to rows [a, b)."""
    names = (*RESULT_ARRAYS, "poses", "pose_cov", "fitted")
    arrays = {n: getattr(res, n) for n in names}
    return dataclasses.replace(res, **{n: v[a:b] for n, v in arrays.items() if v is not None})


# --- the run -------------------------------------------------------------------------------


def track_long(cfg: DictConfig, track: Callable[..., dict]) -> dict | None:
    """Track the session of `cfg` in chunks (see the module doc) and return its summary; None
    when the recipe is to run it whole: ``chunk_frames`` 0 or null, a session no longer than
    one chunk, frames named rather than numbered. track: the recipe, `adjust.pipeline.track`
    (``track(cfg, chunk=hooks)``)."""
    tc = TrackConfig.from_config(cfg)
    chunk = tc.chunk.chunk_frames
    if not chunk:
        return None
    mode = mode_from_config(tc.deformation)
    if isinstance(mode, CheckpointNet):  # a user's checkpoint is checked before any input
        load_deformation(mode.path)
    cfg = with_session(cfg)
    calibration = required(cfg, "input.calibration", "track")
    detections = required(cfg, "input.detections", "track")
    kwargs = tc.input.load_kwargs()
    cameras = load_calibration(calibration)
    paths = match_files(detections, [c.name for c in cameras], kwargs["pattern"])
    rows = max(count_rows(Path(p), kwargs["individual"]) for p in paths.values())
    if rows <= chunk:
        return None
    t_start = time.perf_counter()
    out = output_dir(cfg)
    with tempfile.TemporaryDirectory(prefix="mousetrack-chunks-") as tmp_name:
        tmp = Path(tmp_name)
        t0 = time.perf_counter()
        try:
            cache = SessionCache(cameras, paths, kwargs["individual"], tmp / "cache")
        except NotChunked as exc:
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
        with OutputSet(out) as staged:
            writer = ChunkWriter(staged, tmp, nwb=tc.output.nwb)
            summaries, frames, facts, untracked = _track_chunks(
                cfg, track, cache, plan, model, writer
            )
            summary = session_summary(
                summaries, frames, model.summary, isinstance(model.mode, NetMode), T
            )
            summary["chunked"] = {
                "chunk_frames": chunk,
                "overlap_frames": overlap_frames(chunk),
                "sample_frames": int(len(sample_rows(T))),
                "chunks": facts,
            }
            if untracked:
                _report_untracked(summary, untracked, cache.frames)
            writer.finish(summary["parts"], summary["cameras"], summary)
            if tc.output.nwb:
                write_nwb(  # from the chunks' numbers on disk, block by block of rows
                    staged.path("tracks.nwb"),
                    staged.path("points3d.csv"),
                    calibration,
                    fps=tc.output.fps,
                    session_start_time=tc.output.session_start_time,
                    subject=tc.output.subject or None,
                    detections=detections,
                    table=writer.table.tracks(summary["parts"], cache.frames),
                )
                summary["outputs"]["nwb"] = str(staged.final("tracks.nwb"))
            summary["time_s"]["read_s"] = round(read_s, 3)
            summary["time_s"]["sample_s"] = round(sample_s, 3)
            summary["time_s"]["total_s"] = round(time.perf_counter() - t_start, 3)
            summary = staged.commit(summary)
        report_result(summary, str(detections), out, cache.frames)
        return summary


def _track_chunks(cfg, track, cache: SessionCache, plan, model: SessionModel, writer):
    """Every chunk of `plan` tracked with the sample's `model`, its interior handed to
    `writer`; a chunk in which fewer than two cameras have a usable detection is left empty
    (`ChunkWriter.add_empty`). Returns (the chunks' summaries, their frames, summary.json's
    ``chunked.chunks``, the untracked chunks' row ranges [a, b))."""
    summaries, frames, facts, untracked = [], [], [], []
    for i, (a, b, ra, rb) in enumerate(plan):
        log.info(
            "chunk %d/%d: frames %d..%d", i + 1, len(plan), cache.frames[a], cache.frames[b - 1]
        )
        hooks = ChunkHooks(cache, ra, rb, model=model, keep=(a - ra, b - ra), writer=writer)
        try:
            s = track(cfg, chunk=hooks)
        except Untracked as why:
            log.warning(
                "chunk %d/%d (frames %d..%d): fewer than %d cameras have a usable detection "
                "(usable detections per camera: %s): its %d frames are left EMPTY in "
                "points3d.csv (points3d.extra.csv: tracked 0; summary.json 'untracked')",
                i + 1,
                len(plan),
                cache.frames[a],
                cache.frames[b - 1],
                MIN_CAMERAS,
                ", ".join(f"'{c}' {n}" for c, n in why.usable.items()),
                b - a,
            )
            writer.add_empty(cache.frames[a:b], model)
            s = untracked_summary(b - a, why.usable, model.summary["health"]["limit_px"])
            untracked.append((a, b))
        except InputError as exc:
            raise InputError(
                f"chunk {i + 1}/{len(plan)} (frames {cache.frames[ra]}..{cache.frames[rb - 1]}): "
                f"{exc}"
            ) from None
        s["health"] = offset_health(s["health"], a)
        summaries.append(s)
        frames.append(b - a)
        facts.append(
            {
                "frames": [int(cache.frames[a]), int(cache.frames[b - 1])],
                "rows_read": [int(cache.frames[ra]), int(cache.frames[rb - 1])],
                "tracked": (a, b) not in untracked,
                "usable_per_camera": s["usable_per_camera"],
                "iterations": s.get("iterations"),
                "rigid_iterations": s.get("rigid_iterations"),
                "converged": s.get("converged"),
                "health": s["health"]["status"],
                "time_s": s["time_s"].get("total_s"),
            }
        )
    if len(untracked) == len(plan):
        raise InputError(
            f"{cfg.input.detections}: no chunk of {plan[0][1] - plan[0][0]} frames has two "
            "cameras with usable detections (summary.json would be empty); a larger "
            "chunk_frames, or 0, tracks the session whole"
        )
    return summaries, frames, facts, untracked


def _report_untracked(summary: dict, untracked: list[tuple[int, int]], fnum: np.ndarray):
    """summary.json's ``untracked`` (and ``health.untracked``): the frames left empty."""
    ranges = [[int(fnum[a]), int(fnum[b - 1])] for a, b in untracked]
    n = int(sum(b - a for a, b in untracked))
    summary["health"]["untracked"] = ranges
    summary["untracked"] = {
        "frames": n,
        "ranges": ranges,
        "reason": f"fewer than {MIN_CAMERAS} cameras with a usable detection in the chunk",
        "policy": "left empty (NaN points, _ncams 0; points3d.extra.csv tracked 0): the rest "
        "of the output can be trusted; tokens.npz is not written (a gap in time)",
    }
    log.warning(
        "%d of %d frames left EMPTY (frames %s): fewer than %d cameras saw the animal in "
        "their chunks (summary.json 'untracked')",
        n,
        summary["num_frames"],
        ", ".join(f"{a}..{b}" for a, b in ranges),
        MIN_CAMERAS,
    )
