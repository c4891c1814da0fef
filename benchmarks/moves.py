"""A camera that moved mid-session: the real-motion scenes with one camera turned by a fraction
of a degree from frame ``--at`` on (bumped, its mount slipped), its calibration left as it was;
tracked with the move not looked for (``input.max_camera_moves=0``, what adjust-track did
before stop 57) and with the default check (`adjust.moves`: found from the epipolar geometry,
its detections mapped back), beside aniposelib (`triangulate_optim` with anipose's settings,
`real_motion.py`'s peer), which has no such check.

Scenes: `real_motion.py`'s 8-part scenes of the test segment (frames 2400-3399, fixed before
the check's settings were chosen on the validation segment; ``--split val`` for that one;
``--cameras``, ``--seeds``). Each camera in turn is turned about its own x axis (a tilt: the
image moves up or down) or y axis (a pan: it moves sideways) by each angle of ``--degrees``,
about its centre: its detections from frame AT (each of ``--at``) on are the turned camera's
view of the same points. ``--at 0``: the camera was bumped before the session, after its
calibration (every frame turned); unchecked is then also without the pixel check
(``input.pixel_check=false``), whose crop map takes up such a camera (a small turn moves the
image almost as a crop does). Rows: RMSE
all and seen by >= 2 cameras (mm) unmoved, moved unchecked, moved checked, aniposelib moved /
unmoved; what the check found (the camera, the frame, the turn), or "unresolved" (more than one
camera's turn fits and the parts' continuity does not tell: warned about, not mapped) or
nothing (a turn that slides the images along the epipolar lines is not seen).

Checks: a mapped move is always the camera that moved; a mapped move tracks within 5% of the
unmoved scene; no move on the unmoved scenes.

    .venv/bin/python benchmarks/moves.py [--split test] [--cameras 2,3,4] [--seeds 0] \\
        [--degrees 0.3,1] [--axes x,y] [--at 300,700] [--no-peer] [--work DIR] [--out FILE]
"""

from __future__ import annotations

import argparse
import itertools
import logging
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, print_table, start, subset  # noqa: E402
from real_motion import (  # noqa: E402
    DATA,  # noqa: F401 - the recording read (the tests skip where it is absent)
    SPLITS,
    checked_or_refused,
    film_scene,
    input_args,
    input_run,
    input_settings,
    peer_row,
    scene_key,
    spoil_scene,
)

from adjust.io import load_calibration  # noqa: E402
from adjust.moves import unrotate  # noqa: E402

log = logging.getLogger("benchmarks.moves")

AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0)}
SAME = 1.05  #: a mapped move must track within this factor of the unmoved scene


