"""The demo's report as documents (`adjust.apps.report` computes it): what a reader must know
first (`notes`), the report as blocks (`blocks`), and the blocks as markdown (`to_markdown`)
and a self-contained HTML page (`to_html`, the figures inlined)."""

from __future__ import annotations

import base64
import html
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = ["TABLE_COLUMNS", "blocks", "notes", "to_html", "to_markdown"]

#: the accuracy table's columns: point_errors key -> heading
TABLE_COLUMNS = {
    "completeness": "complete",
    "rmse_all": "RMSE all (mm)",
    "rmse_seen": "RMSE seen >= 2 (mm)",
    "rmse_occluded": "RMSE occluded (mm)",
    "within5_all": "within 5 mm",
}


# ---------------------------------------------------------------------------------------------
# the documents: blocks -> markdown and HTML
# ---------------------------------------------------------------------------------------------
def _f(x, digits: int = 2) -> str:
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return str(x)
    if isinstance(x, float):
        return "-" if not np.isfinite(x) else f"{x:.{digits}f}"
    return str(x)


def notes(rep: Mapping) -> list[str]:
    """What a reader must know before the numbers: the run is a smaller preset than the full
    demo (its numbers check that the pipeline runs, they do not measure it), the behavior
    classifier predicts one class only (it has not learned the behaviors)."""
    out = []
    st = rep.get("settings") or {}
    preset = st.get("preset")
    if preset is not None and preset != "full":
        out.append(
            f"This is the `{preset}` preset ({st.get('frames')} frames, "
            f"{st.get('train_minutes')} min of training per net, {st.get('classify_minutes')} "
            "min for the behavior classifier): it checks that the pipeline runs end to end; its "
            "numbers are not the method's accuracy (run `adjust-demo` for the full preset)."
        )
    s = (rep.get("behavior") or {}).get("session") or {}
    predicted = s.get("predicted_classes")
    if predicted is not None and len(predicted) <= 1:
        what = f"`{predicted[0]}`" if predicted else "nothing"
        out.append(
            f"The behavior classifier predicts one class only ({what} on all {s.get('frames')} "
            "frames of the demo session): it has not learned to tell the behaviors apart "
            "(too little training or labelled data), so its behavior scores mean little."
        )
    return out


