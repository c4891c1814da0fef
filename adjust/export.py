"""NWB export of 3D tracks (Neurodata Without Borders, the DANDI archive's format), with ndx-pose.

`write_nwb` turns an ``adjust-track`` output (``points3d.csv``, anipose's layout plus our pose and
uncertainty columns) into one NWB file:

- ``processing/behavior/PoseEstimation3D``: an ndx-pose ``MultiCameraPoseEstimation`` holding one
  ``PoseEstimationSeries`` per part (``data`` (T, 3) mm in the calibration's world frame,
  ``confidence`` (T,) = ``{part}_ncams`` / number of cameras: the share of cameras with an
  accepted detection of the part, 0 for a part placed by the body model alone), and one
  ``PoseEstimation`` per camera linking its ``CalibratedCamera`` device (intrinsics, world ->
  camera rotation and translation, distortion: the calibration as metadata);
- ``processing/behavior/Skeletons``: the skeleton (nodes = parts; edges given, or the minimum
  spanning tree of the parts' median distances);
- ``processing/behavior``: ``TimeSeries`` with the quality columns, (T, K) one column per part:
  ``reprojection_error_px``, ``ncams``, ``score``, ``sigma_mm`` (the 3D standard error, the
  ``{part}_sigma`` columns), and ``body_pose`` (T, 6: Rodrigues rad, translation mm),
  ``body_pose_sigma`` (T, 2: rad, mm), ``frame_number`` (T,), where the CSV has them;
- ``intervals/behavior_bouts`` and ``intervals/lockbox_events``: ``TimeIntervals`` from a bouts
  CSV (``start, stop, label[, ...]``) and a lock-box events CSV (``start, stop, part, mechanism,
  ...``) when given; every further column is kept.

Times: frame ``fnum`` is at ``fnum / fps`` s (``starting_time`` offsets them); interval
``start``/``stop`` are frame numbers (``intervals_unit="frames"``, converted the same way) or
seconds. The frame rate comes from ``fps`` or the calibration's ``[metadata] fps``; without
either the export is refused (NWB needs times in seconds).

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
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from adjust.io.errors import InputError
from deformnet.behavior_labels import POSE_COLUMNS

log = logging.getLogger(__name__)

#: the NWB objects this module writes
POSE_NAME = "PoseEstimation3D"
BOUTS_NAME = "behavior_bouts"
EVENTS_NAME = "lockbox_events"
BOUTS_COLUMNS = ("start", "stop", "label")
EVENTS_COLUMNS = ("start", "stop", "part", "mechanism")


def _require_nwb():
    try:
        import ndx_pose  # noqa: F401
        import pynwb  # noqa: F401
    except ImportError as exc:  # pragma: no cover - the extra is part of the test install
        raise InputError(
            f"NWB export needs pynwb and ndx-pose: pip install 'mousetrack[nwb]' ({exc})"
        ) from None


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


def _edge_indices(edges, parts: Sequence[str]) -> list[tuple[int, int]]:
    index = {p: k for k, p in enumerate(parts)}
    out = []
    for e in edges:
        pair = list(e)
        if len(pair) != 2:
            raise InputError(f"skeleton edge {pair!r}: give two part names")
        try:
            out.append((index[str(pair[0])], index[str(pair[1])]))
        except KeyError as exc:
            raise InputError(
                f"skeleton edge {pair!r}: unknown part {exc.args[0]!r} (parts: {list(parts)})"
            ) from None
    return out


def read_intervals(
    path: str | os.PathLike, columns: Sequence[str], fps: float, unit: str = "frames"
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """A start/stop CSV -> (start_s, stop_s, {other column: values}).

    ``columns``: those that must be present (``start``, ``stop`` first); ``unit``: ``frames``
    (divided by fps) or ``seconds``. Errors name the file, the column and the row."""
    import pandas as pd

    from deformnet.tables import read_csv

    path = Path(path)
    if unit not in ("frames", "seconds"):
        raise InputError(f"intervals_unit must be 'frames' or 'seconds', got {unit!r}")
    df = read_csv(path, "intervals file", InputError)
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise InputError(f"{path}: missing column(s) {missing} (has {list(df.columns)})")
    times = {}
    for key in ("start", "stop"):
        num = pd.to_numeric(df[key], errors="coerce").to_numpy(np.float64)
        bad = np.flatnonzero(~np.isfinite(num))
        if bad.size:
            r = int(bad[0])
            raise InputError(f"{path}: non-numeric {key} {df[key].iloc[r]!r} at row {r}")
        times[key] = num / fps if unit == "frames" else num
    back = np.flatnonzero(times["stop"] < times["start"])
    if back.size:
        r = int(back[0])
        raise InputError(f"{path}: stop before start at row {r}")
    extra = {c: df[c].to_numpy() for c in df.columns if c not in ("start", "stop")}
    return times["start"], times["stop"], extra


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


def _fps(fps, calibration_meta: dict) -> float:
    from adjust.io import recording_fps

    value = recording_fps(fps, calibration_meta)
    if value is None:
        raise InputError(
            "NWB needs times in seconds: set fps=... (the recording's frame rate, Hz), or give a "
            "calibration whose [metadata] has fps"
        )
    return value


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
    subject_id: str | None = None,
    starting_time: float = 0.0,
) -> Path:
    """Write the tracks of ``points3d.csv`` (and the optional calibration, bouts and events) as
    an NWB file at ``path`` (atomically). Returns the path. See the module doc for the layout.

    session_start_time: ISO 8601 (a naive time is taken as UTC) or a datetime; default: now.
    identifier: default a fresh UUID. Raises `InputError` for unreadable or inconsistent
    inputs (naming the file)."""
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

    import adjust
    from adjust.io import load_calibration, load_calibration_metadata, read_points3d
    from deformnet.atomic import atomic_path

    tracks = Path(tracks)
    d = read_points3d(tracks)  # a file without part columns is an error there
    parts = list(d["parts"])
    points = d["points"]
    T, K = points.shape[:2]
    cameras, meta = [], {}
    if calibration is not None:
        cameras = load_calibration(calibration)
        meta = load_calibration_metadata(calibration)
    rate = _fps(fps, meta)
    fnum = np.asarray(d["fnum"])
    if not np.all(np.isfinite(fnum.astype(np.float64))):
        raise InputError(f"{tracks}: non-finite fnum")
    times = float(starting_time) + fnum.astype(np.float64) / rate
    if T > 1 and np.any(np.diff(times) <= 0):
        raise InputError(f"{tracks}: fnum must increase from row to row")
    ncams = d["ncams"]
    num_cams = len(cameras) if cameras else int(np.nanmax(ncams, initial=0))
    if cameras and np.nanmax(ncams, initial=0) > len(cameras):
        raise InputError(
            f"{tracks}: up to {int(np.nanmax(ncams))} cameras per part, but {calibration} has "
            f"{len(cameras)}"
        )

    if session_start_time is None:
        start = _dt.datetime.now(_dt.UTC)
    elif isinstance(session_start_time, _dt.datetime):
        start = session_start_time
    else:
        try:
            start = _dt.datetime.fromisoformat(str(session_start_time))
        except ValueError:
            raise InputError(
                f"session_start_time must be ISO 8601, got {session_start_time!r}"
            ) from None
    if start.tzinfo is None:
        start = start.replace(tzinfo=_dt.UTC)
    notes = {
        "tracks": str(tracks.resolve()),
        "calibration": None if calibration is None else str(Path(calibration).resolve()),
        "calibration_metadata": meta,
        "fps": rate,
    }
    nwb = NWBFile(
        session_description=session_description,
        identifier=identifier or str(uuid.uuid4()),
        session_start_time=start,
        notes=json.dumps(notes, default=str),
        source_script="mousetrack adjust.export.write_nwb",
        source_script_file_name=str(Path(__file__).name),
    )
    if subject_id is not None:
        nwb.subject = Subject(subject_id=str(subject_id), species="Mus musculus")

    # --- cameras: the calibration as metadata ------------------------------------------
    devices = []
    for cam in cameras:
        dev = CalibratedCamera(
            name=cam.name,
            description=f"calibrated camera, image size {cam.size[0]} x {cam.size[1]} px; "
            "x_cam = R X + t (mm), pinhole with OpenCV distortion k1 k2 p1 p2 k3",
            intrinsic_matrix=np.asarray(cam.K, dtype=np.float64),
            rotation_matrix=np.asarray(cam.R, dtype=np.float64),
            translation_vector=np.asarray(cam.tvec, dtype=np.float64),
            distortion_coefficients=np.asarray(cam.dist, dtype=np.float64),
        )
        nwb.add_device(dev)
        devices.append(dev)

    # --- skeleton and pose -------------------------------------------------------------
    behavior = nwb.create_processing_module(
        name="behavior", description="3D body-part tracks from multi-camera 2D detections"
    )
    pairs = _edge_indices(edges, parts) if edges is not None else spanning_edges(points)
    skeleton = Skeleton(
        name="subject",
        nodes=parts,
        edges=np.asarray(pairs, dtype=np.uint8).reshape(-1, 2),
    )
    behavior.add(Skeletons(skeletons=[skeleton]))
    frame = "world frame of the camera calibration (x_cam = R X + t), mm"
    series = []
    with np.errstate(invalid="ignore", divide="ignore"):
        conf = np.where(np.isfinite(ncams), ncams / max(num_cams, 1), 0.0)
    for k, part in enumerate(parts):
        series.append(
            PoseEstimationSeries(
                name=part,
                description=f"3D position of {part}",
                data=_compressed(points[:, k]),
                unit="mm",
                reference_frame=frame,
                timestamps=_compressed(times) if k == 0 else series[0],
                confidence=_compressed(conf[:, k]),
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
            skeleton=skeleton,
            source_software="mousetrack",
        )
        for dev in devices
    ]
    pose = MultiCameraPoseEstimation(
        name=POSE_NAME,
        description="pose-track adjustment of a body model to incomplete multi-camera "
        "detections (mousetrack adjust-track); each part fused from its own detections and the "
        "model",
        pose_estimation_series=series,
        pose_estimations=views or None,
        scorer="mousetrack",
        source_software="mousetrack",
        source_software_version=getattr(adjust, "__version__", None) or _version(),
        skeleton=skeleton,
    )
    behavior.add(pose)

    # --- quality columns ---------------------------------------------------------------
    cols = ", ".join(parts)
    quality = [
        ("reprojection_error_px", d["error"], "px", "mean reprojection error of the point"),
        ("ncams", ncams, "cameras", "cameras with an accepted detection"),
        ("score", d["score"], "likelihood", "lowest detection likelihood used"),
    ]
    extra = d["extra"]
    sig = [f"{p}_sigma" for p in parts]
    if all(s in extra for s in sig):
        quality.append(
            (
                "sigma_mm",
                np.stack([extra[s] for s in sig], -1),
                "mm",
                "3D standard error (root of the trace of the 3x3 covariance)",
            )
        )
    for name, data, unit, what in quality:
        behavior.add(
            TimeSeries(
                name=name,
                description=f"{what}; columns: {cols}",
                data=_compressed(np.asarray(data, dtype=np.float64)),
                unit=unit,
                timestamps=series[0],
            )
        )
    if all(c in extra for c in POSE_COLUMNS):
        behavior.add(
            TimeSeries(
                name="body_pose",
                description="body model pose, model -> world: Rodrigues vector (rad) "
                "rx, ry, rz and translation (mm) tx, ty, tz",
                data=_compressed(np.stack([extra[c] for c in POSE_COLUMNS], -1)),
                unit="rad, mm",
                timestamps=series[0],
            )
        )
    if "pose_sigma_r" in extra and "pose_sigma_t" in extra:
        behavior.add(
            TimeSeries(
                name="body_pose_sigma",
                description="pose standard errors: rotation (rad), translation (mm)",
                data=_compressed(np.stack([extra["pose_sigma_r"], extra["pose_sigma_t"]], -1)),
                unit="rad, mm",
                timestamps=series[0],
            )
        )
    behavior.add(
        TimeSeries(
            name="frame_number",
            description="video frame number (fnum) of each sample",
            data=_compressed(fnum.astype(np.int64)),
            unit="frame",
            timestamps=series[0],
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
        start_s, stop_s, cols = read_intervals(source, columns, rate, intervals_unit)
        nwb.add_time_intervals(
            _intervals(
                name, f"{what} from {Path(source).name}", start_s, stop_s, cols, descriptions
            )
        )

    with atomic_path(path, suffix=".nwb") as tmp:
        with NWBHDF5IO(str(tmp), mode="w") as io:
            io.write(nwb)
    log.info(
        "wrote %s: %d frames x %d parts, %d cameras%s%s",
        path,
        T,
        K,
        len(cameras),
        ", bouts" if bouts is not None else "",
        ", events" if events is not None else "",
    )
    return Path(path)


def read_nwb_tracks(path: str | os.PathLike) -> dict:
    """Read back what `write_nwb` wrote: ``parts``, ``points`` (T, K, 3) mm, ``confidence``
    (T, K), ``timestamps`` (T,) s, ``skeleton_edges`` [(a, b)], ``cameras`` {name: {K, R, t,
    dist}}, the quality series present (``reprojection_error_px``, ``ncams``, ``score``,
    ``sigma_mm``, ``body_pose``, ``body_pose_sigma``, ``frame_number``) and ``intervals``
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
        pose = behavior[POSE_NAME]
        nodes = [str(n) for n in pose.skeleton.nodes[:]]
        out: dict = {
            "parts": tuple(nodes),
            "points": np.stack([pose.pose_estimation_series[p].data[:] for p in nodes], 1),
            "confidence": np.stack(
                [pose.pose_estimation_series[p].confidence[:] for p in nodes], 1
            ),
            "timestamps": np.asarray(pose.pose_estimation_series[nodes[0]].timestamps[:]),
            "skeleton_edges": [tuple(int(i) for i in e) for e in pose.skeleton.edges[:]],
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
        from importlib.metadata import version

        return version("mousetrack")
    except Exception:  # pragma: no cover - not installed as a distribution
        return "unknown"