def turn(scene: Path, out: Path, camera: str, at: int, degrees: float, axis: str) -> Path:
    """A copy of `scene` whose `camera` turned by `degrees` about its `axis` from frame `at` on
    (its calibration unchanged): each detection moved to where the turned camera sees it."""
    cam = next(c for c in load_calibration(scene / "calibration.toml") if c.name == camera)
    # the turned camera sees x' = dR x: its rays are the calibrated ones turned by dR
    dR = Rotation.from_rotvec(np.deg2rad(degrees) * np.asarray(AXES[axis])).as_matrix()

    def turned(table):
        xy = table.xy.copy()
        xy[at:] = unrotate(table.xy[at:], cam, dR)
        return xy, table.likelihood

    return spoil_scene(scene, out, {camera: turned})


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_args(ap, "moves", "2,3,4")
    ap.add_argument("--degrees", default="0.3,1", help="turns (degrees)")
    ap.add_argument("--axes", default="x,y", help="x (tilt), y (pan)")
    ap.add_argument("--split", default="test", choices=tuple(SPLITS), help="the segment")
    ap.add_argument("--at", default="300,700", help="frames the camera turns at")
    ap.add_argument("--no-peer", action="store_true", help="without aniposelib")
    args = start(ap, argv)
    cameras, seeds = input_settings(ap, args)
    ats = [int(a) for a in args.at.split(",") if a.strip()]
    if not ats or not all(0 <= a < args.frames for a in ats):
        ap.error(f"--at must be frames within 0..{args.frames - 1}, got {args.at}")
    axes = subset(ap, args.axes, tuple(AXES), "--axes")
    degrees = [float(d) for d in args.degrees.split(",") if d.strip()]
    motion, work, threads = input_run(args)
    rows: list[dict] = []

    def tracked(scene: Path, name: str, extra=()) -> tuple[dict, dict]:
        return checked_or_refused(scene, work / "runs" / scene.name / name, [threads, *extra])

    def peer(scene: Path) -> dict:
        return {} if args.no_peer else peer_row(scene)

    for ncams in cameras:
        for seed in seeds:
            key = scene_key(args.split, SPLITS[args.split], args.frames, ncams, 8, seed)
            base = film_scene(work / "scenes" / key, motion, SPLITS[args.split], args.frames,
                              ncams, 8, seed)  # fmt: skip
            ref, ref_check = tracked(base, "checked")
            ref_peer = peer(base)
            names = [c.name for c in load_calibration(base / "calibration.toml")]
            false_moves = len((ref_check.get("moved") or {}).get("moves") or [])
            for at, camera, deg, axis in itertools.product(ats, names, degrees, axes):
                tag = f"{key}_{camera}_{deg:g}deg_{axis}_at{at}"
                scene = turn(base, work / "moved" / tag, camera, at, deg, axis)
                off = ["input.max_camera_moves=0"] + (
                    ["input.pixel_check=false"] if at == 0 else []
                )
                blind, _ = tracked(scene, "unchecked", off)
                fixed, check = tracked(scene, "checked")
                moved = check.get("moved") or {}
                found = moved.get("moves") or []
                pixels = (check.get("pixels") or {}).get("mapped") or {}
                p = peer(scene)
                row = {
                    "cameras": ncams, "seed": seed, "at": at, "camera": camera, "degrees": deg,
                    "axis": axis, "unmoved_all": ref["rmse_all"],
                    "unmoved_seen": ref["rmse_seen2"], "unchecked_all": blind["rmse_all"],
                    "unchecked_seen": blind["rmse_seen2"], "checked_all": fixed["rmse_all"],
                    "checked_seen": fixed["rmse_seen2"], "peer_all": p.get("rmse_all"),
                    "peer_unmoved_all": ref_peer.get("rmse_all"),
                    "found": [[m["camera"], m["first_frame"], round(m["degrees"], 3)]
                              for m in found],
                    "pixel_maps": {n: [m["scale"], m["offset"]] for n, m in pixels.items()},
                    "unresolved": (moved.get("unresolved") or {}).get("cameras"),
                    "excluded": sorted(check.get("excluded") or {}),
                    "false_moves_unmoved": false_moves,
                    "refused_unchecked": blind.get("refused"),
                    "refused_checked": fixed.get("refused"),
                }  # fmt: skip
                rows.append(row)
                log.info("%s: %s", tag, row)
    table: dict[str, dict] = {}
    for r in rows:
        if r["found"]:
            what = ", ".join(f"{c} @{f} {d:.2f} deg" for c, f, d in r["found"])
        elif r["pixel_maps"]:
            what = "pixel map: " + ", ".join(f"{c} {m}" for c, m in r["pixel_maps"].items())
        elif r["unresolved"]:
            what = "unresolved: " + "/".join(r["unresolved"])
        else:
            what = "none"
        label = (f"{r['cameras']} cams s{r['seed']} @{r['at']} {r['camera']} {r['degrees']:g} "
                 f"{r['axis']}")  # fmt: skip
        table[label] = {**r, "what": what}
    cols = [("unmoved_all", "unmoved"), ("unchecked_all", "unchecked"),
            ("checked_all", "checked"), ("peer_all", "anipose"),
            ("peer_unmoved_all", "anip. unm."), ("unchecked_seen", "seen unch."),
            ("checked_seen", "seen chk."), ("unmoved_seen", "seen unm.")]  # fmt: skip
    print(f"\nRMSE all / seen by >= 2 cameras (mm), {args.split} segment, a camera turned:")
    print_table(table, cols, 11)
    print("\nfound by the check (camera @ frame, turn; or mapped by the pixel check):")
    for label, line in table.items():
        print(f"  {label}: {line['what']}")
    mapped = [r for r in rows if r["found"] or r["pixel_maps"]]
    checks = {
        "mapped_moves_right_camera": all(
            all(c == r["camera"] for c, _, _ in r["found"])
            and all(c == r["camera"] for c in r["pixel_maps"])
            for r in mapped
        ),
        "mapped_within_5pct_of_unmoved": all(
            r["checked_all"] <= SAME * r["unmoved_all"] for r in mapped
        ),
        "no_move_on_unmoved": all(r["false_moves_unmoved"] == 0 for r in rows),
        "mapped": f"{len(mapped)} of {len(rows)}",
        "unresolved": sum(bool(r["unresolved"]) for r in rows),
        "refused_unchecked": sum(bool(r["refused_unchecked"]) for r in rows),
        "refused_checked": sum(bool(r["refused_checked"]) for r in rows),
    }
    print(f"\nchecks: {checks}")
    return emit({"split": args.split, "seeds": seeds, "at": ats, "rows": rows, "checks": checks},
                args.out)  # fmt: skip


if __name__ == "__main__":
    main()
