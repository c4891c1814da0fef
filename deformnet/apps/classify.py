"""`deformnet-classify`: fit a behavior classifier on labelled sessions (mode=train), or label a
track with one (mode=predict); the Hydra app over `deformnet.behavior.predict.run(cfg)`.

    deformnet-classify tracks=[s1/points3d.csv,s2/points3d.csv] labels=[s1.csv,s2.csv]
    deformnet-classify mode=predict checkpoint=OUT/classifier.pt tracks=points3d.csv
"""

from __future__ import annotations

from deformnet.apprun import hydra_app
from deformnet.behavior.predict import run

__all__ = ["main"]

# one error handler (deformnet.apprun): bad input or config (one line naming the file or row),
# an unusable or busy output.dir: exit 2; Ctrl-C: exit 130; no Lightning tips on the console
main = hydra_app(run, "classify", quiet=True)


if __name__ == "__main__":
    main()
