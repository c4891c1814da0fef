"""Output folders that are whole: one run at a time, one complete set of outputs at a time.

- `output_or`: the OmegaConf resolver of every app's ``hydra.run.dir``
  (``${output_or:${oc.select:output.dir,null},runs/<app>/<time>}``): ``output.dir`` when it is
  set and usable, locked for this process (`hold_output`) before Hydra writes ``.hydra/`` and
  the log there; an unusable or busy folder gives a scratch folder under the system's temporary
  folder instead, so that the app reports it in one line (`prepare_output`) and nothing lands in
  the working directory or in the other run's folder.
- `hold_output` / `output_lock`: a lock on an output folder, the file ``.mousetrack.lock`` in
  it (``flock``; it holds the owner's process id, host and start time). A second run into the
  folder while one runs is refused (`OutputBusy`, naming the owner). The kernel releases a
  lock when its process ends, however it ends, so the lock left by a killed run is stale: it is
  taken over, with a warning naming the dead process.
- `OutputSet`: a run's output files committed as one set. Each file is written into a hidden
  staging folder inside the output folder (``.mousetrack-staging-<pid>-*``); `OutputSet.commit`
  then writes the summary (with every file's sha256 and size, ``outputs.files``) and a journal
  (``.mousetrack-commit.json``, written atomically: the commit point), removes the previous
  summary, moves the files into place, the summary last, and removes the journal. A run that
  ends before the commit (an error, Ctrl-C, SIGTERM, SIGKILL) leaves the previous outputs as
  they were; one killed during the moves leaves the journal, and the next `OutputSet` (or
  `recover_outputs`) completes the moves. A summary present is therefore always that of the
  files beside it, and a folder holds the previous complete run or the new one.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import fcntl
import json
import logging
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from deformnet.atomic import file_digest, finite_or_none, write_text
from deformnet.paths import output_dir

log = logging.getLogger(__name__)

LOCK_NAME = ".mousetrack.lock"
STAGING_PREFIX = ".mousetrack-staging-"
JOURNAL_NAME = ".mousetrack-commit.json"
SUMMARY_NAME = "summary.json"


class OutputBusy(ValueError):
    """Another running process holds the output folder's lock; the message names it."""


# --- the lock ---------------------------------------------------------------------------------

#: folders this process holds: real path -> [file descriptor, hold count]
_HELD: dict[str, list[int]] = {}


def _read_owner(fd: int) -> dict:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        data = os.read(fd, 4096)
        owner = json.loads(data.decode("utf-8")) if data.strip() else {}
    except (OSError, ValueError, UnicodeDecodeError):
        return {}
    return owner if isinstance(owner, dict) else {}


def _alive(pid) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, TypeError, ValueError, OverflowError):
        return True  # another user's process, or not a pid: assume it runs
    return True


def _describe(owner: dict) -> str:
    if not owner:
        return "another process"
    since = owner.get("started")
    when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(since)) if since else "?"
    return f"process {owner.get('pid', '?')} on {owner.get('host', '?')}, since {when}"


def hold_output(folder: str | os.PathLike) -> None:
    """Lock `folder` (an existing folder) for this process, or raise `OutputBusy` naming the
    process that holds it. Re-entrant: each call needs one `release_output`; every lock still
    held is released when the process exits. A stale lock (its process gone) is taken over with
    a warning."""
    key = os.path.realpath(folder)
    if key in _HELD:
        _HELD[key][1] += 1
        return
    path = os.path.join(key, LOCK_NAME)
    for _ in range(20):
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            owner = _read_owner(fd)
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise  # no locks on this file system: an OSError, one line from the app
            raise OutputBusy(
                f"output.dir={folder} is in use by another run ({_describe(owner)}); wait for "
                "it to finish, or choose another output.dir"
            ) from None
        try:  # the file may have been removed by its last holder meanwhile: lock the new one
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            continue
        owner = _read_owner(fd)
        if owner.get("pid") not in (None, os.getpid()):
            log.warning(
                "output.dir=%s: a stale lock of %s (%s) is taken over",
                folder,
                _describe(owner),
                "no longer running" if not _alive(owner.get("pid")) else "it no longer holds it",
            )
        me = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time()}
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, (json.dumps(me) + "\n").encode())
        _HELD[key] = [fd, 1]
        return
    raise OutputBusy(f"output.dir={folder}: its lock keeps changing hands; try again")


