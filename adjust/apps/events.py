"""`adjust-events`: lock-box interaction events from 3D tracks (see `adjust.events`).

    adjust-events tracks=out/points3d.csv calibration=scene/calibration.toml output.dir=ev
    adjust-events tracks=out/points3d.csv mechanisms='{lever: [90.0, 255.0, 18.0]}'

Mechanism positions (global mm) come from `mechanisms=` or from the calibration's
``[metadata.mechanisms]`` table (written by `adjust-simulate`). Writes into ``output.dir``:
``events.csv`` (start, stop as frame numbers ``fnum``, inclusive; part, mechanism,
min_distance_mm, frames, seen_fraction, inferred), ``operations.csv`` (per mechanism, the events
of any part merged: mechanism, start, stop, parts) and ``summary.json`` (counts, the order in
which the mechanisms were first operated, settings). With the frame rate (``fps=``, or the
calibration's ``[metadata] fps``) both tables also give ``start_s`` / ``stop_s`` (fnum / fps)
and the contact durations may be set in seconds (``contact.min_seconds``,
``contact.merge_gap_seconds``), the same for a 30 and a 100 fps recording.

`run(cfg) -> dict` is the plain function behind the Hydra app.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from adjust.apps.common import finite_or_none, hydra_app
from adjust.events import detect_events, first_operated, operations
from adjust.io import InputError, load_calibration_metadata, read_points3d, recording_fps
from adjust.settings import EventsConfig, required
from deformnet.atomic import atomic_path, write_text
from deformnet.behavior.lockbox import mechanism_table
from deformnet.confutil import to_plain
from deformnet.paths import output_dir
from deformnet.series import interpolate_gaps

log = logging.getLogger(__name__)

EVENT_COLUMNS = (
    "start",
    "stop",
    "part",
    "mechanism",
    "min_distance_mm",
    "frames",
    "seen_fraction",
    "inferred",
)


def mechanism_positions(cfg: DictConfig) -> dict[str, list[float]]:
    """name -> [x, y, z] from `mechanisms=` or the calibration's metadata."""
    mech = to_plain(cfg.get("mechanisms"))
    source = "mechanisms="
    if not mech and cfg.get("calibration"):
        meta = load_calibration_metadata(str(cfg.calibration))
        mech = meta.get("mechanisms")
        source = f"{cfg.calibration} [metadata.mechanisms]"
        if not mech:
            raise InputError(f"{cfg.calibration}: no [metadata.mechanisms] table; set mechanisms=")
    if not mech:
        raise ValueError("set mechanisms={name: [x, y, z], ...} or calibration=calibration.toml")
    return mechanism_table(mech, source)


def contact_frames(cfg: DictConfig, fps: float | None) -> tuple[int, int]:
    """(min_frames, merge_gap) from ``contact``: the seconds (``min_seconds``,
    ``merge_gap_seconds``) times the frame rate where set (they need it), else the frames."""
    c = cfg.contact
    out = []
    keys = (("min_frames", "min_seconds", 1), ("merge_gap", "merge_gap_seconds", 0))
    for key, name, least in keys:
        sec = c.get(name)
        if sec is None:
            n = int(c[key])
        else:
            if fps is None:
                raise ValueError(
                    f"contact.{name}={sec} needs the frame rate: set fps= (Hz) or give a "
                    "calibration whose [metadata] has fps (or use contact."
                    f"{key}, frames)"
                )
            if not float(sec) >= 0:
                raise ValueError(f"contact.{name} must be >= 0 s, got {sec}")
            n = max(least, int(round(float(sec) * fps)))
        if n < 0:
            raise ValueError(f"contact.{key} must be >= 0, got {n}")
        out.append(n)
    return out[0], out[1]


def track_fps(cfg: DictConfig) -> float | None:
    """The recording's frame rate: ``fps=``, else the calibration's ``[metadata] fps``, else
    None (`adjust.io.recording_fps`, as adjust-export)."""
    calib = cfg.get("calibration")
    if cfg.get("fps") is not None or not calib:
        return recording_fps(cfg.get("fps"), {})
    return recording_fps(None, load_calibration_metadata(str(calib)), str(calib))


