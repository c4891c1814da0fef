"""The Kalman-smoother peer: triangulated 3D points, each part smoothed and its gaps filled by a
constant-velocity Kalman filter and Rauch-Tung-Striebel smoother (pykalman, the `bench` extra:
`pip install -e '.[bench]'`), its noise covariances fitted to the track by EM, as a lab does
with the points anipose or a DLT gives it.

Per part, state (position, velocity) in mm and mm/frame, observation the triangulated position
(a missing one is masked: the filter predicts through the gap); the transition and observation
covariances (full 6 x 6 and 3 x 3) and the initial state are fitted by `em_iterations` of EM,
then smoothed. A part never triangulated stays missing (nothing to fill it from).
"""

from __future__ import annotations

import time

import numpy as np


def available() -> bool:
    """Whether pykalman is installed (the `bench` extra)."""
    try:
        import pykalman  # noqa: F401
    except ImportError:
        return False
    return True


def wanted(skip: bool) -> bool:
    """Whether a benchmark runs the Kalman smoother: not skipped (``--no-kalman``) and
    installed; a warning when it is wanted but missing."""
    from peers import wanted as peer_wanted

    return peer_wanted(
        skip,
        available(),
        "pykalman not installed (pip install -e '.[bench]'): the Kalman rows are skipped",
    )


def kalman_smooth(points: np.ndarray, em_iterations: int = 10) -> tuple[np.ndarray, float]:
    """points (T, K, 3) mm, NaN = missing -> (smoothed points (T, K, 3), seconds)."""
    from pykalman import KalmanFilter

    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[-1] != 3:
        raise ValueError(f"points must be (T, K, 3), got {points.shape}")
    T, K, _ = points.shape
    eye, zero = np.eye(3), np.zeros((3, 3))
    F = np.block([[eye, eye], [zero, eye]])  # x += v (one frame)
    H = np.hstack([eye, zero])
    out = np.full_like(points, np.nan)
    t0 = time.perf_counter()
    for k in range(K):
        obs = points[:, k]
        seen = np.isfinite(obs).all(-1)
        if seen.sum() < 2:
            continue
        first = obs[np.argmax(seen)]
        kf = KalmanFilter(
            transition_matrices=F,
            observation_matrices=H,
            initial_state_mean=np.concatenate([first, np.zeros(3)]),
            initial_state_covariance=np.diag([100.0] * 3 + [10.0] * 3),
            transition_covariance=np.diag([1.0] * 3 + [1.0] * 3),
            observation_covariance=np.eye(3) * 4.0,
            em_vars=["transition_covariance", "observation_covariance", "initial_state_mean"],
        )
        z = np.ma.masked_array(np.where(seen[:, None], obs, 0.0), mask=~seen[:, None].repeat(3, 1))
        kf = kf.em(z, n_iter=int(em_iterations))
        mean, _ = kf.smooth(z)
        out[:, k] = mean[:, :3]
    return out, time.perf_counter() - t0
