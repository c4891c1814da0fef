"""The shipped net (deformnet/pretrained, built by adjust.pretrain_real from real motion).

It is part-agnostic: it loads for a skeleton it was not trained on (15 parts of the real mouse;
it trained on 8, 22 and 34) and, on the real motion's held-out third (frames 2400-2799, never
trained on), predicts hidden parts better than the rigid model; the build is seeded.
"""

from __future__ import annotations

import numpy as np
import torch

from adjust.scene.motion import load_motion
from deformnet.body import BodyModel, default_mouse
from deformnet.heldout import heldout_errors
from deformnet.paths import real_mouse_motion_dir
from deformnet.pretrained import load_default
from deformnet.sessions import SessionTokens
from deformnet.so3 import kabsch

DATA = real_mouse_motion_dir() / "poses3d.csv"
#: a skeleton the shipped net never trained on (it saw the 8-, 22- and 34-part sets)
PARTS15 = ("Nose", "Ear_L", "Ear_R", "Neck", "Spine", "TTI", "Shoulder_L", "Shoulder_R",
           "Elbow_L", "Elbow_R", "Hip_L", "Hip_R", "Knee_L", "Knee_R", "Tail_1")  # fmt: skip
START, FRAMES = 2400, 400  # the held-out third (benchmarks/real_motion.py's test segment)


def _real_tokens(parts=PARTS15, seed: int = 0) -> SessionTokens:
    """Tokens of the real motion: the rigid body (Procrustes model of these frames, in the
    default mouse's frame as adjust-track puts it) posed per frame by Kabsch; the truth as
    the measured points (0.5 mm noise) where a random 70% of part-frames are 'seen'."""
    assert DATA.exists(), f"shared data missing: {DATA}"
    X, names = load_motion(DATA)
    X = X[START : START + FRAMES][:, [names.index(p) for p in parts]]
    body = BodyModel.from_observations(X, parts)
    body, facts = body.in_frame_of(default_mouse())
    assert facts["aligned"]
    M = torch.as_tensor(np.array(body.points))
    R, t = kabsch(torch.as_tensor(X), M)
    rigid = (M @ R.transpose(-1, -2) + t[:, None]).numpy()
    rng = np.random.default_rng(seed)
    observed = rng.random(X.shape[:2]) < 0.7
    deformed = X + 0.5 * rng.standard_normal(X.shape)
    return SessionTokens(rigid.astype(np.float32), deformed.astype(np.float32), observed,
                         tuple(parts), np.array(body.points), "real15")  # fmt: skip


def test_shipped_net_on_an_unseen_skeleton_beats_the_rigid_model():
    shipped = load_default()
    assert shipped.part_agnostic
    assert set(PARTS15) != set(shipped.body.parts) and len(shipped.body.parts) != 15
    tokens = _real_tokens()
    body = BodyModel.from_mapping(dict(zip(tokens.parts, tokens.body_points.tolist())))
    h = heldout_errors(shipped.for_body(body), tokens, windows=512)
    n = np.asarray(h["targets"], float)
    rigid = float(np.sqrt(np.sum(n * np.square(h["rigid_mm"])) / n.sum()))
    assert np.isfinite(h["net_all_mm"])
    assert h["net_all_mm"] < 0.8 * rigid, (h["net_all_mm"], rigid)


def test_shipped_net_is_a_part_transformer_on_the_real_skeleton():
    from deformnet.nets import PartTransformer

    shipped = load_default()
    assert isinstance(shipped.net, PartTransformer)
    assert shipped.num_parts == 34  # the real mouse's full skeleton (the build's largest)


def test_pretrain_real_fit_is_seeded(tmp_path):
    """The build's training step gives the same weights for the same seed (a few steps on the
    real tokens above)."""
    from dataclasses import replace

    from adjust.pretrain_real import RECIPE
    from deformnet.pretrained.build import weights_sha256
    from deformnet.pretrained.fit import fit_sessions

    toks = [_real_tokens(), _real_tokens(PARTS15[:8], seed=1)]
    cfg = replace(RECIPE, steps=6, batch_size=16, log_every=0)
    a, _ = fit_sessions(toks, cfg, seed=3)
    b, _ = fit_sessions(toks, cfg, seed=3)
    c, _ = fit_sessions(toks, cfg, seed=4)
    assert weights_sha256(a) == weights_sha256(b) != weights_sha256(c)