def blocks(rep: Mapping) -> list[tuple]:
    """The report as blocks: ("h", level, text), ("p", text), ("note", text: a warning the
    reader must see), ("table", header, rows), ("img", relative path, caption), ("pre", text)."""
    b: list[tuple] = []
    sc = rep["scene"]
    fig = rep["figures"]
    b.append(("h", 1, rep["title"]))
    b += [("note", n) for n in notes(rep)]
    b.append(
        (
            "p",
            f"Run folder `{rep['run_dir']}`, written {rep['created']}. Every number "
            "below was computed by this run from its own files (`report.json` holds them).",
        )
    )
    tot = sum(v for v in rep["timings_s"].values() if isinstance(v, int | float))
    b.append(
        (
            "p",
            f"A simulated mouse ({sc['frames']} frames at {sc['fps']:g} fps, "
            f"{len(sc['parts'])} parts) filmed by {len(sc['cameras'])} cameras, detected "
            "with the simulator's DeepLabCut-like detector: part-frames seen by >= 2 "
            f"cameras {100 * sc['fractions']['ge2_views']:.1f}%, by one "
            f"{100 * sc['fractions']['one_view']:.1f}%, by none "
            f"{100 * sc['fractions']['no_view']:.1f}%. Pipeline time {tot / 60:.1f} min.",
        )
    )

    key = rep.get("key")
    if key and "key" in fig:
        b.append(
            (
                "img",
                fig["key"],
                f"{key['part']} (seen by fewer than 2 cameras in "
                f"{100 * key['occluded_fraction']:.0f}% of the frames), frames "
                f"{key['window_frames'][0]}-{key['window_frames'][1]}: the truth, the DLT "
                f"triangulation and the tracked estimates ({', '.join(key['methods'][1:])}).",
            )
        )
    b.append(("h", 2, "Scene and rig"))
    b.append(
        (
            "img",
            fig["scene"],
            "Plan view and 3D view: arena, lock box and its mechanisms, "
            "the mouse's true track on the plane, camera centres and view directions.",
        )
    )
    b.append(
        (
            "table",
            ["camera", "centre (mm)", "view direction", "image (px)"],
            [
                [
                    c["name"],
                    ", ".join(f"{v:.0f}" for v in c["centre_mm"]),
                    ", ".join(f"{v:.2f}" for v in c["view"]),
                    " x ".join(map(str, c["size_px"])),
                ]
                for c in sc["cameras"]
            ],
        )
    )

    b.append(("h", 2, "Tracking accuracy against truth"))
    b.append(
        (
            "p",
            "3D error of each method's `points3d.csv` against the simulated truth "
            "(`adjust.metrics.point_errors`): completeness (part-frames with an estimate), "
            "RMSE over all part-frames, those seen by >= 2 cameras and the occluded ones "
            "(seen by fewer), the fraction within 5 mm, the median reprojection error "
            "of the method's summary and its run time.",
        )
    )
    header = ["method", *TABLE_COLUMNS.values(), "median reproj (px)", "seconds"]
    rows = []
    for m, r in rep["tracking"].items():
        rows.append(
            [
                m,
                *[
                    _f(r[k], 3 if k in ("completeness", "within5_all") else 2)
                    for k in TABLE_COLUMNS
                ],
                _f(r["median_reprojection_px"]),
                _f(r["seconds"], 1),
            ]
        )
    b.append(("table", header, rows))
    b.append(
        (
            "p",
            "Methods: `dlt` = `adjust-triangulate body=mouse` (linear triangulation, "
            "nothing where fewer than 2 cameras saw a part); `rigid` = `adjust-track "
            "deformation=rigid`; `interp` = `adjust-track` (default: the rigid model plus "
            "each part's interpolated offset); `net` = `adjust-track deformation=<the "
            "demo's LSTM checkpoint>`; `self` = `adjust-track deformation=self` (the shipped "
            "pretrained net fine-tuned on this scene's own detections, no truth). "
            f"Reprojections, behavior and events below use "
            f"`{rep['primary']}`.",
        )
    )
    b.append(
        (
            "img",
            fig["errors"],
            "Per-part 3D error over time against truth; grey: the part "
            "was seen by fewer than 2 cameras (occluded).",
        )
    )
    b.append(("img", fig["body3d"], "The tracked body over time in 3D."))
    b.append(("h", 2, "Reprojections over the detections"))
    b.append(
        (
            "p",
            "Sample frames: each camera's detections (green: accepted by the tracker, "
            "red X: rejected, grey ring: below the likelihood threshold) and the tracked "
            "parts reprojected (blue +). Which detections the track used comes from "
            "adjust-track's `accepted.npz`.",
        )
    )
    b.append(
        (
            "table",
            ["frame", "accepted", "rejected", "missing", "parts seen by < 2 cameras"],
            [
                [
                    s["frame"],
                    s["accepted"],
                    s["rejected"],
                    s["missing"],
                    s["parts_seen_by_fewer_than_2"],
                ]
                for s in rep.get("sample_frames", [])
            ],
        )
    )
    for s in rep.get("sample_frames", []):
        b.append(("img", fig[f"reprojection_frame{s['frame']}"], f"Frame {s['frame']}."))

    if rep["training"]:
        b.append(("h", 2, "Deformation nets: LSTM vs transformer"))
        b.append(
            (
                "p",
                "Both trained side by side for the same time on simulated windows with "
                "hidden parts; validation RMSE of the hidden parts, read from the "
                f"TensorBoard event files (`tensorboard --logdir "
                f"{rep['settings'].get('tensorboard', 'tb')}`).",
            )
        )
        b.append(
            (
                "table",
                [
                    "net",
                    "best val RMSE (mm)",
                    "final",
                    "rigid baseline",
                    "linear baseline",
                    "validations",
                    "steps",
                    "minutes",
                ],
                [
                    [
                        n,
                        _f(t["best_val_rmse_mm"]),
                        _f(t["final_val_rmse_mm"]),
                        _f(t["rigid_baseline_mm"]),
                        _f(t["linear_baseline_mm"]),
                        t["validations"],
                        _f(t["last_step"]),
                        _f(t["train_minutes"]),
                    ]
                    for n, t in rep["training"].items()
                ],
            )
        )
        if "curves" in fig:
            b.append(
                (
                    "img",
                    fig["curves"],
                    "Validation curves (log scale) against step and "
                    "wall time; dashed / dotted: the linear-interpolation and rigid baselines.",
                )
            )

    beh = rep.get("behavior")
    if beh:
        c, s = beh["classifier"], beh["session"]
        box = ""
        if c.get("mechanisms"):
            m = c["mechanisms"]
            box = (f" with the lock-box context (the distances of {', '.join(m['parts'])} to "
                   f"{', '.join(m['names'])} among its frame features)")  # fmt: skip
        b.append(("h", 2, "Behavior"))
        b.append(
            (
                "p",
                "`deformnet-classify` fine-tuned the LSTM's encoder on simulated labelled "
                f"sessions tracked like the `{s['tracks']}` tracks{box} "
                f"({c['labelled_training_frames']} labelled frames, "
                f"{c['training_steps']} steps): on its own {c['split']} split macro-F1 "
                f"{_f(c['macro_f1'], 3)} (smoothed {_f(c['macro_f1_smoothed'], 3)}). Its "
                f"predictions on this demo's `{s['tracks']}` tracks against the scene's "
                f"true labels: macro-F1 {_f(s['macro_f1'], 3)} (raw "
                f"{_f(s['macro_f1_raw'], 3)}), accuracy {_f(s['accuracy'], 3)} over "
                f"{s['frames']} frames; {s['predicted_bouts']} predicted bouts, "
                f"{s['true_bouts']} true."
                + (
                    f" {_f(100 * s['unfamiliar_frames'], 1)}% of those frames are unlike its "
                    "training data (`deformnet-classify`'s check, `unfamiliar`)."
                    if s.get("unfamiliar_frames") is not None
                    else ""
                )
                + (
                    f" The mouse measured {_f(s['body_scale'], 3)} times the body model's size "
                    "(`body_scale`, divided out)."
                    if s.get("body_scale") is not None
                    else ""
                ),
            )
        )
        if s.get("warning"):
            b.append(("p", f"**Warning:** {s['warning']}"))
        b.append(
            (
                "table",
                ["behavior", "precision", "recall", "F1", "frames"],
                [
                    [k, _f(v["precision"], 3), _f(v["recall"], 3), _f(v["f1"], 3), v["support"]]
                    for k, v in s["per_class"].items()
                ],
            )
        )
        b.append(("img", fig["confusion"], "Confusion matrix (smoothed predictions)."))
        b.append(("img", fig["ethogram"], "Ethogram: true labels and predictions over time."))

    ev = rep.get("events")
    if ev:
        b.append(("h", 2, "Lock-box events"))
        b.append(
            (
                "p",
                f"`adjust-events` on the `{rep['primary']}` tracks: {ev['count']} "
                f"contacts ({ev['inferred']} inferred: the part mostly unseen), "
                f"{ev['operations']} operations. Order of first operation: "
                f"{' > '.join(ev['order']) or 'none'}; on the true parts: "
                f"{' > '.join(ev['truth_order']) or 'none'} ({ev['truth_count']} "
                f"contacts); same order: {_f(ev['order_matches_truth'])}.",
            )
        )
        b.append(
            (
                "table",
                ["start", "stop", "part", "mechanism", "min distance (mm)", "inferred"],
                [
                    [
                        e["start"],
                        e["stop"],
                        e["part"],
                        e["mechanism"],
                        _f(e["min_distance_mm"]),
                        _f(e["inferred"]),
                    ]
                    for e in ev["list"]
                ],
            )
        )
        if "events" in fig:
            b.append(("img", fig["events"], "Contacts per mechanism, tracked and true."))

    b.append(("h", 2, "Run times"))
    b.append(("table", ["step", "seconds"], [[k, _f(v, 1)] for k, v in rep["timings_s"].items()]))
    return b


