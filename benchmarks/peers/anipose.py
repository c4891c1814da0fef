"""aniposelib's `triangulate_optim` with anipose's settings, called in its own environment.

aniposelib pulls jax, numba and opencv-contrib-python (whose `cv2` replaces
opencv-python-headless's), so it lives in `.venv-bench` (`make bench-env`), or in the Python
named by $MOUSETRACK_BENCH_PYTHON; `run_anipose` writes the arrays to a temporary file, runs
`anipose_run.py` there and reads the points back.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent

#: anipose's defaults for triangulation with optim: true (anipose's DEFAULT_CONFIG)
ANIPOSE_SETTINGS = {
    "score_threshold": 0.5,  # anipose: 0.8 by default; 0.5 as our likelihood threshold
    "scale_smooth": 2.0,
    "scale_length": 2.0,
    "scale_length_weak": 1.0,
    "reproj_error_threshold": 5.0,
    "n_deriv_smooth": 3,
}

#: length constraints of the 8-part mouse: the head triangle strong, the trunk weak
MOUSE_CONSTRAINTS = [("nose_tip", "left_ear"), ("nose_tip", "right_ear"), ("left_ear", "right_ear")]
MOUSE_CONSTRAINTS_WEAK = [
    ("left_ear", "tail_root"),
    ("right_ear", "tail_root"),
    ("left_hind_paw", "tail_root"),
    ("right_hind_paw", "tail_root"),
]


def bench_python() -> Path | None:
    """The bench environment's Python, or None if it is not installed."""
    env = os.environ.get("MOUSETRACK_BENCH_PYTHON")
    p = Path(env) if env else ROOT / ".venv-bench" / "bin" / "python"
    return p if p.is_file() else None


def wanted(skip: bool) -> bool:
    """Whether a benchmark runs aniposelib: not skipped (``--no-anipose``) and installed; a
    warning when it is wanted but missing."""
    from peers import wanted as peer_wanted

    return peer_wanted(
        skip,
        bench_python() is not None,
        "aniposelib not installed (make bench-env): its rows are skipped",
    )


def constraint_indices(parts, pairs) -> np.ndarray:
    idx = [(parts.index(a), parts.index(b)) for a, b in pairs if a in parts and b in parts]
    return np.asarray(idx, dtype=np.int64).reshape(-1, 2)


def run_anipose(
    calibration: Path,
    cameras,
    xy: np.ndarray,
    scores: np.ndarray,
    constraints: np.ndarray,
    constraints_weak: np.ndarray,
    settings: dict | None = None,
    timeout: float = 3600,
) -> tuple[np.ndarray, float]:
    """Points (T, K, 3) from aniposelib and its seconds. xy (T, K, C, 2), scores (T, K, C)."""
    py = bench_python()
    if py is None:
        raise FileNotFoundError(
            "aniposelib is not installed: run `make bench-env` (creates .venv-bench) or set "
            "MOUSETRACK_BENCH_PYTHON"
        )
    s = {**ANIPOSE_SETTINGS, **(settings or {})}
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(
            src,
            calibration=str(calibration),
            cameras=np.asarray([str(c) for c in cameras]),
            xy=xy,
            scores=scores,
            constraints=constraints,
            constraints_weak=constraints_weak,
            **{k: np.asarray(v) for k, v in s.items()},
        )
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        proc = subprocess.run(
            [str(py), str(HERE / "anipose_run.py"), str(src), str(dst)],
            capture_output=True,
            text=True,
            timeout=timeout,
            env=env,
        )
        if proc.returncode != 0:
            raise RuntimeError(f"aniposelib failed:\n{proc.stderr[-3000:]}")
        out = np.load(dst)
        return np.array(out["points"]), float(out["seconds"])
