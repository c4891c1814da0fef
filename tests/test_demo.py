"""`adjust-demo preset=quick`: the whole pipeline (scene, two nets, DLT / rigid / interp / net
tracking, behavior, events) and the report, once per test session (~40 s on 2 cores)."""

from __future__ import annotations

import ast
import copy
import json
import logging
import re
import warnings
from pathlib import Path

import hydra
import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from adjust.io import read_points3d
from adjust.metrics import point_errors
from deformnet.paths import CONF_DIR, REPO_DIR

PNG = b"\x89PNG\r\n\x1a\n"
#: what the demo fixture's run logged and warned: {"records": [LogRecord], "warnings": [...]}
CONSOLE: dict = {}


class _Keep(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.NOTSET)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    from adjust.apps.demo import run

    out = tmp_path_factory.mktemp("demo")
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra.compose("demo", overrides=["preset=quick", f"output.dir={out}"])
    keep, root = _Keep(), logging.getLogger()
    level = root.level
    root.addHandler(keep)  # every record that reaches the console's handlers, at INFO as
    root.setLevel(logging.INFO)  # under Hydra
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = run(cfg)
    finally:
        root.removeHandler(keep)
        root.setLevel(level)
    CONSOLE.update(records=keep.records, warnings=[str(w.message) for w in caught])
    return out, res, json.loads((out / "report.json").read_text())


def test_every_picture_exists_and_is_a_png(demo):
    out, res, rep = demo
    names = set(rep["figures"])
    expected = {"key", "scene", "body3d", "errors", "curves", "confusion", "ethogram", "events"}
    assert expected <= names
    assert sum(n.startswith("reprojection_frame") for n in names) >= 2
    md = (out / "report.md").read_text()
    referenced = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert sorted(referenced) == sorted(set(referenced))  # each picture once
    assert set(referenced) == set(rep["figures"].values())
    for rel in referenced:
        with open(out / rel, "rb") as fh:
            assert fh.read(8) == PNG, rel
    html = (out / "report.html").read_text()
    srcs = re.findall(r'<img src="([^"]+)"', html)
    assert len(srcs) == len(referenced)
    assert all(s.startswith("data:image/png;base64,iVBORw0KGgo") for s in srcs)  # embedded
    assert Path(res["report"]["html"]) == out / "report.html"
    from adjust.apps.demo import closing_lines

    last = closing_lines(res, 1.0).splitlines()[-2:]
    assert last[0] == f"Report: {out / 'report.md'}"
    assert last[1].strip().startswith(str(out / "report.html"))


def test_console_shows_the_steps_not_library_tips(demo):
    """The demo's console: its steps and results, not Lightning's tips, info lines and
    deprecations, TensorBoard's or numexpr's info lines."""
    records, caught = CONSOLE["records"], CONSOLE["warnings"]
    texts = [r.getMessage() for r in records]
    assert any(t.startswith("== adjust-simulate") for t in texts)  # the steps are there
    for noise in ("💡 Tip", "litlogger", "GPU available", "Directory watcher", "NumExpr"):
        assert not [t for t in texts if noise in t], noise
    assert not [r for r in records if r.name.startswith("lightning") and r.levelno < 30]
    for noise in ("LeafSpec", "smaller than the logging interval"):
        assert not [w for w in caught if noise in w], noise


def test_report_flags_the_quick_preset_and_a_one_class_classifier(demo):
    from adjust.apps.report_text import blocks, notes, to_markdown

    out, _, rep = demo
    html = (out / "report.html").read_text()
    md = (out / "report.md").read_text()
    flagged = re.findall(r'<p class="note"><strong>Note:</strong> (.*?)</p>', html)
    assert any("<code>quick</code> preset" in n for n in flagged)
    assert "> **Note:** This is the `quick` preset" in md
    assert md.index("quick` preset") < md.index("## Tracking accuracy")  # before the numbers
    warned = [r.getMessage() for r in CONSOLE["records"] if r.levelno == logging.WARNING]
    assert any("This is the quick preset" in t for t in warned)
    pred = pd.read_csv(out / "classify" / "predict" / "predictions.csv")
    assert rep["behavior"]["session"]["predicted_classes"] == sorted(set(pred["label"]))
    one = len(set(pred["label"])) == 1
    assert any("predicts one class only" in n for n in flagged) == one
    assert any("predicts one class only" in t for t in warned) == one
    # the notes on their own: one class flagged, two not; the full preset not flagged
    r = copy.deepcopy(rep)
    r["behavior"]["session"]["predicted_classes"] = ["walk"]
    r["settings"]["preset"] = "full"
    assert len(notes(r)) == 1 and "one class only (`walk` on all 300 frames" in notes(r)[0]
    assert "> **Note:** The behavior classifier predicts one class only" in to_markdown(blocks(r))
    r["behavior"]["session"]["predicted_classes"] = ["rear", "walk"]
    assert notes(r) == []


