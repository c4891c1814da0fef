"""NWB export of 3D tracks (Neurodata Without Borders, the DANDI archive's format), with ndx-pose.

`write_nwb` turns an ``adjust-track`` output (``points3d.csv``, anipose's layout plus our pose and
uncertainty columns) into one NWB file that DANDI accepts (nwbinspector: no CRITICAL, no
BEST_PRACTICE_VIOLATION when the subject is described):

- ``processing/behavior/PoseEstimation``: an ndx-pose ``MultiCameraPoseEstimation`` (named as
  ndx-pose's readers, e.g. movement's ``from_nwb_file``, look for it) holding one
  ``PoseEstimationSeries`` per part (``data`` (T, 3) in mm with ``unit="meters"``,
  ``conversion=0.001``, in the calibration's world frame or the frame of an axes alignment;
  ``confidence`` (T,) = ``{part}_ncams`` / number of cameras: the share of cameras with an
  accepted detection of the part, 0 for a part placed by the body model alone), and one
  ``PoseEstimation`` per camera linking its ``CalibratedCamera`` device (intrinsics, world ->
  camera rotation and translation in the points' frame, distortion: the calibration as
  metadata);
- ``processing/behavior/Skeletons``: the skeleton (nodes = parts; edges from the input:
  `adjust.io.skeleton.resolve_skeleton`: given edges, a ``skeleton.csv`` or SLEAP file, the
  session's SLEAP files, the minimum spanning tree last);
- ``processing/behavior``: ``TimeSeries`` with the quality columns, (T, K) one column per part:
  ``reprojection_error_px``, ``ncams``, ``score``, ``sigma_mm`` (the 3D standard error, the
  ``{part}_sigma`` columns; mm, ``unit="meters"``, ``conversion=0.001``), and ``body_pose``
  (T, 6: Rodrigues rad, translation mm), ``body_pose_sigma`` (T, 2: rad, mm), ``frame_number``
  (T,), where the CSV has them;
- ``intervals/behavior_bouts`` and ``intervals/lockbox_events``: ``TimeIntervals`` from a bouts
  CSV (``start, stop, label[, ...]``) and a lock-box events CSV (``start, stop, part, mechanism,
  ...``) when given; every further column is kept;
- ``general/subject``: `subject_metadata` (``subject_id``, ``species``, ``sex``, ``age``, ...;
  what DANDI requires and is missing is logged as a warning; nothing is invented).

Times: frame ``fnum`` is at ``starting_time + fnum / fps`` s after ``session_start_time``;
consecutive (or evenly spaced) frame numbers are stored as ``starting_time`` + ``rate``, others
as timestamps. Interval ``start``/``stop`` are frame numbers (``intervals_unit="frames"``,
converted the same way) or seconds. The frame rate comes from ``fps`` or the calibration's
``[metadata] fps``; ``session_start_time`` from the argument or the calibration's ``[metadata]
session_start_time`` (`session_start`); without either the export is refused, naming the setting
(the export time is never used).

The subject, session start, frame times and interval tables are checked and read by
`adjust.nwb_metadata`.

Needs the optional extra ``nwb`` (``pip install mousetrack[nwb]``: pynwb, ndx-pose); this module
imports them only when called.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
import os
import uuid
from collections.abc import Mapping, Sequence
from importlib.metadata import version
from pathlib import Path

import numpy as np

from adjust.io import load_calibration, load_calibration_metadata, read_points3d, write_points3d
from adjust.io.errors import InputError
from adjust.io.skeleton import resolve_skeleton, spanning_edges
from adjust.kinematics import BoardFrame, align_tracks
from adjust.nwb_metadata import (
    SUBJECT_KEYS,
    file_metadata,
    frame_timing,
    read_intervals,
    recording_rate,
    session_start,
    subject_metadata,
)
from deformnet.atomic import atomic_path
from deformnet.behavior.tracks import POSE_COLUMNS

log = logging.getLogger(__name__)

__all__ = [
    "read_nwb_tracks",
    "write_anipose",
    "session_start",
    "spanning_edges",
    "subject_metadata",
    "write_nwb",
]

#: the NWB objects this module writes; POSE_NAME is what ndx-pose readers (movement) look for
POSE_NAME = "PoseEstimation"
LEGACY_POSE_NAMES = ("PoseEstimation3D",)  # earlier exports, still read by read_nwb_tracks
#: ndx-pose's Skeleton stores edges as uint8 node indices: edges only up to this many parts
MAX_SKELETON_NODES = 256
BOUTS_NAME = "behavior_bouts"
EVENTS_NAME = "lockbox_events"
BOUTS_COLUMNS = ("start", "stop", "label")
EVENTS_COLUMNS = ("start", "stop", "part", "mechanism")
#: positions and sigmas are written in mm with this conversion to NWB's unit, meters
MM = 0.001


def _require_nwb():
    try:
        import ndx_pose  # noqa: F401
        import pynwb  # noqa: F401
    except ImportError as exc:  # pragma: no cover - the extra is part of the test install
        raise InputError(
            f"NWB export needs pynwb and ndx-pose: pip install 'mousetrack[nwb]' ({exc})"
        ) from None


def _intervals(name: str, description: str, start, stop, extra: dict, docs: dict):
    from pynwb.epoch import TimeIntervals

    table = TimeIntervals(name=name, description=description)
    for col in extra:
        table.add_column(name=col, description=docs.get(col, f"column '{col}' of the CSV"))
    for i in range(len(start)):
        row = {}
        for col, values in extra.items():
            v = values[i]
            if isinstance(v, np.generic):
                v = v.item()
            if isinstance(v, float) and math.isnan(v):
                v = float("nan")
            elif not isinstance(v, int | float | bool):
                v = "" if v is None else str(v)
            row[col] = v
        table.add_row(start_time=float(start[i]), stop_time=float(stop[i]), **row)
    return table


def _compressed(data: np.ndarray):
    from hdmf.backends.hdf5.h5_utils import H5DataIO

    data = np.ascontiguousarray(data)
    if data.size < 4096:
        return data
    return H5DataIO(data=data, compression="gzip", compression_opts=4, shuffle=True)


def write_nwb(
    path: str | os.PathLike,
    tracks: str | os.PathLike,
    calibration: str | os.PathLike | None = None,
    fps: float | None = None,
    bouts: str | os.PathLike | None = None,
    events: str | os.PathLike | None = None,
    intervals_unit: str = "frames",
    edges: Sequence[Sequence[str]] | None = None,
    session_description: str = "3D mouse tracks (mousetrack adjust-track)",
    identifier: str | None = None,
    session_start_time: str | _dt.datetime | None = None,
    subject: Mapping | None = None,
    starting_time: float = 0.0,
    skeleton: str | os.PathLike | None = None,
    detections: str | os.PathLike | None = None,
    axes: Mapping[str, Sequence] | BoardFrame | None = None,
    origin=None,
    metadata: Mapping | None = None,
    table: Mapping | None = None,
) -> Path:
    """Write the tracks of ``points3d.csv`` (and the optional calibration, bouts and events) as
    an NWB file at ``path`` (atomically). Returns the path. See the module doc for the layout.

    session_start_time: ISO 8601 (a naive time is taken as UTC) or a datetime; default: the
    calibration's ``[metadata] session_start_time``, else an InputError (`session_start`).
    subject: ``{subject_id, species, sex, age, strain, genotype, description}``
    (`subject_metadata`).
    edges / skeleton / detections: the skeleton's sources (`resolve_skeleton`: pairs of part
    names, a ``skeleton.csv`` or SLEAP file, the session's detection folder).
    axes, origin: an axes alignment applied to the points, body pose and cameras
    (`adjust.kinematics.align_tracks`: named points, or a calibration board's `BoardFrame`,
    whose fit is recorded in the file's notes). metadata: further NWBFile fields (`FILE_KEYS`:
    experimenter, institution, lab, experiment_description, keywords, session_id).
    table: the tracks already read (`read_points3d`'s mapping; memory-mapped arrays, e.g. a
    long session's, `adjust.chunk_writer.TracksOnDisk`): written block by block of rows, never
    whole in memory; `tracks` then only names them.
    identifier: default a fresh UUID. Raises `InputError` for unreadable or inconsistent inputs
    (naming the file) and missing required metadata (naming the setting)."""
    _require_nwb()
    from ndx_pose import (
        CalibratedCamera,
        MultiCameraPoseEstimation,
        PoseEstimation,
        PoseEstimationSeries,
        Skeleton,
        Skeletons,
    )
    from pynwb import NWBHDF5IO, NWBFile, TimeSeries
    from pynwb.file import Subject

    # (hdmf comes with pynwb, the optional nwb extra: imported with it)
    from adjust.nwb_blocks import nanmax_rows, rows_data

    tracks = Path(tracks)
    # a file without part columns is an error there
    d = read_points3d(tracks) if table is None else dict(table)
    blocks = table is not None  # memory-mapped columns: written block by block of rows
    parts = list(d["parts"])
    T, K = d["points"].shape[:2]
    cameras, meta = [], {}
    if calibration is not None:
        cameras = load_calibration(calibration)
        meta = load_calibration_metadata(calibration)
    rate = recording_rate(fps, meta)
    start, start_source = session_start(session_start_time, meta, calibration)
    subject_kwargs = subject_metadata(subject)
    file_kwargs = file_metadata(metadata)
    fnum = np.asarray(d["fnum"])
    try:
        fnum_s = fnum.astype(np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{tracks}: fnum must be frame numbers, got {fnum[:3].tolist()}") from None
    if not np.all(np.isfinite(fnum_s)):
        raise InputError(f"{tracks}: non-finite fnum")
    if T > 1 and np.any(np.diff(fnum_s) <= 0):
        raise InputError(f"{tracks}: fnum must increase from row to row")
    timing = frame_timing(fnum_s, rate, starting_time)
    ncams = d["ncams"]
    most = nanmax_rows(ncams)
    num_cams = len(cameras) if cameras else int(most)
    if cameras and most > len(cameras):
        raise InputError(
            f"{tracks}: up to {int(most)} cameras per part, but {calibration} has {len(cameras)}"
        )
    pairs, skeleton_source = resolve_skeleton(parts, d["points"], edges, skeleton, detections)
    if len(parts) > MAX_SKELETON_NODES and len(pairs):  # ndx-pose: edges are uint8 indices
        log.warning(
            "%s: %d parts; ndx-pose stores a skeleton's edges as node indices 0..%d, so the "
            "NWB skeleton lists the parts without edges (the tracks are all written)",
            tracks,
            len(parts),
            MAX_SKELETON_NODES - 1,
        )
        pairs, skeleton_source = [], f"{skeleton_source} (edges left out: > 256 parts)"
    d = align_tracks(d, axes, origin)
    points, M, center = d["points"], d["M"], d["center"]
    aligned = not (np.array_equal(M, np.eye(3)) and np.array_equal(center, np.zeros(3)))

    notes = {
        "tracks": str(tracks.resolve()),
        "calibration": None if calibration is None else str(Path(calibration).resolve()),
        "calibration_metadata": meta,
        "fps": rate,
        "session_start_time_source": start_source,
        "skeleton_source": skeleton_source,
        "axes": {
            "M": M.tolist(),
            "center_mm": center.tolist(),
            **({"board": axes.summary()} if isinstance(axes, BoardFrame) else {}),
        }
        if aligned
        else None,
    }
    nwb = NWBFile(
        session_description=session_description,
        identifier=identifier or str(uuid.uuid4()),
        session_start_time=start,
        notes=json.dumps(notes, default=str),
        source_script="mousetrack adjust.export.write_nwb",
        source_script_file_name=str(Path(__file__).name),
        **file_kwargs,
    )
    if subject_kwargs is not None:
        nwb.subject = Subject(**subject_kwargs)

    # --- cameras: the calibration as metadata, in the points' frame ---------------------
    devices = []
    for cam in cameras:
        R, t = np.asarray(cam.R, dtype=np.float64), np.asarray(cam.tvec, dtype=np.float64)
        if aligned:  # X_world = M^T (X + center): x_cam = (R M^T) X + (t + R M^T center)
            R, t = R @ M.T, t + R @ M.T @ center
        dev = CalibratedCamera(
            name=cam.name,
            description=f"calibrated camera, image size {cam.size[0]} x {cam.size[1]} px; "
            "x_cam = R X + t (mm, X in the frame of the pose series), "
            + (
                "OpenCV's fisheye model (cv2.fisheye), distortion k1 k2 k3 k4 0"
                if cam.fisheye
                else "pinhole with OpenCV distortion k1 k2 p1 p2 k3"
            ),
            intrinsic_matrix=np.asarray(cam.K, dtype=np.float64),
            rotation_matrix=R,
            translation_vector=t,
            distortion_coefficients=np.asarray(cam.dist, dtype=np.float64),
        )
        nwb.add_device(dev)
        devices.append(dev)

    # --- skeleton and pose -------------------------------------------------------------
    behavior = nwb.create_processing_module(
        name="behavior", description="3D body-part tracks from multi-camera 2D detections"
    )
    skel = Skeleton(
        name="subject",
        nodes=parts,
        edges=np.asarray(pairs, dtype=np.uint8).reshape(-1, 2) if len(pairs) else None,
    )
    behavior.add(Skeletons(skeletons=[skel]))
    if aligned:
        frame = (
            "axes-aligned frame (anipose's triangulation.axes): X = M X_world - center, with "
            f"M = {np.round(M, 9).tolist()}, center = {np.round(center, 6).tolist()} mm, "
            "X_world the camera calibration's world frame (x_cam = R X_world + t)"
        )
    else:
        frame = "world frame of the camera calibration (x_cam = R X + t)"
    series = []

    def conf(a: int, b: int, k: int) -> np.ndarray:
        n = np.asarray(ncams[a:b, k], dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(np.isfinite(n), n / max(num_cams, 1), 0.0)

    for k, part in enumerate(parts):
        series.append(
            PoseEstimationSeries(
                name=part,
                description=f"3D position of {part} (x, y, z; data in mm, conversion to meters)",
                data=rows_data(lambda a, b, k=k: points[a:b, k], (T, 3), np.float64, blocks),
                unit="meters",
                conversion=MM,
                reference_frame=frame,
                **_time_kwargs(timing, series),
                confidence=rows_data(lambda a, b, k=k: conf(a, b, k), (T,), np.float64, blocks),
                confidence_definition=(
                    f"share of the {num_cams} cameras with an accepted detection of the part "
                    "({part}_ncams / cameras); 0: placed by the body model alone. The 3D standard "
                    "error is in processing/behavior/sigma_mm"
                ),
            )
        )
    views = [
        PoseEstimation(
            name=f"camera_{dev.name}",
            description=f"2D view of camera {dev.name} (its detections were inputs)",
            device=dev,
            skeleton=skel,
            source_software="mousetrack",
        )
        for dev in devices
    ]
    pose = MultiCameraPoseEstimation(
        name=POSE_NAME,
        description="3D pose: pose-track adjustment of a body model to incomplete multi-camera "
        "detections (mousetrack adjust-track); each part fused from its own detections and the "
        "model",
        pose_estimation_series=series,
        pose_estimations=views or None,
        scorer="mousetrack",
        source_software="mousetrack",
        source_software_version=_version(),
        skeleton=skel,
    )
    behavior.add(pose)

    # --- quality columns ---------------------------------------------------------------
    cols = ", ".join(parts)
    quality = [  # (name, rows a..b-1 of its (T, K) data, unit, conversion, description)
        ("reprojection_error_px", d["error"].__getitem__, "pixels", 1.0, "mean reprojection error"),
        ("ncams", ncams.__getitem__, "cameras", 1.0, "cameras with an accepted detection"),
        ("score", d["score"].__getitem__, "likelihood", 1.0, "lowest detection likelihood used"),
    ]
    extra = d["extra"]
    sig = [f"{p}_sigma" for p in parts]
    if all(s in extra for s in sig):
        quality.append(
            (
                "sigma_mm",
                lambda rows: np.stack([extra[s][rows] for s in sig], -1),
                "meters",
                MM,
                "3D standard error (root of the trace of the 3x3 covariance; data in mm)",
            )
        )
    for name, data, unit, conversion, what in quality:
        behavior.add(
            TimeSeries(
                name=name,
                description=f"{what}; columns: {cols}",
                data=rows_data(lambda a, b, f=data: f(slice(a, b)), (T, K), np.float64, blocks),
                unit=unit,
                conversion=conversion,
                **_time_kwargs(timing, series),
            )
        )
    if all(c in extra for c in POSE_COLUMNS):
        behavior.add(
            TimeSeries(
                name="body_pose",
                description="body model pose, model -> the points' frame: Rodrigues vector "
                "(rad) rx, ry, rz and translation (mm) tx, ty, tz",
                data=rows_data(
                    lambda a, b: np.stack([extra[c][a:b] for c in POSE_COLUMNS], -1),
                    (T, len(POSE_COLUMNS)),
                    np.float64,
                    blocks,
                ),
                unit="rad, mm",
                **_time_kwargs(timing, series),
            )
        )
    if "pose_sigma_r" in extra and "pose_sigma_t" in extra:
        behavior.add(
            TimeSeries(
                name="body_pose_sigma",
                description="pose standard errors: rotation (rad), translation (mm)",
                data=rows_data(
                    lambda a, b: np.stack(
                        [extra["pose_sigma_r"][a:b], extra["pose_sigma_t"][a:b]], -1
                    ),
                    (T, 2),
                    None,
                    blocks,
                ),
                unit="rad, mm",
                **_time_kwargs(timing, series),
            )
        )
    behavior.add(
        TimeSeries(
            name="frame_number",
            description="video frame number (fnum) of each sample",
            data=_compressed(fnum_s.astype(np.int64)),
            unit="frame",
            **_time_kwargs(timing, series),
        )
    )

    # --- intervals ---------------------------------------------------------------------
    tables = (
        (bouts, BOUTS_NAME, BOUTS_COLUMNS, "behavior bouts", {"label": "behavior label"}),
        (events, EVENTS_NAME, EVENTS_COLUMNS, "lock-box interaction events",
         {"part": "body part", "mechanism": "lock-box mechanism operated"}),
    )  # fmt: skip
    for source, name, columns, what, descriptions in tables:
        if source is None:
            continue
        start_s, stop_s, cols_ = read_intervals(source, columns, rate, intervals_unit)
        if intervals_unit == "frames":  # frames are on the tracks' clock
            start_s, stop_s = start_s + float(starting_time), stop_s + float(starting_time)
        nwb.add_time_intervals(
            _intervals(
                name, f"{what} from {Path(source).name}", start_s, stop_s, cols_, descriptions
            )
        )

    with atomic_path(path, suffix=".nwb") as tmp:
        with NWBHDF5IO(str(tmp), mode="w") as io:
            io.write(nwb)
    log.info(
        "wrote %s: %d frames x %d parts, %d cameras, skeleton: %s%s%s",
        path,
        T,
        K,
        len(cameras),
        skeleton_source,
        ", bouts" if bouts is not None else "",
        ", events" if events is not None else "",
    )
    return Path(path)


def _time_kwargs(timing: dict, series: list) -> dict:
    """The first series' timing; the others link its timestamps (no copies), or repeat the
    rate."""
    if "timestamps" not in timing:
        return dict(timing)
    return {"timestamps": series[0] if series else _compressed(timing["timestamps"])}


def write_anipose(
    path: str | os.PathLike,
    tracks: str | os.PathLike,
    axes: Mapping[str, Sequence] | BoardFrame | None = None,
    origin=None,
    keep_extra: bool = False,
) -> Path:
    """points3d.csv as anipose writes it (per part x, y, z, error, ncams, score; the axes
    columns ``M_..``, ``center_..``; fnum), optionally aligned by `axes` / `origin`
    (`adjust.kinematics.align_tracks`). Our other columns (body pose, sigmas) are dropped unless
    `keep_extra`, which writes them to the sidecar ``<stem>.extra.csv`` beside `path`
    (`adjust.io.points3d`): the CSV itself keeps anipose's columns only, which tools that read
    anipose's files (movement's ``from_anipose_file``) require. Returns the path."""
    d = align_tracks(read_points3d(tracks), axes, origin)
    extra = d["extra"] if keep_extra else {}
    if d["extra"] and not keep_extra:
        log.info("%s: columns not in anipose's layout dropped: %s", tracks, list(d["extra"]))
    out = write_points3d(
        path,
        d["parts"],
        d["points"],
        d["error"],
        d["ncams"],
        d["score"],
        extra=extra,
        fnum=d["fnum"],
        M=d["M"],
        center=d["center"],
    )
    log.info("wrote %s (anipose's layout)", out)
    return out


def read_nwb_tracks(path: str | os.PathLike) -> dict:
    """Read back what `write_nwb` wrote: ``parts``, ``points`` (T, K, 3) mm, ``confidence``
    (T, K), ``timestamps`` (T,) s (from the rate where the file has one), ``skeleton_edges``
    [(a, b)], ``cameras`` {name: {K, R, t, dist}}, the quality series present
    (``reprojection_error_px``, ``ncams``, ``score``, ``sigma_mm``, ``body_pose``,
    ``body_pose_sigma``, ``frame_number``), ``subject`` {field: value} and ``intervals``
    {name: {column: values}}."""
    _require_nwb()
    import ndx_pose  # noqa: F401  (registers the extension's classes)
    from pynwb import NWBHDF5IO

    path = Path(path)
    if not path.is_file():
        raise InputError(f"NWB file not found: {path}")
    with NWBHDF5IO(str(path), mode="r") as io:
        nwb = io.read()
        behavior = nwb.processing["behavior"]
        names = [n for n in (POSE_NAME, *LEGACY_POSE_NAMES) if n in behavior.data_interfaces]
        if not names:
            raise InputError(f"{path}: no processing/behavior/{POSE_NAME}")
        pose = behavior[names[0]]
        nodes = [str(n) for n in pose.skeleton.nodes[:]]
        out: dict = {
            "parts": tuple(nodes),
            "points": np.stack([pose.pose_estimation_series[p].data[:] for p in nodes], 1),
            "confidence": np.stack(
                [pose.pose_estimation_series[p].confidence[:] for p in nodes], 1
            ),
            "timestamps": np.asarray(pose.pose_estimation_series[nodes[0]].get_timestamps()),
            "skeleton_edges": [
                tuple(int(i) for i in e)
                for e in (pose.skeleton.edges[:] if pose.skeleton.edges is not None else [])
            ],
            "cameras": {
                name: {
                    "K": np.asarray(dev.intrinsic_matrix[:]),
                    "R": np.asarray(dev.rotation_matrix[:]),
                    "t": np.asarray(dev.translation_vector[:]),
                    "dist": np.asarray(dev.distortion_coefficients[:]),
                }
                for name, dev in nwb.devices.items()
            },
            "intervals": {},
            "subject": {}
            if nwb.subject is None
            else {
                k: getattr(nwb.subject, k)
                for k in SUBJECT_KEYS
                if getattr(nwb.subject, k, None) is not None
            },
        }
        for name in (
            "reprojection_error_px",
            "ncams",
            "score",
            "sigma_mm",
            "body_pose",
            "body_pose_sigma",
            "frame_number",
        ):
            if name in behavior.data_interfaces:
                out[name] = np.asarray(behavior[name].data[:])
        for name, table in (nwb.intervals or {}).items():
            out["intervals"][name] = {c: table[c][:] for c in table.colnames}
            out["intervals"][name]["start_time"] = np.asarray(table["start_time"][:])
            out["intervals"][name]["stop_time"] = np.asarray(table["stop_time"][:])
    return out


def _version() -> str:
    try:
        return version("mousetrack")
    except Exception:  # pragma: no cover - not installed as a distribution
        return "unknown"
