"""`adjust-demo` (`make demo`): the main job end to end on the embedded default, then a report.

    adjust-demo                    # runs/demo/<time>/report.md and report.html
    adjust-demo preset=quick       # a few hundred frames, seconds of training

Each step is the app a user runs, called through Hydra's compose API (`run(cfg)`), writing into
``OUT = runs/demo/<time>/`` (or ``output.dir``):

1. ``adjust-simulate``        OUT/scene: calibration.toml, detections/<camera>.csv, truth.npz
2. ``deformnet-train``        the LSTM and the transformer, side by side (OUT/train/<net>,
                              one TensorBoard root OUT/tb)
3. ``adjust-triangulate``     OUT/dlt (the DLT baseline)
4. ``adjust-track``           OUT/rigid (deformation=rigid), OUT/interp (the default), OUT/net
                              (deformation=<the trained LSTM checkpoint>), OUT/self
                              (deformation=self: the shipped net fine-tuned on the recording)
5. ``deformnet-classify``     OUT/classify: labelled sessions simulated and tracked like the
                              primary tracks (OUT/classify/sessions/<seed>), the LSTM's encoder
                              fine-tuned on them, then the primary tracks labelled
                              (OUT/classify/predict)
6. ``adjust-events``          OUT/events: lock-box contacts on the primary tracks
7. `adjust.apps.report`            OUT/report.json, report.md, report.html, figures/

`run(cfg) -> dict` is the plain function behind the Hydra app. The last lines printed say where
the report is.
"""

from __future__ import annotations

import json
import logging
import time

import hydra
from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

from adjust.apps import events as events_app
from adjust.apps import simulate as simulate_app
from adjust.apps import track as track_app
from adjust.apps import triangulate as triangulate_app
from adjust.apps.common import run_or_exit
from adjust.apps.report import write_report
from adjust.apps.report_text import notes
from adjust.scene import scene_fps, write_truth_labels
from adjust.settings import DemoSteps
from deformnet.atomic import write_text
from deformnet.paths import CONF_DIR, output_dir
from deformnet.quiet import quiet_lightning
from deformnet.threads import torch_threads

log = logging.getLogger(__name__)

METHODS = ("dlt", "rigid", "interp", "net", "self")


def compose(name: str, overrides: list[str]) -> DictConfig:
    """An app's config (conf/<name>.yaml) with overrides, inside a running Hydra app or not."""
    if GlobalHydra.instance().is_initialized():
        return hydra_compose(config_name=name, overrides=overrides)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        return hydra_compose(config_name=name, overrides=overrides)


def max_time(minutes: float) -> str:
    """Lightning's DD:HH:MM:SS from minutes (at least 1 s)."""
    s = max(1, int(round(float(minutes) * 60)))
    return f"00:{s // 3600:02d}:{s % 3600 // 60:02d}:{s % 60:02d}"


DEFORMATION = {"rigid": "rigid", "interp": "interp", "self": "self"}  # "net": the checkpoint


def track_config(method: str, scene, out, ckpt, p: DictConfig, cfg: DictConfig) -> DictConfig:
    """The config that tracks the scene folder ``scene`` into ``out`` with one of `METHODS`:
    ``dlt`` is `adjust-triangulate`, the others `adjust-track` (``net``: deformation=``ckpt``;
    ``self``: the shipped net fine-tuned on the recording for ``p.adapt_minutes``)."""
    inputs = [
        f"input.calibration={scene / 'calibration.toml'}",
        f"input.detections={scene / 'detections'}",
        f"output.dir={out}",
    ]
    if method == "dlt":
        return compose("triangulate", [*inputs, "body=mouse"])
    extra = []
    if method == "self":
        extra = [f"adapt.max_time={max_time(p.adapt_minutes)}", "adapt.tensorboard=false"]
    return compose(
        "track",
        [
            *inputs,
            f"deformation={DEFORMATION.get(method, ckpt)}",
            "progress=false",
            f"threads={int(cfg.threads)}",
            *extra,
        ],
    )


