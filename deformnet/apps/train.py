"""`deformnet-train`: train a deformation net; the Hydra app over `deformnet.train.run(cfg)`.

deformnet-train net=transformer                 # one net, on simulated mice
deformnet-train data=sessions data.sessions=[runs/track/a,runs/track/b]   # a lab's own
    [pretrained=default|CKPT]                   # recordings (self-supervised), fine-tuned
deformnet-train -m net=lstm,transformer         # both, sequentially (multirun)
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from deformnet.apprun import run_app
from deformnet.paths import CONF_DIR
from deformnet.quiet import quiet_lightning
from deformnet.train import run

__all__ = ["main"]


def _quiet_run(cfg: DictConfig) -> dict:
    with quiet_lightning():  # no Lightning tips or deprecations on the console
        return run(cfg)


@hydra.main(config_path=str(CONF_DIR), config_name="train", version_base=None)
def main(cfg: DictConfig) -> None:
    # one error handler (deformnet.apprun): bad input or config (a refused checkpoint...), an
    # unusable or busy output.dir: one line, exit 2; Ctrl-C: exit 130
    run_app(_quiet_run, cfg)


if __name__ == "__main__":
    main()
