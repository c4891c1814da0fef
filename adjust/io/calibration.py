"""anipose ``calibration.toml``: read into and write from `adjust.camera.Camera`.

Layout (as aniposelib's ``CameraGroup.dump`` writes it)::

    [cam_0]
    name = "A"
    size = [1280, 1024]                  # width, height (px)
    matrix = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
    distortions = [k1, k2, p1, p2, k3]   # OpenCV order; 1 to 5 entries, padded with zeros
    rotation = [rx, ry, rz]              # Rodrigues vector, world -> camera
    translation = [tx, ty, tz]           # world -> camera (the file's length unit)
    [metadata]                           # optional, free-form; units = "mm" | "cm" | "m"

Every top-level table other than ``metadata`` is a camera. Cameras come in the order of their
section names, ``cam_N`` by number (``cam_2`` before ``cam_10``), other names after them in
file order. ``fisheye = true`` (aniposelib's ``FisheyeCamera``) is OpenCV's fisheye model, its
``distortions`` k1 k2 k3 k4 (`adjust.distortion`; `Camera.fisheye`); other keys of a camera
section are kept in `Camera.extra` and written back. Floats are written with ``repr``,
so writing then reading gives bit-identical cameras.

Lengths: mousetrack works in mm. A file whose ``[metadata] units`` is ``"cm"`` or ``"m"``
(`deformnet.units`) is read with its translations and ``[metadata.mechanisms]`` converted to
mm; one that declares none is read as mm, and refused when its cameras then lie within
`MIN_RIG_MM` of their centre (a rig in metres read as mm: every mm setting would be 1000x off).
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from adjust.camera import Camera
from adjust.io.errors import InputError
from deformnet.atomic import write_text
from deformnet.confutil import check_fps
from deformnet.paths import regular_file
from deformnet.units import LENGTH_UNITS, declared_unit

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10 with the `tomli` backport
    import tomli as tomllib

log = logging.getLogger(__name__)

_KNOWN = ("name", "size", "matrix", "distortions", "rotation", "translation")
_SECTION = re.compile(r"^cam_(\d+)$")


#: a calibration larger than this is not one (anipose's are a few kB); refused unread
MAX_BYTES = 16 << 20


def _read_toml(path: Path) -> dict:
    if path.is_dir():
        raise InputError(
            f"calibration {path} is a directory, not a file (give its calibration.toml)"
        )
    regular_file(path, "calibration file", InputError)  # a FIFO or /dev/zero: never opened
    size = path.stat().st_size
    if size > MAX_BYTES:
        raise InputError(
            f"{path}: {size / 2**20:.0f} MB is not a calibration (anipose's calibration.toml "
            "is a few kB)"
        )
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise InputError(f"calibration file not found: {path}") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML: {exc}") from None
    except UnicodeDecodeError:
        raise InputError(
            f"{path}: not a text (TOML) file: it holds bytes that are not UTF-8 (a binary file?)"
        ) from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read calibration: {exc}") from None


def _camera_sections(path: Path, doc: dict) -> list[str]:
    tables = [k for k, v in doc.items() if isinstance(v, dict) and k != "metadata"]
    others = [k for k, v in doc.items() if not isinstance(v, dict)]
    if others:
        raise InputError(
            f"{path}: unexpected top-level keys {others} (expected only [cam_N] sections and "
            "[metadata])"
        )
    if not tables:
        raise InputError(f"{path}: no camera sections ([cam_0], [cam_1], ...) found")
    numbered = sorted((int(m.group(1)), k) for k in tables if (m := _SECTION.match(k)))
    return [k for _, k in numbered] + [k for k in tables if not _SECTION.match(k)]


def _array(path: Path, where: str, key: str, value, shape: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(
            f"{path}: {where}: '{key}' must be numbers with shape {shape}, got {value!r}"
        ) from None
    if arr.shape != shape:
        raise InputError(f"{path}: {where}: '{key}' must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{path}: {where}: '{key}' has non-finite values: {arr.tolist()}")
    return arr


def _camera(path: Path, section: str, item: dict, unit_mm: float = 1.0) -> Camera:
    name = item.get("name", None)
    where = f"camera [{section}]" + (f" ('{name}')" if name is not None else "")
    missing = [k for k in _KNOWN if k not in item]
    if missing:
        raise InputError(f"{path}: {where}: missing keys {missing} (needs {list(_KNOWN)})")
    if not isinstance(name, str | int) or isinstance(name, bool) or str(name) == "":
        raise InputError(f"{path}: {where}: 'name' must be a non-empty string, got {name!r}")
    name = str(name)
    fisheye = item.get("fisheye", False)
    if not isinstance(fisheye, bool):
        raise InputError(f"{path}: {where}: 'fisheye' must be true or false, got {fisheye!r}")
    K = _array(path, where, "matrix", item["matrix"], (3, 3))
    try:
        dist = np.array(item["distortions"], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(
            f"{path}: {where}: 'distortions' must be a list of numbers, got {item['distortions']!r}"
        ) from None
    most = 4 if fisheye else 5
    if dist.size > most:
        raise InputError(
            f"{path}: {where}: 'distortions' has {dist.size} entries; at most {most} ("
            + ("k1 k2 k3 k4, OpenCV's fisheye model" if fisheye else "k1 k2 p1 p2 k3")
            + ") are supported"
        )
    dist = _array(path, where, "distortions", np.pad(dist, (0, 5 - dist.size)), (5,))
    rvec = _array(path, where, "rotation", item["rotation"], (3,))
    tvec = _array(path, where, "translation", item["translation"], (3,)) * unit_mm
    size = _array(path, where, "size", item["size"], (2,))
    if np.any(size < 0) or np.any(size != np.round(size)):
        raise InputError(
            f"{path}: {where}: 'size' must be two non-negative integers [width, height], got "
            f"{item['size']!r}"
        )
    extra = {k: v for k, v in item.items() if k not in _KNOWN and k != "fisheye"}
    _check_intrinsics(path, where, K, dist, size, fisheye)
    try:
        wh = (int(size[0]), int(size[1]))
        return Camera(name, K, dist, rvec, tvec, wh, extra, fisheye=fisheye)
    except ValueError as exc:  # Camera's own checks
        raise InputError(f"{path}: {where}: {exc}") from None


#: the radial distortion factor 1 + k1 r^2 + k2 r^4 + k3 r^6 at the image corner must lie in
#: this range (real lenses, fisheye aside, stay well inside), and r_d(r) must increase up to it
RADIAL_FACTOR = (0.02, 100.0)


def _check_intrinsics(
    path: Path, where: str, K: np.ndarray, dist: np.ndarray, size, fisheye: bool = False
) -> None:
    """Physically impossible intrinsics are an error: focal lengths <= 0, a third row of K
    other than [0, 0, 1], a principal point far outside the image, a distortion that folds the
    image over or scales the corner radius absurdly (e.g. k1 = 1e6). A fisheye's radius is
    its angle theta_d(theta) (`adjust.distortion`), checked the same way."""
    if not np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-9) or K[1, 0] != 0:
        raise InputError(
            f"{path}: {where}: 'matrix' must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]]; got rows "
            f"{K[1].tolist()}, {K[2].tolist()}"
        )
    fx, fy = K[0, 0], K[1, 1]
    if fx <= 0 or fy <= 0:
        raise InputError(f"{path}: {where}: focal lengths must be > 0 px, got fx={fx:g}, fy={fy:g}")
    w, h = float(size[0]), float(size[1])
    if w > 0 and h > 0:
        cx, cy = K[0, 2], K[1, 2]
        if not (-w <= cx <= 2 * w and -h <= cy <= 2 * h):
            raise InputError(
                f"{path}: {where}: principal point ({cx:g}, {cy:g}) lies far outside the "
                f"{w:g}x{h:g} image"
            )
        corner = max(np.hypot(max(cx, w - cx), max(cy, h - cy)) / min(fx, fy), 1e-6)
        inner = min(w, h) / 2 / max(fx, fy)
    else:
        corner = inner = 1.0  # ~ a 90 degree field of view when the image size is unknown
    if fisheye:
        _check_fisheye(path, where, dist, corner, inner)
        return
    k1, k2, p1, p2, k3 = dist
    r = np.linspace(0.0, corner, 201)
    r2 = r * r
    factor = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    rd = r * factor
    lo, hi = RADIAL_FACTOR
    # a fitted polynomial may fold over in the far corners; never inside the inscribed circle
    folds = np.any(np.diff(rd[r <= inner]) <= 0)
    if factor.min() < lo or factor.max() > hi or folds:
        raise InputError(
            f"{path}: {where}: distortion {dist.tolist()} is not a real lens within the image: "
            f"the radial factor 1 + k1 r^2 + k2 r^4 + k3 r^6 reaches {factor.min():.3g} to "
            f"{factor.max():.3g} up to the image corner (r = {corner:.3g}; expected "
            f"{lo:g} to {hi:g}, r(1 + ...) increasing within r = {inner:.3g})"
        )
    if max(abs(p1), abs(p2)) > 0.5:
        raise InputError(
            f"{path}: {where}: tangential distortion p1={p1:g}, p2={p2:g} is absurd (|p| <= 0.5)"
        )


def _check_fisheye(path: Path, where: str, dist: np.ndarray, corner: float, inner: float) -> None:
    """A fisheye's theta_d = theta (1 + k1 theta^2 + ...) must scale theta within
    `RADIAL_FACTOR` up to the image corner (its angle: corner = theta_d there) and increase
    within the inscribed circle."""
    k1, k2, k3, k4 = dist[:4]
    th = np.linspace(0.0, np.pi / 2 * 0.999, 2001)
    t2 = th * th
    factor = 1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
    thd = th * factor
    # the image's corner and inscribed circle are distorted radii: theta_d up to them
    reach = thd <= corner
    inside = thd <= inner
    lo, hi = RADIAL_FACTOR
    folds = np.any(np.diff(thd[inside]) <= 0)
    f = factor[reach] if reach.any() else factor[:1]
    if f.min() < lo or f.max() > hi or folds:
        raise InputError(
            f"{path}: {where}: fisheye distortion {dist[:4].tolist()} is not a real lens within "
            f"the image: the factor 1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8 reaches "
            f"{f.min():.3g} to {f.max():.3g} up to the image corner (theta_d = {corner:.3g}; "
            f"expected {lo:g} to {hi:g}, theta_d increasing within {inner:.3g})"
        )


#: a rig whose cameras all lie within this many mm of their mean centre, in a file that
#: declares no units, is refused: a lab rig in metres (0.2-1 apart) read as mm
MIN_RIG_MM = 10.0
#: ... and one within this many mm is warned about (a rig in centimetres read as mm)
WARN_RIG_MM = 100.0


def _check_rig(path: Path, cameras: Sequence[Camera], declared: bool = True) -> None:
    """Cameras that share one centre (e.g. one camera's extrinsics copied to all) cannot
    triangulate: an error naming them. Without declared units (``[metadata] units``), a rig
    within `MIN_RIG_MM` of its centre is an error too (lengths in metres, read as mm)."""
    if len(cameras) < 2:
        return
    centres = np.array([c.center for c in cameras])
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
    scale = max(spread, 1e-9)
    if not declared and MIN_RIG_MM <= spread < WARN_RIG_MM:
        log.warning(
            "%s: its cameras lie within %.3g mm of their centre, a small rig; if the file is in "
            'centimetres, add units = "cm" under [metadata] (units = "mm" silences this)',
            path,
            spread,
        )
    if not declared and 0 < spread < MIN_RIG_MM:
        raise InputError(
            f"{path}: its cameras lie within {spread:.3g} of their centre, a rig under "
            f"{2 * MIN_RIG_MM:g} mm across if the file is in mm (it is read as mm: its [metadata] "
            "declares no units). Calibrated in metres or centimetres (the board's square "
            'length)? Add units = "m" (or "cm") under [metadata] to have its lengths converted '
            'to mm; units = "mm" reads them as they are'
        )
    groups: list[list[str]] = []
    for ci in centres:
        same = [cameras[j].name for j in range(len(cameras)) if np.linalg.norm(centres[j] - ci)
                <= 1e-6 * max(1.0, float(np.linalg.norm(ci)))]  # fmt: skip
        if len(same) > 1 and same not in groups:
            groups.append(same)
    if groups and len(groups[0]) == len(cameras):
        raise InputError(
            f"{path}: all cameras {[c.name for c in cameras]} are at one position "
            f"{centres[0].round(3).tolist()} mm (copied extrinsics?): nothing can be triangulated"
        )
    for g in groups:
        log.warning(
            "%s: cameras %s are at the same position (spread of the rig %.3g mm); copied "
            "extrinsics? (the camera check will test them against the others)",
            path,
            g,
            scale,
        )


def load_calibration(path: str | os.PathLike) -> list[Camera]:
    """Read an anipose ``calibration.toml`` into cameras (in ``cam_N`` order).

    Raises `InputError` naming the file and camera for missing keys, wrong shapes, non-finite
    values, fisheye cameras and duplicate names.
    """
    path = Path(path)
    doc = _read_toml(path)
    sections = _camera_sections(path, doc)
    unit = _unit(path, doc.get("metadata"))
    factor = LENGTH_UNITS[unit] if unit else 1.0
    cameras = [_camera(path, s, doc[s], factor) for s in sections]
    names = [c.name for c in cameras]
    dups = sorted({n for n in names if names.count(n) > 1})
    if dups:
        raise InputError(f"{path}: duplicate camera names {dups}")
    _check_rig(path, cameras, declared=unit is not None)
    log.info(
        "read %d cameras from %s: %s%s",
        len(cameras),
        path,
        ", ".join(names),
        f" (lengths in {unit}, converted to mm)" if unit not in (None, "mm") else "",
    )
    return cameras


def _unit(path: Path, meta) -> str | None:
    try:
        return declared_unit(meta, str(path))
    except ValueError as exc:
        raise InputError(str(exc)) from None


def calibration_units(path: str | os.PathLike) -> str | None:
    """The length unit a calibration file declares (``[metadata] units``), None where none."""
    path = Path(path)
    return _unit(path, _read_toml(path).get("metadata"))


def load_calibration_metadata(path: str | os.PathLike) -> dict:
    """The ``[metadata]`` table of an anipose calibration ({} if absent), in mm: where it
    declares ``units`` other than mm, a copy whose ``mechanisms`` positions are converted and
    whose ``units`` is ``"mm"`` (as `load_calibration`'s cameras: saved together, they agree)."""
    path = Path(path)
    meta = _read_toml(path).get("metadata", {})
    if not isinstance(meta, dict):
        raise InputError(f"{path}: 'metadata' must be a table, got {meta!r}")
    unit = _unit(path, meta)
    if unit in (None, "mm"):
        return meta
    out = {**meta, "units": "mm"}
    mech = meta.get("mechanisms")
    if isinstance(mech, dict):
        out["mechanisms"] = {k: _scaled(v, LENGTH_UNITS[unit]) for k, v in mech.items()}
    return out


def _scaled(value, factor: float):
    """A position (list of numbers) times `factor`; anything else as it is (the readers of the
    mechanisms table name what is wrong with it)."""
    try:
        return (np.asarray(value, dtype=np.float64) * factor).tolist()
    except (TypeError, ValueError):
        return value


def recording_fps(fps, metadata: dict, where: str = "the calibration") -> float | None:
    """A recording's frame rate (Hz): `fps` (a config's) where given, else the calibration's
    ``[metadata] fps`` (`metadata`: `load_calibration_metadata`'s table of `where`), else None.
    One that is not a number > 0 is an InputError naming where it came from."""
    if fps is not None:
        key, value = "fps", fps
    else:
        key, value = f"{where}: [metadata] fps", metadata.get("fps")
    try:
        return check_fps(value, key)
    except ValueError as exc:
        raise InputError(str(exc)) from None


# --- writing ------------------------------------------------------------------------------


def _key(k) -> str:
    k = str(k)
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k, ensure_ascii=False)


def _value(v, where: str) -> str:
    if isinstance(v, np.ndarray | np.generic):
        v = v.tolist()
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"{where}: non-finite value {v!r} cannot be written")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)  # JSON string escapes are valid TOML
    if isinstance(v, Sequence):
        return "[" + ", ".join(_value(x, where) for x in v) + "]"
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{_key(k)} = {_value(x, where)}" for k, x in v.items()) + "}"
    raise ValueError(f"{where}: cannot write a {type(v).__name__} to TOML: {v!r}")


