"""Detections on videos other than the calibrated ones: the real-motion scenes with every camera's
video downsampled (``--factor``, 2: the pose estimator ran on half-size videos) or one camera's
video cropped (``--crop``, at (200, 150) px: DeepLabCut's ``cropping``), or one camera's video
mirrored left to right (``--cases flip``: a view from below flipped to look like one from
above), or one camera's video turned a quarter turn clockwise (``--cases turn``: a camera
mounted on its side, its video turned upright) or its x and y swapped (``--cases transpose``:
a converter that writes the columns the other way round), the calibration as it was; tracked
with the pixel frames not looked for (``input.pixel_check=false``, what adjust-track did before
stop 58) and with the default check (`adjust.pixels`: the map fitted to the epipolar geometry,
the detections mapped back).

Scenes: `real_motion.py`'s 8-part scenes of the test segment (frames 2400-3399; nothing was
chosen on it; ``--split val`` for the validation one; ``--cameras``, ``--seeds``); downsampled
as a resize does (pixel centres: u = (x + 0.5) / f - 0.5); each camera cropped in turn (two
cameras: the second; the first keeps its frame); each camera flipped, turned or transposed in
turn. Rows: RMSE all and seen by >= 2 cameras (mm) as calibrated, unchecked, checked; the map
found; the cameras excluded. aniposelib has no such check; its RMSE as calibrated is given for
scale, and on the spoilt files (``anip. spoilt``) for the flipped, turned and transposed
cameras.

Checks: every spoilt camera mapped, none other; checked within 5% of the scene as calibrated. A
run adjust-track refuses (its health check: the tracks cannot be trusted, a non-zero exit) is
recorded as refused, its scores NaN.

    .venv/bin/python benchmarks/pixels.py [--split test] [--cameras 2,3,4] [--seeds 0] \\
        [--factor 2] [--crop 200,150] [--cases resize,crop,flip,turn,transpose] [--no-peer] \\
        [--work DIR]
        [--out FILE]
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, print_table, start  # noqa: E402
from real_motion import (  # noqa: E402
    DATA,  # noqa: F401 - the recording read (the tests skip where it is absent)
    SPLITS,
    checked_or_refused,
    checked_row,
    film_scene,
    input_args,
    input_run,
    input_settings,
    peer_row,
    scene_key,
    spoil_scene,
)

from adjust.io import load_calibration  # noqa: E402
from adjust.pixels import edit_map  # noqa: E402

log = logging.getLogger("benchmarks.pixels")

SAME = 1.05  #: checked must track within this factor of the scene as calibrated
KINDS = {
    "resize": "every video downsampled by --factor",
    "crop": "each camera's video cropped at --crop in turn (two cameras: the second)",
    "flip": "each camera's video mirrored left to right in turn",
    "turn": "each camera's video turned a quarter turn clockwise in turn",
    "transpose": "each camera's x and y swapped in turn",
}
EDITS = {"turn": "a quarter turn clockwise", "transpose": "transposed (its x and y swapped)"}


def flipped(width: int):
    """The pixels of a video mirrored left to right (u = W - 1 - x: pixel centres)."""

    def edit(xy: np.ndarray) -> np.ndarray:
        out = xy.copy()
        out[..., 0] = width - 1 - xy[..., 0]
        return out

    return edit


def turned(how: str, size):
    """The pixels u = A^T (x - d) of a video turned or transposed `how` (`adjust.pixels.TURNS`),
    the calibrated image's `size` (W, H): the inverse of the check's map x = A u + d."""
    A, d = (np.array(v) for v in edit_map(how, size))

    def edit(xy: np.ndarray) -> np.ndarray:
        return (xy - d) @ A

    return edit


def spoilt(base: Path, out: Path, edits: dict) -> Path:
    """A copy of `base` with each camera's detections u -> edits[camera](u) (`spoil_scene`)."""
    return spoil_scene(
        base, out, {cam: (lambda t, fn=fn: (fn(t.xy), t.likelihood)) for cam, fn in edits.items()}
    )


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_args(ap, "pixels", "2,3,4")
    ap.add_argument("--factor", type=float, default=2.0, help="every video downsampled by")
    ap.add_argument("--crop", default="200,150", help="one camera's crop origin x,y (px)")
    ap.add_argument("--cases", default="resize,crop", help=f"some of {list(KINDS)}")
    ap.add_argument("--split", default="test", choices=tuple(SPLITS), help="the segment")
    ap.add_argument("--no-peer", action="store_true", help="without aniposelib")
    args = start(ap, argv)
    cameras, seeds = input_settings(ap, args)
    kinds = [k for k in args.cases.split(",") if k.strip()]
    if not kinds or set(kinds) - set(KINDS):
        ap.error(f"--cases must be some of {list(KINDS)}, got {args.cases!r}")
    crop = np.array([float(v) for v in args.crop.split(",")])
    if crop.shape != (2,) or args.factor <= 0:
        ap.error(f"--crop must be x,y and --factor > 0, got {args.crop}, {args.factor}")
    motion, work, threads = input_run(args)
    start_frame = SPLITS[args.split]
    f = args.factor
    rows: dict[str, dict] = {}
    for ncams in cameras:
        for seed in seeds:
            key = scene_key(args.split, start_frame, args.frames, ncams, 8, seed)
            base = film_scene(work / "scenes" / key, motion, start_frame, args.frames, ncams, 8,
                              seed)  # fmt: skip
            ref, _ = checked_row(base, work / "runs" / key / "as_calibrated", [threads])
            peer = None if args.no_peer else peer_row(base)["rmse_all"]
            rig = load_calibration(base / "calibration.toml")
            names = [c.name for c in rig]
            cases = {}
            if "resize" in kinds:
                cases[f"downsampled {f:g}x"] = {n: (lambda xy: (xy + 0.5) / f - 0.5) for n in names}
            for cam in (names[1:] if ncams == 2 else names) if "crop" in kinds else ():
                cases[f"{cam} cropped"] = {cam: (lambda xy: xy - crop)}
            for cam in names if "flip" in kinds else ():  # either of two: a flip is told
                cases[f"{cam} flipped"] = {cam: flipped(rig[names.index(cam)].size[0])}
            for kind in (k for k in EDITS if k in kinds):  # either of two, as a flip
                for cam in names:
                    edit = turned(EDITS[kind], rig[names.index(cam)].size)
                    cases[f"{cam} {'turned' if kind == 'turn' else 'transposed'}"] = {cam: edit}
            for case, edits in cases.items():
                tag = f"{key}_{case.replace(' ', '_')}"
                scene = spoilt(base, work / "spoilt" / tag, edits)
                blind, blind_check = checked_or_refused(scene, work / "runs" / tag / "unchecked",
                                             [threads, "input.pixel_check=false"])  # fmt: skip
                fixed, check = checked_or_refused(scene, work / "runs" / tag / "checked", [threads])
                mapped = (check.get("pixels") or {}).get("mapped") or {}
                edited = any(k in case for k in ("flipped", "turned", "transposed"))
                peer_spoilt = peer_row(scene)["rmse_all"] if edited and not args.no_peer else None
                rows[f"{ncams} cams s{seed} {case}"] = {
                    "cameras": ncams, "seed": seed, "case": case, "spoilt": sorted(edits),
                    "calibrated_all": ref["rmse_all"], "calibrated_seen": ref["rmse_seen2"],
                    "unchecked_all": blind["rmse_all"], "unchecked_seen": blind["rmse_seen2"],
                    "checked_all": fixed["rmse_all"], "checked_seen": fixed["rmse_seen2"],
                    "mapped": {n: [m["scale"], m["offset"]] for n, m in mapped.items()},
                    "excluded_unchecked": sorted(blind_check.get("excluded") or {}),
                    "excluded_checked": sorted(check.get("excluded") or {}),
                    "peer_calibrated_all": peer, "peer_spoilt_all": peer_spoilt,
                    "refused_unchecked": blind.get("refused"),
                    "refused_checked": fixed.get("refused"),
                }  # fmt: skip
                log.info("%s: %s", tag, rows[f"{ncams} cams s{seed} {case}"])
    cols = [("calibrated_all", "calibrated"), ("unchecked_all", "unchecked"),
            ("checked_all", "checked"), ("peer_calibrated_all", "anip. calib."),
            ("peer_spoilt_all", "anip. spoilt"),
            ("calibrated_seen", "seen calib."), ("unchecked_seen", "seen unch."),
            ("checked_seen", "seen chk.")]  # fmt: skip
    print(f"\nRMSE all / seen by >= 2 cameras (mm), {args.split} segment, pixel frames spoilt:")
    print_table(rows, cols, 11)
    print("\nmapped (camera: scale, offset); excluded unchecked / checked; refused:")
    for label, r in rows.items():
        print(f"  {label}: {r['mapped'] or 'none'}; {r['excluded_unchecked']} / "
              f"{r['excluded_checked']}; {r['refused_unchecked'] or '-'} / "
              f"{r['refused_checked'] or '-'}")  # fmt: skip
    checks = {
        "mapped_the_spoilt_cameras": all(sorted(r["mapped"]) == r["spoilt"] for r in rows.values()),
        "checked_within_5pct_of_calibrated": all(
            r["checked_all"] <= SAME * r["calibrated_all"] for r in rows.values()
        ),
        "refused": sum(bool(r["refused_checked"]) for r in rows.values()),
    }
    print(f"\nchecks: {checks}")
    return emit({"split": args.split, "seeds": seeds, "factor": f, "crop": crop.tolist(),
                 "rows": rows, "checks": checks}, args.out)  # fmt: skip


if __name__ == "__main__":
    main()
