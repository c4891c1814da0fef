"""A camera at another frame rate: the real-motion scenes with one camera recorded at twice the
others' frame rate (``--ratios 2``: the others at 50 fps, every 2nd frame of the recording, it
at 100 fps) or half of it (``-2``: the others at 100 fps, it at 50), its file numbered in its
own frames, tracked with the rates not looked for (``input.rate_check=false``, what
adjust-track did before stop 58) and with the default check (`adjust.rates`: the camera's
frames renumbered to the others').

Scenes: `real_motion.py`'s 8-part scenes of the test segment (frames 2400-3399; nothing was
chosen on it; ``--split val`` for the validation one; ``--cameras``, ``--seeds``); each camera
in turn (two cameras: the second; the first keeps the session's time). Rows: RMSE all and seen
by >= 2 cameras (mm) of the scene at one rate, the same detections as renumbering can give at
best (2: all cameras at 50 fps, the fast camera's even frames; -2: all at 100 fps with the slow
camera's odd frames emptied), unchecked,
checked; what the check found (ratio, phase) and the cameras it excluded. aniposelib has no
such check (it pairs rows by index); its RMSE on the scene at one rate is given for scale.

Checks: the camera found with the right ratio in every scene; checked within 5% of the scene
at one rate.

    .venv/bin/python benchmarks/rates.py [--split test] [--cameras 2,3,4] [--seeds 0] \\
        [--ratios 2,-2] [--rate-cameras NAMES] [--no-peer] [--work DIR] [--out FILE]
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, print_table, start  # noqa: E402
from real_motion import (  # noqa: E402
    DATA,  # noqa: F401 - the recording read (the tests skip where it is absent)
    SPLITS,
    film_scene,
    frames_row,
    input_args,
    input_run,
    input_settings,
    peer_row,
    scene_key,
)

from adjust.io import load_calibration, read_dlc, write_dlc_csv  # noqa: E402

log = logging.getLogger("benchmarks.rates")

SAME = 1.05  #: checked must track within this factor of the scene at one rate


def copy_scene(src: Path, out: Path) -> None:
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(src, out, ignore=shutil.ignore_patterns("truth.npz", "aniposelib.npz"))


def faster(base: Path, fast: Path, out: Path, camera: str) -> Path:
    """`base` (every 2nd frame) with `camera`'s file from `fast` (every frame, its own frame
    numbers): the camera at twice the others' rate."""
    if (out / "truth.npz").exists():
        return out
    copy_scene(base, out)
    shutil.copy2(fast / "detections" / f"{camera}.csv", out / "detections" / f"{camera}.csv")
    shutil.copy2(base / "truth.npz", out / "truth.npz")  # last: the cache's mark
    return out


def decimated(base: Path, fast: Path, out: Path, camera: str) -> Path:
    """`base` with `camera`'s file the even rows of its file in `fast`, renumbered 0, 1, ...:
    the same detections at one rate (what renumbering the faster camera can give at best)."""
    if (out / "truth.npz").exists():
        return out
    copy_scene(base, out)
    t = read_dlc(fast / "detections" / f"{camera}.csv")
    write_dlc_csv(out / "detections" / f"{camera}.csv", t.parts, t.xy[::2], t.likelihood[::2])
    shutil.copy2(base / "truth.npz", out / "truth.npz")
    return out


def slower(base: Path, out: Path, camera: str, lost: bool) -> Path:
    """`base` with `camera`'s even frames only: renumbered 0, 1, ... (at half the others'
    rate), or, with `lost`, its odd frames emptied in place (the best renumbering can give)."""
    if (out / "truth.npz").exists():
        return out
    copy_scene(base, out)
    t = read_dlc(base / "detections" / f"{camera}.csv")
    if lost:
        lik = t.likelihood.copy()
        lik[1::2] = 0.0
        xy = t.xy.copy()
        xy[1::2] = np.nan
        write_dlc_csv(out / "detections" / f"{camera}.csv", t.parts, xy, lik)
    else:
        write_dlc_csv(out / "detections" / f"{camera}.csv", t.parts, t.xy[::2], t.likelihood[::2])
    shutil.copy2(base / "truth.npz", out / "truth.npz")
    return out


