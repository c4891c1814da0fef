"""Masked token windows over sequences, without Lightning: what the deformation nets learn from
and are checked on (`deformnet.data` builds its LightningDataModule on these; `adjust-track`
checks a net on a recording's own windows, `deformnet.heldout`).

`WindowBank` cuts windows of W = 2n + 1 frames from sequences (`SequenceArrays`);
`make_masks` hides deformed positions in patterns like multi-camera occlusion (`MaskConfig`):
random dropout, mid-centred gaps (all parts or a subset; the mid frame is always hidden) and
contiguous per-part gaps elsewhere.

A batch is a dict of float32 / bool tensors:
    rigid (B, W, K, 3), deformed (B, W, K, 3)  global mm (deformed: the true values; hidden ones
                                                are zeroed),
    observed (B, W, K)                          input flags (mid frame false),
    target (B, K, 3), target_mask (B, K)        the mid frame's deformed positions and whether
                                                they were observed (the loss uses only those).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torch.utils.data import Dataset, IterableDataset

from deformnet.body import BodyModel
from deformnet.confutil import check_fields, checked_fields
from deformnet.so3 import kabsch, transform_points
from deformnet.tokens import canonicalize

__all__ = [
    "window_summary",
    "Augment",
    "MaskConfig",
    "SequenceArrays",
    "mirror_asymmetry",
    "mirror_permutation",
    "toy_sequence",
    "make_masks",
    "gap_masks",
    "WindowBank",
    "RandomWindowBatches",
    "FixedWindowBatches",
]


# --------------------------------------------------------------------------------------------
# sequences
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SequenceArrays:
    """The parts of a simulated sequence the nets need: rigid, deformed (T, K, 3) global mm,
    observed (T, K) bool; inputs (T, K) bool or None: part-frames whose ``deformed`` value a
    window observes as an input but never a target (a recording's single-view anchors)."""

    rigid: np.ndarray
    deformed: np.ndarray
    observed: np.ndarray
    inputs: np.ndarray | None = None

    @classmethod
    def of(cls, seq: Any) -> SequenceArrays:
        """From a `deformnet.sim.SimData` (or anything with those three attributes)."""
        rigid = np.asarray(seq.rigid, dtype=np.float32)
        deformed = np.asarray(seq.deformed, dtype=np.float32)
        observed = getattr(seq, "observed", None)
        observed = (
            np.ones(rigid.shape[:2], dtype=bool) if observed is None else np.asarray(observed, bool)
        )
        finite = np.isfinite(deformed).all(-1)
        observed = observed & finite
        deformed = np.where(finite[..., None], deformed, rigid)  # truth kept where known
        if rigid.shape != deformed.shape or rigid.ndim != 3 or rigid.shape[-1] != 3:
            raise ValueError(
                f"rigid/deformed must be (T, K, 3), got {rigid.shape}, {deformed.shape}"
            )
        return cls(rigid, deformed, observed)


def toy_sequence(
    body: BodyModel, num_frames: int = 600, seed: int = 0, fps: float = 30.0
) -> SequenceArrays:
    """A small stand-in for the simulator: the rigid model moved along a smooth curve with a
    smoothly turning heading, plus smooth sinusoidal per-part offsets in the body frame."""
    rng = np.random.default_rng(seed)
    T, K = int(num_frames), body.num_parts
    t = np.arange(T) / fps
    yaw = np.cumsum(0.6 * np.sin(2 * np.pi * 0.13 * t + rng.uniform(0, 6.3)) / fps) + rng.uniform(
        0, 6.3
    )
    speed = 50.0 + 20.0 * np.sin(2 * np.pi * 0.21 * t + rng.uniform(0, 6.3))
    xy = np.cumsum(speed[:, None] * np.stack((-np.sin(yaw), np.cos(yaw)), -1) / fps, 0)
    poses = np.zeros((T, 6))
    poses[:, 2] = yaw
    poses[:, 0] = 0.1 * np.sin(2 * np.pi * 0.4 * t)  # small pitch wobble
    poses[:, 3:5] = xy
    poses[:, 5] = 10.0
    model = torch.tensor(np.array(body.points))
    rigid = transform_points(torch.tensor(poses), model.expand(T, K, 3)).numpy()
    amp = rng.uniform(1.0, 4.0, (K, 3))
    freq = rng.uniform(0.5, 2.5, (K, 1))
    phase = rng.uniform(0, 2 * np.pi, (K, 3))
    off_local = amp * np.sin(2 * np.pi * freq * t[:, None, None] + phase)  # (T, K, 3)
    off = transform_points(
        torch.tensor(np.concatenate((poses[:, :3], np.zeros((T, 3))), 1)),
        torch.tensor(off_local),
    ).numpy()
    observed = rng.random((T, K)) > 0.02
    return SequenceArrays(rigid.astype(np.float32), (rigid + off).astype(np.float32), observed)


def mirror_permutation(parts: Sequence[str]) -> list[int] | None:
    """Part order of the mirror image: each left/right part (``left_*``/``right_*``,
    ``l_*``/``r_*``, ``*_left``/``*_right``, ``*_l``/``*_r``, and an ``l``/``r`` before a
    digit, ``L1A``/``R1A`` as insects' legs are named; any case) swapped with its twin, the
    others in place; None when no part has a twin (nothing to mirror)."""
    names = [str(p) for p in parts]
    low = {n.lower(): i for i, n in enumerate(names)}
    swaps = (("left_", "right_"), ("l_", "r_"))
    suffixes = (("_left", "_right"), ("_l", "_r"))
    perm = list(range(len(names)))
    found = False
    for i, n in enumerate(names):
        m = n.lower()
        twin = None
        for a, b in swaps:
            for x, y in ((a, b), (b, a)):
                if twin is None and m.startswith(x):
                    twin = y + m[len(x) :]
        for a, b in suffixes:
            for x, y in ((a, b), (b, a)):
                if twin is None and m.endswith(x):
                    twin = m[: -len(x)] + y
        if twin is None and len(m) > 1 and m[0] in "lr" and m[1].isdigit():
            twin = {"l": "r", "r": "l"}[m[0]] + m[1:]
        if twin is not None and twin in low:
            perm[i] = low[twin]
            found = True
    return perm if found else None


def mirror_asymmetry(points: np.ndarray, perm: Sequence[int]) -> float:
    """How far a body model is from bilateral symmetry: the rms distance (mm) between its points
    and its mirror image (x -> -x, parts permuted by `perm`) moved onto them by the best rigid
    motion (`deformnet.so3.kabsch`); 0 for a body symmetric about any plane."""
    P = torch.tensor(np.array(points, dtype=np.float64))
    M = (P * torch.tensor([-1.0, 1.0, 1.0], dtype=P.dtype))[list(perm)]
    R, t = kabsch(P, M)
    return float(((M @ R.T + t - P) ** 2).sum(-1).mean().sqrt())


@dataclass(frozen=True)
class Augment:
    """Training-window augmentation (self-supervised data is scarce: one recording's tokens).

    mirror: probability of the window's mirror image (reflected through a vertical plane,
    left and right parts swapped; a bilaterally symmetric body only, `mirror_permutation`);
    reverse: probability of the window played backwards (the mid frame stays the mid frame);
    steps: frames between tokens drawn per batch from these (None: the data's step), so one
    recording yields windows at several token rates."""

    mirror: float = 0.0
    reverse: float = 0.0
    steps: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        prob = (float, lambda v: 0.0 <= v <= 1.0, "a probability")
        check_fields(self, "data.augment", mirror=prob, reverse=prob)
        if self.steps is not None:
            ints = (list, lambda v: len(v) > 0 and min(v) >= 1, "integers >= 1")
            check_fields(self, "data.augment", steps=ints)
            object.__setattr__(self, "steps", tuple(self.steps))

    @classmethod
    def from_any(cls, cfg: Mapping[str, Any] | Augment | None) -> Augment:
        if isinstance(cfg, Augment):
            return cfg
        return cls(**checked_fields(cls, cfg, "data.augment"))


# --------------------------------------------------------------------------------------------
# masks
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MaskConfig:
    """Missing-data patterns for training windows (rates are probabilities per sample).

    dropout: [min, max] rate of random token dropout, drawn per sample.
    gap_prob: probability of a gap centred on the mid frame, of length 1..gap_max frames
    (the mid frame is hidden anyway); it hides all parts with probability gap_all_parts, else a
    random subset of parts.
    occlusion_prob: per part, probability of one more contiguous gap of 1..occlusion_max frames at a
    random place in the window (multi-camera occlusion of a single part).
    """

    dropout: tuple[float, float] = (0.0, 0.5)
    gap_prob: float = 0.8
    gap_max: int = 15
    gap_all_parts: float = 0.7
    occlusion_prob: float = 0.2
    occlusion_max: int = 15

    @classmethod
    def from_any(cls, cfg: Mapping[str, Any] | MaskConfig | None) -> MaskConfig:
        if isinstance(cfg, MaskConfig):
            return cfg
        d = checked_fields(cls, cfg, "data.masking")
        if "dropout" in d:
            lo, hi = (float(x) for x in d["dropout"])
            d["dropout"] = (lo, hi)
        return cls(**d)


def _runs(start: Tensor, length: Tensor, W: int) -> Tensor:
    """(..., W) bool: frames start <= f < start + length."""
    f = torch.arange(W)
    return (f >= start[..., None]) & (f < (start + length)[..., None])


def make_masks(B: int, W: int, K: int, cfg: MaskConfig, gen: torch.Generator) -> Tensor:
    """(B, W, K) bool: True where a deformed position is hidden (mid frame always hidden)."""
    mid = W // 2
    lo, hi = cfg.dropout
    rate = lo + (hi - lo) * torch.rand(B, 1, 1, generator=gen)
    hide = torch.rand(B, W, K, generator=gen) < rate
    # mid-centred gap
    L = torch.randint(1, max(1, cfg.gap_max) + 1, (B,), generator=gen)
    shift = torch.randint(0, 2, (B,), generator=gen) * (L % 2 == 0)  # even lengths: either side
    start = mid - (L - 1) // 2 - shift
    gap_t = _runs(start, L, W)  # (B, W)
    all_parts = torch.rand(B, 1, generator=gen) < cfg.gap_all_parts
    parts = all_parts | (torch.rand(B, K, generator=gen) < 0.5)
    use = torch.rand(B, 1, 1, generator=gen) < cfg.gap_prob
    hide |= use & gap_t[:, :, None] & parts[:, None, :]
    # per-part occlusion gaps anywhere
    Lo = torch.randint(1, max(1, cfg.occlusion_max) + 1, (B, K), generator=gen)
    so = torch.randint(-int(cfg.occlusion_max), W, (B, K), generator=gen)
    occ = _runs(so, Lo, W).transpose(1, 2)  # (B, W, K)
    hide |= occ & (torch.rand(B, 1, K, generator=gen) < cfg.occlusion_prob)
    hide[:, mid] = True
    return hide


def gap_masks(B: int, W: int, K: int, gap: int, dropout: float, gen: torch.Generator) -> Tensor:
    """(B, W, K) bool hidden flags for evaluation: a gap of `gap` frames centred on the mid frame
    (all parts; even gaps extend one frame further before the mid frame) plus random dropout of
    the other tokens at rate `dropout`."""
    mid = W // 2
    hide = torch.rand(B, W, K, generator=gen) < dropout
    start = mid - gap // 2
    hide[:, max(0, start) : min(W, start + gap)] = True
    hide[:, mid] = True
    return hide


# --------------------------------------------------------------------------------------------
# windows
# --------------------------------------------------------------------------------------------
class WindowBank:
    """All windows of W frames of a list of sequences, gathered by index without copies.

    step: frames between a window's tokens (the window spans 2 n step + 1 frames): a recording
    at a higher frame rate than the net's training data is seen at the same token rate."""

    def __init__(
        self,
        sequences: Sequence[SequenceArrays],
        half_window: int,
        step: int = 1,
    ) -> None:
        self.n = int(half_window)
        self.W = 2 * self.n + 1
        self.step = int(step)
        if self.step < 1:
            raise ValueError(f"step must be >= 1, got {step}")
        span = self.n * self.step
        # the sequences long enough for a window, by their index in `sequences`
        self.kept = [i for i, s in enumerate(sequences) if s.rigid.shape[0] >= 2 * span + 1]
        seqs = [sequences[i] for i in self.kept]
        if not seqs:
            raise ValueError(f"no sequence has the {2 * span + 1} frames a window needs")
        self.K = seqs[0].rigid.shape[1]
        self.rigid = torch.from_numpy(np.concatenate([s.rigid for s in seqs]))
        self.deformed = torch.from_numpy(np.concatenate([s.deformed for s in seqs]))
        self.observed = torch.from_numpy(np.concatenate([s.observed for s in seqs]))
        # input-only part-frames (`SequenceArrays.inputs`), none where a sequence has none
        self.inputs = torch.from_numpy(
            np.concatenate([np.zeros_like(s.observed) if s.inputs is None else s.inputs
                            for s in seqs]).astype(bool)
        )  # fmt: skip
        self._pieces, off = [], 0
        for s in seqs:
            self._pieces.append((off, s.rigid.shape[0]))
            off += s.rigid.shape[0]
        self._mids: dict[int, Tensor] = {}
        self.mids = self.mids_for(self.step)  # global frame index of every valid mid frame

    def mids_for(self, step: int) -> Tensor:
        """Mid frames (global indices) whose window at this token step lies inside its
        sequence (empty when every sequence is too short for it)."""
        step = int(step)
        if step not in self._mids:
            span = self.n * step
            m = [torch.arange(o + span, o + T - span) for o, T in self._pieces if T > 2 * span]
            self._mids[step] = torch.cat(m) if m else torch.zeros(0, dtype=torch.long)
        return self._mids[step]

    def __len__(self) -> int:
        return len(self.mids)

    def batch(
        self,
        idx: Tensor,
        hide: Tensor,
        noise_mm: float = 0.0,
        gen=None,
        step: int | None = None,
        flip: Tensor | None = None,
        reverse: Tensor | None = None,
        perm: Sequence[int] | None = None,
    ) -> dict:
        """Windows around mids_for(step)[idx] with extra hidden flags `hide` (B, W, K); `step`
        frames between tokens (None: the bank's); flip (B,) bool: mirror those windows (x -> -x,
        parts permuted by `perm`); reverse (B,) bool: play those windows backwards. The batch's
        ``frames`` (B, W): each token's frame in the kept sequences laid end to end (`kept`)."""
        step = self.step if step is None else int(step)
        mids = self.mids_for(step)
        frames = mids[idx][:, None] + step * torch.arange(-self.n, self.n + 1)  # (B, W)
        if reverse is not None:
            frames = torch.where(reverse[:, None], frames.flip(1), frames)
        rigid = self.rigid[frames]
        truth = self.deformed[frames]
        seen = self.observed[frames]
        extra = self.inputs[frames]
        if flip is not None and perm is not None and bool(flip.any()):
            sign = torch.tensor([-1.0, 1.0, 1.0], dtype=rigid.dtype)
            p = torch.as_tensor(list(perm), dtype=torch.long)
            f4 = flip[:, None, None, None]
            rigid = torch.where(f4, (rigid * sign)[:, :, p], rigid)
            truth = torch.where(f4, (truth * sign)[:, :, p], truth)
            seen = torch.where(flip[:, None, None], seen[:, :, p], seen)
            extra = torch.where(flip[:, None, None], extra[:, :, p], extra)
        observed = (seen | extra) & ~hide
        deformed = truth
        if noise_mm > 0:
            deformed = truth + noise_mm * torch.randn(truth.shape, generator=gen)
        deformed = torch.where(observed[..., None], deformed, torch.zeros_like(deformed))
        return {
            "rigid": rigid,
            "deformed": deformed,
            "observed": observed,
            "target": truth[:, self.n],
            "target_mask": seen[:, self.n],
            "frames": frames,
        }


class RandomWindowBatches(IterableDataset):
    """`steps` random batches per pass (epoch), freshly masked each time; seeded by
    (seed, rank, pass)."""

    def __init__(
        self,
        bank: WindowBank,
        batch_size: int,
        steps: int,
        masking: MaskConfig,
        seed: int = 0,
        noise_mm: float = 0.0,
        augment: Augment | None = None,
        mirror_perm: Sequence[int] | None = None,
    ) -> None:
        super().__init__()
        self.bank, self.batch_size, self.steps = bank, int(batch_size), int(steps)
        self.masking, self.seed, self.noise_mm = masking, int(seed), float(noise_mm)
        self.augment = augment or Augment()
        self.mirror_perm = None if mirror_perm is None else list(mirror_perm)
        self.rank = 0
        self._pass = 0

    def __len__(self) -> int:
        return self.steps

    def __iter__(self) -> Iterator[dict]:
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + self.rank * 7919 + self._pass)
        self._pass += 1
        b = self.bank
        a = self.augment
        steps = [s for s in (a.steps or ()) if len(b.mids_for(s))] or None
        for _ in range(self.steps):
            if a.mirror <= 0 and a.reverse <= 0 and a.steps is None:  # the plain windows
                idx = torch.randint(0, len(b), (self.batch_size,), generator=gen)
                hide = make_masks(self.batch_size, b.W, b.K, self.masking, gen)
                yield b.batch(idx, hide, self.noise_mm, gen)
                continue
            step = None
            if steps is not None:  # a step some sequence is long enough for
                step = steps[int(torch.randint(0, len(steps), (1,), generator=gen))]
            n_mids = len(b.mids_for(b.step if step is None else step))
            idx = torch.randint(0, n_mids, (self.batch_size,), generator=gen)
            hide = make_masks(self.batch_size, b.W, b.K, self.masking, gen)
            B = self.batch_size
            flip = torch.rand(B, generator=gen) < a.mirror
            rev = torch.rand(B, generator=gen) < a.reverse
            yield b.batch(idx, hide, self.noise_mm, gen, step, flip, rev, self.mirror_perm)


