"""benchmarks/imputation.py --real's helpers on tiny arrays: the token step a gap needs, the
rigid body fit of 3D truth, the gap masks of the evaluation windows, the DISK peer's training
pieces."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch

from deformnet.so3 import transform_points
from deformnet.windows import SequenceArrays

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "imputation.py"


@pytest.fixture(scope="module")
def imp():
    spec = importlib.util.spec_from_file_location("imputation_bench", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)  # puts benchmarks/ on sys.path for its own imports
    return mod


def test_gap_step_leaves_context_on_both_sides(imp):
    # half window 16, 4 tokens of context: a gap of up to 2 * 11 + 1 frames at step 1
    assert imp.gap_step(1, 16, (1, 2, 3)) == 1
    assert imp.gap_step(15, 16, (1, 2, 3)) == 1
    assert imp.gap_step(23, 16, (1, 2, 3)) == 1
    assert imp.gap_step(24, 16, (1, 2, 3)) == 2
    assert imp.gap_step(45, 16, (1, 2, 3)) == 2
    assert imp.gap_step(45, 12, (1, 2, 3)) == 3
    assert imp.gap_step(200, 12, (3, 1, 2)) == 3  # none does: the widest
    assert imp.gap_step(45, 16, (1,)) == 1


def test_rigid_fit_recovers_a_rigidly_moving_scaled_body(imp):
    rng = np.random.default_rng(0)
    B = rng.normal(0, 20, (5, 3))
    T = 30
    poses = np.concatenate((rng.normal(0, 1, (T, 3)), rng.normal(0, 100, (T, 3))), 1)
    X = transform_points(torch.tensor(poses), torch.tensor(0.6 * B).expand(T, 5, 3)).numpy()
    X[:, 0] += 3.0 * np.sin(np.arange(T))[:, None]  # one part deforms a little
    rigid, body, scale = imp.rigid_fit(X, B, slice(0, 20))
    assert scale == pytest.approx(0.6, rel=0.02)
    np.testing.assert_allclose(body, scale * B)
    err = np.linalg.norm(rigid - X, axis=-1)
    assert np.median(err[:, 1:]) < 1.0 and err[:, 0].max() < 6.0


def test_gap_batches_hide_the_gap_and_keep_the_truth(imp):
    T, K, n = 40, 2, 3
    t = np.arange(T, dtype=np.float32)
    deformed = np.stack([np.stack([t, t + 100 * k, 0 * t], -1) for k in range(K)], 1)
    seq = SequenceArrays(np.zeros_like(deformed), deformed, np.ones((T, K), bool))
    for gap, step, tokens in ((1, 1, 1), (5, 1, 5), (5, 2, 3), (4, 1, 4)):
        (b,) = imp.gap_batches(seq, n, step, gap, 0.0, 10, 0)
        W = 2 * n + 1
        hidden = ~b["observed"]  # (B, W, K): exactly the gap's tokens, every part
        start = n - tokens // 2
        expect = torch.zeros(W, dtype=torch.bool)
        expect[start : start + tokens] = True
        assert torch.equal(hidden, expect[None, :, None].expand_as(hidden)), (gap, step)
        # the mid frame's truth is the target, the visible tokens are the truth at that step
        mids = b["target"][:, 0, 0]
        assert torch.equal(b["target_mask"], torch.ones_like(b["target_mask"]))
        frames = mids[:, None] + step * torch.arange(-n, n + 1)
        assert torch.equal(b["deformed"][..., 0, 0][~hidden[..., 0]], frames[~hidden[..., 0]])
    with_dropout = imp.gap_batches(seq, n, 1, 1, 0.5, 10, 0)[0]["observed"]
    assert 0.2 < with_dropout.float().mean() < 0.8


def test_disk_training_set_pieces(imp):
    T = 100
    X = np.arange(T, dtype=np.float32)[:, None, None].repeat(2, 1).repeat(3, 2)
    seq = SequenceArrays(X, X, np.ones((T, 2), bool))
    pieces = imp.disk_training_set(seq, (1, 2), length=20)
    assert pieces.shape == (5 + 2 * 2, 20, 2, 3)
    assert np.all(np.diff(pieces[0, :, 0, 0]) == 1)  # step 1
    assert np.all(np.diff(pieces[-1, :, 0, 0]) == 2)  # step 2, second phase
    assert pieces[-1, 0, 0, 0] == 41  # frames 1, 3, .. 99: its second piece