def filmed(work, motion, split, start_frame, ncams, seed, stride: int, frames: int) -> Path:
    """`film_scene` of the 8-part scene (cached under work/scenes)."""
    key = scene_key(split, start_frame, frames, ncams, 8, seed, stride)
    return film_scene(work / "scenes" / key, motion, start_frame, frames, ncams, 8, seed, stride)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_args(ap, "rates", "2,3,4")
    ap.add_argument("--ratios", default="2,-2", help="2: a camera at 2x the rate; -2: at half")
    ap.add_argument("--split", default="test", choices=tuple(SPLITS), help="the segment")
    ap.add_argument("--rate-cameras", default="", help="only these cameras (default: each)")
    ap.add_argument("--no-peer", action="store_true", help="without aniposelib")
    args = start(ap, argv)
    only = [c for c in args.rate_cameras.split(",") if c.strip()]
    cameras, seeds = input_settings(ap, args)
    ratios = [int(r) for r in args.ratios.split(",") if r.strip()]
    if not ratios or any(r not in (2, -2) for r in ratios):
        ap.error(f"--ratios must be among 2, -2, got {args.ratios}")
    motion, work, threads = input_run(args)
    start_frame = SPLITS[args.split]
    rows: list[dict] = []

    def tracked(scene: Path, name: str, extra=()) -> tuple[dict, dict]:
        return frames_row(scene, work / "runs" / scene.name / name, [threads, *extra])

    def peer(scene: Path) -> float | None:
        return None if args.no_peer else peer_row(scene)["rmse_all"]

    for ratio in ratios:
        for ncams in cameras:
            for seed in seeds:
                at = (args.split, start_frame, ncams, seed)
                if ratio == 2:
                    base = filmed(work, motion, *at, 2, args.frames // 2)
                    fast = filmed(work, motion, *at, 1, args.frames)
                else:
                    base = filmed(work, motion, *at, 1, args.frames)
                names = [c.name for c in load_calibration(base / "calibration.toml")]
                for camera in [n for n in (names[1:] if ncams == 2 else names)
                               if not only or n in only]:  # fmt: skip
                    tag = f"{base.name}_{camera}_ratio{ratio}"
                    if ratio == 2:
                        ref_scene = decimated(base, fast, work / "one_rate" / tag, camera)
                        scene = faster(base, fast, work / "mixed" / tag, camera)
                    else:
                        ref_scene = slower(base, work / "lost" / tag, camera, lost=True)
                        scene = slower(base, work / "mixed" / tag, camera, lost=False)
                    ref, _ = tracked(ref_scene, "one_rate")
                    blind, blind_check = tracked(scene, "unchecked", ["input.rate_check=false"])
                    fixed, check = tracked(scene, "checked")
                    found = (check.get("rates") or {}).get("renumbered") or {}
                    row = {
                        "ratio": ratio, "cameras": ncams, "seed": seed, "camera": camera,
                        "one_rate_all": ref["rmse_all"], "one_rate_seen": ref["rmse_seen2"],
                        "unchecked_all": blind["rmse_all"],
                        "unchecked_seen": blind["rmse_seen2"],
                        "checked_all": fixed["rmse_all"], "checked_seen": fixed["rmse_seen2"],
                        "frames_truth": ref["frames_out"], "frames_unchecked": blind["frames_out"],
                        "frames_checked": fixed["frames_out"],
                        "found": {n: [v["ratio"], v["phase"]] for n, v in found.items()},
                        "excluded_unchecked": sorted(blind_check.get("excluded") or {}),
                        "excluded_checked": sorted(check.get("excluded") or {}),
                        "peer_one_rate_all": peer(base),
                    }  # fmt: skip
                    rows.append(row)
                    log.info("%s: %s", tag, row)
    table = {
        f"{'2x' if r['ratio'] == 2 else '1/2'} {r['cameras']} cams s{r['seed']} {r['camera']}": r
        for r in rows
    }
    cols = [("one_rate_all", "one rate"), ("unchecked_all", "unchecked"),
            ("checked_all", "checked"), ("peer_one_rate_all", "anip. 1 rate"),
            ("one_rate_seen", "seen 1 rate"), ("unchecked_seen", "seen unch."),
            ("checked_seen", "seen chk.")]  # fmt: skip
    print(f"\nRMSE all / seen by >= 2 cameras (mm), {args.split} segment, a camera at 2x or 1/2:")
    print_table(table, cols, 11)
    print("\nfound (camera: ratio, phase); excluded unchecked / checked:")
    for label, r in table.items():
        print(f"  {label}: {r['found'] or 'none'}; {r['excluded_unchecked']} / "
              f"{r['excluded_checked']}")  # fmt: skip

    def right(r: dict) -> bool:
        want = 2 if r["ratio"] == 2 else 0.5
        return r["found"].get(r["camera"], [None])[0] == want and len(r["found"]) == 1

    checks = {
        "found_every_camera": all(right(r) for r in rows),
        "checked_within_5pct_of_one_rate": all(
            r["checked_all"] <= SAME * r["one_rate_all"] for r in rows
        ),
    }
    print(f"\nchecks: {checks}")
    return emit({"split": args.split, "seeds": seeds, "ratios": ratios, "rows": rows,
                 "checks": checks}, args.out)  # fmt: skip


if __name__ == "__main__":
    main()
