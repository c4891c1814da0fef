"""Simulated multi-camera scenes: a camera rig, per-camera self-occlusion and a detector model.

Turns simulated 3D body parts (``deformnet.sim.SimData``) into what a real user has: calibrated
cameras and DeepLabCut-like 2D detections per camera, with occlusions, misses, swaps, outliers,
pixel noise and likelihoods. One module per concern, every public name re-exported here:

- `adjust.scene.rig` -- `camera_look_at` / `rig_from_config` / `default_rig` / `arena_in_view`:
  `Camera`s from position, look-at point and up vector (world -> camera ``x_cam = R X + t``;
  pixel origin at the top-left pixel's centre, so the principal point of a W x H image is
  ((W-1)/2, (H-1)/2)).
- `adjust.scene.occlusion` -- `Ellipsoid` / `occluded_by_ellipsoids` / `occluded_by_boxes`: a
  part is hidden from a camera when the segment from the camera centre to the part passes
  through a body-proxy ellipsoid moved with the pose (the segment's last `surface_margin` mm,
  the part's own surface vicinity, is not tested) or through the lock box.
- `adjust.scene.detector` -- `DetectorConfig` / `simulate_scene`: the detector model,
  vectorised over (T, K, C) in numpy; deterministic for a seed.
- `adjust.scene.folder` -- `write_scene`: the scene folder (calibration.toml, detections/,
  truth.npz); `write_truth_labels`: its true behavior labels as a `fnum,label` CSV.

Shapes: T frames, K parts, C cameras. Points in mm, pixels in px.
"""

from __future__ import annotations

from adjust.scene.detector import (
    DEFAULT_OCCLUDERS,
    DetectorConfig,
    SceneDetections,
    detector_config,
    simulate_scene,
)
from adjust.scene.folder import scene_fps, write_scene, write_truth_labels
from adjust.scene.occlusion import (
    Ellipsoid,
    ellipsoids_from_config,
    lockbox_boxes,
    occluded_by_boxes,
    occluded_by_ellipsoids,
)
from adjust.scene.rig import arena_in_view, camera_look_at, default_rig, rig_from_config

__all__ = [
    "DEFAULT_OCCLUDERS",
    "DetectorConfig",
    "Ellipsoid",
    "SceneDetections",
    "arena_in_view",
    "camera_look_at",
    "default_rig",
    "detector_config",
    "ellipsoids_from_config",
    "lockbox_boxes",
    "occluded_by_boxes",
    "occluded_by_ellipsoids",
    "rig_from_config",
    "scene_fps",
    "simulate_scene",
    "write_scene",
    "write_truth_labels",
]