def release_output(folder: str | os.PathLike) -> None:
    """Undo one `hold_output`; the last removes the lock file and releases the lock."""
    key = os.path.realpath(folder)
    held = _HELD.get(key)
    if held is None:
        return
    held[1] -= 1
    if held[1] > 0:
        return
    del _HELD[key]
    fd = held[0]
    path = os.path.join(key, LOCK_NAME)
    with contextlib.suppress(OSError):
        if os.stat(path).st_ino == os.fstat(fd).st_ino:
            os.unlink(path)  # still locked: a process that opened it retries on the new file
    os.close(fd)


def holds_output(folder: str | os.PathLike) -> bool:
    """True when this process holds `folder`'s lock."""
    return os.path.realpath(folder) in _HELD


@atexit.register
def _release_all() -> None:
    for key in list(_HELD):
        _HELD[key][1] = 1
        release_output(key)


@contextlib.contextmanager
def output_lock(folder: str | os.PathLike) -> Iterator[Path]:
    """``with output_lock(folder):`` the folder (created) locked for the block (`hold_output`)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    hold_output(folder)
    try:
        yield folder
    finally:
        release_output(folder)


# --- the run folder ---------------------------------------------------------------------------


def _scratch(default: str) -> str:
    return str(Path(tempfile.gettempdir()) / "mousetrack" / default)


def output_or(given, default: str, lock=True) -> str:
    """Hydra run folder: ``output.dir`` when it is set and usable (an existing folder, or one
    that can be created, writable) and, with `lock`, not in use by another run (it is then held
    by this process until it exits); else `default` (under runs/) when it is not set, or, when
    it is set but unusable or busy, `default` under the system's temporary folder, so that the
    app itself reports the folder in one line (`prepare_output`) instead of Hydra failing with a
    traceback, and nothing lands in the working directory or in the other run's folder. Used as
    ``hydra.run.dir: ${output_or:${oc.select:output.dir,null},runs/...}`` (a batch's
    ``hydra.sweep.dir`` passes ``false`` as a third argument: its jobs lock their own folders)."""
    if given is None or str(given) in ("", "None", "null"):
        return default
    p = Path(str(given))
    try:  # Hydra creates it next anyway; a real write test (access() is always true for root)
        p.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".write-test.", dir=p)
        os.close(fd)
        os.unlink(tmp)
    except OSError:  # Hydra's files go to a scratch folder, not the working directory
        return _scratch(default)
    if lock and str(lock).lower() != "false":
        try:
            hold_output(p)  # held until the process exits
        except (OutputBusy, OSError):
            return _scratch(default)
    return str(p)


def output_beside(output, source, default: str) -> str:
    """Hydra run folder of an app that writes one file (adjust-export's ``output``, by default
    beside its ``source``, the tracks): the folder of `output` when given, else that of
    `source`, when it is usable (`output_or`, unlocked: the file itself is written atomically);
    else `default`. Used as ``hydra.run.dir: ${output_beside:${oc.select:output,null},
    ${oc.select:tracks,null},runs/export/...}``, with ``hydra.output_subdir: .hydra-export`` so
    that a track's own ``.hydra/`` beside the tracks stays as it is."""
    for given in (output, source):
        if given is not None and str(given) not in ("", "None", "null", "???"):
            return output_or(str(Path(str(given)).parent), default, lock=False)
    return default


