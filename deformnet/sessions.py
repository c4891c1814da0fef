"""Self-supervised training data from a lab's own recordings: session tokens.

A recording carries no 3D truth, but the masked-mid-token objective needs none: its targets
are the part positions the cameras measured. `adjust-track` writes, into every output folder,
``tokens.npz``:

    rigid (T, K, 3) float32      the rigid body model's points moved by the adjusted poses (mm)
    deformed (T, K, 3) float32   the parts triangulated from >= 2 cameras, gated against
                                 mis-detections by reprojection error; NaN where not
    observed (T, K) bool         where `deformed` is such a measurement
    parts (K,), body_points (K, 3), body_name, fps (NaN if unknown), version

A token pairs the rigid point with the measurement; windows and masks are cut from it as from
a simulated sequence (`deformnet.data`), and only measured part-frames are ever targets. In
memory only (not in ``tokens.npz``), ``inputs`` (T, K) bool may mark part-frames whose
``deformed`` value is an input and never a target (``deformation=self``'s single-view anchors).

This module reads those files and never imports `adjust` (the layering rule). A *raw* session
folder (``calibration.toml`` + detections) is turned into tokens by a builder that the
config names (``data.builder._target_``, by default `adjust.tokens.build_session_tokens`,
which runs ``adjust-track`` on it): the dependency is injected, not imported.

Splits: by session when there are two or more (the last ``ceil(val_fraction * n)``
sessions in sorted order validate), else by time blocks of one session (every
``round(1 / val_fraction)``-th block of ``block_frames`` frames validates).
"""

from __future__ import annotations

import glob
import logging
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from deformnet.atomic import atomic_path
from deformnet.body import BodyModel
from deformnet.windows import SequenceArrays

log = logging.getLogger(__name__)

__all__ = [
    "TOKENS_FILE",
    "SessionTokens",
    "resolve_sessions",
    "load_session_tokens",
    "split_sessions",
]

TOKENS_FILE = "tokens.npz"
VERSION = 1


@dataclass(frozen=True)
class SessionTokens:
    """One session's tokens (see the module docstring for the arrays)."""

    rigid: np.ndarray
    deformed: np.ndarray
    observed: np.ndarray
    parts: tuple[str, ...]
    body_points: np.ndarray
    body_name: str = "body"
    fps: float = float("nan")
    source: str = ""
    inputs: np.ndarray | None = None

    def __post_init__(self) -> None:
        T, K = self.observed.shape
        if self.inputs is not None and np.shape(self.inputs) != (T, K):
            raise ValueError(
                f"{self.source or 'tokens'}: inputs must be (T, K) = ({T}, {K}), "
                f"got {np.shape(self.inputs)}"
            )
        if self.rigid.shape != (T, K, 3) or self.deformed.shape != (T, K, 3):
            raise ValueError(
                f"{self.source or 'tokens'}: rigid/deformed must be (T, K, 3) = ({T}, {K}, 3), "
                f"got {self.rigid.shape}, {self.deformed.shape}"
            )
        if len(self.parts) != K or self.body_points.shape != (K, 3):
            raise ValueError(
                f"{self.source or 'tokens'}: {len(self.parts)} parts / body points "
                f"{self.body_points.shape} for {K} parts"
            )

    def body_model(self) -> BodyModel:
        """The session's rigid body model: its parts at its body points."""
        return BodyModel.from_mapping(
            {p: [float(c) for c in xyz] for p, xyz in zip(self.parts, self.body_points)},
            name=self.body_name,
        )

    @property
    def num_frames(self) -> int:
        return int(self.observed.shape[0])

    def save(self, path: str | os.PathLike) -> Path:
        """Write ``tokens.npz`` atomically."""
        path = Path(path)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(
                    f,
                    rigid=self.rigid.astype(np.float32),
                    deformed=np.where(self.observed[..., None], self.deformed, np.nan).astype(
                        np.float32
                    ),
                    observed=self.observed.astype(bool),
                    parts=np.asarray(self.parts),
                    body_points=np.asarray(self.body_points, dtype=np.float64),
                    body_name=np.asarray(self.body_name),
                    fps=np.asarray(float(self.fps)),
                    version=np.asarray(VERSION),
                )
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> SessionTokens:
        """Read a ``tokens.npz`` (ValueError naming the file if it is not one)."""
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                need = {"rigid", "deformed", "observed", "parts", "body_points"}
                missing = need - set(z.files)
                if missing:
                    raise ValueError(f"{path}: not a session tokens file (no {sorted(missing)})")
                rigid = z["rigid"].astype(np.float32)
                deformed = z["deformed"].astype(np.float32)
                observed = z["observed"].astype(bool) & np.isfinite(deformed).all(-1)
                parts = tuple(str(p) for p in z["parts"])
                body = z["body_points"].astype(np.float64)
                name = str(z["body_name"]) if "body_name" in z.files else "body"
                fps = float(z["fps"]) if "fps" in z.files else float("nan")
        except (OSError, EOFError, KeyError) as exc:
            raise ValueError(f"{path}: cannot read session tokens: {exc}") from None
        if not np.isfinite(rigid).all():
            bad = int(np.argwhere(~np.isfinite(rigid).all(-1))[0, 0])
            raise ValueError(f"{path}: rigid points are not finite (frame {bad})")
        return cls(rigid, deformed, observed, parts, body, name, fps, str(path))

    def to_sequence(self, start: int = 0, stop: int | None = None):
        """Frames start..stop-1 as a `deformnet.windows.SequenceArrays` (unmeasured deformed values
        replaced by the rigid points; they are masked; ``inputs`` kept as input-only)."""
        s = slice(start, stop)
        obs = self.observed[s]
        extra = None if self.inputs is None else self.inputs[s] & ~obs
        seen = obs if extra is None else obs | extra
        deformed = np.where(seen[..., None], self.deformed[s], self.rigid[s])
        return SequenceArrays(self.rigid[s], deformed.astype(np.float32), obs, extra)


