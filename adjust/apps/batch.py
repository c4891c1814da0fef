"""Batch runs: ``adjust-track -m input.session=glob(sessions/*)`` (or ``=DIR1,DIR2,...``).

Hydra's multirun gives one job per session, through the launcher chosen on the command line:
the basic one (sequential), ``hydra/launcher=joblib`` (local processes in parallel) or
``hydra/launcher=slurm`` (SLURM array jobs through submitit, ``conf/hydra/launcher/slurm.yaml``).
Each job runs `run_session`, which never raises: it tracks the session into its own folder
(``runs/batch/<time>/<session name>/``, locked while it runs: `deformnet.outputs`), or records
why it failed, or skips it when an earlier batch already tracked the same inputs with the same
settings: the sha256 of the calibration's and the detection files' contents (`inputs_digest`)
and of the settings (`settings_hash`) match those its status row recorded; file times are not
consulted (``rsync -a`` and ``cp -p`` keep an old time on a changed file). ``force=true``
re-runs. Each job writes one status row (``batch_status.json``). After the
last job the `BatchSummary` callback collects this batch's rows into ``summary.csv`` in the sweep
folder (`SUMMARY_COLUMNS`): ``runs/batch/<time>/summary.csv``, or ``OUTPUT_DIR/summary.csv`` with
``output.dir`` set (the sweep folder is then ``output.dir``: each session's outputs, log and
status row in ``OUTPUT_DIR/<session name>/``). The batch exits with status 1 when a session
failed or none ran (a glob matching no session folder is exit status 2 before any job).
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict

from adjust.io.scene import SUFFIXES
from adjust.pipeline import run as track_run
from adjust.session import SESSION_KEY, session_name, with_session
from adjust.settings import BatchConfig
from deformnet import project
from deformnet.atomic import file_digest, write_text
from deformnet.outputs import output_lock, recover_outputs

log = logging.getLogger(__name__)

STATUS_FILE = "batch_status.json"
SUMMARY_FILE = "summary.csv"
SUMMARY_COLUMNS = (
    "session",
    "status",  # ok | failed | skipped
    "error",
    "frames",
    "completeness",
    "median_reprojection_error_px",
    "net_parts",  # a checked net (deform.require_better): parts it predicted / all, e.g. 6/8
    "seconds",
    "output",
)
#: config keys that do not change a session's result (left out of the settings hash)
_NOT_SETTINGS = ("force", "progress", "output.dir")


def in_multirun() -> bool:
    """True inside a Hydra multirun job (``-m``)."""
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def settings_hash(cfg: DictConfig) -> str:
    """A hash of the resolved job config without the session, output folder and switches that
    do not change the result: a re-run skips a session only when this is unchanged."""
    c = OmegaConf.to_container(cfg, resolve=True)
    c.pop("hydra", None)
    for key in (SESSION_KEY, "input.calibration", "input.detections", *_NOT_SETTINGS):
        node, *rest = key.split(".")
        if rest and isinstance(c.get(node), dict):
            c[node].pop(rest[0], None)
        elif not rest:
            c.pop(node, None)
    return hashlib.sha256(json.dumps(c, sort_keys=True, default=str).encode()).hexdigest()[:16]


def inputs_digest(calibration: Path, detections: Path) -> str:
    """sha256 (hex) of a session's inputs: the calibration file's bytes and every detection
    file's name and bytes (the files `adjust.io.scene` may read: ``.csv``, ``.h5``, ``.hdf5``,
    ``.slp``, not hidden; a detections path that is a file: that file). A missing input hashes
    as missing (the run reports it)."""
    h = hashlib.sha256()
    files = [("calibration", calibration)]
    if detections.is_dir():
        files += sorted(
            (p.name, p)
            for p in detections.iterdir()
            if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in SUFFIXES
        )
    else:
        files.append((detections.name, detections))
    for name, path in files:
        h.update(name.encode() + b"\0")
        try:
            with open(path, "rb") as fh:
                for block in iter(lambda fh=fh: fh.read(1 << 20), b""):
                    h.update(block)
        except OSError:
            h.update(b"<missing>")
        h.update(b"\0")
    return h.hexdigest()


def _done(folder: Path, calibration: Path, detections: Path, settings: str, inputs: str):
    """The summary of a finished run in ``folder`` of inputs with this content digest
    (`inputs_digest`) and these settings whose outputs are whole (the summary's sha256 of
    ``points3d.csv`` matches the file), else None."""
    recover_outputs(folder)  # a commit interrupted by a kill: completed first
    outputs = [folder / "points3d.csv", folder / "summary.json"]
    status_path = folder / STATUS_FILE
    if not all(p.is_file() for p in outputs) or not status_path.is_file():
        return None
    try:
        status = json.loads(status_path.read_text())
        summary = json.loads(outputs[1].read_text())
    except (OSError, ValueError):
        return None
    given = summary.get("inputs", {})
    if status.get("status") not in ("ok", "skipped") or status.get("settings") != settings:
        return None
    if status.get("inputs_sha256") != inputs:  # contents, not file times
        return None
    if given.get("calibration") != str(calibration.resolve()) or given.get("detections") != str(
        detections.resolve()
    ):
        return None
    recorded = (summary.get("outputs") or {}).get("points3d_sha256")
    if recorded is not None and recorded != file_digest(outputs[0]):
        return None
    return summary


def previous_run(
    out: Path, calibration: Path, detections: Path, settings: str, inputs: str | None = None
) -> tuple[Path, dict] | None:
    """An earlier finished run of this session: in its own output folder, or in the folder of
    the same name of a sibling batch (``runs/batch/*/<name>``), newest first. inputs: the
    inputs' `inputs_digest` (default: computed)."""
    if inputs is None:
        inputs = inputs_digest(calibration, detections)
    candidates = [out]
    batches = out.parent.parent
    if batches.is_dir():
        sib = [b / out.name for b in batches.iterdir() if b.is_dir() and b != out.parent]
        candidates += sorted(
            (p for p in sib if p.is_dir()), key=lambda p: p.stat().st_mtime, reverse=True
        )
    for folder in candidates:
        summary = _done(folder, calibration, detections, settings, inputs)
        if summary is not None:
            return folder, summary
    return None


def _row_from_summary(row: dict, summary: dict) -> None:
    row["frames"] = summary.get("num_frames")
    row["completeness"] = summary.get("completeness")
    row["median_reprojection_error_px"] = (summary.get("reprojection_error_px") or {}).get("median")
    held = (summary.get("deformation") or {}).get("heldout") or {}
    if held.get("checked"):  # 0/8: the net was not used, the tracks are interpolated
        row["net_parts"] = f"{len(held['net_parts'])}/{len(held['net_mm'])}"


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if isinstance(exc, ValueError) else f"{type(exc).__name__}: {text}"


def run_session(
    cfg: DictConfig,
    job_dir: str | Path | None = None,
    run: Callable[[DictConfig], dict] = track_run,
) -> dict:
    """The batch job: track one session (`run`: adjust-track's, `adjust.pipeline.run`), never
    raising.

    ``job_dir``: where the status row goes (default: Hydra's job folder); the outputs go there
    too, or to ``output.dir/<session name>`` when output.dir is set. Returns the status row
    (`SUMMARY_COLUMNS` plus ``name``, ``settings``)."""
    t0 = time.perf_counter()
    if job_dir is None:
        hc = HydraConfig.get()
        job_dir, num = Path(hc.runtime.output_dir), hc.job.num
    else:
        job_dir, num = Path(job_dir), None
    job_dir.mkdir(parents=True, exist_ok=True)
    session = OmegaConf.select(cfg, SESSION_KEY)
    name = session_name(session, num)
    given_out = OmegaConf.select(cfg, "output.dir")
    out = Path(str(given_out)) / name if given_out else job_dir
    row: dict[str, Any] = {c: None for c in SUMMARY_COLUMNS}
    row.update(session=str(session) if session else name, name=name, output=str(out), error="")
    try:
        row["settings"] = settings_hash(cfg)
        cfg = with_session(cfg)
        calibration = Path(str(OmegaConf.select(cfg, "input.calibration")))
        detections = Path(str(OmegaConf.select(cfg, "input.detections")))
        row["inputs_sha256"] = inputs_digest(calibration, detections)
        prev = None
        if not BatchConfig.from_config(cfg).force:
            prev = previous_run(out, calibration, detections, row["settings"], row["inputs_sha256"])
        if prev is not None:
            folder, summary = prev
            row.update(status="skipped", output=str(folder))
            row["error"] = "done with the same inputs (sha256) and settings (force=true re-runs)"
            _row_from_summary(row, summary)
            log.info("session %s: skipped, done in %s", name, folder)
        else:
            cfg = cfg.copy()
            with open_dict(cfg):
                cfg.output.dir = str(out)
            with output_lock(out):  # another run in this session's folder: this one fails
                summary = run(cfg)
            row["status"] = "ok"
            _row_from_summary(row, summary)
    except Exception as exc:  # noqa: BLE001 - one failed session must not stop the batch
        row.update(status="failed", error=_one_line(exc))
        if isinstance(exc, ValueError):  # bad input: the message says it all
            log.error("session %s failed: %s", name, row["error"])
        else:
            log.exception("session %s failed", name)
    row["seconds"] = round(time.perf_counter() - t0, 3)
    write_text(job_dir / STATUS_FILE, json.dumps(row, default=str) + "\n")
    if out != job_dir and row["status"] == "ok":
        write_text(out / STATUS_FILE, json.dumps(row, default=str) + "\n")
    return row


def collect(sweep_dir: str | Path, names: set[str] | None = None) -> list[dict]:
    """The status rows of a batch folder's jobs (sorted by session); names: only the jobs of
    these folder names (a sweep folder reused by another batch holds its rows too)."""
    rows = []
    for path in sorted(Path(sweep_dir).glob(f"*/{STATUS_FILE}")):
        if names is not None and path.parent.name not in names:
            continue
        try:
            rows.append(json.loads(path.read_text()))
        except (OSError, ValueError) as exc:
            rows.append({"session": path.parent.name, "status": "failed", "error": str(exc)})
    return sorted(rows, key=lambda r: str(r.get("session")))


def write_summary(sweep_dir: str | Path, rows: list[dict] | None = None) -> Path:
    """Write ``summary.csv`` (`SUMMARY_COLUMNS`) of a batch folder atomically."""
    rows = collect(sweep_dir) if rows is None else rows
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(SUMMARY_COLUMNS), extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if r.get(k) is None else r.get(k) for k in SUMMARY_COLUMNS})
    return write_text(Path(sweep_dir) / SUMMARY_FILE, buf.getvalue())


