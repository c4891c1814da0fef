"""Where a detector seed's change of ``adjust-track``'s error comes from (issue 45).

`real_motion.py`'s stability table re-runs the defaults on another detector seed of the same
frames; this breaks the difference down, on the scenes and runs `real_motion.py` keeps under
``--work`` (missing ones are filmed and tracked here the same way: ``adjust-track`` with its
defaults, aniposelib with anipose's settings). Per seed of ``--seeds`` (the first is the base):

- RMSE all of ``default`` and aniposelib, the body scale, the parts interp smooths along rays;
- the mean squared error (MSE, mm^2, over all part-frames) split per part and per view class
  (part-frames seen by >= 2 cameras / one / none, truth.npz's ``nviews``), and the change
  from the base seed in each cell, aniposelib's beside it;
- the stretches that carry the change: per part, 25- and 150-frame blocks whose MSE share
  changed most from the base seed (aniposelib's change in the same block beside it);
- pose excursions: frames whose tracked body orientation is more than 0.2 rad from the
  truth's (the rotation of the tracked mean shape Kabsch-fitted to the true points), in runs,
  with their share of the MSE;
- single views: on part-frames whose point rests on one view (accepted.npz), the MSE along
  that camera's ray (depth, which one view cannot see) and across it;
- the detector's mistakes: part-frames whose point rests on a wrong view (a left/right swap
  or a far outlier, truth.npz's ``outlier``) and part-frames whose correct views were all
  rejected, each with its MSE.

    .venv/bin/python benchmarks/seed_stability.py [--split val] [--cameras 3] \\
        [--seeds 0,100,1,2] [--frames 1000] [--threads 1] [--work DIR] [--out FILE]

Prints the tables; the last line is JSON, also written to runs/benchmarks/seed_stability.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))

import real_motion as rm  # noqa: E402
from common import emit, start  # noqa: E402

from adjust.io import load_calibration, read_points3d  # noqa: E402
from adjust.plot import runs_of  # noqa: E402
from deformnet.so3 import kabsch  # noqa: E402
from deformnet.tables import read_points3d_table  # noqa: E402

log = logging.getLogger("benchmarks.seed_stability")

ROOT = Path(__file__).resolve().parent.parent
POSE_RAD = 0.2  # an orientation this far from the truth's: a pose excursion
BLOCKS = (25, 150)  # frames per block of the stretch tables
TOP_BLOCKS = 6
VIEW_CLASSES = {"ge2": (2, 10**9), "one": (1, 1), "none": (0, 0)}


# --- the pieces (numpy; T frames, K parts, C cameras) ---------------------------------------


def mse_split(e2: np.ndarray, nviews: np.ndarray) -> dict[str, np.ndarray]:
    """e2 (T, K) squared errors, nviews (T, K): per view class the (K,) sums of e2 over its
    part-frames divided by T * K (so the classes and parts add up to the MSE)."""
    n = e2.size
    return {
        c: np.where((nviews >= lo) & (nviews <= hi), e2, 0.0).sum(0) / n
        for c, (lo, hi) in VIEW_CLASSES.items()
    }


def pose_error(rotvec: np.ndarray, trans: np.ndarray, est: np.ndarray, truth: np.ndarray):
    """(T,) angle (rad) between the tracked orientations (rotation vectors (T, 3), translations
    (T, 3), points est (T, K, 3)) and the truth's: the tracked points' median body-frame shape
    Kabsch-fitted to the true points (T, K, 3) of each frame."""
    R = Rotation.from_rotvec(rotvec).as_matrix()
    body = np.einsum("tji,tkj->tki", R, est - trans[:, None])
    Rt, _ = kabsch(torch.as_tensor(truth), torch.as_tensor(np.median(body, 0)))
    Rt = Rt.numpy()
    return Rotation.from_matrix(np.einsum("tji,tjk->tik", Rt, R)).magnitude()


def along_across(err: np.ndarray, points: np.ndarray, centers: np.ndarray, view: np.ndarray):
    """err (N, 3) errors of points (N, 3) each seen through one camera, view (N,) its index
    into centers (C, 3): the squared error along that camera's ray and across it, (N,) each."""
    u = points - centers[view]
    u = u / np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-9)
    a = (err * u).sum(-1)
    return a * a, (err * err).sum(-1) - a * a


# --- one seed -------------------------------------------------------------------------------


