"""Rebuild the simulator-only LSTM net bit for bit: ``python -m deformnet.pretrained.build``.

(The earlier default, ``mouse_lstm_small.pt``, `deformnet.pretrained.SIM_CHECKPOINT`; the
shipped default is now built from real motion by `adjust.pretrain_real`.)

`deformnet-train` on the default simulator (Table 1 mouse) with net=lstm_small, a fixed number
of optimiser steps (not a time budget, which would depend on the machine), one thread and
Lightning's deterministic mode; the final weights are exported without Lightning state
(`DeformationModel.save`). The same seed gives the same weights: the script prints their
SHA-256 (over the tensors' bytes), which the shipped file's matches on the kind of CPU that
built it (another CPU's float kernels round differently over 3000 steps: other bits, a net as
good; the slow test checks either).

    python -m deformnet.pretrained.build [--steps 3000] [--seed 0] [--out PATH] [--work DIR]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import tempfile
from pathlib import Path

from deformnet.confutil import compose
from deformnet.deformation import DeformationModel
from deformnet.pretrained import SIM_CHECKPOINT

log = logging.getLogger("deformnet.pretrained.build")

STEPS = 3000
SEED = 0


def overrides(steps: int, seed: int, work: Path) -> list[str]:
    """The deformnet-train overrides of the shipped net."""
    epochs = max(1, -(-int(steps) // 100))
    return [
        "net=lstm_small",
        "half_window=16",
        f"seed={int(seed)}",
        "threads=1",
        "logger=none",
        "progress_bar=none",
        "trainer.max_time=null",
        f"trainer.max_steps={int(steps)}",
        f"trainer.max_epochs={epochs}",
        "trainer.deterministic=true",
        "trainer.enable_model_summary=false",
        "data.steps_per_epoch=100",
        "data.train_sequences=16",
        "data.num_frames=3000",
        f"output.dir={work}",
    ]


def weights_sha256(model) -> str:
    """SHA-256 over the state dict's names and tensor bytes (in order)."""
    h = hashlib.sha256()
    for k, v in model.state_dict().items():
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def build(steps: int = STEPS, seed: int = SEED, out: Path | None = None, work=None) -> dict:
    """Train and export; returns {"checkpoint", "sha256", "metrics"}."""
    # Lightning, on demand: adjust.pretrain_real imports weights_sha256 from here without it
    from deformnet.train import run

    out = Path(out) if out is not None else SIM_CHECKPOINT
    with tempfile.TemporaryDirectory() as tmp:
        wdir = Path(work) if work is not None else Path(tmp)
        res = run(compose("train", overrides(steps, seed, wdir)))
        if not res.get("last_checkpoint"):
            raise RuntimeError("deformnet-train wrote no checkpoint")
        model = DeformationModel.from_checkpoint(res["last_checkpoint"])
        model.save(out)
    sha = weights_sha256(DeformationModel.from_checkpoint(out))
    return {"checkpoint": str(out), "sha256": sha, "metrics": res.get("metrics", {})}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=STEPS)
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--out", default=None)
    ap.add_argument("--work", default=None, help="keep deformnet-train's folder here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    res = build(args.steps, args.seed, args.out, args.work)
    print(json.dumps(res, indent=2))
    return res


if __name__ == "__main__":
    main()
