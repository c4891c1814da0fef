"""`deformnet-classify`: fit a behavior classifier on labelled sessions (mode=train), or label a
track with one (mode=predict); the Hydra app over `deformnet.behavior.predict.run(cfg)`.

    deformnet-classify tracks=[s1/points3d.csv,s2/points3d.csv] labels=[s1.csv,s2.csv]
    deformnet-classify mode=predict checkpoint=OUT/classifier.pt tracks=points3d.csv
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from deformnet.apprun import run_app
from deformnet.behavior.predict import run
from deformnet.paths import CONF_DIR
from deformnet.quiet import quiet_lightning

__all__ = ["main"]


def _quiet_run(cfg: DictConfig) -> dict:
    with quiet_lightning():  # no Lightning tips or deprecations on the console
        return run(cfg)


@hydra.main(config_path=str(CONF_DIR), config_name="classify", version_base=None)
def main(cfg: DictConfig) -> None:
    # one error handler (deformnet.apprun): bad input or config (one line naming the file or
    # row), an unusable or busy output.dir: exit 2; Ctrl-C: exit 130
    run_app(_quiet_run, cfg)


if __name__ == "__main__":
    main()