def read_summary(path: str | Path) -> list[dict]:
    """The rows of a batch ``summary.csv`` (strings; empty cells as '')."""
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def batch_sessions(config: DictConfig) -> set[str] | None:
    """The folder names of a multirun's sessions (its ``input.session`` override, a list or one
    folder), or None when it sweeps no session (then its jobs are named job<N>)."""
    task = [str(o) for o in OmegaConf.select(config, "hydra.overrides.task", default=[]) or []]
    given = [o for o in task if o.split("=", 1)[0].lstrip("+~") == SESSION_KEY and "=" in o]
    if not given:
        return None
    value = OverridesParser.create().parse_override(given[-1]).value()
    values = getattr(value, "list", [value])
    return {session_name(str(getattr(v, "text", v))) for v in values}


class BatchSummary(Callback):
    """Hydra callback: after a multirun, ``summary.csv`` in the sweep folder, one log line per
    failed session, and exit status 1 when a session failed or none ran."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        project.announce()  # the per-project settings the console script added

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        rows = collect(sweep_dir, batch_sessions(config))
        if not rows:
            log.error("batch: no session ran (no status row in %s)", sweep_dir)
            raise SystemExit(1)
        path = write_summary(sweep_dir, rows)
        counts = {s: sum(r.get("status") == s for r in rows) for s in ("ok", "skipped", "failed")}
        for r in rows:
            if r.get("status") == "failed":
                log.error("session %s failed: %s", r.get("session"), r.get("error"))
        log.info(
            "batch: %d sessions, %d ok, %d skipped, %d failed; %s",
            len(rows),
            counts["ok"],
            counts["skipped"],
            counts["failed"],
            path,
        )
        if counts["failed"]:
            log.error(
                "batch: %d of %d sessions failed (see %s); exit status 1",
                counts["failed"],
                len(rows),
                path,
            )
            raise SystemExit(1)
