"""`adjust-simulate`: simulate a mouse (deformnet.sim), film it with a camera rig, and write a
scene folder exactly as a real user has one (``calibration.toml``, ``detections/<camera>.csv``)
plus ``truth.npz``.

    adjust-simulate num_frames=3000 seed=1 output.dir=scenes/s1 detector.dropout_rate=0.3

`run(cfg) -> dict` is the plain function behind the Hydra app (tests call it through Hydra's
compose API).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from adjust.apps.common import run_or_exit
from adjust.scene import default_rig, simulate_scene, write_scene
from deformnet.atomic import write_text
from deformnet.body import BodyModel
from deformnet.confutil import int_setting
from deformnet.paths import CONF_DIR, output_dir
from deformnet.sim import simulate

log = logging.getLogger(__name__)

#: detector stream of the scene's seed (the simulator uses the seed itself)
DETECTOR_STREAM = 1


def _simulate(cfg: DictConfig, body: BodyModel, num_frames: int, seed: int) -> Any:
    return simulate(cfg.sim, num_frames=num_frames, seed=seed, body=body)


def run(cfg: DictConfig) -> dict:
    """Simulate, detect, write the scene folder; returns its paths and the measured fractions."""
    num_frames = int_setting(cfg, "num_frames", 1)
    seed = int_setting(cfg, "seed", 0)
    body = BodyModel.from_config(cfg.body)
    sim = _simulate(cfg, body, num_frames, seed)
    cameras = default_rig(cfg, arena_size=getattr(sim, "arena_size", None))
    det = simulate_scene(sim, cameras, cfg.detector, seed=(seed, DETECTOR_STREAM))
    out = output_dir(cfg)
    fractions = det.fractions()
    result = write_scene(
        out,
        sim,
        cameras,
        det,
        scorer=str(cfg.get("scorer") or "DLC_mousetrack_sim"),
        metadata={"seed": seed},
    )
    summary = {
        "num_frames": num_frames,
        "seed": seed,
        "cameras": [c.name for c in cameras],
        "parts": list(det.parts),
        "threshold": det.threshold,
        "fractions": fractions,
        "nviews_per_part": {
            p: np.bincount(det.nviews[:, k], minlength=len(cameras) + 1).tolist()
            for k, p in enumerate(det.parts)
        },
        "visible_per_camera": {
            c.name: float(det.visible[..., i].mean()) for i, c in enumerate(cameras)
        },
    }
    write_text(out / "scene.json", json.dumps(summary, indent=2) + "\n")
    log.info(
        "scene %s: %d frames, cameras %s; part-frames seen by >= 2 cameras %.1f%%, by 1 %.1f%%, "
        "by none %.1f%% (likelihood >= %.2f, correct)",
        out,
        num_frames,
        ", ".join(c.name for c in cameras),
        100 * fractions["ge2_views"],
        100 * fractions["one_view"],
        100 * fractions["no_view"],
        det.threshold,
    )
    return {
        **result,
        "summary": out / "scene.json",
        "fractions": fractions,
        "cameras": summary["cameras"],
        "parts": summary["parts"],
        "num_frames": num_frames,
    }


@hydra.main(config_path=str(CONF_DIR), config_name="scene", version_base=None)
def _app(cfg: DictConfig) -> None:
    log.debug("config:\n%s", OmegaConf.to_yaml(cfg))
    res = run_or_exit(run, cfg)  # bad input or config: one line, exit 2
    f = res["fractions"]
    print(
        f"scene written to {Path(res['dir']).resolve()}\n"
        f"part-frames seen by >= 2 cameras: {f['ge2_views']:.3f}, by 1: {f['one_view']:.3f}, "
        f"by none: {f['no_view']:.3f}"
    )


def main() -> None:
    _app()


if __name__ == "__main__":
    main()
