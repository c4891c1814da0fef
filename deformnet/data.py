"""Training data for the deformation nets: simulated sequences -> masked token windows.

`DeformDataModule` (a LightningDataModule) simulates sequences with `deformnet.sim` (or loads
simulator files, or uses the small built-in `toy_sequence` generator) and serves the masked
windows of `deformnet.windows` (which needs no Lightning; its names are re-exported here).
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import lightning as L
import numpy as np
from torch.utils.data import DataLoader

from deformnet import windows
from deformnet.body import BodyModel
from deformnet.sim import simulate
from deformnet.sim.dataset import load_sim
from deformnet.windows import (  # noqa: F401  (re-exported)
    Augment,
    FixedWindowBatches,
    MaskConfig,
    RandomWindowBatches,
    SequenceArrays,
    WindowBank,
    gap_masks,
    make_masks,
    mirror_asymmetry,
    mirror_permutation,
    toy_sequence,
)

log = logging.getLogger(__name__)

__all__ = [*windows.__all__, "DeformDataModule", "load_sequences", "simulate_sequences"]


def simulate_sequences(
    sim_cfg: Any, body: BodyModel, num_frames: int, seeds: Sequence[int]
) -> list[SequenceArrays]:
    """Simulate one sequence per seed with `deformnet.sim.simulate` (the simulator is
    training's input, not the windows': `deformnet.windows` imports no simulator)."""
    out = []
    for s in seeds:
        data = simulate(sim_cfg, num_frames=int(num_frames), seed=int(s), body=body)
        out.append(SequenceArrays.of(data))
    return out


def load_sequences(paths: Sequence[str | os.PathLike]) -> list[SequenceArrays]:
    """Load simulator files with `deformnet.sim.dataset.load_sim`."""
    return [SequenceArrays.of(load_sim(p)) for p in paths]


def _identity(x):
    return x


# --------------------------------------------------------------------------------------------
# Lightning data module
# --------------------------------------------------------------------------------------------
class DeformDataModule(L.LightningDataModule):
    """Simulated training / validation windows.

    source: "sim" (simulate with deformnet.sim from `sim` config and seeds), "files" (load
    `train_files` / `val_files` with deformnet.sim.dataset.load_sim), "toy" (`toy_sequence`)
    or "arrays" (given `train_data` / `val_data` sequences, e.g. a lab's session tokens,
    `deformnet.sessions`).
    Train and validation sequences use disjoint seeds (seed + i, seed + 10_000 + i).
    """

    def __init__(
        self,
        body: BodyModel,
        half_window: int = 16,
        step: int = 1,
        source: str = "sim",
        sim: Any = None,
        train_sequences: int = 4,
        val_sequences: int = 1,
        num_frames: int = 3000,
        train_files: Sequence[str] | None = None,
        val_files: Sequence[str] | None = None,
        seed: int = 0,
        batch_size: int = 256,
        steps_per_epoch: int = 100,
        val_windows: int = 2048,
        noise_mm: float = 0.0,
        masking: Mapping[str, Any] | MaskConfig | None = None,
        augment: Mapping[str, Any] | Augment | None = None,
        train_data: Sequence[SequenceArrays] | None = None,
        val_data: Sequence[SequenceArrays] | None = None,
    ) -> None:
        super().__init__()
        if source not in ("sim", "files", "toy", "arrays"):
            raise ValueError(
                f"data.source must be 'sim', 'files', 'toy' or 'arrays', got '{source}'"
            )
        if source == "arrays" and (not train_data or not val_data):
            raise ValueError("data.source=arrays needs train_data and val_data sequences")
        self.train_data, self.val_data = list(train_data or []), list(val_data or [])
        self.body = body
        self.half_window = int(half_window)
        self.step = int(step)
        self.source = source
        self.sim_cfg = sim
        self.train_sequences, self.val_sequences = int(train_sequences), int(val_sequences)
        self.num_frames = int(num_frames)
        self.train_files = list(train_files or [])
        self.val_files = list(val_files or [])
        self.seed = int(seed)
        self.batch_size, self.steps_per_epoch = int(batch_size), int(steps_per_epoch)
        self.val_windows = int(val_windows)
        self.noise_mm = float(noise_mm)
        self.masking = MaskConfig.from_any(masking)
        self.augment = Augment.from_any(augment)
        self.mirror_perm = mirror_permutation(body.parts) if self.augment.mirror > 0 else None
        if self.augment.mirror > 0 and self.mirror_perm is None:
            log.info(
                "data.augment.mirror: no left/right part pairs among %s; no mirroring",
                list(body.parts),
            )
        elif self.mirror_perm is not None:
            pts = np.asarray(body.points, dtype=np.float64)
            asym = mirror_asymmetry(pts, self.mirror_perm)
            size = float(np.sqrt(((pts - pts.mean(0)) ** 2).sum(-1).mean()))
            if asym > 0.1 * size:  # its mirror image is another body, not this one
                log.info(
                    "data.augment.mirror: the body model is %.1f mm rms from its mirror image "
                    "(%.0f%% of its size); no mirroring", asym, 100 * asym / size,
                )  # fmt: skip
                self.mirror_perm = None
        self.train_set: RandomWindowBatches | None = None
        self.val_set: FixedWindowBatches | None = None

    def sequences(self, split: str) -> list[SequenceArrays]:
        if self.source == "arrays":
            return self.train_data if split == "train" else self.val_data
        count = self.train_sequences if split == "train" else self.val_sequences
        base = self.seed + (0 if split == "train" else 10_000)
        seeds = [base + i for i in range(count)]
        if self.source == "toy":
            return [toy_sequence(self.body, self.num_frames, s) for s in seeds]
        if self.source == "files":
            files = self.train_files if split == "train" else self.val_files
            if not files:
                raise ValueError(f"data.source=files needs data.{split}_files")
            return load_sequences(files)
        return simulate_sequences(self.sim_cfg, self.body, self.num_frames, seeds)

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is None and stage in (None, "fit"):
            bank = WindowBank(self.sequences("train"), self.half_window, self.step)
            self.train_set = RandomWindowBatches(
                bank,
                self.batch_size,
                self.steps_per_epoch,
                self.masking,
                self.seed,
                self.noise_mm,
                self.augment,
                self.mirror_perm,
            )
            log.info("training windows: %d mid frames, %d parts", len(bank), bank.K)
        if self.val_set is None and stage in (None, "fit", "validate"):
            bank = WindowBank(self.sequences("val"), self.half_window, self.step)
            self.val_set = FixedWindowBatches.build(
                bank, self.val_windows, self.batch_size, self.seed + 1, self.masking
            )

    def train_dataloader(self) -> DataLoader:
        # our batches are generated in-process (num_workers=0): the length is exact
        warnings.filterwarnings("ignore", message=r".*`IterableDataset` has `__len__` defined")
        if self.trainer is not None:
            self.train_set.rank = self.trainer.global_rank
        return DataLoader(self.train_set, batch_size=None, collate_fn=_identity)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, batch_size=None, shuffle=False, collate_fn=_identity)
