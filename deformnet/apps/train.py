"""`deformnet-train`: train a deformation net; the Hydra app over `deformnet.train.run(cfg)`.

deformnet-train net=transformer                 # one net, on simulated mice
deformnet-train data=sessions data.sessions=[runs/track/a,runs/track/b]   # a lab's own
    [pretrained=default|CKPT]                   # recordings (self-supervised), fine-tuned
deformnet-train -m net=lstm,transformer         # both, sequentially (multirun)
"""

from __future__ import annotations

from deformnet.apprun import hydra_app
from deformnet.train import run

__all__ = ["main"]

# one error handler (deformnet.apprun): bad input or config (a refused checkpoint...), an
# unusable or busy output.dir: one line, exit 2; Ctrl-C: exit 130; no Lightning tips
main = hydra_app(run, "train", quiet=True)


if __name__ == "__main__":
    main()
