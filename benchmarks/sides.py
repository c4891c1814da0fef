"""Left and right named the other way round in one camera: the real-motion scenes with one
camera's left/right pairs swapped in its detection file (a view from below or through a mirror,
labelled by the image's sides; or a labeller's slip on some parts), the calibration as it was;
tracked with the check off (``input.side_check=false``, what adjust-track did before stop 59)
and with the default check (`adjust.sides`: the camera and its pairs found from the epipolar
geometry and swapped back; with two cameras the body model's handedness tells which camera,
where the body is a named one).

Scenes: `real_motion.py`'s scenes of the test segment (frames 2400-3399; nothing was chosen on
it; ``--split val`` for the validation one; ``--cameras``, ``--seeds``, ``--parts`` 8 (the
default mouse: a named body) or 22 / 34 (their body estimated from the data: no handedness
known, the first camera keeps its labels)); each camera in turn, with every pair swapped
(``all``) and every pair but the first (``but_first``: the paws, not the ears, of the 8 parts;
``--cases``). Rows: RMSE all and seen by >= 2 cameras (mm) as labelled, unchecked, checked;
aniposelib on the same swapped files and as labelled.

Checks: the swapped pairs of the swapped camera found, and nothing else; checked within 2% of
the scene as labelled.

    .venv/bin/python benchmarks/sides.py [--split test] [--cameras 2,3,4] [--seeds 0] \\
        [--parts 8] [--cases all,but_first] [--no-peer] [--work DIR] [--out FILE]
"""

from __future__ import annotations

import argparse
import itertools
import logging
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, print_table, start  # noqa: E402
from real_motion import (  # noqa: E402
    DATA,  # noqa: F401 - the recording read (the tests skip where it is absent)
    PART_SETS,
    SPLITS,
    checked_row,
    film_scene,
    input_args,
    input_run,
    input_settings,
    peer_row,
    scene_key,
    spoil_scene,
)

from adjust.io import load_calibration, read_dlc  # noqa: E402
from adjust.sides import side_pairs  # noqa: E402

log = logging.getLogger("benchmarks.sides")

SAME = 1.02  #: checked must track within this factor of the scene as labelled


CASES = {"all": "every pair", "but_first": "every pair but the first"}


def swapped_scene(base: Path, out: Path, cam: str, case: str) -> tuple[Path, list]:
    """A copy of `base` with camera `cam`'s left/right pairs swapped (`CASES`: every pair, or
    every pair but the first in the file's order: a labeller's slip on some parts), cached;
    and the pairs swapped."""
    t = read_dlc(base / "detections" / f"{cam}.csv")
    pairs = side_pairs(t.parts)[(1 if case == "but_first" else 0) :]
    perm = list(range(len(t.parts)))
    for i, j in pairs:
        perm[i], perm[j] = j, i
    spoil_scene(base, out, {cam: lambda t: (t.xy[:, perm], t.likelihood[:, perm])})
    return out, sorted([t.parts[i], t.parts[j]] for i, j in pairs)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_args(ap, "sides", "2,3,4")
    ap.add_argument("--parts", type=int, default=8, choices=PART_SETS, help="the part set")
    ap.add_argument("--cases", default="all,but_first", help=f"which pairs: {CASES}")
    ap.add_argument("--split", default="test", choices=tuple(SPLITS), help="the segment")
    ap.add_argument("--no-peer", action="store_true", help="without aniposelib")
    args = start(ap, argv)
    cameras, seeds = input_settings(ap, args)
    cases = [c for c in args.cases.split(",") if c.strip()]
    if not cases or set(cases) - set(CASES):
        ap.error(f"--cases must be some of {list(CASES)}, got {args.cases!r}")
    motion, work, threads = input_run(args)
    start_frame = SPLITS[args.split]
    rows: dict[str, dict] = {}
    for ncams in cameras:
        for seed in seeds:
            key = scene_key(args.split, start_frame, args.frames, ncams, args.parts, seed)
            base = film_scene(work / "scenes" / key, motion, start_frame, args.frames, ncams,
                              args.parts, seed)  # fmt: skip
            ref, _ = checked_row(base, work / "runs" / key / "as_labelled", [threads])
            peer_ref = None if args.no_peer else peer_row(base, args.parts)["rmse_all"]
            for case, cam in itertools.product(
                cases, [c.name for c in load_calibration(base / "calibration.toml")]
            ):
                tag = f"{key}_{cam}_swapped_{case}"
                scene, want = swapped_scene(base, work / "swapped" / tag, cam, case)
                blind, blind_check = checked_row(scene, work / "runs" / tag / "unchecked",
                                                 [threads, "input.side_check=false"])  # fmt: skip
                fixed, check = checked_row(scene, work / "runs" / tag / "checked", [threads])
                found = (check.get("sides") or {}).get("swapped") or {}
                peer = None if args.no_peer else peer_row(scene, args.parts)["rmse_all"]
                label = f"{ncams} cams s{seed} {cam} {case}"
                rows[label] = {
                    "cameras": ncams, "seed": seed, "swapped": cam, "case": case,
                    "want": want,
                    "labelled_all": ref["rmse_all"], "labelled_seen": ref["rmse_seen2"],
                    "unchecked_all": blind["rmse_all"], "unchecked_seen": blind["rmse_seen2"],
                    "checked_all": fixed["rmse_all"], "checked_seen": fixed["rmse_seen2"],
                    "found": {n: sorted(v["pairs"]) for n, v in found.items()},
                    "decided_by": sorted({d for v in found.values() for d in v["decided_by"]}),
                    "excluded_unchecked": sorted(blind_check.get("excluded") or {}),
                    "excluded_checked": sorted(check.get("excluded") or {}),
                    "peer_swapped_all": peer, "peer_labelled_all": peer_ref,
                }  # fmt: skip
                log.info("%s: %s", tag, rows[label])
    cols = [("labelled_all", "as labelled"), ("unchecked_all", "unchecked"),
            ("checked_all", "checked"), ("peer_swapped_all", "anip. swap"),
            ("peer_labelled_all", "anip. lab."), ("labelled_seen", "seen lab."),
            ("unchecked_seen", "seen unch."), ("checked_seen", "seen chk.")]  # fmt: skip
    print(f"\nRMSE all / seen by >= 2 cameras (mm), {args.split} segment, {args.parts} parts, "
          "one camera's left and right swapped:")  # fmt: skip
    print_table(rows, cols, 11)
    print("\nfound (decided by); excluded unchecked / checked:")
    for label, r in rows.items():
        print(f"  {label}: {r['found'] or 'none'} ({', '.join(r['decided_by']) or '-'}); "
              f"{r['excluded_unchecked']} / {r['excluded_checked']}")  # fmt: skip
    ratio = {k: float(np.exp(np.mean([np.log(r[f"{k}_all"] / r["labelled_all"])
                                      for r in rows.values()])))
             for k in ("unchecked", "checked")}  # fmt: skip
    checks = {
        "found_the_swapped_pairs": sum(
            r["found"] == {r["swapped"]: r["want"]} for r in rows.values()
        ),
        "runs": len(rows),
        "checked_within_2pct_of_labelled": sum(
            r["checked_all"] <= SAME * r["labelled_all"] for r in rows.values()
        ),
        "geomean_over_labelled": ratio,
    }
    print(f"\nchecks: {checks}")
    return emit({"split": args.split, "seeds": seeds, "parts": args.parts, "rows": rows,
                 "checks": checks}, args.out)  # fmt: skip


if __name__ == "__main__":
    main()
