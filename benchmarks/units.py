"""A calibration in centimetres or metres: the real-motion scenes tracked with their
calibration.toml rewritten in another length unit, read as mm (what adjust-track did before
``[metadata] units``, and does with ``units = "mm"``) and read with the unit declared.

An anipose calibration is in the unit of its board's square length (mm, cm or m). mousetrack
works in mm: every length setting (the track constraint's 0.2 mm, the deformation and ray
priors, gates) is in mm. The scenes are `real_motion.py`'s 8-part validation scenes (frames
1200-2199, `--cameras`, `--seeds`); each is copied with its camera translations divided by 10
(cm) or 1000 (m) and its truth likewise, tracked by ``adjust-track`` (its defaults, and
``deformation=rigid``), and scored in mm against the truth:

- ``mm``: the file as filmed (the reference);
- ``cm as mm`` / ``m as mm``: the file in cm / m with ``units = "mm"`` (lengths read as they
  are: the old behaviour; a file in metres that declares nothing is now refused);
- ``cm`` / ``m``: the unit declared (``units = "cm"`` / ``"m"``): converted to mm on reading.

Target: a declared unit gives the mm file's RMSE (within 2%: the translations' float rounding,
divided and multiplied back, moved a 2-camera run by 0.9%, stop 56).

    .venv/bin/python benchmarks/units.py [--cameras 2,3] [--frames 1000] [--seeds 0] \\
        [--methods default,rigid] [--work DIR] [--out FILE]
"""

from __future__ import annotations

import argparse
import logging
import re
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import emit, print_table, start, subset  # noqa: E402
from real_motion import (  # noqa: E402
    DATA,
    SPLITS,
    Motion,
    film_scene,
    input_args,
    input_settings,
    scene_key,
    track_overrides,
    track_row,
)

log = logging.getLogger("benchmarks.units")

#: (row name, mm per unit of the file, the unit it declares)
VARIANTS = (
    ("mm", 1.0, None),
    ("cm as mm", 10.0, "mm"),
    ("cm", 10.0, "cm"),
    ("m as mm", 1000.0, "mm"),
    ("m", 1000.0, "m"),
)


def rewrite(scene: Path, out: Path, mm_per_unit: float, unit: str | None) -> Path:
    """A copy of `scene` whose calibration's translations are in a unit of `mm_per_unit` mm,
    declaring `unit` under ``[metadata]`` (None: nothing); its truth stays in mm."""
    if (out / "truth.npz").exists():
        return out
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(scene, out, ignore=shutil.ignore_patterns("truth.npz"))
    text = (scene / "calibration.toml").read_text()
    text = re.sub(
        r"translation = \[([^\]]*)\]",
        lambda m: (
            "translation = "
            + repr([float(v) / mm_per_unit for v in m.group(1).split(",") if v.strip()])
        ),
        text,
    )
    if unit is not None:
        text = text.replace("[metadata]\n", f'[metadata]\nunits = "{unit}"\n', 1)
        if f'units = "{unit}"' not in text:
            text += f'\n[metadata]\nunits = "{unit}"\n'
    (out / "calibration.toml").write_text(text)
    shutil.copy2(scene / "truth.npz", out / "truth.npz")  # last: the cache's mark
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    input_args(ap, "units", "2,3")
    ap.add_argument("--methods", default="default,rigid", help="default, rigid")
    args = start(ap, argv)
    cameras, seeds = input_settings(ap, args)
    methods = subset(ap, args.methods, ("default", "rigid"), "--methods")
    motion = Motion(DATA)
    work = Path(args.work) / motion.tag
    start_frame = SPLITS["val"]
    rows: list[dict] = []
    for cams in cameras:
        for seed in seeds:
            key = scene_key("val", start_frame, args.frames, cams, 8, seed)
            base = film_scene(work / "scenes" / key, motion, start_frame, args.frames, cams, 8,
                              seed)  # fmt: skip
            for name, mm_per_unit, unit in VARIANTS:
                scene = rewrite(base, work / "units" / f"{key}_{name.replace(' ', '_')}",
                                mm_per_unit, unit)  # fmt: skip
                truth = np.load(scene / "truth.npz")
                parts = [str(p) for p in truth["parts"]]
                # read as mm, the tracks are in the file's unit; declared, in mm
                misread = unit == "mm" and mm_per_unit != 1.0
                scale = mm_per_unit if misread else 1.0
                for m in methods:
                    out = work / "runs" / scene.name / m
                    ov = [f"threads={args.threads}", *track_overrides(m, 0.0)]
                    r = track_row(scene, out, ov, truth["points"] / scale, truth["nviews"], parts)
                    rows.append({
                        "cameras": cams, "seed": seed, "variant": name, "method": m,
                        "rmse_all": r["rmse_all"] * scale,
                        "rmse_occluded": r["rmse_occluded"] * scale,
                        "calib_occluded": r.get("calib_occluded"),
                    })  # fmt: skip
                    log.info("%s %s %s: RMSE all %.3f mm", key, name, m, rows[-1]["rmse_all"])
    table: dict[str, dict] = {}
    for cams in cameras:
        for m in methods:
            sel = [r for r in rows if r["cameras"] == cams and r["method"] == m]
            ref = np.mean([r["rmse_all"] for r in sel if r["variant"] == "mm"])
            line = {}
            for name, _, _ in VARIANTS:
                v = float(np.mean([r["rmse_all"] for r in sel if r["variant"] == name]))
                line[name] = v
                line[f"{name} / mm"] = v / ref
            table[f"{cams} cameras, {m}"] = line
    print(f"\nRMSE all (mm) by the calibration's unit and how it is read (seeds {seeds}):")
    cols = [(n, n) for n, _, _ in VARIANTS]
    print_table(table, cols, 12)
    print("\nratio to the mm file's:")
    print_table(table, [(f"{n} / mm", n) for n, _, _ in VARIANTS], 12)
    declared = [v for line in table.values() for k, v in line.items()
                if k in ("cm / mm", "m / mm")]  # fmt: skip
    checks = {"declared_within_2pct": bool(all(abs(v - 1) < 0.02 for v in declared))}
    print(f"\nchecks: {checks}")
    return emit({"seeds": seeds, "rows": rows, "table": table, "checks": checks}, args.out)


if __name__ == "__main__":
    main()
