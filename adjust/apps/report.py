"""The demo's report: every number computed from the run's own files, written as
``report.json``, then ``report.md`` and a self-contained ``report.html`` generated from it.

    from adjust.apps.report import write_report
    write_report(out, record)   # record: what `adjust.apps.demo` ran (folders, timings, settings)

`record` names the run's folders: ``scene`` (an `adjust-simulate` folder: calibration.toml,
detections/, truth.npz, scene.json), ``methods`` (method -> an `adjust-triangulate` /
`adjust-track` output folder with points3d.csv and summary.json), ``primary`` (the method whose
tracks the reprojection figures, behavior and events use), ``tensorboard`` (the training runs'
TensorBoard root), ``train`` (net -> `deformnet-train`'s result), ``classify`` (the
`deformnet-classify` training folder and the predictions on the primary tracks, optional),
``events`` (the `adjust-events` folder, optional), ``timings_s`` and ``settings``.

The pictures go to ``figures/`` beside the report; ``report.json["figures"]`` lists them
(relative paths), and the markdown refers to exactly those. numpy + matplotlib; no Lightning.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from adjust import plot, report_figures
from adjust.apps.common import finite_or_none
from adjust.apps.report_text import blocks, to_html, to_markdown
from adjust.camera import CameraTensors, project_cameras
from adjust.events import detect_events, first_operated
from adjust.io import load_calibration, load_calibration_metadata, load_scene, read_points3d
from adjust.metrics import point_errors
from adjust.plot import camera_axes
from deformnet.atomic import write_text
from deformnet.behavior.labels import bouts
from deformnet.behavior.report import confusion_figure, ethogram_figure, evaluate

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------
# reading the run's files
# ---------------------------------------------------------------------------------------------
def load_truth(scene: str | Path) -> dict:
    """truth.npz of a simulated scene as a dict of arrays (parts as str)."""
    with np.load(Path(scene) / "truth.npz") as z:
        t = {k: z[k] for k in z.files}
    t["parts"] = [str(p) for p in t["parts"]]
    t["behaviors"] = [str(b) for b in t["behaviors"]]
    t["cameras"] = [str(c) for c in t["cameras"]]
    return t


def tracks_in_truth_order(path: str | Path, parts: Sequence[str]) -> dict:
    """read_points3d with points / ncams / error / sigma reordered to `parts`; a part missing
    from the file is a ValueError naming it."""
    res = read_points3d(path)
    missing = [p for p in parts if p not in res["parts"]]
    if missing:
        raise ValueError(f"{path}: no columns for part(s) {missing}")
    order = [res["parts"].index(p) for p in parts]
    sigma = None
    if all(f"{p}_sigma" in res["extra"] for p in parts):
        sigma = np.stack([np.asarray(res["extra"][f"{p}_sigma"], float) for p in parts], -1)
    return {
        "points": res["points"][:, order],
        "ncams": res["ncams"][:, order],
        "error": res["error"][:, order],
        "sigma": sigma,
        "fnum": res["fnum"],
        "extra": res["extra"],
    }


def tracking_table(truth: Mapping, tracks: Mapping[str, Mapping]) -> dict[str, dict]:
    """method -> `adjust.metrics.point_errors` of its points against truth (per_part dropped)."""
    rows = {}
    for method, tr in tracks.items():
        r = point_errors(tr["points"], truth["points"], truth["nviews"], part_names=truth["parts"])
        rows[method] = {k: v for k, v in r.items() if k != "per_part"}
        rows[method]["per_part_rmse"] = {p: v["rmse"] for p, v in r["per_part"].items()}
    return rows


def tensorboard_scalars(root: str | Path) -> dict[str, dict[str, tuple[list, list]]]:
    """Scalars of every run below a TensorBoard root, read from the event files
    (`event_accumulator`): {run: {tag: (steps, values)}, with ``_wall`` = (seconds since the
    run's first event, val/rmse_mm)}. A run is a logger name folder (``lstm``, ``transformer``);
    of several versions the newest is read."""
    from tensorboard.backend.event_processing import event_accumulator

    root = Path(root)
    out: dict[str, dict] = {}
    if not root.is_dir():
        return out
    for run_dir in sorted(p for p in root.iterdir() if p.is_dir()):
        versions = sorted(
            (p for p in run_dir.iterdir() if p.is_dir() and any(p.glob("events.out.tfevents.*"))),
            key=lambda p: p.stat().st_mtime,
        )
        if not versions:
            continue
        acc = event_accumulator.EventAccumulator(str(versions[-1]), size_guidance={"scalars": 0})
        acc.Reload()
        tags = {}
        t0 = None
        for tag in acc.Tags().get("scalars", []):
            ev = acc.Scalars(tag)
            tags[tag] = ([int(e.step) for e in ev], [float(e.value) for e in ev])
            if ev:
                t0 = min(t0 if t0 is not None else ev[0].wall_time, ev[0].wall_time)
        if "val/rmse_mm" in tags and t0 is not None:
            ev = acc.Scalars("val/rmse_mm")
            tags["_wall"] = ([e.wall_time - t0 for e in ev], [float(e.value) for e in ev])
        out[run_dir.name] = tags
    return out


def _png_ok(path: Path) -> bool:
    with open(path, "rb") as fh:
        return fh.read(8) == b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------------------------
def sample_frames(truth: Mapping, codes_fn, n: int = 3) -> list[int]:
    """Frames worth looking at: the one with most parts seen by fewer than 2 cameras, the one
    with most detections the tracker rejected (`codes_fn(frame)` -> (K, C) codes), and a
    middle frame; distinct, sorted."""
    nviews = np.asarray(truth["nviews"])
    T = len(nviews)
    occl = (nviews < 2).sum(1)
    picks = [int(np.argmax(occl))]
    outl = np.asarray(truth.get("outlier", np.zeros((T, 1, 1), bool))).sum((1, 2))
    candidates = np.argsort(-outl, kind="stable")[:20]
    rejected = [(int((codes_fn(int(f)) == 2).sum()), -int(f)) for f in candidates]
    if rejected:
        best = max(rejected)
        picks.append(-best[1])
    picks.append(T // 2)
    out = []
    for p in picks:
        if p not in out:
            out.append(p)
    return sorted(out[:n])


def make_figures(out: Path, record: Mapping, truth: Mapping, tracks: Mapping, data: dict) -> dict:
    """Write the report's pictures into out/figures; returns name -> relative path."""

    fig_dir = out / "figures"
    figs: dict[str, str] = {}
    fps = float(truth["fps"]) if np.isfinite(truth["fps"]) else None
    parts = truth["parts"]
    primary = str(record["primary"])
    scene = Path(record["scene"])
    calib = scene / "calibration.toml"
    cameras = load_calibration(calib)
    meta = load_calibration_metadata(calib)

    def keep(name: str, fig) -> None:
        figs[name] = str(plot.save(fig, fig_dir / f"{name}.png").relative_to(out))

    keep(
        "scene",
        plot.scene_figure(
            cameras,
            track_xy=np.asarray(truth["poses"])[:, 3:5],
            arena_size=truth.get("arena_size"),
            lockbox_corners=truth.get("lockbox_corners"),
            mechanisms=meta.get("mechanisms"),
        ),
    )
    keep(
        "body3d",
        plot.body3d_figure(
            tracks[primary]["points"], parts, fps=fps, title=f"tracked body over time ({primary})"
        ),
    )
    errors = {
        m: np.linalg.norm(tr["points"] - truth["points"], axis=-1) for m, tr in tracks.items()
    }
    occ = np.asarray(truth["nviews"]) < 2
    keep("errors", plot.error_figure(errors, parts, occ, fps=fps))
    # the key figure: the part occluded most often (not always), in the most occluded window
    frac = occ.mean(0)
    k = int(np.argmax(np.where(frac < 0.8, frac, -1.0)))
    T = len(occ)
    span = min(T, 600)
    dens = np.convolve(occ[:, k].astype(float), np.ones(span), mode="valid")
    a = int(np.argmax(dens))
    shown = {m: tracks[m]["points"][:, k] for m in ("dlt", primary, "net") if m in tracks}
    keep(
        "key",
        report_figures.key_figure(
            truth["points"][:, k], shown, parts[k], occ[:, k], fps, (a, a + span)
        ),
    )
    data["key"] = {
        "part": parts[k],
        "occluded_fraction": float(frac[k]),
        "window_frames": [a, a + span],
        "methods": list(shown),
    }

    # sample frames: the primary tracks reprojected over every camera's detections
    import torch

    cams_t = CameraTensors.from_cameras(cameras)
    uv_all = project_cameras(torch.as_tensor(tracks[primary]["points"]), cams_t).numpy()
    _, det = load_scene(calib, scene / "detections", None)
    order = [list(det.parts).index(p) for p in parts]
    det_xy, det_lik = det.xy[:, order], det.likelihood[:, order]
    raw, _ = _raw_positions(scene, cameras, parts)
    ncams = tracks[primary]["ncams"]
    acc = plot.load_accepted(Path(record["methods"][primary]) / "points3d.csv", parts, cameras)
    if acc is not None and acc.shape[0] == ncams.shape[0]:
        ncams = acc  # exactly which detections the track used

    def codes(f: int) -> np.ndarray:
        return plot.classify_detections(det_xy[f], det_lik[f], det.threshold, uv_all[f], ncams[f])

    frames = sample_frames(truth, codes)
    data["sample_frames"] = []
    for f in frames:
        c = codes(f)
        data["sample_frames"].append(
            {
                "frame": f,
                "accepted": int((c == 1).sum()),
                "rejected": int((c == 2).sum()),
                "missing": int((c == 0).sum()),
                "parts_seen_by_fewer_than_2": int((np.asarray(truth["nviews"])[f] < 2).sum()),
            }
        )
        keep(
            f"reprojection_frame{f}",
            plot.reprojection_figure(
                f"frame {f} ({primary})",
                cameras,
                det_xy[f],
                det_lik[f],
                det.threshold,
                uv_all[f],
                ncams[f],
                parts,
                raw_xy=None if raw is None else raw[f],
            ),
        )
    curves = data.get("_curves") or {}
    nets = {k: v for k, v in curves.items() if k in (record.get("train") or {})}
    if nets:
        keep("curves", report_figures.curves_figure(nets))
    beh = data.get("behavior")
    if beh and "_labels" in beh:
        lab = beh.pop("_labels")
        s = beh["session"]
        keep(
            "confusion",
            confusion_figure(
                s["confusion"],
                beh["classes"],
                f"demo session ({primary} tracks): macro-F1 {s['macro_f1']:.3f}",
            ),
        )
        keep("ethogram", ethogram_figure(lab, beh["classes"], fps or 30.0))
    ev = data.get("events")
    if ev:
        sources = {"tracked": ev["list"], "truth": ev["truth_list"]}
        keep(
            "events",
            report_figures.events_figure(sources, ev["mechanisms"], len(truth["points"]), fps),
        )
    for name, rel in figs.items():
        if not _png_ok(out / rel):  # pragma: no cover - matplotlib writes PNGs
            raise RuntimeError(f"figure {name} ({rel}) is not a PNG")
    return figs


def _raw_positions(scene: Path, cameras, parts) -> tuple[np.ndarray | None, float]:
    """(T, K, C, 2) the detection files' positions regardless of likelihood (for drawing the
    ones below the threshold), or None when they cannot be read."""
    try:
        _, det0 = load_scene(scene / "calibration.toml", scene / "detections", None, 0.0)
    except ValueError:
        return None, 0.0
    order = [list(det0.parts).index(p) for p in parts]
    return det0.xy[:, order], det0.threshold


# ---------------------------------------------------------------------------------------------
# numbers
# ---------------------------------------------------------------------------------------------
def behavior_numbers(record: Mapping, truth: Mapping) -> dict | None:
    """The classifier's own report (its test split) and its predictions on the demo session's
    primary tracks scored against the scene's truth labels
    (`deformnet.behavior_report.evaluate`)."""
    cls = record.get("classify")
    if not cls:
        return None
    import pandas as pd

    rep = json.loads((Path(cls["dir"]) / "report.json").read_text())
    classes = list(rep["raw"]["per_class"])
    pred = pd.read_csv(cls["predictions"])
    lut = {c: i for i, c in enumerate(classes)}
    behaviors = truth["behaviors"]
    y_true = np.array(
        [lut.get(behaviors[i], -1) if i >= 0 else -1 for i in np.asarray(truth["labels"])]
    )
    fnum = pred["fnum"].to_numpy().astype(np.int64)
    y_pred = np.array([lut[c] for c in pred["label"]])
    y_raw = np.array([lut[c] for c in pred["label_raw"]])
    y_true = y_true[fnum]
    smoothed = evaluate(y_true, y_pred, classes)
    raw = evaluate(y_true, y_raw, classes)
    predicted = sorted({str(c) for c in pred["label"]})  # the classes it predicts at all
    summary_path = Path(cls["predictions"]).parent / "summary.json"  # mode=predict's summary
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    return {
        "classes": classes,
        "classifier": {
            "split": rep["split"],
            "macro_f1": rep["raw"]["macro_f1"],
            "macro_f1_smoothed": rep["smoothed"]["macro_f1"],
            "accuracy": rep["raw"]["accuracy"],
            "frames": rep["raw"]["frames"],
            "training_steps": rep.get("training_steps"),
            "labelled_training_frames": rep.get("labelled_training_frames"),
            "mechanisms": rep.get("mechanisms"),
            "checkpoint": rep.get("checkpoint"),
            "report": str(Path(cls["dir"]) / "report.json"),
        },
        "session": {
            "tracks": str(record["primary"]),
            "predictions": str(cls["predictions"]),
            "macro_f1": smoothed["macro_f1"],
            "accuracy": smoothed["accuracy"],
            "macro_f1_raw": raw["macro_f1"],
            "frames": smoothed["frames"],
            "unfamiliar_frames": summary.get("unfamiliar_frames"),
            "body_scale": summary.get("body_scale"),
            "warning": summary.get("warning"),
            "per_class": smoothed["per_class"],
            "confusion": smoothed["confusion"],
            "true_bouts": len(bouts(y_true)),
            "predicted_bouts": len(bouts(y_pred)),
            "predicted_classes": predicted,
        },
        "_labels": {"true": y_true, "predicted (raw)": y_raw, "predicted (smoothed)": y_pred},
    }


def event_numbers(record: Mapping, truth: Mapping) -> dict | None:
    """`adjust-events` on the primary tracks (its summary and events.csv) and the same
    detector on the true parts, for the order of the mechanisms."""
    ev = record.get("events")
    if not ev:
        return None
    import pandas as pd

    folder = Path(ev["dir"])
    summary = json.loads((folder / "summary.json").read_text())
    df = pd.read_csv(folder / "events.csv")
    events = [
        {
            "start": int(r.start),
            "stop": int(r.stop),
            "part": str(r.part),
            "mechanism": str(r.mechanism),
            "min_distance_mm": float(r.min_distance_mm),
            "inferred": bool(r.inferred),
        }
        for r in df.itertuples()
    ]
    c = summary["contact"]
    mechs = summary["mechanisms"]
    true_events = detect_events(
        np.asarray(truth["points"]),
        truth["parts"],
        mechs,
        use_parts=summary["parts"],
        on_mm=float(c["on_mm"]),
        off_mm=float(c["off_mm"]),
        min_frames=int(c["min_frames"]),
        merge_gap=int(c["merge_gap"]),
    )
    truth_list = [
        {k: (v if not isinstance(v, np.generic) else v.item()) for k, v in e.items()}
        for e in true_events
    ]
    truth_order = first_operated(true_events)
    return {
        "summary": str(folder / "summary.json"),
        "count": int(summary["events"]),
        "inferred": int(summary["inferred_events"]),
        "operations": int(summary["operations"]),
        "order": list(summary["order"]),
        "truth_count": len(truth_list),
        "truth_order": truth_order,
        "order_matches_truth": list(summary["order"]) == list(truth_order),
        "mechanisms": list(mechs),
        "parts": list(summary["parts"]),
        "list": events,
        "truth_list": truth_list,
    }


def training_numbers(record: Mapping, curves: Mapping) -> dict:
    out = {}
    for net, res in (record.get("train") or {}).items():
        m = res.get("metrics", {})
        c = curves.get(net, {})
        val = c.get("val/rmse_mm", ([], []))
        wall = c.get("_wall", ([], []))
        out[net] = {
            "best_val_rmse_mm": m.get("best/val_rmse_mm"),
            "final_val_rmse_mm": val[1][-1] if val[1] else None,
            "rigid_baseline_mm": m.get("val/rmse_mm_rigid"),
            "linear_baseline_mm": m.get("val/rmse_mm_linear"),
            "validations": len(val[1]),
            "last_step": val[0][-1] if val[0] else None,
            "train_minutes": round(wall[0][-1] / 60.0, 2) if wall[0] else None,
            "checkpoint": res.get("best_checkpoint") or res.get("last_checkpoint"),
        }
    return out


def compute(out: Path, record: Mapping) -> dict:
    """report.json's content (figures included, written to out/figures)."""
    scene = Path(record["scene"])
    truth = load_truth(scene)
    parts = truth["parts"]
    tracks = {
        m: tracks_in_truth_order(Path(d) / "points3d.csv", parts)
        for m, d in record["methods"].items()
    }
    summaries = {
        m: json.loads((Path(d) / "summary.json").read_text()) for m, d in record["methods"].items()
    }
    table = tracking_table(truth, tracks)
    for m, row in table.items():
        s = summaries[m]
        reproj = s.get("reprojection_error_px") or {}
        row["median_reprojection_px"] = reproj.get("median")
        row["seconds"] = (record.get("timings_s") or {}).get(m)
        row["summary"] = str(Path(record["methods"][m]) / "summary.json")
    scene_json = json.loads((scene / "scene.json").read_text())
    cameras = load_calibration(scene / "calibration.toml")

    data: dict = {
        "title": "mousetrack demo report",
        "created": time.strftime("%Y-%m-%d %H:%M:%S"),
        "run_dir": str(out),
        "settings": dict(record.get("settings") or {}),
        "timings_s": dict(record.get("timings_s") or {}),
        "scene": {
            "dir": str(scene),
            "frames": int(len(truth["points"])),
            "fps": float(truth["fps"]),
            "parts": parts,
            "cameras": [
                {
                    "name": c.name,
                    "centre_mm": camera_axes(c)[0].round(1).tolist(),
                    "view": camera_axes(c)[1].round(3).tolist(),
                    "size_px": list(c.size),
                }
                for c in cameras
            ],
            "fractions": scene_json["fractions"],
            "arena_size_mm": np.asarray(truth["arena_size"]).tolist(),
            "behaviors": truth["behaviors"],
        },
        "primary": str(record["primary"]),
        "tracking": table,
    }
    curves = tensorboard_scalars(record["tensorboard"]) if record.get("tensorboard") else {}
    data["_curves"] = curves
    data["training"] = training_numbers(record, curves)
    data["behavior"] = behavior_numbers(record, truth)
    data["events"] = event_numbers(record, truth)
    data["figures"] = make_figures(out, record, truth, tracks, data)
    data.pop("_curves")
    return data


def write_report(out: str | Path, record: Mapping) -> dict:
    """Compute, write out/report.json, out/report.md and out/report.html; returns
    {"json", "markdown", "html", "report"} (paths and the report.json content)."""
    out = Path(out)
    rep = finite_or_none(_plain(compute(out, record)))
    write_text(out / "report.json", json.dumps(rep, indent=2) + "\n")
    bl = blocks(rep)
    write_text(out / "report.md", to_markdown(bl))
    write_text(out / "report.html", to_html(bl, out, rep["title"]))
    return {
        "json": out / "report.json",
        "markdown": out / "report.md",
        "html": out / "report.html",
        "report": rep,
    }


def _plain(x):
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    return x
