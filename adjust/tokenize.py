"""Self-supervised tokens from a tracked session (the format: `deformnet.sessions`).

A token pairs a body part's rigid-model point, the rigid body moved by the adjusted pose, with
its measured position: the part triangulated from >= 2 cameras and gated against
mis-detections by reprojection error (`adjust.estimate.consensus`). Part-frames that are not
measured are masked; they are never targets. `adjust-track` writes them into every output folder
(``tokens.npz``, `adjust.pipeline`) and ``deformation=self`` trains on them directly;
`deformnet-train data=sessions` reads them (or, for a raw session folder, calls
`adjust.tokens.build_session_tokens`, which tracks it first).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from adjust.lsq.geometry import rigid_points
from deformnet.sessions import SessionTokens

__all__ = ["session_tokens"]


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
