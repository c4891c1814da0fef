"""What an NWB export needs besides the tracks (`adjust.export.write_nwb`): the subject
(`subject_metadata`, checked against what DANDI requires), the recording's start
(`session_start`), the frame times (`recording_rate`, `frame_timing`), further NWBFile fields
(`file_metadata`) and the interval tables read from start/stop CSVs (`read_intervals`).

Errors are `InputError`s naming the setting or the file, column and row.
"""

from __future__ import annotations

import datetime as _dt
import logging
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from adjust.io import recording_fps
from adjust.io.errors import InputError
from deformnet.tables import read_csv

log = logging.getLogger(__name__)

__all__ = [
    "DANDI_SUBJECT",
    "FILE_KEYS",
    "SUBJECT_KEYS",
    "file_metadata",
    "frame_timing",
    "read_intervals",
    "recording_rate",
    "session_start",
    "subject_metadata",
]

#: NWB Subject fields the export takes (``subject.<key>``); DANDI requires the first four
SUBJECT_KEYS = ("subject_id", "species", "sex", "age", "strain", "genotype", "description")
DANDI_SUBJECT = ("subject_id", "species", "sex", "age")
SEXES = ("M", "F", "U", "O")
#: ISO 8601 durations (DANDI's and nwbinspector's form), and a range of two ("P90D/P120D")
DURATION = re.compile(
    r"P(?!$)(\d+(?:\.\d+)?Y)?(\d+(?:\.\d+)?M)?(\d+(?:\.\d+)?W)?(\d+(?:\.\d+)?D)?"
    r"(T(?=\d)(\d+(?:\.\d+)?H)?(\d+(?:\.\d+)?M)?(\d+(?:\.\d+)?S)?)?"
)
#: Latin binomial ("Mus musculus") or an NCBI taxonomy link, as DANDI asks
SPECIES = re.compile(r"([A-Z][a-z]* [a-z]+)|(http://purl\.obolibrary\.org/obo/NCBITaxon_\d+)")
#: further NWBFile metadata the export takes (nwbinspector suggests them)
FILE_KEYS = (
    "experimenter",
    "institution",
    "lab",
    "experiment_description",
    "keywords",
    "session_id",
)


def read_intervals(
    path: str | os.PathLike, columns: Sequence[str], fps: float, unit: str = "frames"
) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """A start/stop CSV -> (start_s, stop_s, {other column: values}).

    ``columns``: those that must be present (``start``, ``stop`` first); ``unit``: ``frames``
    (divided by fps) or ``seconds``. Errors name the file, the column and the row."""
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
    extra = {}
    for c in df.columns:
        if c in ("start", "stop"):
            continue
        values = df[c]
        if pd.api.types.is_numeric_dtype(values) or pd.api.types.is_bool_dtype(values):
            extra[c] = values.to_numpy()
        else:  # text, or text mixed with numbers and empty cells: one column of text
            extra[c] = np.array(["" if pd.isna(v) else str(v) for v in values], dtype=object)
    return times["start"], times["stop"], extra


def recording_rate(fps, calibration_meta: dict) -> float:
    value = recording_fps(fps, calibration_meta)
    if value is None:
        raise InputError(
            "NWB needs times in seconds: set fps=... (the recording's frame rate, Hz), or give a "
            "calibration whose [metadata] has fps"
        )
    return value


def _age_ok(age: str) -> bool:
    parts = age.split("/")
    if len(parts) == 1:
        return DURATION.fullmatch(age) is not None
    return len(parts) == 2 and all(p == "" or DURATION.fullmatch(p) for p in parts) and any(parts)