class FixedWindowBatches(Dataset):
    """A fixed list of pre-built batches (validation / evaluation); indexable for samplers."""

    def __init__(self, batches: Sequence[dict]) -> None:
        self.batches = list(batches)

    def __len__(self) -> int:
        return len(self.batches)

    def __getitem__(self, i: int) -> dict:
        return self.batches[i]

    @classmethod
    def build(
        cls,
        bank: WindowBank,
        num_windows: int,
        batch_size: int,
        seed: int,
        masking: MaskConfig | None = None,
        gap: int | None = None,
        dropout: float = 0.3,
    ) -> FixedWindowBatches:
        """Evenly spaced windows, masked with `masking` (training-like) or, with `gap`, by
        `gap_masks` (evaluation)."""
        gen = torch.Generator().manual_seed(int(seed))
        n = min(int(num_windows), len(bank))
        idx = torch.linspace(0, len(bank) - 1, n).round().long()
        out = []
        for chunk in idx.split(int(batch_size)):
            B = len(chunk)
            if gap is not None:
                hide = gap_masks(B, bank.W, bank.K, int(gap), float(dropout), gen)
            else:
                hide = make_masks(B, bank.W, bank.K, masking or MaskConfig(), gen)
            out.append(bank.batch(chunk, hide))
        return cls(out)


def window_summary(
    net: nn.Module,
    body_points: Tensor,
    rigid: Tensor,
    deformed: Tensor,
    observed: Tensor,
    up: Tensor | None = None,
) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor, Tensor]]:
    """A deformation net's summary of global windows: its `encode` outputs in the mid frame's
    canonical coordinates, at the mid frame and averaged over the window (B, 2 encode_dim),
    and the canonical window (rigid_c, deformed_c (B, W, K, 3), R (B, 3, 3), t (B, 3)).

    rigid, deformed (B, W, K, 3) global mm (unobserved deformed values are ignored), observed
    (B, W, K) bool; body_points (K, 3); up: the world's up (3,) for a net trained in the heading
    frame (`deformnet.tokens.canonicalize`), None for the body frame."""
    observed = observed.bool()
    deformed = torch.where(observed[..., None], deformed, torch.zeros_like(deformed))
    mid = net.half_window
    rigid_c, deformed_c, R, t = canonicalize(rigid, deformed, body_points.to(rigid.dtype), mid, up)
    seq, _ = net.encode(rigid_c, deformed_c, observed)  # (B, W, encode_dim)
    return torch.cat((seq[:, mid], seq.mean(1)), -1), (rigid_c, deformed_c, R, t)
