"""Run aniposelib's `triangulate_optim` (the peer) on arrays; executed by the bench
environment's Python (`make bench-env`: .venv-bench with aniposelib, whose opencv-contrib `cv2`
must not replace the main environment's opencv-python-headless).

    .venv-bench/bin/python benchmarks/peers/anipose_run.py IN.npz OUT.npz

IN.npz: calibration (path, str), cameras (C,) names in the order of xy, xy (T, K, C, 2) px
(NaN missing), scores (T, K, C), constraints (M, 2) int, constraints_weak (M', 2) int, and the
anipose settings score_threshold, scale_smooth, scale_length, scale_length_weak,
reproj_error_threshold, n_deriv_smooth. OUT.npz: points (T, K, 3) mm, seconds.
"""

import sys
import time

import numpy as np
from aniposelib.cameras import CameraGroup


def main(src: str, dst: str) -> None:
    d = np.load(src, allow_pickle=False)
    cgroup = CameraGroup.load(str(d["calibration"]))
    names = [str(c) for c in d["cameras"]]
    order = [cgroup.get_names().index(n) for n in names]
    cgroup = cgroup.subset_cameras(order)
    xy = np.array(d["xy"], dtype=np.float64)  # (T, K, C, 2)
    scores = np.array(d["scores"], dtype=np.float64)
    xy[scores < float(d["score_threshold"])] = np.nan  # anipose's recipe
    pts = np.transpose(xy, (2, 0, 1, 3))  # (C, T, K, 2)
    sc = np.transpose(np.where(np.isfinite(xy[..., 0]), scores, 0.0), (2, 0, 1))
    t0 = time.perf_counter()
    p3 = cgroup.triangulate_optim(
        pts,
        init_ransac=False,
        init_progress=False,
        constraints=d["constraints"].tolist(),
        constraints_weak=d["constraints_weak"].tolist(),
        scale_smooth=float(d["scale_smooth"]),
        scale_length=float(d["scale_length"]),
        scale_length_weak=float(d["scale_length_weak"]),
        reproj_error_threshold=float(d["reproj_error_threshold"]),
        n_deriv_smooth=int(d["n_deriv_smooth"]),
        scores=sc,
        verbose=False,
    )
    secs = time.perf_counter() - t0
    np.savez(dst, points=np.asarray(p3, dtype=np.float64), seconds=secs)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