def run(cfg: DictConfig) -> dict:
    """Detect events, write events.csv, operations.csv and summary.json; returns the summary
    plus the events and operations (frame numbers)."""
    tracks = required(cfg, "tracks", "events")
    mechs = mechanism_positions(cfg)
    fps = track_fps(cfg)
    min_frames, merge_gap = contact_frames(cfg, fps)
    tr = read_points3d(tracks)
    if tr["fnum"].dtype.kind not in "iu":
        raise InputError(
            f"{tracks}: fnum holds labelled images' names ({', '.join(map(str, tr['fnum'][:2]))}"
            ", ...), not a video's frame numbers: events need tracks of a recording"
        )
    parts = list(tr["parts"])
    use = [str(p) for p in (cfg.get("parts") or parts)]
    missing = [p for p in use if p not in parts]
    if missing:
        raise InputError(f"{tracks}: no columns for part(s) {missing} (the file has {parts})")
    pts = tr["points"]
    if EventsConfig.from_config(cfg).interpolate:
        pts = interpolate_gaps(pts)
    sigma = None
    if all(f"{p}_sigma" in tr["extra"] for p in parts):
        sigma = np.stack([np.asarray(tr["extra"][f"{p}_sigma"], float) for p in parts], -1)
    c, inf = cfg.contact, cfg.inferred
    events = detect_events(
        pts,
        parts,
        mechs,
        use_parts=use,
        on_mm=float(c.on_mm),
        off_mm=float(c.off_mm),
        min_frames=min_frames,
        merge_gap=merge_gap,
        ncams=tr["ncams"] if np.isfinite(tr["ncams"]).any() else None,
        sigma=sigma,
        max_sigma_mm=None if inf.get("max_sigma_mm") is None else float(inf.max_sigma_mm),
        inferred_below=float(inf.below),
        mechanism_parts=to_plain(cfg.get("mechanism_parts")),
    )
    fnum = np.asarray(tr["fnum"]).astype(np.int64)
    for e in events:
        e["start"], e["stop"] = int(fnum[e["start"]]), int(fnum[e["stop"]])
    ops = operations(events, merge_gap)
    order = first_operated(events)
    out = output_dir(cfg)
    times = [] if fps is None else ["start_s", "stop_s"]  # fnum / fps

    def timed(rows: list[dict]) -> list[dict]:
        if fps is None:
            return rows
        return [r | {"start_s": r["start"] / fps, "stop_s": r["stop"] / fps} for r in rows]

    with atomic_path(out / "events.csv") as tmp:
        cols = [*EVENT_COLUMNS[:2], *times, *EVENT_COLUMNS[2:]]
        pd.DataFrame(timed(events), columns=cols).to_csv(tmp, index=False)
    with atomic_path(out / "operations.csv") as tmp:
        rows = [{**o, "parts": ";".join(o["parts"])} for o in ops]
        cols = ["mechanism", "start", "stop", *times, "parts"]
        pd.DataFrame(timed(rows), columns=cols).to_csv(tmp, index=False)
    summary = {
        "tracks": str(tracks),
        "frames": int(len(fnum)),
        "mechanisms": mechs,
        "parts": use,
        "events": len(events),
        "inferred_events": int(sum(e["inferred"] for e in events)),
        "operations": len(ops),
        "order": order,
        "first_operated": {
            m: min(o["start"] for o in ops if o["mechanism"] == m) for m in order
        },  # fmt: skip
        "fps": fps,
        "contact": dict(to_plain(c)) | {"min_frames": min_frames, "merge_gap": merge_gap},
        "inferred": dict(to_plain(inf)),
    }
    write_text(out / "summary.json", json.dumps(finite_or_none(summary), indent=2) + "\n")
    log.info(
        "%d events (%d inferred), %d operations; first operated: %s -> %s",
        len(events),
        summary["inferred_events"],
        len(ops),
        " > ".join(order) or "none",
        out / "events.csv",
    )
    return {**summary, "event_list": events, "operation_list": ops, "output_dir": str(out)}


main = hydra_app(run, "events")


if __name__ == "__main__":
    main()