def to_markdown(bl: Sequence[tuple]) -> str:
    lines: list[str] = []
    for blk in bl:
        kind = blk[0]
        if kind == "h":
            lines += ["#" * blk[1] + " " + blk[2], ""]
        elif kind == "p":
            lines += [blk[1], ""]
        elif kind == "note":
            lines += [f"> **Note:** {blk[1]}", ""]
        elif kind == "img":
            lines += [f"![{Path(blk[1]).stem}]({blk[1]})", "", f"*{blk[2]}*", ""]
        elif kind == "table":
            header, rows = blk[1], blk[2]
            lines.append("| " + " | ".join(header) + " |")
            lines.append("|" + "|".join(" --- " for _ in header) + "|")
            lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
            lines.append("")
        elif kind == "pre":
            lines += ["```", blk[1], "```", ""]
    return "\n".join(lines)


def _inline(text: str) -> str:
    """`code` spans -> <code>, everything escaped."""
    parts = html.escape(text).split("`")
    return "".join(f"<code>{p}</code>" if i % 2 else p for i, p in enumerate(parts))


def to_html(bl: Sequence[tuple], base: Path, title: str) -> str:
    """Self-contained HTML: the pictures base64-embedded."""
    body: list[str] = []
    for blk in bl:
        kind = blk[0]
        if kind == "h":
            body.append(f"<h{blk[1]}>{_inline(blk[2])}</h{blk[1]}>")
        elif kind == "p":
            body.append(f"<p>{_inline(blk[1])}</p>")
        elif kind == "note":
            body.append(f'<p class="note"><strong>Note:</strong> {_inline(blk[1])}</p>')
        elif kind == "img":
            data = base64.b64encode((base / blk[1]).read_bytes()).decode("ascii")
            body.append(
                f'<figure><img src="data:image/png;base64,{data}" '
                f'alt="{html.escape(blk[2])}"><figcaption>{_inline(blk[2])}'
                "</figcaption></figure>"
            )
        elif kind == "table":
            head = "".join(f"<th>{_inline(str(h))}</th>" for h in blk[1])
            rows = "".join(
                "<tr>" + "".join(f"<td>{_inline(str(c))}</td>" for c in r) + "</tr>" for r in blk[2]
            )
            body.append(f"<table><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>")
        elif kind == "pre":
            body.append(f"<pre>{html.escape(blk[1])}</pre>")
    style = (
        "body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;"
        "line-height:1.45;color:#222}img{max-width:100%}table{border-collapse:collapse;"
        "margin:1em 0;font-size:0.9em}td,th{border:1px solid #ccc;padding:3px 8px;"
        "text-align:right}th{background:#f3f3f3}td:first-child{text-align:left}"
        "code{background:#f3f3f3;padding:0 3px}figcaption{font-style:italic;color:#555}"
        ".note{background:#fff4d6;border-left:4px solid #e0a800;padding:0.5em 0.8em}"
    )
    return (
        f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{html.escape(title)}</title><style>{style}</style></head><body>\n"
        + "\n".join(body)
        + "\n</body></html>\n"
    )
