"""Fisheye lenses: the real motion filmed through a rig of wide-angle fisheye cameras (OpenCV's
``cv2.fisheye`` model, anipose's ``fisheye = true``), tracked with that calibration, with the
best pinhole calibration of the same lenses (what a user had to do before stop 58, when a
fisheye file was refused: recalibrate without fisheye, here the pinhole model with OpenCV's
five coefficients fitted to each lens out to 50 degrees off its axis, as far as a board
reaches), and by aniposelib (`triangulate_optim`
with anipose's settings, `real_motion.py`'s peer, which reads fisheye files).

Scenes: `real_motion.py`'s 8-part scenes of the test segment (frames 2400-3399; nothing was
chosen on it; ``--split val`` for the validation one; ``--cameras``, ``--seeds``), the rig of
`adjust.scene.motion.motion_rig` moved to ``--distance`` mm from the arena's centre (the
default rig's 750 mm: 400) with fisheye lenses of focal ``--focal`` px (500) and k1-k4
``--k`` (0.05, -0.02, 0.004, 0): the mouse spans up to about 60 degrees off a camera's
axis. Rows: RMSE all and seen by >= 2 cameras (mm), fisheye calibration / pinhole refit /
aniposelib; the refit's largest error at the camera's detections (px).

    .venv/bin/python benchmarks/fisheye.py [--split test] [--cameras 2,3,4] [--seeds 0] \\
        [--distance 400] [--focal 500] [--k 0.05,-0.02,0.004,0] [--no-peer] [--work DIR] \\
        [--out FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import shutil
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, print_table, start  # noqa: E402
from real_motion import (  # noqa: E402
    DATA,  # noqa: F401 - the recording read (the tests skip where it is absent)
    checked_row,
    input_run,
    input_settings,
    lens_args,
    lens_scene,
    peer_row,
)

from adjust.camera import Camera  # noqa: E402
from adjust.distortion import distort_normalized, undistort_points  # noqa: E402
from adjust.io import read_dlc, save_calibration  # noqa: E402

log = logging.getLogger("benchmarks.fisheye")

GRID = 60  #: pixels per side of the grid the pinhole model is fitted on
FIT_DEG = 50.0  #: ... those whose rays are within this angle of the axis (a board's reach)


def pinhole_refit(cam: Camera, seen: np.ndarray) -> tuple[Camera, float]:
    """The pinhole camera (fx, fy, cx, cy, k1 k2 p1 p2 k3) closest to fisheye `cam` over the
    part of its image within `FIT_DEG` of its axis (least squares on a GRID x GRID grid of
    pixels, their rays from the fisheye model: a board calibration's reach), and its largest
    error at the pixels `seen` (N, 2) (the camera's detections)."""
    w, h = cam.size
    u, v = np.meshgrid(np.linspace(0, w - 1, GRID), np.linspace(0, h - 1, GRID))
    K, d, flag = torch.as_tensor(cam.K), torch.as_tensor(cam.dist), torch.tensor(True)
    grid = torch.as_tensor(np.stack([u.ravel(), v.ravel()], -1))
    rays = undistort_points(grid, K, d, fisheye=flag)
    near = rays.norm(dim=-1) <= np.tan(np.radians(FIT_DEG))
    px, rays = grid[near].numpy(), rays[near]
    seen_rays = undistort_points(torch.as_tensor(seen), K, d, fisheye=flag)

    def pixels(p: np.ndarray, r: torch.Tensor) -> np.ndarray:
        xd = distort_normalized(r, torch.as_tensor(p[4:]))
        return (xd * torch.as_tensor(p[:2]) + torch.as_tensor(p[2:4])).numpy()

    p0 = np.array([cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2], 0, 0, 0, 0, 0.0])
    p = least_squares(lambda q: (pixels(q, rays) - px).ravel(), p0, method="lm").x
    Kp = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
    worst = float(np.linalg.norm(pixels(p, seen_rays) - seen, axis=-1).max()) if len(seen) else 0.0
    return dataclasses.replace(cam, K=Kp, dist=p[4:].copy(), fisheye=False), worst


def read_dlc_folder(scene: Path, rig: list[Camera]) -> dict[str, np.ndarray]:
    """{camera: (N, 2) px} of the scene's accepted detections (likelihood >= 0.5)."""
    out = {}
    for cam in rig:
        t = read_dlc(scene / "detections" / f"{cam.name}.csv")
        ok = np.isfinite(t.xy).all(-1) & (t.likelihood >= 0.5)
        out[cam.name] = t.xy[ok]
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    lens_args(ap, "fisheye", distance=400.0, focal=500.0)
    ap.add_argument("--k", default="0.05,-0.02,0.004,0", help="fisheye k1,k2,k3,k4")
    args = start(ap, argv)
    cameras, seeds = input_settings(ap, args)
    k = [float(v) for v in args.k.split(",")]
    if len(k) != 4:
        ap.error(f"--k must be 4 numbers k1,k2,k3,k4, got {args.k}")
    motion, work, threads = input_run(args)
    rows: dict[str, dict] = {}
    for ncams in cameras:
        for seed in seeds:
            key, scene, rig = lens_scene(work, motion, args.split, args.frames, ncams, seed,
                                         args.distance, args.focal, k, fisheye=True)  # fmt: skip
            det = read_dlc_folder(scene, rig)
            refits = [pinhole_refit(c, det[c.name]) for c in rig]
            pin = work / "pinhole" / key
            if not (pin / "truth.npz").exists():
                if pin.exists():
                    shutil.rmtree(pin)
                shutil.copytree(scene, pin, ignore=shutil.ignore_patterns("aniposelib.npz"))
                save_calibration(pin / "calibration.toml", [c for c, _ in refits])
            fish, fish_check = checked_row(scene, work / "runs" / key / "fisheye", [threads])
            pinr, pin_check = checked_row(pin, work / "runs" / key / "pinhole", [threads])
            peer = {} if args.no_peer else peer_row(scene)
            label = f"{ncams} cams s{seed}"
            rows[label] = {
                "cameras": ncams, "seed": seed,
                "fisheye_all": fish["rmse_all"], "fisheye_seen": fish["rmse_seen2"],
                "pinhole_all": pinr["rmse_all"], "pinhole_seen": pinr["rmse_seen2"],
                "peer_all": peer.get("rmse_all"), "peer_seen": peer.get("rmse_seen2"),
                "refit_worst_px": max(w for _, w in refits),
                "excluded_fisheye": sorted(fish_check.get("excluded") or {}),
                "excluded_pinhole": sorted(pin_check.get("excluded") or {}),
            }  # fmt: skip
            log.info("%s: %s", label, rows[label])
    cols = [("fisheye_all", "fisheye"), ("pinhole_all", "pinh. refit"), ("peer_all", "anipose"),
            ("fisheye_seen", "seen fish."), ("pinhole_seen", "seen pinh."),
            ("peer_seen", "seen anip."), ("refit_worst_px", "refit px")]  # fmt: skip
    print(f"\nRMSE all / seen by >= 2 cameras (mm), {args.split} segment, fisheye lenses:")
    print_table(rows, cols, 11)
    for label, r in rows.items():
        print(f"  {label}: excluded with the fisheye calibration {r['excluded_fisheye']}, "
              f"with the pinhole refit {r['excluded_pinhole']}")  # fmt: skip
    checks = {
        "no_camera_excluded_fisheye": all(not r["excluded_fisheye"] for r in rows.values()),
        "fisheye_over_pinhole_refit": {
            label: r["fisheye_all"] / r["pinhole_all"] for label, r in rows.items()
        },
        "fisheye_over_aniposelib": {
            label: r["fisheye_all"] / r["peer_all"] for label, r in rows.items() if r["peer_all"]
        },
    }
    print(f"\nchecks: {checks}")
    return emit({"split": args.split, "seeds": seeds, "distance": args.distance,
                 "focal": args.focal, "k": k, "rows": rows, "checks": checks},
                args.out)  # fmt: skip


if __name__ == "__main__":
    main()
