"""Where the project's Hydra configs live, and where a Hydra app writes its outputs."""

from __future__ import annotations

from pathlib import Path

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def output_dir(cfg) -> Path:
    """The folder a Hydra app writes into.

    `cfg.output.dir` when it is set (tests and users pass it), else Hydra's run folder
    (`hydra.runtime.output_dir`, under `runs/`). Never the working directory.
    """
    out = cfg.get("output") if hasattr(cfg, "get") else None
    given = out.get("dir") if out is not None else None
    if given:
        path = Path(str(given))
    else:
        from hydra.core.hydra_config import HydraConfig

        if not HydraConfig.initialized():
            raise ValueError(
                "no output folder: set output.dir=... (Hydra's run folder exists only under "
                "@hydra.main)"
            )
        path = Path(HydraConfig.get().runtime.output_dir)
    path.mkdir(parents=True, exist_ok=True)
    return path
