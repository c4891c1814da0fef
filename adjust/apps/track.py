"""`adjust-track`: complete 3D tracks from a calibration and a folder of DeepLabCut files.

    adjust-track input.calibration=calibration.toml input.detections=trial_000 output.dir=out \
        [body=mouse|auto] [deformation=runs/train/.../checkpoints/best.ckpt] \
        [solver.constraint=spline|grid] [input.likelihood_threshold=0.6]

Pipeline: load the anipose calibration and one DeepLabCut file per camera (`adjust.io`), get
the rigid body model (a config from ``conf/body/``, or with ``body=auto`` estimated from the
data: robust triangulation, then `BodyModel.from_observations`), then the pose-track
adjustment (`adjust.lsq.adjust_poses`: initialisation, banded Levenberg-Marquardt with the
motion-track constraint; rigid observation, or the learned deformation with ``deformation=``),
then each part's position fused from its own detections and the (deformed) model.

Writes into ``output.dir``:

- ``points3d.csv``: anipose's layout. Per part ``{part}_x,_y,_z`` (mm; never empty: a part no
  camera saw comes from the model moved along the track), ``{part}_error`` (mean reprojection
  error, px, of the reported point over the cameras with an accepted detection of it; NaN when
  none), ``{part}_ncams`` (cameras with an accepted detection, likelihood >= threshold; 0
  allowed), ``{part}_score`` (lowest likelihood among those detections; NaN when ``_ncams`` is
  0); then anipose's axes columns (``M_..`` identity, ``center_..`` 0) and ``fnum``: anipose's
  columns only, so movement's ``from_anipose_file`` reads it as it is.
- ``points3d.extra.csv`` (the sidecar `adjust.io.read_points3d` joins back): ``fnum``, then
  ``pose_rx, pose_ry, pose_rz`` (Rodrigues vector, rad) and ``pose_tx, pose_ty, pose_tz`` (mm)
  of the body model (model -> global), ``pose_sigma_r`` (rad) and ``pose_sigma_t`` (mm) (root
  of the trace of the rotation / translation block of the pose covariance), ``{part}_sigma``
  (mm, root of the trace of the part's 3x3 covariance: its 3D standard error).
- ``summary.json``: settings, iterations, costs, convergence, reprojection error statistics
  (all, per camera, per part), completeness, uncertainty, timings.

The recipe is `adjust.pipeline` (`run(cfg) -> dict`, the plain function behind the Hydra app;
tests call it through Hydra's compose API; it returns the summary); a batch's sessions
(``-m``) go through `adjust.apps.batch.run_session`.
"""

from __future__ import annotations

import logging
import sys

import hydra
from omegaconf import DictConfig

from adjust.apps.batch import in_multirun, run_session
from adjust.apps.common import run_or_exit
from adjust.pipeline import run
from adjust.session import expand_session_globs
from deformnet.paths import CONF_DIR

log = logging.getLogger(__name__)

__all__ = ["main", "run"]


@hydra.main(config_path=str(CONF_DIR), config_name="track", version_base=None)
def _main(cfg: DictConfig) -> dict | None:
    if in_multirun():  # one session of a batch (adjust.apps.batch): records a failure, never raises
        return run_session(cfg, run=run)
    run_or_exit(run, cfg)


def main() -> None:
    """Console script: ``input.session=glob(PATTERN)`` -> the matching folders, then Hydra."""
    try:
        sys.argv = expand_session_globs(sys.argv)
    except ValueError as exc:
        log.error("%s", exc)
        raise SystemExit(2) from None
    _main()


if __name__ == "__main__":  # pragma: no cover
    main()