def _table(name: str, items: Mapping) -> list[str]:
    lines = [f"[{name}]"]
    subtables = []
    for k, v in items.items():
        if isinstance(v, Mapping):
            subtables.append((k, v))
        else:
            lines.append(f"{_key(k)} = {_value(v, f'[{name}] {k}')}")
    for k, v in subtables:
        lines += [""] + _table(f"{name}.{_key(k)}", v)
    return lines


def _camera_dict(cam: Camera) -> dict:
    d = {
        "name": cam.name,
        "size": [int(cam.size[0]), int(cam.size[1])],
        "matrix": cam.K.tolist(),
        "distortions": (cam.dist[:4] if cam.fisheye else cam.dist).tolist(),
        "rotation": cam.rvec.tolist(),
        "translation": cam.tvec.tolist(),
    }
    if cam.fisheye:
        d["fisheye"] = True
    for k, v in cam.extra.items():
        if k in d:
            raise ValueError(f"camera '{cam.name}': extra key '{k}' clashes with a standard key")
        d[k] = v
    return d


def save_calibration(
    path: str | os.PathLike, cameras: Sequence[Camera], metadata: Mapping | None = None
) -> Path:
    """Write cameras (sections ``cam_0``, ``cam_1``, ... in the given order) and an optional
    ``[metadata]`` table to an anipose ``calibration.toml``, atomically. Cameras are in mm, so
    a `metadata` ``units`` other than ``"mm"`` is a ValueError."""
    if not cameras:
        raise ValueError("no cameras to write")
    if declared_unit(metadata, str(path)) not in (None, "mm"):
        raise ValueError(
            f"{path}: metadata units = {metadata['units']!r}, but cameras are written in mm "
            '(units = "mm", or none)'
        )
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate camera names {names}")
    lines: list[str] = []
    for i, cam in enumerate(cameras):
        lines += _table(f"cam_{i}", _camera_dict(cam)) + [""]
    lines += _table("metadata", dict(metadata or {})) + [""]
    text = "\n".join(lines)
    tomllib.loads(text)  # never write a file we cannot read back
    return write_text(path, text)