for _name, _fn in (("output_or", output_or), ("output_beside", output_beside)):
    if not OmegaConf.has_resolver(_name):
        OmegaConf.register_new_resolver(_name, _fn)


def prepare_output(cfg) -> Path:
    """The app's output folder (`deformnet.paths.output_dir`), checked before any computing:
    a file in its place, a folder that cannot be created or written is a ValueError naming it
    (`deformnet.apprun.run_app` then locks a given ``output.dir``: `hold_output`)."""
    given = (
        OmegaConf.select(cfg, "output.dir", default=None) if isinstance(cfg, DictConfig) else None
    )
    if given:
        p = Path(str(given))
        probe = p
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        if probe.exists() and not probe.is_dir():
            raise ValueError(f"output.dir={p}: {probe} is a file, not a folder")
    try:
        out = output_dir(cfg)
    except OSError as exc:
        raise ValueError(f"output folder cannot be created: {exc}") from None
    try:
        fd, tmp = tempfile.mkstemp(prefix=".write-test.", dir=out)
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        raise ValueError(f"output folder {out} is not writable: {exc.strerror or exc}") from None
    return out


# --- the set of outputs -----------------------------------------------------------------------

#: staging folders of the OutputSets open in this process
_OPEN: set[str] = set()


def _staging_pid(name: str) -> int | None:
    try:
        return int(name[len(STAGING_PREFIX) :].split("-", 1)[0])
    except ValueError:
        return None


def _apply(folder: Path, journal: dict) -> None:
    """Carry out a commit journal (again, after an interruption: each step is idempotent)."""
    staging = folder / str(journal["staging"])
    summary = str(journal.get("summary") or SUMMARY_NAME)
    if (staging / summary).exists():  # the new summary not yet in place: the old one goes
        (folder / summary).unlink(missing_ok=True)
    for name in journal.get("remove", []):
        (folder / name).unlink(missing_ok=True)
    for name in journal["files"]:  # the summary last
        src = staging / name
        if src.exists():
            os.replace(src, folder / name)
    (folder / JOURNAL_NAME).unlink(missing_ok=True)
    shutil.rmtree(staging, ignore_errors=True)


def recover_outputs(folder: str | os.PathLike) -> bool:
    """Complete a commit that was interrupted (its journal present) and remove the staging
    folders of runs that ended before committing (their process gone). Returns True when a
    commit was completed."""
    folder = Path(folder)
    done = False
    journal = folder / JOURNAL_NAME
    if journal.is_file():
        try:
            record = json.loads(journal.read_text(encoding="utf-8"))
            staging = str(record["staging"])
            files = [str(n) for n in record["files"]]
        except (OSError, ValueError, KeyError, TypeError):
            record = None
        if record is not None and all(_plain_name(n) for n in [staging, *files]):
            _apply(folder, record)
            log.warning(
                "%s: completed the outputs of a run interrupted while moving them into place (%s)",
                folder,
                ", ".join(files),
            )
            done = True
        else:
            journal.unlink(missing_ok=True)
    if folder.is_dir():
        for d in folder.glob(STAGING_PREFIX + "*"):
            pid = _staging_pid(d.name)
            if str(d) in _OPEN or (pid not in (None, os.getpid()) and _alive(pid)):
                continue  # an open set: this process's, or another running process's
            shutil.rmtree(d, ignore_errors=True)
    return done


def _plain_name(name: str) -> bool:
    return bool(name) and "/" not in name and "\\" not in name and name not in (".", "..")


def _manifest(folder: Path, summary: str) -> dict:
    """The ``outputs.files`` record of the summary now in `folder` ({} when none)."""
    try:
        old = json.loads((folder / summary).read_text(encoding="utf-8"))
        files = (old.get("outputs") or {}).get("files") or {}
    except (OSError, ValueError, AttributeError):
        return {}
    return files if isinstance(files, dict) else {}


