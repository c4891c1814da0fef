"""A camera out of step by a fraction of a frame: the real-motion scenes with one camera's
exposures ``--late`` frames after the others' (cameras without a common trigger), tracked
with the offset not looked for (``input.subframe_sync=false``, what adjust-track did before
stop 58) and with the default check (`adjust.subframe`: found from the epipolar geometry, the
camera's detections interpolated in time to the others' frames), beside aniposelib
(`triangulate_optim` with anipose's settings, `real_motion.py`'s peer), which has no such
check.

Scenes: `real_motion.py`'s 8-part scenes of the test segment (frames 2400-3399, fixed before the
check's settings were chosen on the validation segment; ``--split val`` for that one; ``--cameras``,
``--seeds``), at the full rate (100 fps) and at every ``--strides``-th frame (every 3rd: about 33
fps, a webcam's rate; ``--frames`` // stride frames). The late camera is filmed from the recording
interpolated in time (a cubic spline through its frames) at f + late (in the scene's frames); the
other cameras and the truth at f. Each camera in turn is the late one, except with two cameras:
there the first keeps the session's time (`adjust.subframe`), so the second is late. Rows: RMSE all
and seen by >= 2 cameras (mm) in step, late unchecked, late checked, aniposelib late / in step; the
offset found.

Checks: every offset found is the late camera's, within 0.1 frame; no offset on the scenes in
step; checked no worse than unchecked in the geometric mean of each rate.

    .venv/bin/python benchmarks/subframe.py [--split test] [--cameras 2,3,4] [--seeds 0] \\
        [--late 0.5,-0.3] [--strides 1,3] [--late-cameras NAMES] [--no-peer] [--work DIR] \\
        [--out FILE]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import (  # noqa: E402
    CHECK_COLUMNS,
    CHECK_RATIOS,
    emit,
    geo_mean,
    print_means,
    print_table,
    ratio_means,
    start,
)
from real_motion import (  # noqa: E402
    DATA,  # noqa: F401 - the recording read (the tests skip where it is absent)
    SPLITS,
    Motion,
    checked_row,
    film_scene,
    input_args,
    input_run,
    input_settings,
    peer_row,
    refilmed_scene,
    scene_key,
)

from adjust.io import load_calibration  # noqa: E402

log = logging.getLogger("benchmarks.subframe")

FOUND_WITHIN = 0.1  #: frames: an offset found this close to the truth counts as right


def late_scene(
    base: Path, out: Path, motion: Motion, start_frame: int, frames: int, stride: int,
    ncams: int, seed: int, camera: str, late: float,
) -> Path:  # fmt: skip
    """A copy of `base` (`film_scene`'s) whose `camera` is filmed `late` frames (the scene's)
    after the others: at the recording's f + late (`real_motion.refilmed_scene`). Cached."""
    t = np.arange(start_frame, start_frame + frames * stride, stride, dtype=np.float64)
    return refilmed_scene(base, out, motion, camera, t + late * stride, t, ncams, seed)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_args(ap, "subframe", "2,3,4")
    ap.add_argument("--late", default="0.5,-0.3", help="frames the camera is late (< 0: early)")
    ap.add_argument("--strides", default="1,3", help="every n-th frame of the recording")
    ap.add_argument("--split", default="test", choices=tuple(SPLITS), help="the segment")
    ap.add_argument("--late-cameras", default="", help="only these cameras late (default: each)")
    ap.add_argument("--no-peer", action="store_true", help="without aniposelib")
    args = start(ap, argv)
    only = [c for c in args.late_cameras.split(",") if c.strip()]
    cameras, seeds = input_settings(ap, args)
    lates = [float(v) for v in args.late.split(",") if v.strip()]
    strides = [int(v) for v in args.strides.split(",") if v.strip()]
    if not lates or any(not 0 < abs(v) < 1 for v in lates):
        ap.error(f"--late must be fractions of a frame within (-1, 1), not 0: {args.late}")
    if not strides or any(s < 1 for s in strides):
        ap.error(f"--strides must be positive integers, got {args.strides}")
    motion, work, threads = input_run(args)
    start_frame = SPLITS[args.split]
    rows: list[dict] = []

    def tracked(scene: Path, name: str, extra=()) -> tuple[dict, dict]:
        row, check = checked_row(scene, work / "runs" / scene.name / name, [threads, *extra])
        return row, check.get("subframe") or {}

    def peer(scene: Path) -> dict:
        return {} if args.no_peer else peer_row(scene)

    for stride in strides:
        frames = args.frames // stride  # the segment's frames (1000), every stride-th
        for ncams in cameras:
            for seed in seeds:
                key = scene_key(args.split, start_frame, frames, ncams, 8, seed, stride)
                base = film_scene(work / "scenes" / key, motion, start_frame, frames, ncams, 8,
                                  seed, stride)  # fmt: skip
                ref, ref_check = tracked(base, "checked")
                ref_peer = peer(base)
                names = [c.name for c in load_calibration(base / "calibration.toml")]
                late_cams = [c for c in (names[1:] if ncams == 2 else names)
                             if not only or c in only]  # fmt: skip
                for camera in late_cams:
                    for late in lates:
                        tag = f"{key}_{camera}_late{late:g}"
                        scene = late_scene(base, work / "late" / tag, motion, start_frame,
                                           frames, stride, ncams, seed, camera, late)  # fmt: skip
                        blind, _ = tracked(scene, "unchecked", ["input.subframe_sync=false"])
                        fixed, check = tracked(scene, "checked")
                        p = peer(scene)
                        row = {
                            "stride": stride, "cameras": ncams, "seed": seed,
                            "camera": camera, "late": late,
                            "instep_all": ref["rmse_all"], "instep_seen": ref["rmse_seen2"],
                            "unchecked_all": blind["rmse_all"],
                            "unchecked_seen": blind["rmse_seen2"],
                            "checked_all": fixed["rmse_all"],
                            "checked_seen": fixed["rmse_seen2"],
                            "peer_all": p.get("rmse_all"),
                            "peer_instep_all": ref_peer.get("rmse_all"),
                            "found": check.get("offsets") or {},
                            "false_offsets_instep": ref_check.get("offsets") or {},
                        }  # fmt: skip
                        rows.append(row)
                        log.info("%s: %s", tag, row)
    table: dict[str, dict] = {}
    for r in rows:
        what = ", ".join(f"{c} {o:+.2f}" for c, o in r["found"].items()) or "none"
        label = f"x{r['stride']} {r['cameras']} cams s{r['seed']} {r['camera']} {r['late']:+g}"
        table[label] = {**r, "what": what}
    print(f"\nRMSE all / seen by >= 2 cameras (mm), {args.split} segment, a camera late:")
    print_table(table, CHECK_COLUMNS, 11)
    print("\nfound by the check (camera, offset: its frame f + offset is the others' f):")
    for label, line in table.items():
        print(f"  {label}: {line['what']}")
    summary: dict = {}
    for stride in strides:
        for ncams in cameras:
            rs = [r for r in rows if r["stride"] == stride and r["cameras"] == ncams]
            if not rs:
                continue
            summary[f"x{stride} {ncams} cameras"] = ratio_means(
                rs,
                {
                    **CHECK_RATIOS,
                    "peer_late/peer_instep": ("peer_all", "peer_instep_all"),
                    "checked/peer_late": ("checked_all", "peer_all"),
                },
            )
            summary[f"x{stride} {ncams} cameras"]["found"] = (
                f"{sum(bool(r['found']) for r in rs)} of {len(rs)}"
            )
    print_means(summary)

    def right(r: dict) -> bool:
        """The late camera found, alone, at -late (two cameras: the second)."""
        return (
            set(r["found"]) == {r["camera"]}
            and abs(r["found"][r["camera"]] + r["late"]) <= FOUND_WITHIN
        )

    checks = {
        "found_right_camera_within_0.1": all(right(r) for r in rows if r["found"]),
        "found": f"{sum(bool(r['found']) for r in rows)} of {len(rows)}",
        "no_offset_in_step": all(not r["false_offsets_instep"] for r in rows),
        "checked_no_worse_than_unchecked": all(
            geo_mean([r["checked_all"] / r["unchecked_all"] for r in rows if r["stride"] == s]) <= 1
            for s in strides
        ),
    }
    print(f"\nchecks: {checks}")
    return emit(
        {"split": args.split, "seeds": seeds, "late": lates, "strides": strides, "rows": rows,
         "summary": summary, "checks": checks},
        args.out,
    )  # fmt: skip


if __name__ == "__main__":
    main()