def test_tracking_numbers_equal_the_run_files(demo):
    out, _, rep = demo
    with np.load(out / "scene" / "truth.npz") as z:
        truth, nviews, parts = z["points"], z["nviews"], [str(p) for p in z["parts"]]
    assert set(rep["tracking"]) == {"dlt", "rigid", "interp", "net", "self"}
    md = (out / "report.md").read_text()
    for method, row in rep["tracking"].items():
        tr = read_points3d(out / method / "points3d.csv")
        est = tr["points"][:, [tr["parts"].index(p) for p in parts]]
        ref = point_errors(est, truth, nviews, part_names=parts)
        for key in ("completeness", "rmse_all", "rmse_seen", "rmse_occluded", "within5_all"):
            assert row[key] == pytest.approx(ref[key], rel=1e-12, abs=1e-12), (method, key)
        summary = json.loads((out / method / "summary.json").read_text())
        assert row["median_reprojection_px"] == summary["reprojection_error_px"]["median"]
        assert row["completeness"] == pytest.approx(summary["completeness"], abs=1e-12)
        line = next(ln for ln in md.splitlines() if ln.startswith(f"| {method} |"))
        assert f"{row['rmse_all']:.2f}" in line and f"{row['completeness']:.3f}" in line
    # DLT leaves the occluded part-frames empty; the adjustments fill every one
    assert rep["tracking"]["dlt"]["completeness"] < 0.9
    for m in ("rigid", "interp", "net", "self"):
        assert rep["tracking"][m]["completeness"] == 1.0
    assert (out / "self" / "deformation.ckpt").is_file()  # the adapted net, reusable


def test_training_behavior_events_numbers_equal_the_run_files(demo):
    out, _, rep = demo
    for net in ("lstm", "transformer"):
        metrics = json.loads((out / "train" / net / "metrics.json").read_text())["metrics"]
        assert rep["training"][net]["best_val_rmse_mm"] == metrics["best/val_rmse_mm"]
        assert rep["training"][net]["validations"] >= 1  # read from the event files
        assert (out / "tb" / net).is_dir()
    cls = json.loads((out / "classify" / "report.json").read_text())
    # the classifier learnt from labelled sessions tracked like the demo's primary tracks (not
    # from simulator truth), and the demo's own scene is not one of them
    ccfg = OmegaConf.load(out / "classify" / "config.yaml")
    sessions = out.resolve() / "classify" / "sessions"
    assert list(ccfg.data.train_tracks) == [str(sessions / "0" / "interp" / "points3d.csv")]
    assert list(ccfg.data.test_labels) == [str(sessions / "20000" / "labels.csv")]
    # with the lock-box context: the labelled sessions' lock box to train, the scene's to predict
    assert ccfg.mechanisms.calibration == str(sessions / "0" / "scene" / "calibration.toml")
    pcfg = OmegaConf.load(out / "classify" / "predict" / "config.yaml")
    assert pcfg.mechanisms.calibration == str(out.resolve() / "scene" / "calibration.toml")
    assert cls["mechanisms"]["names"] == ["lever", "splint", "ball", "slider"]
    with np.load(sessions / "0" / "scene" / "truth.npz") as z:
        names = [str(b) for b in z["behaviors"]]
        want = [names[i] for i in z["labels"]]
    assert pd.read_csv(sessions / "0" / "labels.csv")["label"].tolist() == want
    beh = rep["behavior"]
    assert beh["classifier"]["macro_f1"] == cls["raw"]["macro_f1"]
    assert beh["classifier"]["training_steps"] == cls["training_steps"]
    pred = pd.read_csv(out / "classify" / "predict" / "predictions.csv")
    with np.load(out / "scene" / "truth.npz") as z:
        names = [str(b) for b in z["behaviors"]]
        y = np.array([names[i] for i in z["labels"]])
    acc = float(np.mean(pred["label"].to_numpy() == y[pred["fnum"].to_numpy()]))
    assert beh["session"]["accuracy"] == pytest.approx(acc, abs=1e-12)
    assert np.asarray(beh["session"]["confusion"]).sum() == len(pred)
    # mode=predict's check of the recording against the training data, in the report
    summ = json.loads((out / "classify" / "predict" / "summary.json").read_text())
    assert 0.0 <= summ["unfamiliar_frames"] <= 1.0
    assert beh["session"]["unfamiliar_frames"] == summ["unfamiliar_frames"]
    assert beh["session"]["body_scale"] == summ["body_scale"]
    assert 0.9 < summ["body_scale"] < 1.1  # the simulated mouse is the body model's size
    ev = json.loads((out / "events" / "summary.json").read_text())
    assert rep["events"]["order"] == ev["order"]
    assert rep["events"]["count"] == ev["events"] == len(rep["events"]["list"])
    md = (out / "report.md").read_text()
    assert f"macro-F1 {beh['session']['macro_f1']:.3f}" in md
    assert "with the lock-box context (the distances of nose_tip, left_front_paw" in md
    assert "unlike its training data" in md
    assert "Order of first operation: " + (" > ".join(ev["order"]) or "none") in md
    assert set(rep["timings_s"]) >= {"scene", "train_lstm", "train_transformer", "dlt", "net"}


