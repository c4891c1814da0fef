"""Defective track files: the inputs that once raised tracebacks in the console scripts that read
a ``points3d.csv`` (issue 46), built in one place for `benchmarks/robustness.py` and
``tests/test_one_line_errors.py``.

Shapes: T frames, K parts; points in mm (random, N(0, 20 mm) per coordinate, seeded).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from adjust.io import write_points3d

BOUTS_MIXED = "start,stop,label,score\n0,5,walk,0.5\n6,9,,high\n10,12,3,\n"


def tracks_file(
    path: Path,
    parts: int,
    T: int = 20,
    fnum: list[str] | None = None,
    names: list[str] | None = None,
    seed: int = 0,
) -> Path:
    """A valid tracks file of T frames and `parts` parts (named `names`, else p0, p1, ...);
    fnum: the frame column (default 0..T-1)."""
    rng = np.random.default_rng(seed)
    names = list(names) if names is not None else [f"p{k}" for k in range(parts)]
    return write_points3d(path, names, rng.normal(0, 20, (T, parts, 3)), np.zeros((T, parts)),
                          np.full((T, parts), 2), np.ones((T, parts)), fnum=fnum)  # fmt: skip


def defective_tracks(folder: Path, good: Path, T: int = 20) -> dict[str, Path]:
    """The defective inputs built from the valid tracks file `good`, written into `folder`:

    - ``empty``: `good`'s header, no rows;
    - ``huge``: `good` with its last frame number beyond the int64 range;
    - ``big``: 300 parts (more than ndx-pose's uint8 edges can index), T frames;
    - ``labelled``: 3 parts, T frames numbered by labelled images' names (img000.png, ...);
    - ``bouts``: a bouts file whose label and score columns mix text and numbers.
    """
    folder = Path(folder)
    empty = folder / "empty.csv"
    lines = Path(good).read_text().splitlines()
    empty.write_text(lines[0] + "\n")
    huge = folder / "huge.csv"
    lines[-1] = lines[-1].rsplit(",", 1)[0] + ",99999999999999999999999"
    huge.write_text("\n".join(lines) + "\n")
    big = tracks_file(folder / "big.csv", 300, T=T)
    labelled = tracks_file(
        folder / "labelled.csv", 3, T=T, fnum=[f"img{i:03d}.png" for i in range(T)]
    )
    bouts = folder / "bouts.csv"
    bouts.write_text(BOUTS_MIXED)
    return {"empty": empty, "huge": huge, "big": big, "labelled": labelled, "bouts": bouts}