def _is_raw_session(path: Path) -> bool:
    return path.is_dir() and (path / "calibration.toml").is_file()


def resolve_sessions(patterns: Sequence[str | os.PathLike]) -> list[Path]:
    """Folders (or ``tokens.npz`` files) named by paths or glob patterns (``glob(PATTERN)``, as
    in ``adjust-track -m input.session=glob(...)``, works too), sorted, each once.

    A folder counts when it holds ``tokens.npz`` (an adjust-track output folder) or
    ``calibration.toml`` (a raw session); ValueError naming a pattern that matches nothing
    usable."""
    if isinstance(patterns, (str, os.PathLike)):
        patterns = [patterns]
    flat: list = []
    exclude: list[str] = []
    for pat in patterns:  # Hydra parses an unquoted glob(...) into {include, exclude}
        if hasattr(pat, "get") and pat.get("include") is not None:
            flat.extend(str(i) for i in pat["include"])
            exclude.extend(str(e) for e in (pat.get("exclude") or []))
        else:
            flat.append(pat)
    out: list[Path] = []
    for pat in flat:
        pat = os.fspath(pat)
        if pat.startswith("glob(") and pat.endswith(")"):  # adjust-track -m's batch syntax
            pat = pat[5:-1]
        hits = sorted(glob.glob(pat)) if glob.has_magic(pat) else [pat]
        found = []
        for h in hits:
            p = Path(h)
            if p.is_file() and p.name.endswith(".npz"):
                found.append(p)
            elif p.is_dir() and ((p / TOKENS_FILE).is_file() or _is_raw_session(p)):
                found.append(p)
        if not found:
            raise ValueError(
                f"data.sessions: {pat!r} names no session (a folder with {TOKENS_FILE} from "
                "adjust-track, or with calibration.toml + detections)"
            )
        out.extend(found)
    if exclude:
        import fnmatch

        out = [p for p in out if not any(fnmatch.fnmatch(str(p), e) for e in exclude)]
    seen: set[Path] = set()
    unique = []
    for p in out:
        r = p.resolve()
        if r not in seen:
            seen.add(r)
            unique.append(p)
    return unique