def labelled_sessions(folder, p: DictConfig, method: str, ckpt, cfg: DictConfig) -> dict:
    """The behavior classifier's labelled sessions, made as a lab makes them: each seed of
    ``p.classify_{train,val,test}_seeds`` simulated (`adjust-simulate`, ``p.classify_frames``
    frames), tracked with ``method`` (the demo's primary tracks) and its true labels written as
    ``labels.csv``: ``folder/<seed>/{scene, <method>, labels.csv}``. Returns the
    `deformnet-classify` ``data.*`` lists: {"train_tracks": "[...]", "train_labels": ..., ...}.
    """
    data: dict[str, list[str]] = {}
    for split, seeds in session_seeds(p, int(cfg.seed)).items():
        for s in seeds:
            d = folder / str(s)
            simulate_app.run(
                compose(
                    "scene",
                    [
                        f"num_frames={int(p.classify_frames)}",
                        f"seed={s}",
                        f"output.dir={d / 'scene'}",
                    ],
                )
            )
            app = triangulate_app if method == "dlt" else track_app
            app.run(track_config(method, d / "scene", d / method, ckpt, p, cfg))
            data.setdefault(f"{split}_tracks", []).append(str(d / method / "points3d.csv"))
            data.setdefault(f"{split}_labels", []).append(
                str(write_truth_labels(d / "scene", d / "labels.csv"))
            )
    return {k: "[" + ",".join(v) + "]" for k, v in data.items()}


def session_seeds(p: DictConfig, scene_seed: int) -> dict[str, list[int]]:
    """The labelled sessions' seeds per split ({"train", "val", "test"} -> seeds), or a
    ValueError naming the preset key that is empty, holds the demo scene's own seed or a seed
    of another split (sessions are split by session: none in two splits)."""
    out: dict[str, list[int]] = {}
    for split in ("train", "val", "test"):
        key = f"classify_{split}_seeds"
        seeds = [int(s) for s in p[key]]
        if not seeds:
            raise ValueError(f"{key} is empty: the behavior classifier needs a {split} session")
        if scene_seed in seeds:
            raise ValueError(
                f"{key} holds the demo scene's seed {scene_seed}: the scene the demo labels "
                "must not be one of the classifier's labelled sessions"
            )
        for other, prev in out.items():
            both = sorted(set(seeds) & set(prev))
            if both:
                raise ValueError(
                    f"classify_{other}_seeds and {key} share seed(s) {both}: a session belongs "
                    "to one split"
                )
        out[split] = seeds
    return out


class _Steps:
    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    def __call__(self, key: str, title: str, fn, cfg: DictConfig):
        log.info("== %s", title)
        t0 = time.perf_counter()
        res = fn(cfg)
        self.seconds[key] = round(time.perf_counter() - t0, 2)
        log.info("== %s: %.1f s", title, self.seconds[key])
        return res


def run(cfg: DictConfig) -> dict:
    """Run the pipeline and write the report; returns {"output_dir", "report" (paths), the
    tracking table, timings}. ``threads`` (torch's intra-op threads) applies for the call and
    is restored after it; so does the quiet console (`deformnet.quiet.quiet_lightning`: the
    steps' progress and results, not Lightning's, TensorBoard's and numexpr's info lines, tips
    and deprecations)."""
    with torch_threads(cfg.get("threads")), quiet_lightning(info=False):
        return _run(cfg)