def test_deformnet_never_imports_adjust():
    """The layering rule: deformnet/ (the demo moved to adjust/) has no `adjust` import."""
    for path in (REPO_DIR / "deformnet").rglob("*.py"):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                mods = [node.module or ""]
            else:
                continue
            assert not any(m == "adjust" or m.startswith("adjust.") for m in mods), path


@pytest.mark.parametrize(
    "override, message",
    [
        (
            "presets.quick.classify_train_seeds=[7]",
            "classify_train_seeds holds the demo scene's seed 7",
        ),
        (
            "presets.quick.classify_test_seeds=[0]",
            "classify_train_seeds and classify_test_seeds share seed",
        ),
        ("presets.quick.classify_val_seeds=[]", "classify_val_seeds is empty"),
    ],
)
def test_bad_labelled_sessions_fail_before_anything_runs(tmp_path, override, message):
    from adjust.apps.demo import run

    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra.compose("demo", overrides=["preset=quick", f"output.dir={tmp_path}", override])
    with pytest.raises(ValueError, match=message):
        run(cfg)
    assert not (tmp_path / "scene").exists()


def test_the_steps_are_typed_and_their_yaml_defaults_are_the_dataclass_s(tmp_path):
    """conf/demo.yaml's behavior, behavior_box and events are `DemoSteps`' defaults (the one
    copy in the code); absent, each keeps its default; a bad value names the setting before
    anything runs."""
    from adjust.apps.demo import run
    from adjust.settings import DemoSteps

    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra.compose("demo", overrides=["preset=quick", f"output.dir={tmp_path}"])
    steps = DemoSteps.from_config(cfg)
    assert steps == DemoSteps() == DemoSteps.from_config({})
    assert {k: cfg[k] for k in ("behavior", "behavior_box", "events")} == vars(steps)
    cfg.behavior_box = "sometimes"
    with pytest.raises(ValueError, match="behavior_box='sometimes'"):
        run(cfg)
    assert not (tmp_path / "scene").exists()


def test_unknown_preset_is_one_clear_error(tmp_path):
    from adjust.apps.demo import run

    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra.compose("demo", overrides=["preset=huge", f"output.dir={tmp_path}"])
    with pytest.raises(ValueError, match="preset=huge is not one of"):
        run(cfg)


@pytest.mark.slow
def test_dlt_primary_classifier_fills_gaps_in_training_and_prediction(tmp_path):
    """primary=dlt: the labelled sessions are DLT-triangulated, and both the classifier's training
    and its prediction fill the gaps (data.interpolate=true); every frame gets a label."""
    from adjust.apps.demo import run

    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra.compose(
            "demo", overrides=["preset=quick", f"output.dir={tmp_path}", "primary=dlt"]
        )
    run(cfg)
    out = tmp_path.resolve()
    ccfg = OmegaConf.load(out / "classify" / "config.yaml")
    assert ccfg.data.interpolate is True
    assert list(ccfg.data.train_tracks) == [
        str(out / "classify" / "sessions" / "0" / "dlt" / "points3d.csv")
    ]
    pcfg = OmegaConf.load(out / "classify" / "predict" / "config.yaml")
    assert pcfg.data.interpolate is True
    pred = pd.read_csv(out / "classify" / "predict" / "predictions.csv")
    assert len(pred) == 300 and pred["label"].notna().all()
