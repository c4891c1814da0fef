"""adjust-track's outputs, written as one set (`deformnet.outputs.OutputSet`): accepted.npz,
tokens.npz, points3d.csv and its sidecar, tracks.nwb (``output.nwb``), summary.json last."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from adjust.export import write_nwb
from adjust.io import InputError, load_calibration_metadata, recording_fps, write_points3d
from adjust.nwb_metadata import session_start
from adjust.summary import TrackColumns
from adjust.tokenize import session_tokens
from adjust.track_config import OutputConfig
from deformnet.body import BodyModel
from deformnet.outputs import OutputSet
from deformnet.tables import extra_path

__all__ = ["check_nwb_output", "write_outputs"]


def check_nwb_output(output: OutputConfig, calibration: str) -> None:
    """``output.nwb=true`` needs the recording's frame rate and start time: checked before
    any computing."""
    if not output.nwb:
        return
    meta = load_calibration_metadata(calibration)
    if recording_fps(output.fps, meta) is None:
        raise InputError(
            f"output.nwb=true needs the recording's frame rate: set output.fps=... (Hz), or "
            f"give a calibration whose [metadata] has fps ({calibration} has none)"
        )
    try:
        session_start(output.session_start_time, meta, calibration)
    except InputError as exc:
        raise InputError(f"output.nwb=true: {exc} (output.session_start_time=...)") from None


def write_outputs(
    out: Path,
    summary: dict,
    det,
    cols: TrackColumns,
    poses: np.ndarray,
    body: BodyModel,
    cons,
    output: OutputConfig,
    calibration: str,
    detections: str,
) -> dict:
    """Write a tracked session's outputs into `out` as one set and return the summary as
    committed (with every file's sha256). det: the `adjust.io.Detections`; cols: the result's
    points3d columns (`adjust.summary.track_columns`); poses (T, 6) the adjusted poses; cons:
    the session's `adjust.estimate.Consensus` (None: no tokens); output: the ``output``
    block (nwb, fps, session_start_time, subject)."""
    points_path = out / "points3d.csv"
    fnum = det.frames
    # every output as one set (deformnet.outputs.OutputSet): a run stopped at any moment (SIGKILL
    # included) leaves the previous run's outputs whole; summary.json last, with every file's
    # sha256 (outputs.files)
    with OutputSet(out) as staged:
        # which detections every point rests on (for figures: adjust-plot, the demo report)
        np.savez_compressed(
            staged.path("accepted.npz"),
            accepted=cols.observed,
            parts=np.asarray(det.parts),
            cameras=np.asarray(det.cameras),
        )
        summary["outputs"]["accepted"] = str(out / "accepted.npz")
        if cons is not None:  # self-supervised tokens for deformnet-train data=sessions
            tokens = session_tokens(
                poses, body.points, cons, body.parts, body.name, source=str(out)
            )
            tokens.save(staged.path("tokens.npz"))
            summary["outputs"]["tokens"] = str(out / "tokens.npz")
        write_points3d(
            staged.path("points3d.csv"),
            det.parts,
            cols.points,
            cols.error,
            cols.ncams,
            cols.score,
            extra=cols.extra,
            fnum=fnum,
        )
        staged.path(extra_path(points_path).name)  # its sidecar (pose, sigmas) joins the set
        summary["outputs"]["extra"] = str(extra_path(points_path))
        if output.nwb:  # the same tracks as NWB (ndx-pose), adjust.export
            write_nwb(
                staged.path("tracks.nwb"),
                staged.path("points3d.csv"),
                calibration,
                fps=output.fps,
                session_start_time=output.session_start_time,
                subject=output.subject or None,
                detections=detections,
            )
            summary["outputs"]["nwb"] = str(out / "tracks.nwb")
        summary = staged.commit(summary)
    return summary
