"""`deformnet-simulate`: simulate a deformable mouse, write ``sim.npz`` and a figure.

    deformnet-simulate num_frames=30000 seed=3 sim.arena.size=[400,400] output.dir=runs/mysim

`run(cfg)` does the work (tests call it through Hydra's compose API); `main` is the Hydra app
(pyproject.toml's console script, through `deformnet.entry`).
"""

from __future__ import annotations

import json
import logging

import hydra
import numpy as np
from omegaconf import DictConfig

from deformnet.apprun import run_app
from deformnet.body import BodyModel
from deformnet.confutil import int_setting
from deformnet.paths import CONF_DIR, output_dir
from deformnet.sim.dataset import save_sim
from deformnet.sim.engine import simulate
from deformnet.sim.plot import plot_sim, track_xy

log = logging.getLogger(__name__)


def run(cfg: DictConfig) -> dict:
    """Simulate from the app config; write ``sim.npz`` and ``sim.png`` into the output folder.

    Returns ``{"data": path, "figure": path, "num_frames", "seed", "duration_s",
    "behavior_fractions": {name: fraction}, "observed_fraction", "mean_speed_mm_s"}``.
    """
    num_frames = int_setting(cfg, "num_frames", 1)
    seed = int_setting(cfg, "seed", 0)
    body = BodyModel.from_config(cfg.body)
    data = simulate(cfg.sim, num_frames=num_frames, seed=seed, body=body)
    out = output_dir(cfg)
    npz = save_sim(out / "sim.npz", data)
    png = plot_sim(out / "sim.png", data)
    xy = track_xy(data)
    speed = np.hypot(*np.diff(xy, axis=0).T) * data.fps if num_frames > 1 else np.zeros(1)
    fractions = np.bincount(data.labels, minlength=len(data.behaviors)) / num_frames
    result = {
        "data": str(npz),
        "figure": str(png),
        "num_frames": num_frames,
        "seed": seed,
        "duration_s": num_frames / data.fps,
        "behavior_fractions": {b: float(f) for b, f in zip(data.behaviors, fractions)},
        "observed_fraction": float(data.observed.mean()),
        "mean_speed_mm_s": float(speed.mean()),
    }
    log.info("wrote %s and %s", npz, png)
    return result


@hydra.main(config_path=str(CONF_DIR), config_name="simulate", version_base=None)
def _app(cfg: DictConfig) -> None:
    print(json.dumps(run_app(run, cfg), indent=2))  # one error handler: bad input is exit 2


def main() -> None:
    _app()


if __name__ == "__main__":
    main()
