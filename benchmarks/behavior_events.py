"""Lock-box events on tracked input: `adjust-events` on what the trackers give, against the
events the same detector finds on the simulator's truth.

Scenes: `adjust-simulate` lock-box scenes (the default rig, detector and lock box), seeds fixed
here (held out: nothing was chosen on them). Each scene is tracked by `adjust-track` (the
default config) and triangulated by `adjust-triangulate` (DLT, its gaps filled in time:
`adjust-events interpolate=true`); `adjust-events` (its default contact settings) labels the
tracks, and `adjust.events.detect_events` with the same settings labels the truth points.

An event found on the tracks is a true positive when a truth event of the same part and
mechanism overlaps it in time (each truth event matched once); precision = true positives /
events found, recall = matched truth events / truth events, pooled over the scenes.

    flock /tmp/mousetrack-cpu.lock nice -n 5 .venv/bin/python benchmarks/behavior_events.py \\
        [--scenes 3] [--frames 3000] [--quick]

Prints a table; the last line is JSON, also written to runs/benchmarks/behavior_events.json.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np
from common import emit, start

from adjust.apps.events import run as events_run
from adjust.apps.simulate import run as simulate_run
from adjust.apps.track import run as track_run
from adjust.apps.triangulate import run as triangulate_run
from adjust.events import detect_events
from deformnet.confutil import compose

log = logging.getLogger("benchmarks.behavior_events")

SCENE_SEED = 72_500  # held out: never used for a choice
METHODS = ("track", "dlt")


def match_events(found: list[dict], truth: list[dict]) -> dict:
    """Events found (start, stop inclusive, part, mechanism) against truth events: each found
    event is a true positive when an unmatched truth event of the same part and mechanism
    overlaps it; {"found", "truth", "tp", "matched_truth"}."""
    used = np.zeros(len(truth), bool)
    tp = 0
    for e in found:
        for j, t in enumerate(truth):
            same = t["part"] == e["part"] and t["mechanism"] == e["mechanism"]
            if same and not used[j] and e["start"] <= t["stop"] and t["start"] <= e["stop"]:
                used[j] = True
                tp += 1
                break
    return {"found": len(found), "truth": len(truth), "tp": tp, "matched_truth": int(used.sum())}


def scene_events(scene: Path, work: Path) -> dict:
    """{method: match_events of its tracks' events against the truth's} for one scene."""
    inputs = [f"input.calibration={scene / 'calibration.toml'}",
              f"input.detections={scene / 'detections'}"]  # fmt: skip
    track_run(compose("track", [*inputs, f"output.dir={work / 'track'}", "progress=false"]))
    triangulate_run(compose("triangulate", [*inputs, f"output.dir={work / 'dlt'}", "body=mouse"]))
    with np.load(scene / "truth.npz") as z:
        points, parts = z["points"], [str(p) for p in z["parts"]]
    out = {}
    for method in METHODS:
        res = events_run(compose("events", [
            f"tracks={work / method / 'points3d.csv'}", f"calibration={scene / 'calibration.toml'}",
            f"output.dir={work / method / 'events'}", f"interpolate={method == 'dlt'}",
        ]))  # fmt: skip
        c = res["contact"]
        truth = detect_events(
            points, parts, res["mechanisms"], use_parts=res["parts"], on_mm=float(c["on_mm"]),
            off_mm=float(c["off_mm"]), min_frames=int(c["min_frames"]),
            merge_gap=int(c["merge_gap"]),
        )  # fmt: skip
        found = [{**e, "start": int(e["start"]), "stop": int(e["stop"])} for e in res["event_list"]]
        out[method] = match_events(found, truth)  # fnum = frame index in a simulated scene
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=3)
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--quick", action="store_true", help="a smoke run (one short scene)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--work", default="runs/benchmarks/behavior_events_work")
    ap.add_argument("--out", default="runs/benchmarks/behavior_events.json")
    args = start(ap, argv)
    if args.quick:
        args.scenes, args.frames = 1, 600
    work = Path(args.work)
    t0 = time.perf_counter()
    per_scene = []
    for i in range(args.scenes):
        seed = SCENE_SEED + i
        scene = work / f"scene{i}"
        if not (scene / "truth.npz").exists():
            simulate_run(compose("scene", [f"output.dir={scene}", f"num_frames={args.frames}",
                                           f"seed={seed}"]))  # fmt: skip
        per_scene.append({"seed": seed, **scene_events(scene, work / f"out{i}")})
        log.info("scene %d (seed %d): %s", i, seed, per_scene[-1])
    rows = {}
    for method in METHODS:
        tot = {k: sum(s[method][k] for s in per_scene) for k in ("found", "truth", "tp")}
        tot["matched_truth"] = sum(s[method]["matched_truth"] for s in per_scene)
        tot["precision"] = tot["tp"] / tot["found"] if tot["found"] else float("nan")
        tot["recall"] = tot["matched_truth"] / tot["truth"] if tot["truth"] else float("nan")
        rows[method] = tot
    print(f"\nlock-box events, {args.scenes} scenes x {args.frames} frames (seeds from "
          f"{SCENE_SEED})\n| input | truth events | found | precision | recall |\n| --- | --- | "
          "--- | --- | --- |")  # fmt: skip
    for method, r in rows.items():
        print(f"| {method} | {r['truth']} | {r['found']} | {r['precision']:.3f} | "
              f"{r['recall']:.3f} |")  # fmt: skip
    summary = {"scenes": args.scenes, "frames": args.frames, "seed": SCENE_SEED, "rows": rows,
               "per_scene": per_scene, "target": ">= 0.9 precision and recall on tracked input",
               "met": bool(rows["track"]["precision"] >= 0.9 and rows["track"]["recall"] >= 0.9),
               "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip
    return emit(summary, args.out)


if __name__ == "__main__":
    main()