def _run(cfg: DictConfig) -> dict:
    name = str(cfg.preset)
    if name not in cfg.presets:
        raise ValueError(f"preset={name} is not one of {list(cfg.presets)}")
    p = cfg.presets[name]
    primary = str(cfg.primary)
    if primary not in METHODS:
        raise ValueError(f"primary={primary} is not one of {list(METHODS)}")
    nets = [str(n) for n in cfg.nets]
    deform_net = str(cfg.deformable_net)
    if deform_net not in nets:
        raise ValueError(f"deformable_net={deform_net} is not among nets={nets}")
    steps = DemoSteps.from_config(cfg)  # behavior, behavior_box, events
    out = output_dir(cfg).resolve()
    step = _Steps()
    seed = int(cfg.seed)
    if steps.behavior:
        session_seeds(p, seed)  # before anything runs

    # 1. the scene
    scene = out / "scene"
    step(
        "scene",
        "adjust-simulate: the scene",
        simulate_app.run,
        compose("scene", [f"num_frames={int(p.frames)}", f"seed={seed}", f"output.dir={scene}"]),
    )

    # 2. the nets, side by side, one TensorBoard root
    from deformnet import train  # (Lightning: adjust imports without it, tests/test_layering)

    tb = out / "tb"
    trained = {}
    for net in nets:
        tcfg = compose(
            "train",
            [
                f"net={net}",
                f"trainer.max_time={max_time(p.train_minutes)}",
                f"trainer.max_epochs={int(p.max_epochs)}",
                "trainer.enable_model_summary=false",
                f"data.train_sequences={int(p.train_sequences)}",
                f"data.num_frames={int(p.train_frames)}",
                f"data.steps_per_epoch={int(p.steps_per_epoch)}",
                f"data.val_windows={int(p.val_windows)}",
                "progress_bar=none",
                f"threads={int(cfg.threads)}",
                f"logger.save_dir={tb}",
                f"output.dir={out / 'train' / net}",
            ],
        )
        trained[net] = step(f"train_{net}", f"deformnet-train net={net}", train.run, tcfg)
    ckpt = trained[deform_net]["best_checkpoint"] or trained[deform_net]["last_checkpoint"]
    if not ckpt:
        raise RuntimeError(f"deformnet-train net={deform_net} wrote no checkpoint")

    # 3-4. tracking: DLT, rigid, interp, the deformable net
    step(
        "dlt",
        "adjust-triangulate (DLT)",
        triangulate_app.run,
        track_config("dlt", scene, out / "dlt", ckpt, p, cfg),
    )
    for method in ("rigid", "interp", "net", "self"):
        step(
            method,
            f"adjust-track deformation={DEFORMATION.get(method, ckpt)}",
            track_app.run,
            track_config(method, scene, out / method, ckpt, p, cfg),
        )
    tracks = out / primary / "points3d.csv"

    # 5. behavior
    classify = None
    if steps.behavior:
        from deformnet.behavior import predict as cls_app  # (Lightning, as deformnet.train above)

        sessions = step(
            "classify_sessions",
            f"labelled sessions: adjust-simulate, then tracked as the {primary} tracks",
            lambda _: labelled_sessions(out / "classify" / "sessions", p, primary, ckpt, cfg),
            None,
        )
        fill = ["data.interpolate=true"] if primary == "dlt" else []  # DLT's gaps, filled
        data = [f"data.{k}={v}" for k, v in sessions.items()] + fill
        first = session_seeds(p, int(cfg.seed))["train"][0]
        fps_train = scene_fps(out / "classify" / "sessions" / str(first) / "scene")
        fps_here = scene_fps(scene)  # the frame rates: stored in classifier.pt, the track's
        rate_train = [] if fps_train is None else [f"fps={fps_train:g}"]
        rate_here = [] if fps_here is None else [f"fps={fps_here:g}"]
        box_train, box_here = [], []
        if steps.behavior_box:  # the lock-box context
            rig = out / "classify" / "sessions" / str(first) / "scene" / "calibration.toml"
            box_train = [f"mechanisms.calibration={rig}"]  # the labelled sessions' lock box:
            # where the mouse is relative to each mechanism
            box_here = [f"mechanisms.calibration={scene / 'calibration.toml'}"]  # the scene's
        ccfg = compose(
            "classify",
            [
                f"pretrained={ckpt}",
                *data,
                *box_train,
                *rate_train,
                f"data.steps_per_epoch={int(p.classify_steps_per_epoch)}",
                f"trainer.max_time={max_time(p.classify_minutes)}",
                f"trainer.max_epochs={int(p.classify_max_epochs)}",
                # every frame labelled: one MLP (the ensemble is for few labels; five L-BFGS
                # fits on 12000 frames would take the demo several more minutes)
                "head.ensemble=1",
                f"threads={int(cfg.threads)}",
                f"logger.save_dir={tb}",
                f"output.dir={out / 'classify'}",
            ],
        )
        res = step("classify", "deformnet-classify (fine-tune)", cls_app.run, ccfg)
        pcfg = compose(
            "classify",
            [
                "mode=predict",
                f"checkpoint={res['checkpoint']}",
                f"tracks={tracks}",
                *fill,  # DLT: the gaps filled as in training
                *box_here,
                *rate_here,
                f"output.dir={out / 'classify' / 'predict'}",
            ],
        )
        pred = step("classify_predict", "deformnet-classify mode=predict", cls_app.run, pcfg)
        classify = {"dir": str(out / "classify"), "predictions": pred["predictions"]}

    # 6. events
    events = None
    if steps.events:
        ecfg = compose(
            "events",
            [
                f"tracks={tracks}",
                f"calibration={scene / 'calibration.toml'}",
                f"output.dir={out / 'events'}",
            ],
        )
        step("events", "adjust-events", events_app.run, ecfg)
        events = {"dir": str(out / "events")}

    # 7. the report
    record = {
        "scene": str(scene),
        "methods": {m: str(out / m) for m in METHODS},
        "primary": primary,
        "tensorboard": str(tb),
        "train": trained,
        "classify": classify,
        "events": events,
        "timings_s": step.seconds,
        "settings": {
            "preset": name,
            **OmegaConf.to_container(p, resolve=True),
            "seed": seed,
            "nets": nets,
            "deformable_net": deform_net,
            "deformation_checkpoint": str(ckpt),
            "tensorboard": str(tb),
        },
    }
    # the run's record first: `adjust.apps.report.write_report(out, record)` can redo the report
    write_text(out / "demo.json", json.dumps(record, indent=2, default=str) + "\n")
    t0 = time.perf_counter()
    written = write_report(out, record)
    log.info("report written in %.1f s", time.perf_counter() - t0)
    rep = written["report"]
    for note in notes(rep):  # also at the top of the report
        log.warning("%s", note.replace("`", ""))
    return {
        "output_dir": str(out),
        "report": {k: str(v) for k, v in written.items() if k != "report"},
        "tracking": rep["tracking"],
        "timings_s": step.seconds,
        "tensorboard": str(tb),
    }


