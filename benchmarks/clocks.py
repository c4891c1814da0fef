"""A camera whose clock runs at another rate than the others': the real-motion scenes with one
camera's frame g showing the others' frame (g - offset) / rate, its file numbered in its own
frames: a clock that drifts (``--rates 0.995``: 0.5% slow, 5 frames over the 1000, as a
free-running webcam at 29.85 against 30 fps) or a frame rate that is not a whole multiple of
theirs (``0.8333``: 25 against 30 fps; ``1.2``: 30 against 25), the camera started
``--offset`` frames after the others; and a webcam that cannot keep up (``--drops 150``: it
drops one frame in every 150, its file lacks them and numbers the rest consecutively, as its
video does: a lag that grows by a frame at a time). Tracked with the clock not looked for
(``input.rate_check=false``, what adjust-track did before stop 60) and with the default check
(`adjust.clocks`: the camera's rate and offset found from the epipolar geometry, its
detections read at the others' times), beside aniposelib (`triangulate_optim` with anipose's
settings, `real_motion.py`'s peer; it pairs rows by index, as the files give them).

Scenes: `real_motion.py`'s 8-part scenes of the test segment (frames 2400-3399; nothing was
chosen on it; ``--split val`` for the validation one; ``--cameras``, ``--seeds``). The camera is
filmed from the recording interpolated in time (a cubic spline) at its own times; the other
cameras and the truth at the others' frames. Each camera in turn, except with two cameras: the
first keeps the session's time, so the second runs otherwise. Rows: RMSE all and seen by >= 2
cameras (mm) in step, unchecked, checked, aniposelib on the same files / in step; the rate and
offset found.

Checks: every map found is the camera's own, its lag within 0.5 frame of the truth over the
session (1 frame for the dropped frames: a line through a staircase); no map on the scenes in
step; checked no worse than unchecked in the geometric mean.

    .venv/bin/python benchmarks/clocks.py [--split test] [--cameras 2,3,4] [--seeds 0] \\
        [--rates 0.995,0.8333,1.2] [--offset 2.5] [--drops 150] [--clock-cameras NAMES] \\
        [--no-peer] [--work DIR] [--out FILE]
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
    film_scene,
    frames_row,
    input_args,
    input_run,
    input_settings,
    peer_row,
    refilmed_scene,
    scene_key,
    spoil_scene,
)

from adjust.io import load_calibration  # noqa: E402

log = logging.getLogger("benchmarks.clocks")

LAG_WITHIN = 0.5  #: frames: a map found this close to the true lag everywhere counts as right
DROPS_WITHIN = 1.0  #: ... for a camera dropping frames (a line through a staircase)
PEER_RATIOS = {"checked/peer_all": ("checked_all", "peer_all"),
               "peer/peer_instep": ("peer_all", "peer_instep_all")}  # fmt: skip


def clock_scene(
    base: Path, out: Path, motion: Motion, start_frame: int, frames: int, ncams: int,
    seed: int, camera: str, rate: float, offset: float,
) -> Path:  # fmt: skip
    """A copy of `base` (`film_scene`'s) whose `camera` has its own clock: its frame g (0, 1,
    ... while the session lasts) shows the scene's frame (g - offset) / rate
    (`real_motion.refilmed_scene`). Cached."""
    g = np.arange(int(np.floor((frames - 1) * rate + offset)) + 1, dtype=np.float64)
    g = g[g >= offset]  # the camera started `offset` frames after the others
    t = start_frame + (g - offset) / rate
    return refilmed_scene(base, out, motion, camera, t, t, ncams, seed)


def dropped_scene(base: Path, out: Path, camera: str, every: int) -> Path:
    """A copy of `base` whose `camera` drops one frame in every `every` (a webcam that cannot
    keep up): its file lacks frames every - 1, 2 every - 1, ..., its rows renumbered 0, 1, ...
    as the video's frames are. Cached."""

    def edit(t):
        keep = (np.arange(len(t.xy)) + 1) % every != 0
        return t.xy[keep], t.likelihood[keep]

    return spoil_scene(base, out, {camera: edit})


def true_rows(cond: tuple[str, float], offset: float, frames: int):
    """(the others' frames f, the camera's file row at each) under condition `cond`: ("rate",
    r), its row r f + offset - ceil(offset) (its first row is its file's 0); ("drops", N),
    the frames it kept and their rows f - floor((f + 1) / N)."""
    f = np.arange(frames, dtype=np.float64)
    kind, v = cond
    if kind == "rate":
        return f, v * f + offset - np.ceil(offset)
    kept = (f + 1) % v != 0
    return f[kept], f[kept] - np.floor((f[kept] + 1) / v)


def lag_error(found: dict, truth: tuple[np.ndarray, np.ndarray]) -> float:
    """The largest difference (frames of the camera) over the session's frames between the
    found map's row and the true one (`true_rows`; NaN without a map)."""
    if not found:
        return float("nan")
    f, true = truth
    return float(np.abs(found["rate"] * f + found["offset"] - true).max())