def load_session_tokens(path: Path, builder: Callable[[Path], Path] | None = None) -> SessionTokens:
    """The tokens of one resolved session: its ``tokens.npz``, or, for a raw session folder,
    those `builder(path) -> tokens.npz path` makes (ValueError if there is no builder)."""
    path = Path(path)
    if path.is_file():
        return SessionTokens.load(path)
    if (path / TOKENS_FILE).is_file():
        return SessionTokens.load(path / TOKENS_FILE)
    if builder is None:
        raise ValueError(
            f"{path} is a raw session (calibration.toml + detections) and no data.builder is "
            f"configured to track it; run adjust-track input.session={path} first"
        )
    log.info("session %s: tracking it to get its tokens", path)
    return SessionTokens.load(builder(path))


def check_compatible(tokens: Sequence[SessionTokens]) -> None:
    """All sessions must share the parts (same names, same order)."""
    first = tokens[0]
    for t in tokens[1:]:
        if t.parts != first.parts:
            raise ValueError(
                f"{t.source}: parts {list(t.parts)} differ from {first.source}'s "
                f"{list(first.parts)}; train one net per skeleton"
            )


def split_sessions(
    tokens: Sequence[SessionTokens],
    val_fraction: float = 0.2,
    block_frames: int = 500,
    min_frames: int = 1,
) -> tuple[list, list, dict]:
    """(train sequences, val sequences, facts) as `SequenceArrays`.

    Two or more sessions: split by session (the last ceil(val_fraction n) validate); one:
    by time blocks of ``block_frames`` frames (fewer for a short session: at least two val
    blocks) where every round(1/val_fraction)-th block validates and the first trains;
    consecutive blocks of one kind form one piece. Pieces shorter than ``min_frames`` (a
    window) are dropped."""
    if not tokens:
        raise ValueError("data.sessions: no sessions")
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"data.val_fraction must be in (0, 1), got {val_fraction}")
    if len(tokens) >= 2:
        nval = max(1, int(math.ceil(val_fraction * len(tokens))))
        nval = min(nval, len(tokens) - 1)
        train = [t.to_sequence() for t in tokens[:-nval]]
        val = [t.to_sequence() for t in tokens[-nval:]]
        facts = {
            "split": "by session",
            "train_sessions": [t.source for t in tokens[:-nval]],
            "val_sessions": [t.source for t in tokens[-nval:]],
        }
    else:
        t = tokens[0]
        T = t.num_frames
        every = max(2, int(round(1.0 / val_fraction)))
        # a short session gets shorter blocks (down to a window); blocks of equal length, the
        # last one taking the remainder, so none is shorter than a window
        block = max(int(min_frames), min(int(block_frames), T // (2 * every)))
        nblocks = max(1, T // block)
        block = T // nblocks
        starts = [i * block for i in range(nblocks)]
        is_val = [i % every == every - 1 for i in range(len(starts))]
        if not any(is_val) and len(starts) >= 2:  # short session: its last block validates
            is_val[-1] = True
        train, val, vb = [], [], []
        i = 0
        while i < len(starts):  # consecutive blocks of one kind make one piece
            j = i
            while j + 1 < len(starts) and is_val[j + 1] == is_val[i]:
                j += 1
            s, e = starts[i], (T if j == nblocks - 1 else starts[j] + block)
            (val if is_val[i] else train).append(t.to_sequence(s, e))
            if is_val[i]:
                vb.append([s, e])
            i = j + 1
        facts = {"split": "by time blocks", "block_frames": block, "val_blocks": vb}
    train = [s for s in train if s.rigid.shape[0] >= min_frames]
    val = [s for s in val if s.rigid.shape[0] >= min_frames]
    if not train or not val:
        raise ValueError(
            f"data.sessions: too few frames for a train/val split with windows of {min_frames} "
            f"frames (sessions: {', '.join(t.source for t in tokens)}; frames: "
            f"{', '.join(str(t.num_frames) for t in tokens)})"
        )
    facts["train_frames"] = int(sum(s.rigid.shape[0] for s in train))
    facts["val_frames"] = int(sum(s.rigid.shape[0] for s in val))
    facts["train_targets"] = int(sum(s.observed.sum() for s in train))
    facts["val_targets"] = int(sum(s.observed.sum() for s in val))
    return train, val, facts
