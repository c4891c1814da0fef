"""Pose-track least-squares adjustment (paper: "Motion-Track Constraint", "Least-Squares
Adjustment"): per-frame rigid poses of the body model from incomplete multi-camera detections,
a cubic motion-track constraint, a two-Gaussian + robust stochastic model, a banded
Levenberg-Marquardt solver in O(T), pose covariances by selected inversion and fused part
positions with uncertainties.

Entry point: `adjust_poses(xy, weight, cams, body_points, SolverConfig(...)) -> AdjustmentResult`.
"""

from adjust.lsq.config import SolverConfig
from adjust.lsq.constraint import make_grid, track_residuals
from adjust.lsq.net_observation import DeformableObservation
from adjust.lsq.observation import ObservationModel, RigidObservation
from adjust.lsq.solver import AdjustmentResult, adjust_poses, normal_matrix

__all__ = [
    "AdjustmentResult",
    "DeformableObservation",
    "ObservationModel",
    "RigidObservation",
    "SolverConfig",
    "adjust_poses",
    "make_grid",
    "normal_matrix",
    "track_residuals",
]