class OutputSet:
    """A run's outputs, committed as one set (see the module doc)::

        with OutputSet(out) as outputs:
            write_points3d(outputs.path("points3d.csv"), ...)
            np.savez_compressed(outputs.path("accepted.npz"), ...)
            summary = outputs.commit(summary)  # summary.json last, with every file's sha256

    `path(name)` is where to write output `name` (a plain file name) now; `final(name)` where it
    will be after the commit. Leaving the block without `commit` (an exception, Ctrl-C,
    SIGTERM) discards the staged files: the folder keeps the previous outputs."""

    def __init__(self, folder: str | os.PathLike, summary: str = SUMMARY_NAME):
        self.folder = Path(folder)
        self.summary_name = summary
        self.staging: Path | None = None
        self.names: list[str] = []
        self.committed = False

    def __enter__(self) -> OutputSet:
        self.folder.mkdir(parents=True, exist_ok=True)
        recover_outputs(self.folder)
        self.staging = Path(
            tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}{os.getpid()}-", dir=self.folder)
        )
        _OPEN.add(str(self.staging))
        return self

    def __exit__(self, *exc) -> None:
        if self.staging is not None:
            _OPEN.discard(str(self.staging))
            if not self.committed:
                shutil.rmtree(self.staging, ignore_errors=True)

    def path(self, name: str) -> Path:
        """The staged path of output `name` (write the file there before `commit`)."""
        if self.staging is None:
            raise RuntimeError("OutputSet.path outside its `with` block")
        if not _plain_name(name) or name == self.summary_name or name.startswith("."):
            raise ValueError(f"output name {name!r}: a plain file name other than the summary")
        if name not in self.names:
            self.names.append(name)
        return self.staging / name

    def final(self, name: str) -> Path:
        """Where output `name` will be after the commit."""
        return self.folder / name

    def commit(self, summary: dict | None = None) -> dict | None:
        """Move the staged files into the folder as one set; with a `summary`, write it as
        ``summary.json`` last, with ``outputs.files`` (every file's sha256 and size; for
        ``points3d.csv`` also ``outputs.points3d_sha256`` / ``points3d_bytes``) and
        ``outputs.summary``. Files of the previous set (in its summary's ``outputs.files``,
        unchanged since) that this set lacks are removed. Returns the summary as written."""
        if self.staging is None or self.committed:
            raise RuntimeError("OutputSet.commit outside its `with` block, or twice")
        files = [n for n in self.names if (self.staging / n).exists()]
        manifest = {
            n: {"sha256": file_digest(self.staging / n), "bytes": (self.staging / n).stat().st_size}
            for n in files
        }
        order = list(files)
        if summary is not None:
            summary = dict(summary)
            outputs = dict(summary.get("outputs") or {})
            outputs["summary"] = str(self.folder / self.summary_name)
            if "points3d.csv" in manifest:
                outputs["points3d_sha256"] = manifest["points3d.csv"]["sha256"]
                outputs["points3d_bytes"] = manifest["points3d.csv"]["bytes"]
            outputs["files"] = manifest
            summary["outputs"] = outputs
            summary = finite_or_none(summary)
            write_text(self.staging / self.summary_name, json.dumps(summary, indent=2) + "\n")
            order.append(self.summary_name)
        old = _manifest(self.folder, self.summary_name)
        remove = []
        for name, facts in old.items():
            if name in manifest or not _plain_name(str(name)) or name == self.summary_name:
                continue
            p = self.folder / str(name)
            with contextlib.suppress(OSError, TypeError, AttributeError):
                if p.is_file() and file_digest(p) == facts.get("sha256"):
                    remove.append(str(name))  # the previous run's, untouched since
        journal = {
            "staging": self.staging.name,
            "files": order,
            "summary": self.summary_name,
            "remove": remove,
        }
        write_text(self.folder / JOURNAL_NAME, json.dumps(journal) + "\n")  # the commit point
        self.committed = True
        _apply(self.folder, journal)
        return summary
