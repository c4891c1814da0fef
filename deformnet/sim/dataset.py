"""The simulated data set `SimData` (the paper's D_t per frame) and its file format.

File format (``sim.npz``, written atomically by `save_sim`, read by `load_sim`): an uncompressed
NumPy ``.npz`` archive with these arrays (T frames, K parts, M lock-box corners; mm, s, global
frame: arena x, y in [0, size], z up, ground z = 0):

====================  ==========  ========  ====================================================
key                   shape       dtype     meaning
====================  ==========  ========  ====================================================
format                ()          str       ``"mousetrack-sim"``
version               ()          int64     format version (1)
time                  (T,)        float64   time stamp of frame t in s (t / fps)
poses                 (T, 6)      float64   rigid pose model->global: Rodrigues vector r (rad),
                                            translation tau (mm); X_g = R(r) X_m + tau
rigid                 (T, K, 3)   float64   rigid part positions X̄ = R(r) model + tau
deformed              (T, K, 3)   float64   deformed (true) part positions X̃
labels                (T,)        int64     behavior index into ``behaviors``
behaviors             (B,)        str       behavior names (walk, scan, rear, groom, lever,
                                            splint, ball, slider)
observed              (T, K)      bool      True = part observed, False = missing
parts                 (K,)        str       part names in model order
model                 (K, 3)      float64   rigid body model (model frame: X right, Y forward,
                                            Z up)
fps                   ()          float64   frame rate (Hz)
seed                  ()          int64     random seed used
lockbox_corners       (M, 3)      float64   lock-box corners (M = 8: z in {0, h}, then y in
                                            {front, back}, then x in {left, right}); known 3D
                                            points for camera resection
mechanism_names       (4,)        str       lever, splint, ball, slider
mechanism_positions   (4, 3)      float64   3D positions of the mechanisms
arena_size            (2,)        float64   arena extent in x and y
====================  ==========  ========  ====================================================

``deformed`` and ``rigid`` are complete; ``observed`` says which entries a detector would have
seen (random dropout and contiguous occlusion episodes). Load with `load_sim` (or plain
``np.load(path)``; no pickles are used).
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from deformnet.atomic import atomic_path

FORMAT = "mousetrack-sim"
VERSION = 1


@dataclass(frozen=True, eq=False)
class SimData:
    """One simulated sequence (see the module docstring for units). The fields cannot be
    reassigned; the arrays are ordinary (writable) NumPy arrays, not copied on construction."""

    time: np.ndarray  # (T,) float64 s
    poses: np.ndarray  # (T, 6) float64: Rodrigues vector, translation (model -> global)
    rigid: np.ndarray  # (T, K, 3) float64
    deformed: np.ndarray  # (T, K, 3) float64
    labels: np.ndarray  # (T,) int64
    behaviors: tuple[str, ...]
    observed: np.ndarray  # (T, K) bool
    parts: tuple[str, ...]
    model: np.ndarray  # (K, 3) float64
    fps: float
    seed: int
    lockbox_corners: np.ndarray  # (M, 3) float64
    mechanisms: tuple[tuple[str, ...], np.ndarray]  # (names, (4, 3) positions)
    arena_size: np.ndarray  # (2,) float64

    def __post_init__(self) -> None:
        conv = {
            "time": np.float64,
            "poses": np.float64,
            "rigid": np.float64,
            "deformed": np.float64,
            "labels": np.int64,
            "observed": np.bool_,
            "model": np.float64,
            "lockbox_corners": np.float64,
            "arena_size": np.float64,
        }
        for name, dtype in conv.items():
            arr = np.asarray(getattr(self, name))
            if arr.dtype != dtype:
                arr = arr.astype(dtype)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "behaviors", tuple(str(b) for b in self.behaviors))
        object.__setattr__(self, "parts", tuple(str(p) for p in self.parts))
        object.__setattr__(self, "fps", float(self.fps))
        object.__setattr__(self, "seed", int(self.seed))
        names, pos = self.mechanisms
        pos = np.asarray(pos, dtype=np.float64)
        object.__setattr__(self, "mechanisms", (tuple(str(n) for n in names), pos))
        self._check()

    def _check(self) -> None:
        T = self.time.shape[0] if self.time.ndim == 1 else -1
        K = len(self.parts)
        expect = {
            "time": (T,),
            "poses": (T, 6),
            "rigid": (T, K, 3),
            "deformed": (T, K, 3),
            "labels": (T,),
            "observed": (T, K),
            "model": (K, 3),
            "arena_size": (2,),
        }
        for name, shape in expect.items():
            got = getattr(self, name).shape
            if got != shape:
                raise ValueError(f"SimData.{name}: expected shape {shape}, got {got}")
        if self.lockbox_corners.ndim != 2 or self.lockbox_corners.shape[1] != 3:
            raise ValueError(
                f"SimData.lockbox_corners: expected shape (M, 3), got {self.lockbox_corners.shape}"
            )
        names, pos = self.mechanisms
        if pos.shape != (len(names), 3):
            raise ValueError(
                f"SimData.mechanisms: {len(names)} names need positions of shape "
                f"({len(names)}, 3), got {pos.shape}"
            )
        if T and (self.labels.min() < 0 or self.labels.max() >= len(self.behaviors)):
            raise ValueError("SimData.labels: values must index `behaviors`")

    # --- conveniences -------------------------------------------------------------------
    @property
    def num_frames(self) -> int:
        return int(self.time.shape[0])

    @property
    def num_parts(self) -> int:
        return len(self.parts)

    @property
    def mechanism_names(self) -> tuple[str, ...]:
        return self.mechanisms[0]

    @property
    def mechanism_positions(self) -> np.ndarray:
        return self.mechanisms[1]

    def part_index(self, name: str) -> int:
        try:
            return self.parts.index(name)
        except ValueError:
            raise KeyError(f"part '{name}' not in {list(self.parts)}") from None

    def label_name(self, t: int) -> str:
        return self.behaviors[int(self.labels[t])]

    def masked_deformed(self) -> np.ndarray:
        """(T, K, 3) deformed positions with NaN where not observed."""
        return np.where(self.observed[..., None], self.deformed, np.nan)

    def slice(self, start: int, stop: int) -> SimData:
        """Frames [start, stop) as a new SimData (time stamps kept)."""
        kw = {f.name: getattr(self, f.name) for f in fields(self)}
        for name in ("time", "poses", "rigid", "deformed", "labels", "observed"):
            kw[name] = kw[name][start:stop]
        return SimData(**kw)


def save_sim(path: str | os.PathLike, data: SimData) -> Path:
    """Write `data` to `path` (``.npz``, see the module docstring) atomically; returns the path."""
    if not isinstance(data, SimData):
        raise TypeError(f"save_sim: expected SimData, got {type(data).__name__}")
    path = Path(path)
    if path.suffix != ".npz":
        raise ValueError(f"save_sim: the file name must end in .npz, got '{path}'")
    arrays = {
        "format": np.array(FORMAT),
        "version": np.array(VERSION, dtype=np.int64),
        "time": data.time,
        "poses": data.poses,
        "rigid": data.rigid,
        "deformed": data.deformed,
        "labels": data.labels,
        "behaviors": np.array(data.behaviors, dtype=np.str_),
        "observed": data.observed,
        "parts": np.array(data.parts, dtype=np.str_),
        "model": data.model,
        "fps": np.array(data.fps, dtype=np.float64),
        "seed": np.array(data.seed, dtype=np.int64),
        "lockbox_corners": data.lockbox_corners,
        "mechanism_names": np.array(data.mechanisms[0], dtype=np.str_),
        "mechanism_positions": data.mechanisms[1],
        "arena_size": data.arena_size,
    }
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    return path


_REQUIRED = (
    "format",
    "version",
    "time",
    "poses",
    "rigid",
    "deformed",
    "labels",
    "behaviors",
    "observed",
    "parts",
    "model",
    "fps",
    "seed",
    "lockbox_corners",
    "mechanism_names",
    "mechanism_positions",
    "arena_size",
)


def load_sim(path: str | os.PathLike) -> SimData:
    """Read a file written by `save_sim`. Raises FileNotFoundError if it is missing and
    ValueError if it is not a valid simulator file (naming what is wrong)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"simulated data file not found: '{path}'")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in _REQUIRED if k not in z.files]
            if missing:
                raise ValueError(
                    f"'{path}' is not a mousetrack simulator file: missing arrays {missing}"
                )
            fmt = str(z["format"])
            if fmt != FORMAT:
                raise ValueError(f"'{path}': format is '{fmt}', expected '{FORMAT}'")
            version = int(z["version"])
            if version != VERSION:
                raise ValueError(
                    f"'{path}': file format version {version}, this code reads {VERSION}"
                )
            a = {k: z[k] for k in _REQUIRED}
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        raise ValueError(f"'{path}' is not a readable .npz file: {exc}") from exc
    except ValueError as exc:
        if str(path) in str(exc):
            raise
        raise ValueError(f"'{path}' is not a valid mousetrack simulator file: {exc}") from exc
    return SimData(
        time=a["time"],
        poses=a["poses"],
        rigid=a["rigid"],
        deformed=a["deformed"],
        labels=a["labels"],
        behaviors=tuple(a["behaviors"].tolist()),
        observed=a["observed"],
        parts=tuple(a["parts"].tolist()),
        model=a["model"],
        fps=float(a["fps"]),
        seed=int(a["seed"]),
        lockbox_corners=a["lockbox_corners"],
        mechanisms=(tuple(a["mechanism_names"].tolist()), a["mechanism_positions"]),
        arena_size=a["arena_size"],
    )