def subject_metadata(subject: Mapping | None) -> dict | None:
    """pynwb ``Subject`` keyword arguments from ``subject.<key>`` settings (`SUBJECT_KEYS`), or
    None when none is set. Checked: ``sex`` one of M, F, U, O; ``age`` an ISO 8601 duration
    (``P90D``, ``P12W``, ``P3M``; a range ``P90D/P120D``); anything else an InputError naming the
    setting. Nothing is defaulted: each field DANDI requires (subject_id, species, sex, age)
    that is missing is logged as a warning, as is a species not in Latin binomial form."""
    given = {}
    for key, value in dict(subject or {}).items():
        if key not in SUBJECT_KEYS:
            raise InputError(f"subject.{key}: unknown setting (known: {list(SUBJECT_KEYS)})")
        if value is not None and str(value).strip() != "":
            given[key] = str(value).strip()
    if not given:
        log.warning(
            "no subject metadata: DANDI needs subject.subject_id, subject.species (e.g. "
            "'Mus musculus'), subject.sex (M/F/U/O) and subject.age (ISO 8601, e.g. P90D)"
        )
        return None
    if "sex" in given:
        given["sex"] = given["sex"].upper()
        if given["sex"] not in SEXES:
            raise InputError(f"subject.sex must be one of {list(SEXES)}, got {subject['sex']!r}")
    if "age" in given:
        given["age"] = given["age"].upper()
        if not _age_ok(given["age"]):
            raise InputError(
                f"subject.age must be an ISO 8601 duration (P90D: 90 days, P12W, P3M, P1Y; a "
                f"range P90D/P120D), got {subject['age']!r}"
            )
    if "species" in given and not SPECIES.fullmatch(given["species"]):
        log.warning(
            "subject.species %r: DANDI expects a Latin binomial ('Mus musculus') or an NCBI "
            "taxonomy link (http://purl.obolibrary.org/obo/NCBITaxon_10090)",
            given["species"],
        )
    missing = [k for k in DANDI_SUBJECT if k not in given]
    if missing:
        log.warning(
            "subject: %s not set; DANDI requires them (subject.species is never assumed)",
            ", ".join(f"subject.{k}" for k in missing),
        )
    return given


def _parse_time(value, where: str) -> _dt.datetime:
    if isinstance(value, _dt.datetime):
        start = value
    elif isinstance(value, _dt.date):
        start = _dt.datetime(value.year, value.month, value.day)
    else:
        text = str(value).strip()
        try:
            start = _dt.datetime.fromisoformat(text[:-1] + "+00:00" if text.endswith("Z") else text)
        except ValueError:
            raise InputError(
                f"{where} must be ISO 8601 (2026-03-01T09:30:00+01:00), got {value!r}"
            ) from None
    if start.tzinfo is None:
        log.info("%s %s has no time zone: taken as UTC", where, start.isoformat())
        start = start.replace(tzinfo=_dt.UTC)
    if start > _dt.datetime.now(_dt.UTC) + _dt.timedelta(days=1):
        raise InputError(f"{where} {start.isoformat()} is in the future")
    return start


def session_start(
    value, calibration_meta: Mapping | None = None, calibration=None
) -> tuple[_dt.datetime, str]:
    """The recording's start (timezone-aware; a naive time is UTC) and where it came from:
    `value` (the ``session_start_time`` setting: ISO 8601 or a datetime), else the calibration's
    ``[metadata] session_start_time``, else an InputError saying how to set it. Never the
    export's own time."""
    if value is not None and str(value).strip() != "":
        return _parse_time(value, "session_start_time"), "setting session_start_time"
    meta = calibration_meta or {}
    if meta.get("session_start_time") not in (None, ""):
        where = f"{calibration}: [metadata] session_start_time"
        return _parse_time(meta["session_start_time"], where), where
    raise InputError(
        "NWB needs the recording's start time: set session_start_time=2026-03-01T09:30:00+01:00 "
        "(ISO 8601), or give a calibration whose [metadata] has session_start_time"
        + (f" ({calibration} has none)" if calibration is not None else "")
    )


def frame_timing(fnum: np.ndarray, fps: float, starting_time: float) -> dict:
    """TimeSeries timing keywords: ``starting_time`` + ``rate`` when the frame numbers are evenly
    spaced (consecutive frames: rate = fps), else ``timestamps`` (s)."""
    f = fnum.astype(np.float64)
    if len(f) > 1:
        step = np.diff(f)
        if np.all(step == step[0]) and step[0] > 0:
            return {"starting_time": float(starting_time) + f[0] / fps, "rate": fps / step[0]}
        log.info("frame numbers not evenly spaced: NWB timestamps instead of a rate")
        return {"timestamps": float(starting_time) + f / fps}
    return {"starting_time": float(starting_time) + (f[0] / fps if len(f) else 0.0), "rate": fps}


def file_metadata(metadata: Mapping | None) -> dict:
    """NWBFile keyword arguments from `FILE_KEYS` settings (None or "" skipped); experimenter
    and keywords may be one string or a list."""
    out = {}
    for key, value in dict(metadata or {}).items():
        if key not in FILE_KEYS:
            raise InputError(f"unknown NWB metadata setting {key!r} (known: {list(FILE_KEYS)})")
        if value is None or (isinstance(value, str) and not value.strip()):
            continue
        if key in ("experimenter", "keywords"):
            value = [value] if isinstance(value, str) else [str(v) for v in value]
            if not value:
                continue
        else:
            value = str(value)
        out[key] = value
    return out