def test_truth_window_bank_targets_every_part_with_the_recordings_own_masks():
    """`TruthWindowBank`: the inputs are the measured tokens, the targets the true mid-frame
    positions of every part (measured or not); with real_masks=1 a window hides only what the
    recording did not measure and the mid frame; a mirrored window's target is mirrored too."""
    from deformnet.pretrained.fit import TruthWindowBank
    from deformnet.windows import MaskConfig, make_masks, mirror_permutation

    tok = _real_tokens(PARTS15[:8], seed=2)
    X, names = load_motion(DATA)
    truth = X[START : START + FRAMES][:, [names.index(p) for p in tok.parts]]
    seq = tok.to_sequence()
    gen = torch.Generator().manual_seed(0)
    n = 6
    bank = TruthWindowBank([seq], [truth], n, real_masks=1.0)
    idx = torch.arange(0, len(bank), 37)
    hide = make_masks(len(idx), bank.W, bank.K, MaskConfig(dropout=(0.9, 0.9)), gen)
    b = bank.batch(idx, hide, gen=gen)
    mids = bank.mids[idx]
    np.testing.assert_allclose(b["target"].numpy(), truth[mids.numpy()], atol=1e-4)
    assert bool(b["target_mask"].all())
    own = torch.as_tensor(seq.observed)[mids[:, None] + torch.arange(-n, n + 1)]
    own[:, n] = False
    assert torch.equal(b["observed"], own)  # the recording's own missing frames only
    measured = torch.as_tensor(seq.deformed)[mids[:, None] + torch.arange(-n, n + 1)]
    assert torch.allclose(b["deformed"][own], measured[own])  # inputs: the measurements
    perm = mirror_permutation(tok.parts)
    assert perm is not None
    flip = torch.ones(len(idx), dtype=torch.bool)
    f = bank.batch(idx, hide, gen=gen, flip=flip, perm=perm)
    sign = torch.tensor([-1.0, 1.0, 1.0])
    assert torch.allclose(f["target"], (b["target"] * sign)[:, perm])
    assert torch.allclose(f["rigid"], (b["rigid"] * sign)[:, :, perm])
    # without real_masks the extra hidden flags stay
    plain = TruthWindowBank([seq], [truth], n).batch(idx, hide, gen=gen)
    assert int(plain["observed"].sum()) < int(b["observed"].sum())


def test_fit_sessions_learns_from_the_truth_when_given():
    """``truths``: the targets are the true positions (a different net from the same seed)."""
    from dataclasses import replace

    from adjust.pretrain_real import RECIPE
    from deformnet.pretrained.build import weights_sha256
    from deformnet.pretrained.fit import fit_sessions

    tok = _real_tokens(PARTS15[:8], seed=1)
    X, names = load_motion(DATA)
    truth = X[START : START + FRAMES][:, [names.index(p) for p in tok.parts]]
    cfg = replace(RECIPE, steps=4, batch_size=16, log_every=0, real_masks=0.5)
    a, _ = fit_sessions([tok], cfg, seed=3)
    b, _ = fit_sessions([tok], cfg, seed=3, truths=[truth])
    assert weights_sha256(a) != weights_sha256(b)


def test_pretrain_real_track_cache_is_keyed_by_the_trackers_settings_and_the_scene(tmp_path):
    """The build's cached tracks (``--work``) are keyed by adjust-track's resolved settings and
    the scene's files: a changed default (here ``deform.single_views``) or a re-filmed
    detection file gives another key; where the output goes does not."""
    from adjust.pretrain_real import track_key

    scene = tmp_path / "scene"
    (scene / "detections").mkdir(parents=True)
    (scene / "calibration.toml").write_text("[cam_0]\n", encoding="utf-8")
    (scene / "detections" / "cam_0.csv").write_text("a,b\n1,2\n", encoding="utf-8")
    base = track_key(scene)
    assert track_key(scene) == base
    assert track_key(scene, ["output.dir=/elsewhere"]) == base
    assert track_key(scene, ["deform.single_views=false"]) != base
    (scene / "detections" / "cam_0.csv").write_text("a,b\n1,3\n", encoding="utf-8")
    assert track_key(scene) != base


def test_a_saved_net_is_the_same_bytes_for_the_same_weights(tmp_path):
    """`DeformationModel.save` writes the same file for the same weights (the shipped file is
    reproducible byte for byte, not only its weights' SHA-256), and it loads back."""
    from deformnet.deformation import DeformationModel
    from deformnet.pretrained.build import weights_sha256

    shipped = load_default()
    shipped.save(tmp_path / "a.pt")
    shipped.save(tmp_path / "sub" / "b.pt")
    assert (tmp_path / "a.pt").read_bytes() == (tmp_path / "sub" / "b.pt").read_bytes()
    back = DeformationModel.from_checkpoint(tmp_path / "a.pt")
    assert weights_sha256(back) == weights_sha256(shipped)