def table(tracking: dict) -> str:
    """The accuracy table as text."""
    head = f"{'method':<8}{'complete':>9}{'rmse all':>10}{'seen>=2':>9}{'occluded':>10}{'<=5mm':>7}"
    lines = [head, "-" * len(head)]
    for m, r in tracking.items():

        def f(x, d=2):
            return "-" if x is None else f"{x:.{d}f}"

        lines.append(
            f"{m:<8}{f(r['completeness'], 3):>9}{f(r['rmse_all']):>10}{f(r['rmse_seen']):>9}"
            f"{f(r['rmse_occluded']):>10}{f(r['within5_all'], 3):>7}"
        )
    return "\n".join(lines)


def closing_lines(res: dict, minutes: float) -> str:
    """What `adjust-demo` prints at the end: the accuracy table, then where everything is; the
    last lines name the report."""
    return "\n".join(
        [
            "",
            "mousetrack demo: 3D error (mm) against the simulated truth",
            "",
            table(res["tracking"]),
            "",
            f"TensorBoard: tensorboard --logdir {res['tensorboard']}",
            f"Demo finished in {minutes:.1f} min; all outputs: {res['output_dir']}",
            f"Report: {res['report']['markdown']}",
            f"        {res['report']['html']} (self-contained: open it in a browser)",
        ]
    )


@hydra.main(config_path=str(CONF_DIR), config_name="demo", version_base=None)
def _app(cfg: DictConfig) -> None:
    t0 = time.perf_counter()
    res = run_or_exit(run, cfg)
    print(closing_lines(res, (time.perf_counter() - t0) / 60))


def main() -> None:
    _app()


if __name__ == "__main__":
    main()
