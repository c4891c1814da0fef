"""Real file formats: anipose calibration TOML, DeepLabCut 2D tables, anipose-style points3d CSV.

- `load_calibration` / `save_calibration`: anipose ``calibration.toml`` <-> list of `Camera`
  (mm; a file's ``[metadata] units``, `calibration_units`, is converted on reading).
- `read_dlc` / `write_dlc_csv`: one DeepLabCut 2D table (CSV or H5) <-> `DLCTable`.
- `load_detections` / `load_scene`: a folder with one DeepLabCut file per camera -> `Detections`
  (T, K, C, 2), matched to the calibration's cameras by name and to a body model by aliases;
  `check_cameras_usable`: refuse a session where fewer than two cameras have a usable detection.
- `write_points3d` / `read_points3d`: anipose's 3D CSV layout.

Every error about an input is an `InputError` (a `ValueError`) naming the file and the camera,
part, frame or cell at fault. Every output is written atomically.
"""

from adjust.io.calibration import (
    calibration_units,
    load_calibration,
    load_calibration_metadata,
    recording_fps,
    save_calibration,
)
from adjust.io.dlc import DLCTable, read_dlc, write_dlc_csv
from adjust.io.errors import InputError, UnknownPartsError
from adjust.io.points3d import read_points3d, write_points3d
from adjust.io.scene import (
    Detections,
    check_cameras_usable,
    load_detections,
    load_scene,
    match_files,
)

__all__ = [
    "DLCTable",
    "Detections",
    "InputError",
    "UnknownPartsError",
    "calibration_units",
    "check_cameras_usable",
    "load_calibration",
    "load_calibration_metadata",
    "recording_fps",
    "load_detections",
    "load_scene",
    "match_files",
    "read_dlc",
    "read_points3d",
    "save_calibration",
    "write_dlc_csv",
    "write_points3d",
]