def seed_facts(scene: Path, run: Path, ani: np.ndarray) -> dict:
    """Everything of one seed's run against its truth (the arrays too, under ``_``)."""
    tr = np.load(scene / "truth.npz")
    parts = [str(p) for p in tr["parts"]]
    X, nv = tr["points"], tr["nviews"]
    pts = read_points3d(run / "points3d.csv")
    est = pts["points"][:, [list(map(str, pts["parts"])).index(p) for p in parts]]
    used = np.load(run / "accepted.npz")["accepted"]  # (T, K, C) the views the points rest on
    e2 = ((est - X) ** 2).sum(-1)
    a2 = ((ani - X) ** 2).sum(-1)
    n = e2.size
    summ = json.loads((run / "summary.json").read_text())
    df = read_points3d_table(run / "points3d.csv")
    tvec = df[["pose_tx", "pose_ty", "pose_tz"]].to_numpy(float)
    ang = pose_error(rm.read_poses(run / "points3d.csv"), tvec, est, X)
    far = ang > POSE_RAD
    cams = load_calibration(scene / "calibration.toml")
    centers = np.stack([c.center for c in cams])
    one = used.sum(-1) == 1
    al, ac = along_across((est - X)[one], est[one], centers, np.argmax(used, -1)[one])
    acc = tr["likelihood"] >= 0.5
    wrong = tr["outlier"]
    correct = acc & tr["visible"] & ~wrong
    on_wrong = (used & wrong).any(-1)
    lost = correct.any(-1) & ~(used & correct).any(-1)
    return {
        "rmse_default": float(np.sqrt(e2.mean())),
        "rmse_aniposelib": float(np.sqrt(a2.mean())),
        "body_scale": (summ.get("body", {}).get("frame") or {}).get("scale"),
        "ray_parts": (summ.get("deformation") or {}).get("ray_parts"),
        "mse": float(e2.mean()),
        "mse_part_views": {c: v.tolist() for c, v in mse_split(e2, nv).items()},
        "pose_excursion_frames": int(far.sum()),
        "pose_excursion_mse": float(e2[far].sum() / n),
        "pose_excursion_runs": [
            [a, b, round(float(ang[a : b + 1].max()), 3), round(float(e2[a : b + 1].sum() / n), 3)]
            for a, b in ((a, stop - 1) for a, stop in runs_of(far))
        ],
        "single_view_part_frames": int(one.sum()),
        "single_view_mse_along_ray": float(al.sum() / n),
        "single_view_mse_across_ray": float(ac.sum() / n),
        "on_wrong_view_part_frames": int(on_wrong.sum()),
        "on_wrong_view_mse": float(e2[on_wrong].sum() / n),
        "correct_views_lost_part_frames": int(lost.sum()),
        "correct_views_lost_mse": float(e2[lost].sum() / n),
        "_": {"e2": e2, "a2": a2, "nviews": nv, "parts": parts},
    }


