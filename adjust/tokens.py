"""Self-supervised tokens from a tracked session (the format: `deformnet.sessions`).

A token pairs a body part's rigid-model point, the rigid body moved by the adjusted pose, with
its measured position: the part triangulated from >= 2 cameras and gated against
mis-detections by reprojection error (`adjust.estimate.consensus`). Part-frames that are not
measured are masked; they are never targets. `adjust-track` writes them into every output folder
(``tokens.npz``) and ``deformation=self`` trains on them directly; `deformnet-train
data=sessions` reads them (or, for a raw session folder, calls `build_session_tokens`, which
tracks it first).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from deformnet.sessions import TOKENS_FILE, SessionTokens

__all__ = ["session_tokens", "build_session_tokens"]


def session_tokens(
    poses: np.ndarray,
    body_points: np.ndarray,
    cons,
    parts,
    body_name: str = "body",
    fps: float | None = None,
    source: str = "",
) -> SessionTokens:
    """Tokens of one session.

    poses (T, 6) the adjusted poses (Rodrigues rad, mm; model -> global); body_points (K, 3)
    mm; cons: the session's `adjust.estimate.Consensus` (points (T, K, 3), observed (T, K)
    gated >= 2-view measurements); parts (K names)."""
    from adjust.lsq.geometry import rigid_points

    poses = np.asarray(poses, dtype=np.float64)
    B = np.asarray(body_points, dtype=np.float64)
    T, K = cons.observed.shape
    if poses.shape != (T, 6) or B.shape != (K, 3):
        raise ValueError(
            f"session tokens: poses {poses.shape} / body {B.shape} do not fit {T} frames x {K} "
            "parts"
        )
    with torch.no_grad():
        X, _ = rigid_points(torch.tensor(poses), torch.tensor(B))
    rigid = X.numpy()
    ok = np.isfinite(poses).all(-1)
    observed = cons.observed & np.isfinite(cons.points).all(-1) & ok[:, None]
    rigid = np.where(ok[:, None, None], rigid, np.nan_to_num(cons.points))
    if not np.isfinite(rigid).all():
        rigid = np.nan_to_num(rigid)
    deformed = np.where(observed[..., None], cons.points, np.nan)
    return SessionTokens(
        rigid.astype(np.float32),
        deformed.astype(np.float32),
        observed,
        tuple(str(p) for p in parts),
        B,
        str(body_name),
        float(fps) if fps is not None and math.isfinite(float(fps)) else float("nan"),
        source,
    )


def build_session_tokens(
    session: str | Path, out_root: str | Path, overrides: list[str] | None = None
) -> Path:
    """A raw session folder (``calibration.toml`` + detections) -> its ``tokens.npz``:
    ``adjust-track input.session=SESSION output.dir=OUT_ROOT/<name>`` (default
    ``deformation=interp``), reused when that folder already holds tokens newer than the
    session's files. The `data.builder` of `deformnet-train data=sessions`."""
    from adjust.track import run
    from deformnet.confutil import compose

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
