"""Token steps (windows over every s-th frame), training-window augmentation (mirror, time
reversal, several steps) and the tracker's wider windows where a part is out of reach."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from deformnet.body import default_mouse
from deformnet.data import (
    Augment,
    DeformDataModule,
    MaskConfig,
    RandomWindowBatches,
    SequenceArrays,
    WindowBank,
    mirror_asymmetry,
    mirror_permutation,
)
from deformnet.tokens import canonicalize

MOUSE = list(default_mouse().parts)


def _frame_coded(T: int, K: int) -> SequenceArrays:
    """rigid[t, k] = (t, k, 0), deformed = rigid + (0, 0, 1): a window shows its frames."""
    t = np.arange(T, dtype=np.float32)[:, None].repeat(K, 1)
    k = np.arange(K, dtype=np.float32)[None].repeat(T, 0)
    rigid = np.stack([t, k, np.zeros_like(t)], -1)
    deformed = rigid + np.array([0, 0, 1], np.float32)
    return SequenceArrays(rigid, deformed, np.ones((T, K), bool))


def test_mirror_permutation_pairs_left_and_right():
    assert mirror_permutation(MOUSE) == [0, 2, 1, 4, 3, 6, 5, 7]
    assert mirror_permutation(["Snout", "ear_L", "ear_R", "tail"]) == [0, 2, 1, 3]
    assert mirror_permutation(["l_wrist", "r_wrist", "Left_Hand"]) == [1, 0, 2]  # no twin
    assert mirror_permutation(["thumb", "index", "wrist"]) is None


def test_mirror_asymmetry_and_an_asymmetric_body_is_not_mirrored(caplog):
    """Table 1's mouse is its own mirror image wherever it stands; an ear moved 5 mm forward
    makes it 2.46 mm rms from it (computed: the two ears' 5 mm spread over the best rigid fit);
    a body far from symmetric (e.g. `body=auto` with parts guessed at the centre) is not
    mirrored, since its mirror image would be another animal."""
    import logging

    body = default_mouse()
    P = np.asarray(body.points, dtype=np.float64)
    perm = mirror_permutation(body.parts)
    assert mirror_asymmetry(P, perm) < 1e-9
    Q, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))
    Q *= np.sign(np.linalg.det(Q))
    assert mirror_asymmetry(P @ Q.T + 7.0, perm) < 1e-9
    ear = P.copy()
    ear[1] += [0.0, 5.0, 0.0]
    assert mirror_asymmetry(ear, perm) == pytest.approx(2.456, abs=1e-3)
    kw = dict(half_window=2, source="toy", augment={"mirror": 0.5})
    assert DeformDataModule(body, **kw).mirror_perm == perm
    far = P.copy()
    far[[1, 3, 5]] = far[[1, 3, 5]].mean(0)  # the left parts at one point
    lopsided = type(body).from_mapping(dict(zip(body.parts, far.tolist())))
    with caplog.at_level(logging.INFO, logger="deformnet.data"):
        assert DeformDataModule(lopsided, **kw).mirror_perm is None
    assert "from its mirror image" in caplog.text


def test_augment_options_are_checked():
    assert Augment.from_any(None) == Augment()
    assert Augment.from_any({"steps": [1, 3]}).steps == (1, 3)
    with pytest.raises(ValueError, match="unknown data.augment"):
        Augment.from_any({"flip": 0.5})
    with pytest.raises(ValueError, match="steps must be integers >= 1"):
        Augment.from_any({"steps": [0, 1]})
    with pytest.raises(ValueError, match="mirror must be a probability"):
        Augment.from_any({"mirror": 1.5})


def test_window_bank_steps_reverse_and_mirror():
    T, K, n = 60, 3, 2
    bank = WindowBank([_frame_coded(T, K)], n, step=1)
    assert bank.mids[0] == 2 and bank.mids[-1] == T - 3 and len(bank) == T - 4
    m3 = bank.mids_for(3)  # the mids a step-3 window fits around
    assert m3[0] == 6 and m3[-1] == T - 7
    assert len(bank.mids_for(15)) == 0  # 61 frames: longer than the sequence
    hide = torch.zeros(2, 2 * n + 1, K, dtype=torch.bool)
    idx = torch.tensor([0, 10])
    b1 = bank.batch(idx, hide)
    np.testing.assert_array_equal(b1["rigid"][0, :, 0, 0], [0, 1, 2, 3, 4])
    b3 = bank.batch(idx, hide, step=3)
    np.testing.assert_array_equal(b3["rigid"][1, :, 0, 0], [10, 13, 16, 19, 22])
    np.testing.assert_array_equal(b3["target"][1, :, 0], [16, 16, 16])  # the mid frame
    rev = bank.batch(idx, hide, step=3, reverse=torch.tensor([False, True]))
    np.testing.assert_array_equal(rev["rigid"][1, :, 0, 0], [22, 19, 16, 13, 10])
    np.testing.assert_array_equal(rev["rigid"][0], b3["rigid"][0])
    perm = [0, 2, 1]
    fl = bank.batch(idx, hide, flip=torch.tensor([True, False]), perm=perm)
    # x negated, parts 1 and 2 swapped (their y codes show it), the other window unchanged
    np.testing.assert_array_equal(fl["rigid"][0, :, :, 0], -b1["rigid"][0, :, :, 0])
    np.testing.assert_array_equal(fl["rigid"][0, 0, :, 1], [0, 2, 1])
    np.testing.assert_array_equal(fl["target"][0, :, 1], [0, 2, 1])
    np.testing.assert_array_equal(fl["rigid"][1], b1["rigid"][1])
    with pytest.raises(ValueError, match="step must be >= 1"):
        WindowBank([_frame_coded(T, K)], n, step=0)
    with pytest.raises(ValueError, match="frames a window needs"):
        WindowBank([_frame_coded(T, K)], n, step=20)


def test_mirrored_window_is_the_mirror_image_in_the_body_frame():
    """The mirror of a symmetric body's window, parts swapped, is a proper rigid motion of it:
    canonicalised, it is the original's canonical window reflected through the body's
    sagittal plane (x -> -x), parts swapped, so the augmented tokens are a real mouse's."""
    body = torch.tensor(np.asarray(default_mouse().points), dtype=torch.float64)
    perm = mirror_permutation(MOUSE)
    g = torch.Generator().manual_seed(0)
    W, K = 5, len(MOUSE)
    from deformnet.so3 import rodrigues_to_matrix

    R = rodrigues_to_matrix(0.5 * torch.randn(W, 3, generator=g, dtype=torch.float64))
    t = 100 * torch.randn(W, 3, generator=g, dtype=torch.float64)
    rigid = torch.einsum("wij,kj->wki", R, body) + t[:, None]
    deformed = rigid + 3 * torch.randn(W, K, 3, generator=g, dtype=torch.float64)
    sign = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    rc, dc, _, _ = canonicalize(rigid[None], deformed[None], body, W // 2)
    frc, fdc, Rf, _ = canonicalize(
        (rigid * sign)[:, perm][None], (deformed * sign)[:, perm][None], body, W // 2
    )
    assert torch.det(Rf).item() == pytest.approx(1.0)
    torch.testing.assert_close(frc[0], (rc[0] * sign)[:, perm], atol=1e-9, rtol=0)
    torch.testing.assert_close(fdc[0], (dc[0] * sign)[:, perm], atol=1e-9, rtol=0)


def test_training_batches_draw_the_augmentation():
    T, K, n = 200, 3, 2
    bank = WindowBank([_frame_coded(T, K)], n)
    aug = Augment(mirror=0.5, reverse=0.5, steps=(1, 3, 99))  # 99: too long, never drawn
    it = RandomWindowBatches(bank, 64, 40, MaskConfig(), seed=0, augment=aug, mirror_perm=[0, 2, 1])
    spans, flips, revs = set(), 0, 0
    for b in it:
        d = b["rigid"][:, :, 0, 0]  # frame codes (x, negated when mirrored)
        step = (d[:, 1] - d[:, 0]).abs()
        spans |= set(step.unique().tolist())
        flips += int((d[:, n] < 0).sum())
        revs += int((d.abs()[:, 1] < d.abs()[:, 0]).sum())
    assert spans == {1.0, 3.0}
    assert 0.4 < flips / (64 * 40) < 0.6 and 0.4 < revs / (64 * 40) < 0.6
    # no augmentation: the plain windows
    plain = next(iter(RandomWindowBatches(bank, 8, 1, MaskConfig(), seed=0)))
    assert (plain["rigid"][:, 1, 0, 0] - plain["rigid"][:, 0, 0, 0] == 1).all()


def test_data_module_step_and_the_model_keeps_its_steps(tmp_path):
    from deformnet.deformation import DeformationModel
    from deformnet.nets import LSTMPredictor

    body = default_mouse()
    dm = DeformDataModule(
        body, half_window=2, step=2, source="toy", num_frames=80, train_sequences=1,
        batch_size=4, steps_per_epoch=1, val_windows=8, augment={"steps": [2, 4]},
    )  # fmt: skip
    dm.setup("fit")
    b = next(iter(dm.train_dataloader()))
    assert b["rigid"].shape == (4, 5, body.num_parts, 3)
    bank = dm.train_set.bank
    assert bank.mids.min() == 4 and bank.mids_for(4).min() == 8  # step 2 and step 4 windows
    net = LSTMPredictor(body.num_parts, 2, hidden=8, layers=1, embed=8)
    cfg = {"_target_": "deformnet.nets.LSTMPredictor", "num_parts": body.num_parts,
           "half_window": 2, "hidden": 8, "layers": 1, "embed": 8}  # fmt: skip
    m = DeformationModel(net, body, 2, cfg, step=2, steps=[2, 4])
    assert m.steps == (2, 4)
    m.save(tmp_path / "m.ckpt")
    back = DeformationModel.from_checkpoint(tmp_path / "m.ckpt")
    assert back.step == 2 and back.steps == (2, 4)
    one = DeformationModel(net, body, 2, cfg)
    assert "step" not in one.export() and "steps" not in one.export()  # the old format
    assert DeformationModel.from_export(one.export()).steps == (1,)
    with pytest.raises(ValueError, match="step must be >= 1"):
        DeformationModel(net, body, 2, cfg, step=0)


class WindowMean(nn.Module):
    """A stand-in net: each part's mean observed deformed position over the window (rigid
    mid point where none), global mm: what a window can see is what it predicts."""

    def __init__(self) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.zeros(()))

    def forward(self, rigid, deformed, observed):
        o = observed[..., None].to(rigid.dtype)
        s = (deformed * o).sum(-3)
        c = o.sum(-3)
        mid = rigid[..., rigid.shape[-3] // 2, :, :]
        return torch.where(c > 0, s / c.clamp_min(1), mid)


def test_far_steps_reach_across_long_gaps():
    """A 5-token window (n = 2) sees a part on both sides of a gap only if the gap's far
    end is within 2 steps. Part 0 hidden on frames 20..25: step 1 reaches none of them, step
    2 the middle two, step 3 all; part 1 hidden from frame 50 to the end: never reached (the
    interpolation's prediction); part 2 hidden on 60..61: step 1 reaches both."""
    from adjust.lsq.net_observation import NetObservation

    body = torch.tensor(np.asarray(default_mouse().points), dtype=torch.float64)
    T, K = 80, body.shape[0]
    poses = torch.zeros(T, 6, dtype=torch.float64)
    poses[:, 3] = torch.arange(T, dtype=torch.float64)  # walking along x
    g = torch.Generator().manual_seed(1)
    data = body[None] + poses[:, None, 3:] + torch.randn(T, K, 3, generator=g, dtype=torch.float64)
    observed = torch.ones(T, K, dtype=torch.bool)
    observed[20:26, 0] = False
    observed[50:, 1] = False
    observed[60:62, 2] = False
    obs = NetObservation(
        WindowMean(), body, 5, data, observed, 0.0, 4096, "frozen", far_steps=(2, 3)
    )
    obs.prepare(poses)
    torch.testing.assert_close(obs.step_used[20:26, 0], torch.tensor([3, 3, 2, 2, 3, 3]))
    assert (obs.step_used[50:, 1] == 0).all() and not obs.use_net[50:, 1].any()
    assert (obs.step_used[60:62, 2] == 1).all() and obs.use_net[60:62, 2].all()
    assert (obs.step_used[2:48, 3:] == 1).all()  # seen everywhere: the window's own step
    assert bool(obs.reach[20:26, 0].all()) and obs.use_net[20:26, 0].all()
    X, _ = obs.points(poses, jacobian=False)
    # frame 22, step 2: frames 18, 20, 22, 24, 26 of which 18 and 26 are seen
    torch.testing.assert_close(X[22, 0], (data[18, 0] + data[26, 0]) / 2)
    # frame 20, step 3: frames 14, 17, 20, 23, 26 of which 14, 17 and 26 are seen
    torch.testing.assert_close(X[20, 0], (data[14, 0] + data[17, 0] + data[26, 0]) / 3)
    without = NetObservation(WindowMean(), body, 5, data, observed, 0.0, 4096, "frozen")
    without.prepare(poses)
    assert not without.use_net[20:26, 0].any()
    with pytest.raises(ValueError, match="far_steps needs deform.jacobian=frozen"):
        NetObservation(WindowMean(), body, 5, data, observed, 0.0, 64, "central", far_steps=(3,))


def test_track_step_settings_are_checked():
    from adjust.deformation_modes import deform_step, far_steps
    from adjust.io import InputError

    class M:
        step, steps = 1, (1, 2, 3)

    assert deform_step(M(), {}) == 1 and deform_step(M(), {"step": 2}) == 2
    assert far_steps(M(), {}) == (2, 3) and far_steps(M(), {"step": 2}) == (3,)
    assert far_steps(M(), {"far_steps": []}) == ()
    with pytest.raises(InputError, match="deform.step must be an integer >= 1"):
        deform_step(M(), {"step": 0})
    with pytest.raises(InputError, match="deform.far_steps must be auto or a list"):
        far_steps(M(), {"far_steps": "wide"})


def test_input_only_part_frames_are_observed_inputs_and_never_targets():
    """`SequenceArrays.inputs` (a recording's single-view anchors): a window observes them
    unless its mask hides them, and they are never the mid frame's targets; each token's
    recording frame is in the batch ('frames'); `SessionTokens.to_sequence` keeps them."""
    from deformnet.sessions import SessionTokens

    T, K, n = 40, 3, 4
    base = _frame_coded(T, K)
    observed = np.ones((T, K), bool)
    observed[10:30, 1] = False  # part 1 measured in 3D outside frames 10-29 only
    inputs = np.zeros((T, K), bool)
    inputs[10:30:2, 1] = True  # seen by one camera on every other frame of the gap
    seq = SequenceArrays(base.rigid, base.deformed, observed, inputs)
    bank = WindowBank([seq], n)
    idx = torch.arange(len(bank))
    b = bank.batch(idx, torch.zeros(len(idx), bank.W, K, dtype=torch.bool))
    frames = b["frames"]
    assert torch.equal(frames, bank.mids[:, None] + torch.arange(-n, n + 1))
    expect = torch.as_tensor(observed | inputs)[frames]
    assert torch.equal(b["observed"], expect)
    assert torch.equal(b["target_mask"], torch.as_tensor(observed)[bank.mids])
    hidden = bank.batch(idx, torch.ones(len(idx), bank.W, K, dtype=torch.bool))
    assert not hidden["observed"].any()
    plain = WindowBank([SequenceArrays(base.rigid, base.deformed, observed)], n).batch(
        idx, torch.zeros(len(idx), bank.W, K, dtype=torch.bool)
    )
    assert torch.equal(plain["observed"], torch.as_tensor(observed)[frames])
    tok = SessionTokens(
        base.rigid, base.deformed, observed, ("a", "b", "c"), np.eye(3), inputs=inputs
    )
    s = tok.to_sequence(5, 35)
    assert np.array_equal(s.inputs, inputs[5:35]) and np.array_equal(s.observed, observed[5:35])
    np.testing.assert_array_equal(s.deformed[5:25:2, 1], base.deformed[10:30:2, 1])
    np.testing.assert_array_equal(s.deformed[6:25:2, 1], base.rigid[11:30:2, 1])