def stretches(base: dict, other: dict, size: int, top: int = TOP_BLOCKS) -> list[dict]:
    """The `top` (part, `size`-frame block) cells whose MSE share changed most from `base` to
    `other` (`seed_facts`' arrays), aniposelib's change beside each."""
    e0, a0, e1, a1 = base["_"]["e2"], base["_"]["a2"], other["_"]["e2"], other["_"]["a2"]
    T, K = e0.shape
    n = e0.size
    nb = -(-T // size)

    def blocks(x):
        pad = np.zeros((nb * size, K))
        pad[:T] = x
        return pad.reshape(nb, size, K).sum(1) / n

    d, da = blocks(e1) - blocks(e0), blocks(a1) - blocks(a0)
    order = np.argsort(-np.abs(d), axis=None)[:top]
    out = []
    for b, k in zip(*np.unravel_index(order, d.shape)):
        sl = slice(b * size, min((b + 1) * size, T))
        out.append(
            {
                "part": base["_"]["parts"][k],
                "frames": [int(sl.start), int(sl.stop - 1)],
                "change": float(d[b, k]),
                "aniposelib_change": float(da[b, k]),
                "views_base": float(base["_"]["nviews"][sl, k].mean()),
                "views_other": float(other["_"]["nviews"][sl, k].mean()),
            }
        )
    return out


# --- main -----------------------------------------------------------------------------------


def ensure_runs(args, motion: rm.Motion, start_frame: int, work: Path, seed: int):
    """The scene, the default run folder and aniposelib's points of one seed (made if missing)."""
    key = rm.scene_key(args.split, start_frame, args.frames, args.cameras, 8, seed)
    scene = rm.film_scene(
        work / "scenes" / key, motion, start_frame, args.frames, args.cameras, 8, seed
    )
    run = work / "runs" / key / "default"
    if not (run / "accepted.npz").exists():
        tr = np.load(scene / "truth.npz")
        threads = [f"threads={args.threads}"] if args.threads else ["threads=null"]
        rm.track_row(scene, run, threads, tr["points"], tr["nviews"], [str(p) for p in tr["parts"]])
    ani, _, _ = rm.run_aniposelib(scene, 8, Path(args.data).parent / "skeleton.csv")
    return scene, run, ani


def print_tables(res: dict, seeds: list[int]) -> None:
    base = str(seeds[0])
    print(f"\n{res['scene']}: per seed (RMSE mm, MSE mm^2 over all part-frames)")
    head = ("seed", "default", "anipose", "scale", "MSE", "excursion", "1-view along",
            "1-view across", "on wrong view", "views lost")  # fmt: skip
    print("".join(f"{h:>14}" for h in head))
    for s in seeds:
        r = res["seeds"][str(s)]
        exc = f"{r['pose_excursion_mse']:.2f} ({r['pose_excursion_frames']})"
        wrong = f"{r['on_wrong_view_mse']:.2f} ({r['on_wrong_view_part_frames']})"
        lost = f"{r['correct_views_lost_mse']:.2f} ({r['correct_views_lost_part_frames']})"
        one = (r["single_view_mse_along_ray"], r["single_view_mse_across_ray"])
        cells = (s, r["rmse_default"], r["rmse_aniposelib"], r["body_scale"], r["mse"], exc,
                 *one, wrong, lost)  # fmt: skip
        print("".join(f"{c:>14.3f}" if isinstance(c, float) else f"{c!s:>14}" for c in cells))
    for s in seeds[1:]:
        d = res["changes"][str(s)]
        print(
            f"\nseed {s} - seed {base}: MSE {d['mse']:+.2f} (aniposelib "
            f"{d['aniposelib_mse']:+.1f}); per part and view class (>=2 / one / none):"
        )
        for p, row in d["part_views"].items():
            print(f"  {p:<18}" + "".join(f"{row[c]:+8.2f}" for c in VIEW_CLASSES))
        for size, rows in d["stretches"].items():
            print(f"  the {size}-frame stretches that changed most (part, frames, MSE change, "
                  "aniposelib's, mean views base -> this seed):")  # fmt: skip
            for b in rows:
                a, z = b["frames"]
                print(f"    {b['part']:<18}{a:5d}-{z:<5d}{b['change']:+8.2f}"
                      f"{b['aniposelib_change']:+10.1f}   "
                      f"{b['views_base']:.2f} -> {b['views_other']:.2f}")  # fmt: skip
        runs = res["seeds"][str(s)]["pose_excursion_runs"]
        print(f"  pose excursions (first, last, max rad, MSE): {runs}")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", choices=sorted(rm.SPLITS), default="val")
    ap.add_argument("--cameras", type=int, default=3)
    ap.add_argument("--seeds", default="0,100,1,2", help="detector seeds; the first is the base")
    ap.add_argument("--frames", type=int, default=rm.SEGMENT_FRAMES)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--data", default=str(rm.DATA))
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "real_motion"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "seed_stability.json"))
    args = start(ap, argv)
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    if len(seeds) < 2:
        ap.error("--seeds: at least two (the first is the base)")
    motion = rm.Motion(Path(args.data))
    work = Path(args.work) / motion.tag
    start_frame = rm.SPLITS[args.split]
    facts = {}
    for s in seeds:
        scene, run, ani = ensure_runs(args, motion, start_frame, work, s)
        tr_parts = [str(p) for p in np.load(scene / "truth.npz")["parts"]]
        facts[s] = seed_facts(scene, run, ani)
        facts[s]["_"]["parts"] = tr_parts
    base = facts[seeds[0]]
    parts = base["_"]["parts"]
    changes = {}
    for s in seeds[1:]:
        o = facts[s]
        split0, split1 = (mse_split(f["_"]["e2"], f["_"]["nviews"]) for f in (base, o))
        changes[str(s)] = {
            "mse": o["mse"] - base["mse"],
            "aniposelib_mse": float(o["_"]["a2"].mean() - base["_"]["a2"].mean()),
            "part_views": {
                p: {c: float(split1[c][k] - split0[c][k]) for c in VIEW_CLASSES}
                for k, p in enumerate(parts)
            },
            "stretches": {str(n): stretches(base, o, n) for n in BLOCKS},
        }
    res = {
        "scene": rm.scene_key(args.split, start_frame, args.frames, args.cameras, 8, seeds[0]),
        "split": args.split,
        "cameras": args.cameras,
        "seeds": {str(s): {k: v for k, v in f.items() if k != "_"} for s, f in facts.items()},
        "changes": changes,
        "parts": parts,
    }
    print_tables(res, seeds)
    return emit(res, args.out)


if __name__ == "__main__":
    main()
