"""Domain-gap benchmark: the sim-to-real gap reproduced in simulation, with the peer side by side.

A `sim=mouse_b` scene (the second simulated mouse: 1.2x Table 1, 100 fps, trot, spine bending,
free head, rearing; not the mouse any net is trained on) filmed by the default rig and detector,
with a seed nothing trains on. Against its truth, for every method: completeness, RMSE all /
seen by >= 2 cameras / occluded (< 2) / fraction within 5 mm (missing = miss), and seconds:

- ``dlt``: `adjust-triangulate` (linear, >= 2 views);
- ``robust_tri``: robust triangulation (`adjust.triangulate.triangulate(robust=True)`);
- ``aniposelib``: aniposelib's `triangulate_optim` with anipose's settings and length
  constraints (head triangle strong, trunk weak), run in its own environment (`make bench-env`);
- ``dlt_kalman``, ``aniposelib_kalman``: the Kalman-smoother peer (`peers/kalman.py`, pykalman,
  the `bench` extra): each part of the DLT / aniposelib points smoothed and its gaps filled by a
  constant-velocity Kalman filter + RTS smoother, noise covariances fitted by EM
  (``--no-kalman`` skips them);
- ``dlt_disk``, ``dlt_disk_sim``: the DISK-style imputation peer (`peers/disk.py`: a
  transformer that fills the gaps of the DLT points from the other keypoints and frames, no
  body model, no cameras), trained for ``--disk-seconds`` on this scene's own DLT points
  (``dlt_disk``: self-supervised, hidden present points as targets, as ``self`` learns from
  the scene) or, DISK's own protocol, on complete data: 4 x 3000 frames of the default
  simulator's mouse at the scene's frame rate (``dlt_disk_sim``, as ``default``'s net was
  trained) (``--no-disk`` skips them);
- ``rigid``: `adjust-track deformation=rigid` (Table 1 scaled to the data, stochastic model
  estimated from the data);
- ``interp``: `adjust-track` (its default, `deformation=interp`);
- ``net_sim``: `adjust-track deformation=CKPT` with a net trained on the default simulator only
  (``--checkpoint``, or trained here for ``--train-minutes``; ``--no-net`` skips it);
- ``default``: `adjust-track deformation=default` (the shipped net, pretrained on the default
  simulator only, not adapted);
- ``self``: `adjust-track deformation=self`: the shipped net fine-tuned on this scene's own
  detections (self-supervised tokens, no truth) for ``--adapt-minutes``, then used;
- ``sessions``: `deformnet-train data=sessions pretrained=default` on three *other* mouse_b
  sessions (seeds + 1..3, tracked with adjust-track), ``--adapt-minutes`` of training, then
  `adjust-track deformation=CKPT` on this scene (``--no-self`` skips the last three,
  ``--no-sessions`` this one).

Also printed: the scene's rigid floor (generalized Procrustes against the truth), and per
adjust-track variant the uncertainty calibration ratios rms error / rms ``{part}_sigma`` on seen
and occluded part-frames. Targets: interp beats aniposelib on every column; seen >= 2 RMSE of
every adjust-track variant <= robust triangulation's; calibration ratios within 0.8-1.25;
``self`` beats aniposelib on every column with occluded RMSE <= 0.6x rigid's, <= 0.7x
aniposelib's and below interp's. ``self``'s fine-tuning time is reported apart (``adapt_s``).

    .venv/bin/python benchmarks/domain_gap.py [--frames 1500] [--seed 92000] [--checkpoint CKPT]
        [--train-minutes 3] [--adapt-minutes 3] [--no-net] [--no-self] [--no-anipose]
        [--no-kalman] [--no-disk] [--disk-seconds 180] [--no-sessions]
        [-o OVERRIDE ...]  (adjust-track overrides for every variant, e.g. -o body.shape=table)

Last line JSON, also written to runs/benchmarks/domain_gap.json.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import print_table, start  # noqa: E402
from peers.anipose import (  # noqa: E402
    MOUSE_CONSTRAINTS,
    MOUSE_CONSTRAINTS_WEAK,
    constraint_indices,
    run_anipose,
)
from peers.anipose import wanted as anipose_wanted  # noqa: E402
from peers.disk import fit_disk, impute  # noqa: E402
from peers.kalman import kalman_smooth  # noqa: E402
from peers.kalman import wanted as kalman_wanted  # noqa: E402
from tracking import (  # noqa: E402
    compose,
    emit,
    ensure_scene,
    run_dlt,
    run_track,
    train_net,
    view_fractions,
)

from adjust.io import read_points3d  # noqa: E402
from adjust.metrics import point_errors  # noqa: E402
from deformnet.paths import CONF_DIR  # noqa: E402
from deformnet.shape import rigid_floor  # noqa: E402

log = logging.getLogger("benchmarks.domain_gap")
ROOT = CONF_DIR.parent
SCENE_SEED = 92_000  # held out: no training run uses it


def make_scene(out: Path, frames: int, seed: int) -> Path:
    """The mouse_b scene folder `out` (simulated first unless it is there)."""
    return ensure_scene(out, frames, seed, ["sim=mouse_b"])


def evaluate(est: np.ndarray, truth: np.ndarray, nviews: np.ndarray) -> dict:
    m = point_errors(est, truth, nviews)
    return {
        "completeness": m["completeness"],
        "rmse_all": m["rmse_all"],
        "rmse_seen2": m["rmse_seen"],
        "rmse_occluded": m["rmse_occluded"],
        "within5": m["within5_strict_all"],
    }


def calibration(out: Path, est: np.ndarray, truth: np.ndarray, nviews: np.ndarray, parts) -> dict:
    """rms error / rms sigma on seen (>= 2 cameras) and occluded part-frames."""
    extra = read_points3d(out / "points3d.csv")["extra"]  # the sigmas: in the sidecar
    sig = np.stack([np.asarray(extra[f"{p}_sigma"], float) for p in parts], 1)
    err = np.linalg.norm(est - truth, axis=-1)
    res = {}
    for name, m in (("seen", nviews >= 2), ("occluded", nviews < 2)):
        res[f"calib_{name}"] = float(np.sqrt(np.mean(err[m] ** 2)) / np.sqrt(np.mean(sig[m] ** 2)))
    return res


def beats_every_column(a: dict, b: dict) -> bool:
    """a is better than b in RMSE all / seen / occluded, within 5 mm and completeness."""
    return bool(
        a["rmse_all"] < b["rmse_all"]
        and a["rmse_seen2"] < b["rmse_seen2"]
        and a["rmse_occluded"] < b["rmse_occluded"]
        and a["within5"] > b["within5"]
        and a["completeness"] >= b["completeness"]
    )


def _hms(minutes: float) -> str:
    secs = int(round(60 * minutes))
    return f"00:{secs // 3600:02d}:{secs % 3600 // 60:02d}:{secs % 60:02d}"


def train_on_sessions(work: Path, frames: int, seed: int, budget: str) -> tuple[str, dict]:
    """``deformnet-train data=sessions pretrained=default`` on three other mouse_b sessions
    (seeds seed+1..seed+3, tracked by adjust-track's default): split by session."""
    from deformnet.train import run

    folders = []
    for i in (1, 2, 3):
        sc = make_scene(work / f"scene_mouse_b_{frames}_{seed + i}", frames, seed + i)
        tr = work / f"sessions_track_{seed + i}"
        if not (tr / "tokens.npz").exists():
            run_track(sc, tr, ["threads=1"])
        folders.append(str(tr))
    out = work / "sessions_net"
    t0 = time.perf_counter()
    res = run(
        compose(
            "train",
            [
                "data=sessions",
                f"data.sessions=[{','.join(folders)}]",
                "data.val_fraction=0.3",  # ceil(0.3 * 3) = 1 of the 3 sessions validates
                "pretrained=default",
                "optim.lr=1e-3",
                "optim.warmup_steps=20",
                "data.steps_per_epoch=50",
                f"trainer.max_time={budget}",
                "logger=none",
                "progress_bar=none",
                f"output.dir={out}",
            ],
        )
    )
    ckpt = res.get("best_checkpoint") or res.get("last_checkpoint")
    facts = {
        "seconds": round(time.perf_counter() - t0, 1),
        "data": res.get("data"),
        "val_rmse_mm": res["metrics"].get("best/val_rmse_mm"),
        "val_rmse_mm_linear": res["metrics"].get("val/rmse_mm_linear"),
        "val_rmse_mm_rigid": res["metrics"].get("val/rmse_mm_rigid"),
    }
    return str(ckpt), facts


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=SCENE_SEED)
    ap.add_argument("--checkpoint", default=None, help="simulator-trained net (else train one)")
    ap.add_argument("--train-minutes", type=float, default=3.0)
    ap.add_argument("--no-net", action="store_true")
    ap.add_argument("--no-anipose", action="store_true")
    ap.add_argument("--no-kalman", action="store_true", help="skip the Kalman-smoother peer")
    ap.add_argument("--no-disk", action="store_true", help="skip the DISK-style imputation peer")
    ap.add_argument("--disk-seconds", type=float, default=180.0, help="its training, per variant")
    ap.add_argument("--no-self", action="store_true")
    ap.add_argument("--adapt-minutes", type=float, default=3.0)
    ap.add_argument("--no-sessions", action="store_true", help="skip the sessions variant")
    ap.add_argument(
        "-o", "--override", action="append", default=[], help="adjust-track override (repeat)"
    )
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "domain_gap"))
    ap.add_argument("--out", default=str(ROOT / "runs" / "benchmarks" / "domain_gap.json"))
    ap.set_defaults(threads=1)  # one torch thread (`start`)
    args = start(ap, argv)
    work = Path(args.work)
    scene = make_scene(work / f"scene_mouse_b_{args.frames}_{args.seed}", args.frames, args.seed)
    tr = np.load(scene / "truth.npz")
    truth, nviews = tr["points"], tr["nviews"]
    parts = [str(p) for p in tr["parts"]]
    floor = rigid_floor(truth, parts=parts)
    fractions = view_fractions(nviews)
    results: dict[str, dict] = {}
    extra: dict = {"rigid_floor": floor.as_dict()}

    est, secs = run_dlt(scene, work / "dlt")
    results["dlt"] = {**evaluate(est, truth, nviews), "seconds": round(secs, 2)}
    smooth_on = {"dlt": (est, secs)}  # the gap-filling peers' inputs (and their seconds)

    from adjust.camera import CameraTensors
    from adjust.io import load_scene
    from adjust.triangulate import triangulate
    from deformnet.body import default_mouse

    cameras, det = load_scene(scene / "calibration.toml", scene / "detections", default_mouse())
    cams = CameraTensors.from_cameras(cameras, dtype=torch.float64)
    t0 = time.perf_counter()
    with torch.no_grad():
        rt = triangulate(torch.as_tensor(det.xy), torch.as_tensor(det.weight()), cams, robust=True)
    secs = time.perf_counter() - t0
    results["robust_tri"] = {
        **evaluate(rt.points.numpy(), truth, nviews),
        "seconds": round(secs, 2),
    }

    if anipose_wanted(args.no_anipose):
        pts, secs = run_anipose(
            scene / "calibration.toml",
            det.cameras,
            det.xy,
            det.likelihood,
            constraint_indices(parts, MOUSE_CONSTRAINTS),
            constraint_indices(parts, MOUSE_CONSTRAINTS_WEAK),
        )
        results["aniposelib"] = {**evaluate(pts, truth, nviews), "seconds": round(secs, 2)}
        smooth_on["aniposelib"] = (pts, secs)
    if kalman_wanted(args.no_kalman):
        for base, (pts, secs) in smooth_on.items():
            sm, ksecs = kalman_smooth(pts)
            results[f"{base}_kalman"] = {
                **evaluate(sm, truth, nviews),
                "seconds": round(secs + ksecs, 2),
            }

    if not args.no_disk:
        from deformnet.sim import simulate

        dlt_pts = smooth_on["dlt"][0]
        fps = float(tr["fps"])
        sim_cfg = compose("simulate", [f"sim.fps={fps:g}"])
        complete = np.stack([simulate(sim_cfg, num_frames=3000, seed=91_000 + i).deformed
                             for i in range(4)])  # fmt: skip
        for name, data in (("dlt_disk", dlt_pts[None]), ("dlt_disk_sim", complete)):
            model, facts = fit_disk(data, seconds=args.disk_seconds)
            t0 = time.perf_counter()
            filled = impute(model, dlt_pts)
            results[name] = {
                **evaluate(filled, truth, nviews),
                "seconds": round(time.perf_counter() - t0 + smooth_on["dlt"][1], 2),
                "adapt_s": facts["seconds"],
            }
            extra[f"{name}_training"] = facts

    variants = {"rigid": ["deformation=rigid"], "interp": []}
    if not args.no_net:
        ckpt = args.checkpoint
        if ckpt is None:
            mins = args.train_minutes
            ckpt, tsecs, _ = train_net(
                work / "net_sim",
                [f"trainer.max_time=00:00:{int(mins):02d}:{int(60 * (mins % 1)):02d}"],
            )
            extra["net_training_s"] = round(tsecs, 1)
        extra["checkpoint"] = str(ckpt)
        variants["net_sim"] = [f"deformation={ckpt}"]
    budget = _hms(args.adapt_minutes)
    if not args.no_self:
        variants["default"] = ["deformation=default"]
        variants["self"] = ["deformation=self", f"adapt.max_time={budget}"]
        if not args.no_sessions:
            ckpt, facts = train_on_sessions(work, args.frames, args.seed, budget)
            extra["sessions_training"] = facts
            variants["sessions"] = [f"deformation={ckpt}"]
    for name, ov in variants.items():
        est, secs, summ = run_track(scene, work / name, ["threads=1", *args.override, *ov])
        results[name] = {
            **evaluate(est, truth, nviews),
            "seconds": round(secs, 2),
            **calibration(work / name, est, truth, nviews, parts),
        }
        t = summ.get("time_s", {})
        if "adapt_s" in t:
            results[name]["adapt_s"] = t["adapt_s"]
            results[name]["seconds"] = round(secs - t["adapt_s"], 2)  # the tracking alone
        if summ["deformation"].get("adapt"):
            extra[f"{name}_adapt"] = summ["deformation"]["adapt"]
        if name == "interp":
            extra["stochastic"] = summ.get("stochastic")
            extra["body"] = {k: summ["body"].get(k) for k in ("scale", "rigid_rms_mm")}

    cols = [
        ("completeness", "complete"),
        ("rmse_all", "rmse all"),
        ("rmse_seen2", "rmse >=2"),
        ("rmse_occluded", "rmse occl"),
        ("within5", "<=5mm"),
        ("seconds", "seconds"),
        ("adapt_s", "adapt s"),
        ("calib_seen", "calib seen"),
        ("calib_occluded", "calib occl"),
    ]
    print(f"\nmouse_b scene {scene}: {args.frames} frames, seed {args.seed}")
    print(
        f"part-frames seen by >=2 cameras {fractions['seen_ge2']:.3f}, by 1 "
        f"{fractions['seen_1']:.3f}, by none {fractions['seen_0']:.3f}; rigid floor "
        f"{floor.rms:.2f} mm rms ("
        + ", ".join(f"{p} {v:.1f}" for p, v in zip(parts, floor.per_part))
        + ")"
    )
    print_table(results, cols, 12)
    checks: dict = {}
    if "aniposelib" in results:
        a, b = results["interp"], results["aniposelib"]
        checks["interp_beats_aniposelib_every_column"] = beats_every_column(a, b)
        checks["interp_over_aniposelib_all"] = round(a["rmse_all"] / b["rmse_all"], 3)
    for k in ("dlt_kalman", "aniposelib_kalman", "dlt_disk", "dlt_disk_sim"):
        if k in results:
            a, b = results["interp"], results[k]
            checks[f"interp_beats_{k}_every_column"] = beats_every_column(a, b)
            checks[f"interp_over_{k}_all"] = round(a["rmse_all"] / b["rmse_all"], 3)
            checks[f"interp_over_{k}_occluded"] = round(a["rmse_occluded"] / b["rmse_occluded"], 3)
    for v in variants:
        checks[f"{v}_seen2_le_robust_tri"] = bool(
            results[v]["rmse_seen2"] <= results["robust_tri"]["rmse_seen2"]
        )
        checks[f"{v}_calibrated"] = bool(
            0.8 <= results[v]["calib_seen"] <= 1.25 and 0.8 <= results[v]["calib_occluded"] <= 1.25
        )
    if "self" in results and "aniposelib" in results:
        a, b, r, i = (results[k] for k in ("self", "aniposelib", "rigid", "interp"))
        checks["self_beats_aniposelib_every_column"] = beats_every_column(a, b)
        checks["self_occl_over_rigid"] = round(a["rmse_occluded"] / r["rmse_occluded"], 3)
        checks["self_occl_over_aniposelib"] = round(a["rmse_occluded"] / b["rmse_occluded"], 3)
        checks["self_occl_over_interp"] = round(a["rmse_occluded"] / i["rmse_occluded"], 3)
        checks["self_targets_met"] = bool(
            checks["self_beats_aniposelib_every_column"]
            and checks["self_occl_over_rigid"] <= 0.6
            and checks["self_occl_over_aniposelib"] <= 0.7
            and checks["self_occl_over_interp"] < 1.0
        )
    print("checks: " + ", ".join(f"{k}={v}" for k, v in checks.items()))
    summary = {
        **results,
        "scene": {"frames": args.frames, "seed": args.seed, "sim": "mouse_b", **fractions},
        "checks": checks,
        **extra,
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    return emit(summary, args.out)


if __name__ == "__main__":
    main()
