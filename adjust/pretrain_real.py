"""Build the shipped deformation net from real motion: ``python -m adjust.pretrain_real``.

The net (`deformnet.nets.PartTransformer`, conf/net/parts.yaml: parts identified by their rest
coordinates, so one set of weights serves any skeleton) learns from tokens of tracked,
re-filmed real motion what the tracker asks of it:

1. frames ``--frames`` (default 0-2399; never the last third, 2400-3599, which
   `benchmarks/real_motion.py` tests on) of the real mouse's 3D motion
   (``shared/data/real-mouse-motion-3d/poses3d.csv``) are filmed through simulated rigs
   (`adjust.scene.motion`: rigs of 2, 3 and 4 cameras around the floor the paws define, the
   scene detector model with occlusion by the body, dropout bursts, swaps, outliers) with
   detector seeds and part subsets (the paper's 8, 22, all 34 parts) listed in `SCENES`;
2. each scene is tracked by ``adjust-track`` with its defaults (through its ``run(cfg)``),
   whose ``tokens.npz`` pairs the rigid model's points with the measured deformed points;
3. `deformnet.pretrained.fit.fit_sessions` trains the net on all of them (a fixed number of
   steps, fixed seeds, one thread), and the weights are exported without any training state
   (`DeformationModel.save`); their SHA-256 is printed. The targets (``--targets``, `TARGETS`):
   ``truth`` (shipped): the filmed motion's true position of every part of the mid frame,
   measured or not, half the windows with the recording's own missing part-frames only
   (`RECIPE.real_masks`): the tracker asks the net for the parts a recording did not
   measure, often over long occlusions (``deform.beyond_window=net``); ``measured``:
   `deformation=self`'s self-supervised objective (the mid frame's measured parts).

Choices (`RECIPE`) were made with frames 1200-2199 held out of training (``--train-frames
0-1200 --eval-frames 1200-2200``: the same tracks, the net trained on their first 1200 frames
and judged on the validation segment's tokens; then ``benchmarks/real_motion.py --split
val``); the shipped net is trained on 0-2399.

    python -m adjust.pretrain_real [--frames 0-2400] [--steps N] [--seed 0] [--out PATH]
        [--work DIR] [--data poses3d.csv] [--scenes 3x8s1,2x34s2,...] [--report JSON]
    # choices: train on 0-1199 of the same tracks, evaluate on the validation segment
    python -m adjust.pretrain_real --train-frames 0-1200 --eval-frames 1200-2200 --out X.pt \
        --report runs/benchmarks/pretrain_real_heldout_val.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from adjust.pipeline import run as track_run
from adjust.scene.motion import MOTION_FEET, film_part_set, floor_frame, load_motion
from deformnet.confutil import compose
from deformnet.deformation import DeformationModel
from deformnet.heldout import heldout_errors
from deformnet.paths import real_mouse_motion_dir
from deformnet.pretrained import DEFAULT_CHECKPOINT
from deformnet.pretrained.build import weights_sha256
from deformnet.pretrained.fit import FitConfig, fit_sessions
from deformnet.sessions import TOKENS_FILE, SessionTokens
from deformnet.threads import torch_threads

log = logging.getLogger("adjust.pretrain_real")

__all__ = ["SceneSpec", "SCENES", "RECIPE", "build", "track_key", "track_scene", "main"]

DATA = real_mouse_motion_dir() / "poses3d.csv"
#: frames the shipped net trains on; the last third (2400-3599) is never trained on
TRAIN_FRAMES = (0, 2400)
HELD_OUT_START = 2400
SEED = 0
TARGET_CHOICES = ("measured", "truth")
#: the training targets (`build`): the filmed motion's true positions of every part of the mid
#: frame (validation tracks, 3 cameras, with deform.beyond_window=net: occluded 0.973x / 0.745x
#: the defaults' on 8 / 34 parts; the measured targets' net 1.003x on 8 parts)
TARGETS = "truth"


@dataclass(frozen=True)
class SceneSpec:
    """One filmed scene: a rig of `cameras`, the `parts`-part set, a detector `seed`."""

    cameras: int
    parts: int
    seed: int

    @property
    def name(self) -> str:
        return f"{self.cameras}x{self.parts}s{self.seed}"

    @classmethod
    def parse(cls, text: str) -> SceneSpec:
        """``3x8s1`` -> 3 cameras, 8 parts, seed 1."""
        try:
            c, rest = text.split("x")
            p, s = rest.split("s")
            return cls(int(c), int(p), int(s))
        except ValueError:
            raise ValueError(f"a scene is CAMERASxPARTSsSEED (e.g. 3x8s1), got {text!r}") from None


#: the scenes the shipped net learns from (detector seeds 1.. : none is a benchmark's seed 0)
SCENES = (
    SceneSpec(3, 8, 1),
    SceneSpec(2, 8, 2),
    SceneSpec(4, 8, 3),
    SceneSpec(3, 22, 4),
    SceneSpec(3, 34, 5),
    SceneSpec(4, 34, 6),
)

#: the recipe (chosen on the validation segment, see the module docstring)
RECIPE = FitConfig(
    net={
        "_target_": "deformnet.nets.PartTransformer",
        "half_window": 12,
        "d_model": 64,
        "heads": 4,
        "layers": 2,
        "ff": 128,
        "hidden": 128,
        # on top of the interpolation prior (validation tracks: occluded 0.964x / 0.986x the
        # defaults' with it, 0.980x / 1.007x without; 8 / 34 parts)
        "prior_residual": True,
    },  # fmt: skip
    steps=1500,
    batch_size=128,
    lr=2e-3,
    real_masks=0.5,  # half the windows with the recording's own missing part-frames only
)


#: the track settings that do not change the tokens (left out of the cache's key)
UNKEYED = ("input.calibration", "input.detections", "output.dir", "progress", "threads")


#: the recipe's tracking beside adjust-track's defaults: the shipped net was trained on interp's
#: tracks with the single views at their fused points from a robust rigid start, without the
#: world prior or the gated view pairs (``deform.anchors=rays``, ``deform.rigid_robust=none``,
#: ``deform.world_prior`` and ``deform.gate_pairs``, the defaults since stops 49, 50 and 52,
#: came after it), so `make pretrained` still rebuilds the shipped file
RECIPE_TRACK = (
    "deform.anchors=fused",
    "deform.rigid_robust=cauchy",
    "deform.world_prior=false",
    "deform.gate_pairs=false",
)


def track_config(scene: Path, out: Path, overrides=()) -> DictConfig:
    """``adjust-track``'s configuration for a scene folder: its defaults with `RECIPE_TRACK`
    (and `overrides`), one thread."""
    return compose("track", [
        f"input.calibration={scene / 'calibration.toml'}",
        f"input.detections={scene / 'detections'}",
        f"output.dir={out}", "progress=false", "threads=1", *RECIPE_TRACK, *overrides,
    ])  # fmt: skip


def track_key(scene: Path, overrides=()) -> str:
    """The tracks' cache key: SHA-256 (12 hex digits) of adjust-track's resolved settings (all
    but `UNKEYED`) and of the scene's calibration and detection files, so a changed default
    (e.g. ``deform.single_views``) or a re-filmed scene never reuses stale tokens. The
    tracker's code is not in the key: after a change of code that keeps the settings, use a
    fresh ``--work``."""
    cfg = OmegaConf.to_container(track_config(scene, Path("-"), overrides), resolve=True)
    for dotted in UNKEYED:
        *head, last = dotted.split(".")
        node = cfg
        for k in head:
            node = node[k]
        node.pop(last, None)
    h = hashlib.sha256(json.dumps(cfg, sort_keys=True, default=str).encode())
    files = [scene / "calibration.toml", *sorted((scene / "detections").iterdir())]
    for f in files:
        h.update(f.name.encode() + b"\0" + hashlib.sha256(f.read_bytes()).digest())
    return h.hexdigest()[:12]


def track_scene(scene: Path, out: Path) -> Path:
    """``adjust-track`` (`track_config`) on a scene folder (through its ``run(cfg)``);
    returns its tokens.npz (cached: kept if it is there; `scene_tokens` keys `out` by
    `track_key`)."""

    tokens = out / TOKENS_FILE
    if tokens.is_file():
        return tokens
    track_run(track_config(scene, out))
    if not tokens.is_file():
        raise ValueError(f"adjust-track wrote no {TOKENS_FILE} into {out}")
    return tokens


def scene_tokens(data: Path, frames: tuple[int, int], scenes, work: Path) -> list[SessionTokens]:
    """Film and track each scene of `frames` [start, stop) of the recording (cached in
    `work`); returns their tokens (`scene_truths`: the filmed motion's true positions)."""
    start, stop = frames
    if stop > HELD_OUT_START:
        raise ValueError(
            f"frames {start}-{stop}: the shipped net never trains on frames from "
            f"{HELD_OUT_START} (the benchmark's held-out third)"
        )
    points, parts = load_motion(data)
    if not 0 <= start < stop <= len(points):
        raise ValueError(f"frames {start}-{stop} are not inside {data} ({len(points)} frames)")
    floor = floor_frame(points, parts, MOTION_FEET)
    out = []
    for spec in scenes:
        key = f"f{start}-{stop}_{spec.name}"
        scene = work / "scenes" / key
        t0 = time.perf_counter()
        if not (scene / "truth.npz").is_file():
            film_part_set(scene, points[start:stop], parts, floor, spec.cameras, spec.parts,
                          seed=spec.seed)  # fmt: skip
        run_dir = work / "track" / f"{key}_{track_key(scene)}"
        tok = SessionTokens.load(track_scene(scene, run_dir))
        log.info("scene %s: %d frames, %d parts, %.0f%% of part-frames measured, tracks %s "
                 "(%.0f s)", key, tok.num_frames, len(tok.parts), 100 * tok.observed.mean(),
                 run_dir.name, time.perf_counter() - t0)  # fmt: skip
        out.append(tok)
    return out


def scene_truths(frames: tuple[int, int], scenes, work: Path, tokens) -> list[np.ndarray]:
    """The true positions (T, K, 3) mm of the scenes `scene_tokens` filmed into `work`, in
    their tokens' parts and frames."""
    start, stop = frames
    return [scene_truth(work / "scenes" / f"f{start}-{stop}_{spec.name}" / "truth.npz", tok)
            for spec, tok in zip(scenes, tokens)]  # fmt: skip


def scene_truth(path: Path, tok: SessionTokens) -> np.ndarray:
    """A filmed scene's true positions (T, K, 3) mm in the order of its tokens' parts."""
    tr = np.load(path)
    names = [str(p) for p in tr["parts"]]
    missing = [p for p in tok.parts if p not in names]
    if missing or tr["points"].shape[0] != tok.num_frames:
        raise ValueError(
            f"{path}: its truth ({tr['points'].shape[0]} frames, parts {names}) does not "
            f"cover the tokens ({tok.num_frames} frames, {missing} missing)"
        )
    return np.asarray(tr["points"], np.float64)[:, [names.index(p) for p in tok.parts]]


def token_slice(tok: SessionTokens, start: int, stop: int, offset: int) -> SessionTokens:
    """Frames [start, stop) of the recording (tokens of a track that starts at `offset`)."""
    a, b = start - offset, stop - offset
    if not 0 <= a < b <= tok.num_frames:
        raise ValueError(f"{tok.source}: frames {start}-{stop} not in its {tok.num_frames} frames")
    return replace(tok, rigid=tok.rigid[a:b], deformed=tok.deformed[a:b],
                   observed=tok.observed[a:b])  # fmt: skip


def evaluate(model: DeformationModel, tokens, specs) -> list[dict]:
    """The net against offset interpolation (interp's within-window model) and the rigid
    model on masked windows of each session's tokens (`deformnet.heldout.heldout_errors`:
    the mid frame's measured parts hidden from every predictor), RMSE mm over all parts."""
    rows = []
    for tok, spec in zip(tokens, specs):
        h = heldout_errors(model.for_body(tok.body_model()), tok)
        n = np.asarray(h["targets"], dtype=float)
        rig = np.asarray(h["rigid_mm"], dtype=float)
        ok = n > 0
        rigid_all = float(np.sqrt(np.sum(n[ok] * rig[ok] ** 2) / n[ok].sum()))
        rows.append({"scene": spec.name, "net_mm": round(h["net_all_mm"], 3),
                     "interp_mm": round(h["interp_all_mm"], 3),
                     "linear_mm": round(h["linear_all_mm"], 3), "rigid_mm": round(rigid_all, 3),
                     "ratio_interp": round(h["net_all_mm"] / h["interp_all_mm"], 3)})  # fmt: skip
        log.info("held-out %s: net %.2f mm, interp %.2f, linear %.2f, rigid %.2f", spec.name,
                 h["net_all_mm"], h["interp_all_mm"], h["linear_all_mm"], rigid_all)  # fmt: skip
    return rows


def build(
    frames: tuple[int, int] = TRAIN_FRAMES,
    scenes=SCENES,
    recipe: FitConfig = RECIPE,
    seed: int = SEED,
    out: Path | None = None,
    work: Path | None = None,
    data: Path = DATA,
    train_frames: tuple[int, int] | None = None,
    eval_frames: tuple[int, int] | None = None,
    targets: str = TARGETS,
) -> dict:
    """Film and track `frames` of the recording in each scene, train on `train_frames` of
    the tracks (default: all of `frames`), export; with `eval_frames` (frames of the tracks
    not trained on, e.g. the validation segment 1200-2200 when training on 0-1200) the net is
    evaluated on them (`evaluate`). targets: ``measured`` (`deformation=self`'s objective: the
    mid frame's measured parts) or ``truth`` (the filmed motion's true positions of every part
    of the mid frame, `deformnet.pretrained.fit.TruthWindowBank`). Returns {"checkpoint",
    "sha256", "facts"}."""
    if targets not in TARGET_CHOICES:
        raise ValueError(f"targets must be one of {', '.join(TARGET_CHOICES)}, got {targets!r}")
    out = Path(out) if out is not None else DEFAULT_CHECKPOINT
    train_frames = tuple(frames) if train_frames is None else tuple(train_frames)
    if eval_frames is not None and max(train_frames[0], eval_frames[0]) < min(
        train_frames[1], eval_frames[1]
    ):
        raise ValueError(f"eval frames {eval_frames} overlap the training frames {train_frames}")
    with tempfile.TemporaryDirectory() as tmp, torch_threads(1):
        wdir = Path(work) if work is not None else Path(tmp)
        tokens = scene_tokens(Path(data), frames, scenes, wdir)
        train = [token_slice(t, *train_frames, frames[0]) for t in tokens]
        truths = None
        if targets == "truth":
            a, b = train_frames[0] - frames[0], train_frames[1] - frames[0]
            truths = [t[a:b] for t in scene_truths(frames, scenes, wdir, tokens)]
        t0 = time.perf_counter()
        model, facts = fit_sessions(train, recipe, seed, truths=truths)
        facts["train_s"] = round(time.perf_counter() - t0, 1)
        out.parent.mkdir(parents=True, exist_ok=True)
        model.save(out)
        if eval_frames is not None:
            held = [token_slice(t, *eval_frames, frames[0]) for t in tokens]
            facts["heldout"] = evaluate(model, held, scenes)
            facts["eval_frames"] = list(eval_frames)
    sha = weights_sha256(DeformationModel.from_checkpoint(out))
    facts.update(frames=list(frames), train_frames=list(train_frames),
                 scenes=[s.name for s in scenes], seed=int(seed), targets=targets,
                 real_masks=recipe.real_masks)  # fmt: skip
    return {"checkpoint": str(out), "sha256": sha, "facts": facts}


def _frames(text: str) -> tuple[int, int]:
    a, b = text.split("-")
    return int(a), int(b)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=_frames, default=TRAIN_FRAMES, help="START-STOP (0-2400)")
    ap.add_argument(
        "--train-frames",
        type=_frames,
        default=None,
        help="train on these frames of the tracks only (default: all of --frames)",
    )
    ap.add_argument(
        "--eval-frames",
        type=_frames,
        default=None,
        help="evaluate on these frames of the tracks (not trained on)",
    )
    ap.add_argument("--steps", type=int, default=RECIPE.steps)
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--scenes", default=",".join(s.name for s in SCENES),
                    help="CAMERASxPARTSsSEED,... (e.g. 3x8s1,3x34s5)")  # fmt: skip
    ap.add_argument("--out", default=None, help=f"the checkpoint (default {DEFAULT_CHECKPOINT})")
    ap.add_argument("--work", default=None, help="keep the scenes and tracks here (a cache)")
    ap.add_argument("--data", default=str(DATA))
    ap.add_argument("--report", default=None, help="also write the result's JSON here")
    ap.add_argument(
        "--targets",
        choices=TARGET_CHOICES,
        default=TARGETS,
        help="the mid frame's measured parts or the filmed motion's truth",
    )
    ap.add_argument(
        "--real-masks",
        type=float,
        default=RECIPE.real_masks,
        help="with --targets truth: the windows with the recording's own masks only",
    )
    ap.add_argument(
        "--net",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a net argument of the recipe (e.g. prior_residual=true)",
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    scenes = [SceneSpec.parse(s) for s in args.scenes.split(",") if s]
    net = dict(RECIPE.net)
    for item in args.net:
        key, _, value = item.partition("=")
        net[key] = json.loads(value.lower() if value.lower() in ("true", "false") else value)
    recipe = replace(RECIPE, steps=int(args.steps), net=net, real_masks=float(args.real_masks))
    res = build(args.frames, scenes, recipe, args.seed,
                args.out, args.work, Path(args.data), args.train_frames,
                args.eval_frames, args.targets)  # fmt: skip
    text = json.dumps(res, indent=2)
    print(text)
    if args.report:
        Path(args.report).parent.mkdir(parents=True, exist_ok=True)
        Path(args.report).write_text(text + "\n", encoding="utf-8")
    return res


if __name__ == "__main__":
    main()
