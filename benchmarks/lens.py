"""Detections on undistorted videos: the real motion filmed through lenses like the real SLEAP
rig's (pinhole, k1 -0.29), then a camera's video (each in turn, and every camera's) undistorted
before the pose estimator (``cv2.undistort``: the camera matrix kept) while the calibration
keeps the lens's distortion, so that its detections are undistorted twice; tracked with the
lens not looked for (``input.pixel_check=false``, what adjust-track did before stop 62) and with
the default check (`adjust.lens`: the cameras read as undistorted found from the epipolar
geometry away from the image's centre, their detections mapped back into the calibrated
images).

Scenes: `real_motion.py`'s 8-part scenes (frames 2400-3399 of the test segment, where nothing
was chosen; ``--split val`` for the validation one, where the check's settings were chosen;
``--cameras``, ``--seeds``), the rig of `adjust.scene.motion.motion_rig` moved to
``--distance`` mm from the arena's centre (the default rig's 750 mm: 250) with lenses of focal
``--focal`` px (770) and OpenCV coefficients ``--dist`` (-0.29,0,0,0,0): the mouse's detections
lie up to 0.5 of the focal length from the image's centre, as on the real SLEAP mouse (median
0.18-0.32, its lenses' k1 -0.29 to -0.30). Rows: RMSE all and seen by >= 2 cameras (mm) as
filmed, unchecked, checked; the cameras mapped; aniposelib (`triangulate_optim`, anipose's
settings; it reads the calibration's distortion too) as filmed and on the same files.

Checks: every undistorted camera mapped; none other (as filmed: none); checked within 5% of the
scene as filmed. A run adjust-track refuses is recorded as refused, its scores NaN.

    .venv/bin/python benchmarks/lens.py [--split test] [--cameras 2,3,4] [--seeds 0] \\
        [--distance 250] [--focal 770] [--dist -0.29,0,0,0,0] [--cases each,every] \\
        [--no-peer] [--work DIR] [--out FILE]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, print_table, start  # noqa: E402
from real_motion import (  # noqa: E402
    DATA,  # noqa: F401 - the recording read (the tests skip where it is absent)
    checked_or_refused,
    input_run,
    input_settings,
    lens_args,
    lens_scene,
    peer_row,
    spoil_scene,
)

from adjust.camera import Camera  # noqa: E402
from adjust.distortion import undistort_points  # noqa: E402

log = logging.getLogger("benchmarks.lens")

SAME = 1.05  #: checked must track within this factor of the scene as filmed


def undistorted(cam: Camera):
    """A detections edit: the pixels of `cam`'s video undistorted with its camera matrix kept
    (``cv2.undistort``), u = K undistort(x)."""

    def edit(t):
        xy = t.xy.copy()
        ok = np.isfinite(xy).all(-1)
        K, d = torch.as_tensor(cam.K), torch.as_tensor(cam.dist)
        xy[ok] = undistort_points(torch.as_tensor(xy[ok]), K, d, pixels=True).numpy()
        return xy, t.likelihood

    return edit


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    lens_args(ap, "lens", distance=250.0, focal=770.0)
    ap.add_argument("--dist", default="-0.29,0,0,0,0", help="OpenCV k1,k2,p1,p2,k3")
    ap.add_argument("--cases", default="each,every", help="each camera in turn, every camera")
    args = start(ap, argv)
    kinds = [k for k in args.cases.split(",") if k.strip()]
    if not kinds or set(kinds) - {"each", "every"}:
        ap.error(f"--cases must be some of each,every, got {args.cases!r}")
    cameras, seeds = input_settings(ap, args)
    dist = [float(v) for v in args.dist.split(",")]
    if len(dist) != 5 or not any(dist):
        ap.error(f"--dist must be 5 numbers k1,k2,p1,p2,k3, not all 0, got {args.dist}")
    motion, work, threads = input_run(args)
    rows: dict[str, dict] = {}
    for ncams in cameras:
        for seed in seeds:
            key, base, rig = lens_scene(work, motion, args.split, args.frames, ncams, seed,
                                        args.distance, args.focal, dist)  # fmt: skip
            ref, ref_check = checked_or_refused(base, work / "runs" / key / "as_filmed", [threads])
            peer = None if args.no_peer else peer_row(base)["rmse_all"]
            cases = {f"{cam.name} undistorted": [cam] for cam in rig} if "each" in kinds else {}
            if "every" in kinds:
                cases["every camera undistorted"] = list(rig)
            for case, cams in cases.items():
                tag = f"{key}_{case.replace(' ', '_')}"
                scene = spoil_scene(base, work / "spoilt" / tag,
                                    {c.name: undistorted(c) for c in cams})  # fmt: skip
                blind, blind_check = checked_or_refused(scene, work / "runs" / tag / "unchecked",
                                             [threads, "input.pixel_check=false"])  # fmt: skip
                fixed, check = checked_or_refused(scene, work / "runs" / tag / "checked", [threads])
                mapped = (check.get("lens") or {}).get("undistorted") or {}
                rows[f"{ncams} cams s{seed} {case}"] = {
                    "cameras": ncams, "seed": seed, "case": case,
                    "spoilt": sorted(c.name for c in cams),
                    "filmed_all": ref["rmse_all"], "filmed_seen": ref["rmse_seen2"],
                    "filmed_mapped": sorted((ref_check.get("lens") or {}).get("undistorted") or {}),
                    "unchecked_all": blind["rmse_all"], "unchecked_seen": blind["rmse_seen2"],
                    "checked_all": fixed["rmse_all"], "checked_seen": fixed["rmse_seen2"],
                    "mapped": {n: m["epipolar_px"] for n, m in mapped.items()},
                    "excluded_unchecked": sorted(blind_check.get("excluded") or {}),
                    "excluded_checked": sorted(check.get("excluded") or {}),
                    "peer_filmed_all": peer,
                    "peer_spoilt_all": None if args.no_peer else peer_row(scene)["rmse_all"],
                    "refused_unchecked": blind.get("refused"),
                    "refused_checked": fixed.get("refused"),
                }  # fmt: skip
                log.info("%s: %s", tag, rows[f"{ncams} cams s{seed} {case}"])
    cols = [("filmed_all", "as filmed"), ("unchecked_all", "unchecked"),
            ("checked_all", "checked"), ("peer_filmed_all", "anip. filmed"),
            ("peer_spoilt_all", "anip. spoilt"),
            ("filmed_seen", "seen filmed"), ("unchecked_seen", "seen unch."),
            ("checked_seen", "seen chk.")]  # fmt: skip
    print(f"\nRMSE all / seen by >= 2 cameras (mm), {args.split} segment, videos undistorted:")
    print_table(rows, cols, 12)
    print("\nmapped (camera: epipolar px as read, mapped); excluded unchecked / checked; refused:")
    for label, r in rows.items():
        print(f"  {label}: {r['mapped'] or 'none'}; {r['excluded_unchecked']} / "
              f"{r['excluded_checked']}; {r['refused_unchecked'] or '-'} / "
              f"{r['refused_checked'] or '-'}")  # fmt: skip
    checks = {
        "mapped_the_undistorted_cameras": all(
            sorted(r["mapped"]) == r["spoilt"] for r in rows.values()
        ),
        "no_other_camera_mapped": all(set(r["mapped"]) <= set(r["spoilt"]) for r in rows.values()),
        "none_mapped_as_filmed": all(not r["filmed_mapped"] for r in rows.values()),
        "checked_within_5pct_of_filmed": all(
            r["checked_all"] <= SAME * r["filmed_all"] for r in rows.values()
        ),
        "refused": sum(bool(r["refused_checked"]) for r in rows.values()),
    }
    print(f"\nchecks: {checks}")
    return emit({"split": args.split, "seeds": seeds, "distance": args.distance,
                 "focal": args.focal, "dist": dist, "rows": rows, "checks": checks},
                args.out)  # fmt: skip


if __name__ == "__main__":
    main()
