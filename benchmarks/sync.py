"""A camera out of step in time: the real-motion scenes with one camera's detections moved by
k frames (its video started k frames early: its file's frame f + k is the others' frame f),
tracked with the offset not looked for (``input.max_frame_offset=0``, what adjust-track did
before stop 56) and with the default check (`adjust.sync`: found from the epipolar geometry
and shifted back); and the real recordings, which must show no offset.

Scenes: `real_motion.py`'s 8-part validation scenes (frames 1200-2199, ``--cameras``,
``--seeds``), the rig's last camera moved by each k of ``--lags`` (with two cameras nothing
tells which one keeps the session's time: the first is taken to, `adjust.sync`). Rows: RMSE
all and seen by >= 2 cameras (mm) in step, moved and unchecked, moved and checked; the offset
found; "lost": in step, with the frames the moved file lost emptied (what shifting it back can
give at best). Then the same camera drops k frames at frame AT (``--drops AT:K``: its rows from
AT on hold the frame k later, a lag that changes during the session): unchecked, checked, the
change found. Targets: every offset found exactly, the checked run the same as "lost"; every
drop found (lag -k, within `DROP_TOLERANCE` frames of AT); no offset on the real hand, fly and
SLEAP mouse.

    .venv/bin/python benchmarks/sync.py [--cameras 2,3] [--seeds 0] [--lags 1,2,5,15,-7] \\
        [--drops 300:3,600:6] [--frames 1000] [--work DIR] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, print_table, start  # noqa: E402
from real_motion import (  # noqa: E402
    DATA,
    SPLITS,
    Motion,
    film_scene,
    input_args,
    input_settings,
    scene_key,
    track_row,
)

from adjust.io import load_calibration, load_scene, read_dlc, write_dlc_csv  # noqa: E402
from adjust.sync import check_sync  # noqa: E402
from deformnet.paths import shared_dir  # noqa: E402

log = logging.getLogger("benchmarks.sync")

#: a change of lag found within this many frames of the drop counts as found (where the lags
#: fit alike, e.g. a still animal, the frame is not defined better)
DROP_TOLERANCE = 30

#: the real recordings: (folder, detections below it, file pattern)
REAL = (
    ("real-hand-4cam", "trial_000", None),
    ("real-fly-3cam", ".", None),
    ("real-mouse-sleap-4cam", ".", "*.analysis.h5"),
)


def edited(scene: Path, out: Path, camera: str, edit) -> Path:
    """A copy of `scene` whose `camera`'s detections (xy (T, K, 2), likelihood (T, K)) are
    replaced by ``edit(xy, likelihood)`` (cached: kept if truth.npz is there)."""
    if (out / "truth.npz").exists():
        return out
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(scene, out, ignore=shutil.ignore_patterns("truth.npz"))
    table = read_dlc(scene / "detections" / f"{camera}.csv")
    xy, lik = edit(table.xy, table.likelihood)
    write_dlc_csv(out / "detections" / f"{camera}.csv", table.parts, xy, lik)
    shutil.copy2(scene / "truth.npz", out / "truth.npz")  # last: the cache's mark
    return out


def moved(lag: int, back: bool = False):
    """The edit moving a camera's rows by `lag` (its row f + lag holds the others' frame f;
    rows with nothing to hold are empty); ``back``: in step, with the frames that the moved
    file lost emptied instead (what shifting it back can give)."""

    def edit(xy, lik):
        new_xy, new_lik = np.full_like(xy, np.nan), np.zeros_like(lik)
        if back:  # frames T - lag.. (lag > 0) or ..-lag (lag < 0) have no row left
            keep = slice(0, len(xy) - lag) if lag > 0 else slice(-lag, len(xy))
            new_xy[keep], new_lik[keep] = xy[keep], lik[keep]
        elif lag > 0:
            new_xy[lag:], new_lik[lag:] = xy[:-lag], lik[:-lag]
        else:
            new_xy[:lag], new_lik[:lag] = xy[-lag:], lik[-lag:]
        return new_xy, new_lik

    return edit


def dropped(at: int, k: int):
    """The edit of a camera that dropped k frames at frame `at` (its rows from there hold the
    frame k later; its last k rows are empty)."""

    def edit(xy, lik):
        new_xy, new_lik = xy.copy(), lik.copy()
        new_xy[at:], new_lik[at:] = np.nan, 0.0
        new_xy[at:-k], new_lik[at:-k] = xy[at + k :], lik[at + k :]
        return new_xy, new_lik

    return edit


def _cells(r: dict, **more) -> dict:
    """A table row's RMSE cells (mm) of in-step, unchecked and checked runs (``more`` after
    the in-step one)."""
    return {
        "in step": r["in_step"]["rmse_all"],
        **more,
        "unchecked": r["unchecked"]["rmse_all"],
        "checked": r["checked"]["rmse_all"],
        "seen unch.": r["unchecked"]["rmse_seen2"],
        "seen chk.": r["checked"]["rmse_seen2"],
    }


def tracked(scene: Path, runs: Path, name: str, truth, threads: int, extra=()) -> dict:
    """adjust-track on `scene` (run `name`): RMSE all, seen by >= 2 cameras, offsets found."""
    out = runs / scene.name / name
    parts = [str(p) for p in truth["parts"]]
    r = track_row(scene, out, [f"threads={threads}", *extra], truth["points"], truth["nviews"],
                  parts)  # fmt: skip
    sync = (json.loads((out / "summary.json").read_text()).get("camera_check") or {}).get("sync")
    return {"rmse_all": r["rmse_all"], "rmse_seen2": r["rmse_seen2"],
            "offsets": (sync or {}).get("offsets", {}),
            "steps": (sync or {}).get("steps", {})}  # fmt: skip


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_args(ap, "sync", "2,3")
    ap.add_argument("--lags", default="1,2,5,15,-7", help="frames the camera is moved by")
    ap.add_argument("--drops", default="300:3,600:6",
                    help="AT:K, the camera drops K frames at frame AT (comma list)")  # fmt: skip
    args = start(ap, argv)
    cameras, seeds = input_settings(ap, args)
    lags = [int(k) for k in args.lags.split(",") if k.strip()]
    if not lags or 0 in lags:
        ap.error("--lags: non-zero frame offsets")
    try:
        drops = [tuple(int(v) for v in d.split(":")) for d in args.drops.split(",") if d.strip()]
    except ValueError:
        ap.error(f"--drops: AT:K pairs, got {args.drops!r}")
    if any(len(d) != 2 or d[1] < 1 or not 0 < d[0] < args.frames - d[1] for d in drops):
        ap.error(f"--drops: AT:K with 0 < AT < frames - K and K >= 1, got {args.drops!r}")
    motion = Motion(DATA)
    work = Path(args.work) / motion.tag
    start_frame = SPLITS["val"]
    rows: list[dict] = []
    drop_rows: list[dict] = []
    for cams in cameras:
        for seed in seeds:
            key = scene_key("val", start_frame, args.frames, cams, 8, seed)
            base = film_scene(work / "scenes" / key, motion, start_frame, args.frames, cams, 8,
                              seed)  # fmt: skip
            truth = np.load(base / "truth.npz")
            # the calibration's last camera: with two, the first is the reference (module doc)
            camera = load_calibration(base / "calibration.toml")[-1].name
            runs = work / "runs"
            in_step = tracked(base, runs, "in_step", truth, args.threads)
            for lag in lags:
                name = f"{key}_{camera}{lag:+d}"
                scene = edited(base, work / "moved" / name, camera, moved(lag))
                lost = edited(base, work / "moved" / f"{name}_lost", camera, moved(lag, True))
                blind = tracked(scene, runs, "unchecked", truth, args.threads,
                                ["input.max_frame_offset=0"])  # fmt: skip
                checked = tracked(scene, runs, "checked", truth, args.threads)
                ref = tracked(lost, runs, "in_step", truth, args.threads)
                rows.append({
                    "cameras": cams, "seed": seed, "camera": camera, "lag": lag,
                    "in_step": in_step, "in_step_lost": ref, "unchecked": blind,
                    "checked": checked, "found": checked["offsets"].get(camera, 0),
                    "checked_over_lost": checked["rmse_all"] / ref["rmse_all"],
                })  # fmt: skip
                log.info("%s %s moved by %+d: found %s", key, camera, lag, checked["offsets"])
            for at, k in drops:
                name = f"{key}_{camera}_drop{at}x{k}"
                scene = edited(base, work / "moved" / name, camera, dropped(at, k))
                blind = tracked(scene, runs, "unchecked", truth, args.threads,
                                ["input.max_frame_offset=0"])  # fmt: skip
                checked = tracked(scene, runs, "checked", truth, args.threads)
                steps = checked["steps"].get(camera) or []
                drop_rows.append({
                    "cameras": cams, "seed": seed, "camera": camera, "at": at, "k": k,
                    "in_step": in_step, "unchecked": blind, "checked": checked, "steps": steps,
                    "found": len(steps) == 2 and steps[1][1] == -k and abs(steps[1][0] - at)
                    <= DROP_TOLERANCE,
                })  # fmt: skip
    table = {
        f"{r['cameras']} cameras s{r['seed']}, {r['lag']:+d}": {
            **_cells(r, lost=r["in_step_lost"]["rmse_all"]),
            "found": r["found"],
        }
        for r in rows
    }
    print("\nRMSE all / seen by >= 2 cameras (mm), one camera moved by k frames (lost: in step,")
    print("the frames the moved file lost emptied):")
    print_table(table, [(k, k) for k in next(iter(table.values()))], 12)
    drops_table = {
        f"{r['cameras']} cameras s{r['seed']}, {r['k']} at {r['at']}": {
            **_cells(r),
            "change at": r["steps"][1][0] if len(r["steps"]) > 1 else "-",
        }
        for r in drop_rows
    }
    if drops_table:
        print("\nthe camera drops k frames at a frame (its lag changes during the session):")
        print_table(drops_table, [(k, k) for k in next(iter(drops_table.values()))], 12)
    real = {}
    for folder, sub, pattern in REAL:
        root = shared_dir() / "data" / folder
        cams, det = load_scene(root / "calibration.toml", root / sub, None, pattern=pattern)
        real[folder] = check_sync(cams, det, 30)[1]["offsets"]
    print(f"\noffsets found on the real recordings: {real}")
    checks = {
        "every_offset_found": all(r["found"] == r["lag"] for r in rows),
        "checked_equals_in_step": all(abs(r["checked_over_lost"] - 1) < 1e-6 for r in rows),
        "every_drop_found": all(r["found"] for r in drop_rows),
        "drops_checked_within_5pct": all(
            r["checked"]["rmse_all"] < 1.05 * r["in_step"]["rmse_all"] for r in drop_rows
        ),
        "no_offset_on_real": not any(real.values()),
    }
    print(f"checks: {checks}")
    summary = {"seeds": seeds, "rows": rows, "drops": drop_rows, "real": real, "checks": checks}
    return emit(summary, args.out)


if __name__ == "__main__":
    main()
