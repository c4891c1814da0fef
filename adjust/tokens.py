"""Self-supervised tokens of a session folder: `build_session_tokens`, the ``data.builder`` of
`deformnet-train data=sessions` for a raw session (tracked first). The tokens of a tracked
session are `adjust.tokenize.session_tokens` (re-exported here).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig

from adjust.pipeline import run as track_run
from adjust.tokenize import session_tokens
from deformnet.confutil import compose
from deformnet.sessions import TOKENS_FILE

__all__ = ["session_tokens", "build_session_tokens"]


def build_session_tokens(
    session: str | Path,
    out_root: str | Path,
    overrides: list[str] | None = None,
    run: Callable[[DictConfig], dict] = track_run,
) -> Path:
    """A raw session folder (``calibration.toml`` + detections) -> its ``tokens.npz``:
    ``adjust-track input.session=SESSION output.dir=OUT_ROOT/<name>`` (default
    ``deformation=interp``), reused when that folder already holds tokens newer than the
    session's files. The `data.builder` of `deformnet-train data=sessions`. run: the tracker
    (`adjust.pipeline.run`, adjust-track's function)."""
    session = Path(session)
    out = Path(out_root) / session.name
    tokens = out / TOKENS_FILE
    newest = max((p.stat().st_mtime for p in session.rglob("*") if p.is_file()), default=0.0)
    if tokens.is_file() and tokens.stat().st_mtime >= newest:
        return tokens
    cfg = compose(
        "track",
        [
            f"input.session={session}",
            f"output.dir={out}",
            "progress=false",
            *(overrides or []),
        ],
    )
    run(cfg)
    if not tokens.is_file():  # pragma: no cover - run() always writes them
        raise ValueError(f"{session}: adjust-track wrote no {TOKENS_FILE} into {out}")
    return tokens