def label_of(cond: tuple[str, float]) -> str:
    """A condition's label: x0.995 (a rate), drops 1/150."""
    kind, v = cond
    return f"x{v:g}" if kind == "rate" else f"drops 1/{v}"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_args(ap, "clocks", "2,3,4")
    ap.add_argument("--rates", default="0.995,0.8333,1.2", help="the camera's rate / theirs")
    ap.add_argument("--offset", type=float, default=2.5, help="frames it started after them")
    ap.add_argument("--drops", default="150", help="a camera dropping 1 frame in N (N, ...)")
    ap.add_argument("--split", default="test", choices=tuple(SPLITS), help="the segment")
    ap.add_argument("--clock-cameras", default="", help="only these cameras (default: each)")
    ap.add_argument("--no-peer", action="store_true", help="without aniposelib")
    args = start(ap, argv)
    only = [c for c in args.clock_cameras.split(",") if c.strip()]
    cameras, seeds = input_settings(ap, args)
    rates = [float(v) for v in args.rates.split(",") if v.strip()]
    if any(not 0.5 <= r <= 2 or r == 1 for r in rates):
        ap.error(f"--rates must lie within [0.5, 2], not 1: {args.rates}")
    if not 0 <= args.offset <= 20:
        ap.error(f"--offset must lie within [0, 20] frames, got {args.offset}")
    drops = [int(v) for v in args.drops.split(",") if v.strip()]
    if any(n < 10 for n in drops):
        ap.error(f"--drops must be at least 10 frames, got {args.drops}")
    conditions = [("rate", r) for r in rates] + [("drops", n) for n in drops]
    motion, work, threads = input_run(args)
    start_frame = SPLITS[args.split]
    frames = args.frames
    rows: list[dict] = []

    def tracked(scene: Path, name: str, extra=()) -> tuple[dict, dict]:
        return frames_row(scene, work / "runs" / scene.name / name, [threads, *extra])

    def peer(scene: Path) -> dict:
        return {} if args.no_peer else peer_row(scene, truth_frames=True)

    for ncams in cameras:
        for seed in seeds:
            key = scene_key(args.split, start_frame, frames, ncams, 8, seed)
            base = film_scene(work / "scenes" / key, motion, start_frame, frames, ncams, 8, seed)
            ref, ref_check = tracked(base, "checked")
            ref_peer = peer(base)
            names = [c.name for c in load_calibration(base / "calibration.toml")]
            for camera in [c for c in (names[1:] if ncams == 2 else names)
                           if not only or c in only]:  # fmt: skip
                for cond in conditions:
                    kind, v = cond
                    if kind == "rate":
                        tag = f"{key}_{camera}_rate{v:g}_off{args.offset:g}"
                        scene = clock_scene(
                            base, work / "clocked" / tag, motion, start_frame, frames, ncams,
                            seed, camera, v, args.offset,
                        )  # fmt: skip
                    else:
                        tag = f"{key}_{camera}_drops{v}"
                        scene = dropped_scene(base, work / "clocked" / tag, camera, v)
                    blind, _ = tracked(scene, "unchecked", ["input.rate_check=false"])
                    fixed, check = tracked(scene, "checked")
                    found = (check.get("clocks") or {}).get("retimed") or {}
                    p = peer(scene)
                    row = {
                        "cameras": ncams, "seed": seed, "camera": camera,
                        "condition": label_of(cond),
                        "rate": v if kind == "rate" else None,
                        "offset": args.offset if kind == "rate" else 0.0,
                        "drop_every": v if kind == "drops" else None,
                        "instep_all": ref["rmse_all"], "instep_seen": ref["rmse_seen2"],
                        "unchecked_all": blind["rmse_all"], "unchecked_seen": blind["rmse_seen2"],
                        "checked_all": fixed["rmse_all"], "checked_seen": fixed["rmse_seen2"],
                        "peer_all": p.get("rmse_all"), "peer_instep_all": ref_peer.get("rmse_all"),
                        "found": {n: [v["rate"], v["offset"]] for n, v in found.items()},
                        "lag_error": lag_error(
                            found.get(camera) or {}, true_rows(cond, args.offset, frames)
                        ),
                        "excluded_checked": sorted(check.get("excluded") or {}),
                        "false_maps_instep": sorted(
                            (ref_check.get("clocks") or {}).get("retimed") or {}
                        ),
                    }  # fmt: skip
                    rows.append(row)
                    log.info("%s: %s", tag, row)
    table = {f"{r['cameras']} cams s{r['seed']} {r['camera']} {r['condition']}": r for r in rows}
    print(f"\nRMSE all / seen by >= 2 cameras (mm), {args.split} segment, a camera's own clock:")
    print_table(table, CHECK_COLUMNS, 11)
    print("\nfound by the check (camera: rate, offset; the largest lag error in frames):")
    for label, r in table.items():
        print(f"  {label}: {r['found'] or 'none'}; {r['lag_error']:.2f}")
    summary: dict = {}
    for ncams in cameras:
        for cond in conditions:
            rs = [r for r in rows if r["cameras"] == ncams and r["condition"] == label_of(cond)]
            if not rs:
                continue
            summary[f"{ncams} cameras {label_of(cond)}"] = {
                **ratio_means(rs, {**CHECK_RATIOS, **PEER_RATIOS}),
                "found": f"{sum(bool(r['found']) for r in rs)} of {len(rs)}",
            }
    print_means(summary)

    def right(r: dict) -> bool:
        within = LAG_WITHIN if r["drop_every"] is None else DROPS_WITHIN
        return set(r["found"]) == {r["camera"]} and r["lag_error"] <= within

    checks = {
        "found_right": f"{sum(right(r) for r in rows)} of {len(rows)}",
        "every_found_right": all(right(r) for r in rows if r["found"]),
        "no_map_in_step": all(not r["false_maps_instep"] for r in rows),
        "checked_no_worse_than_unchecked": geo_mean(
            [r["checked_all"] / r["unchecked_all"] for r in rows]
        )
        <= 1,
    }
    print(f"\nchecks: {checks}")
    return emit(
        {"split": args.split, "seeds": seeds, "rates": rates, "offset": args.offset, "drops": drops,
         "rows": rows, "summary": summary, "checks": checks},
        args.out,
    )  # fmt: skip


if __name__ == "__main__":
    main()
