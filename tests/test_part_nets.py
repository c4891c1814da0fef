"""The part-agnostic net (deformnet.nets.PartTransformer): one set of weights for any skeleton.

Parts are identified by their rest coordinates, not an index: the output is equivariant to the
parts' order, the same weights run on 8, 22 and 34 parts, `DeformationModel.for_body` moves a
model onto another skeleton (an index net refuses), `deformnet-train pretrained=` fine-tunes it
on another skeleton, and a mixed-skeleton fit (`deformnet.pretrained.fit`) learns.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deformnet.body import BodyModel, default_mouse
from deformnet.deformation import DeformationModel, build_net
from deformnet.nets import NETS, LSTMPredictor, PartTransformer, rest_features
from deformnet.so3 import rodrigues_to_matrix, transform_points

torch.set_num_threads(1)
N = 3
W = 2 * N + 1


def _body(K: int, seed: int = 0) -> BodyModel:
    """A symmetric-ish random body of K parts (mm), X right, Y forward, Z up."""
    g = np.random.default_rng(seed)
    pts = g.normal(size=(K, 3)) * np.array([10.0, 30.0, 8.0])
    return BodyModel.from_mapping({f"p{i}": list(map(float, p)) for i, p in enumerate(pts)})


def _net(**kw) -> PartTransformer:
    torch.manual_seed(0)
    net = PartTransformer(None, N, d_model=16, heads=2, layers=2, ff=32, hidden=32, **kw)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():  # not the zero-initialised rigid baseline
        net.out.weight.copy_(0.3 * torch.randn(net.out.weight.shape, generator=g))
        net.out.bias.copy_(0.3 * torch.randn(net.out.bias.shape, generator=g))
    return net.eval()


def _window(body: BodyModel, B: int = 4, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    K = body.num_parts
    M = torch.tensor(np.array(body.points), dtype=torch.float64)
    t = torch.arange(W, dtype=torch.float64)[None, :, None]
    poses = torch.cat(
        (torch.randn(B, 1, 3, generator=g, dtype=torch.float64) + 0.05 * t,
         50 * torch.randn(B, 1, 3, generator=g, dtype=torch.float64) + 2 * t),
        -1,
    )  # fmt: skip
    rigid = transform_points(poses, M.expand(B, W, K, 3))
    deformed = rigid + 2 * torch.randn(B, W, K, 3, generator=g, dtype=torch.float64)
    observed = torch.rand(B, W, K, generator=g) > 0.3
    return rigid, deformed, observed


@pytest.mark.parametrize("K", [8, 22, 34])
def test_one_net_runs_on_any_number_of_parts(K):
    body = _body(K)
    model = DeformationModel(_net(), body, N).double().eval()
    rigid, deformed, observed = _window(body)
    out = model(rigid, deformed, observed)
    assert out.shape == (4, K, 3) and torch.isfinite(out).all()
    assert not torch.allclose(out, rigid[:, N], atol=1e-3)  # the net does something


def test_untrained_part_net_is_the_rigid_baseline():
    body = _body(8)
    net = PartTransformer(None, N, d_model=16, heads=2, layers=1, ff=32, hidden=32).double()
    rigid, deformed, observed = _window(body)
    model = DeformationModel(net, body, N).double()
    assert torch.allclose(model(rigid, deformed, observed), rigid[:, N], atol=1e-9)


def test_permuting_the_parts_permutes_the_output():
    body = _body(22, seed=3)
    rigid, deformed, observed = _window(body, seed=2)
    perm = torch.randperm(22, generator=torch.Generator().manual_seed(5))
    pbody = BodyModel(
        tuple(body.parts[i] for i in perm), np.array(body.points)[perm.numpy()], {}, "perm"
    )
    net = _net().double()
    out = DeformationModel(net, body, N).double()(rigid, deformed, observed)
    out_p = DeformationModel(net, pbody, N).double()(
        rigid[:, :, perm], deformed[:, :, perm], observed[:, :, perm]
    )
    assert torch.allclose(out_p, out[:, perm], atol=1e-9)
    # an index net (LSTMPredictor) is not equivariant: the test can tell
    torch.manual_seed(0)
    lstm = LSTMPredictor(22, N, hidden=8, embed=8).double().eval()
    with torch.no_grad():
        lstm.head.out.weight.normal_(0, 0.3)
    a = DeformationModel(lstm, body, N).double()(rigid, deformed, observed)
    b = DeformationModel(lstm, pbody, N).double()(
        rigid[:, :, perm], deformed[:, :, perm], observed[:, :, perm]
    )
    assert not torch.allclose(b, a[:, perm], atol=1e-4)


def test_rigid_motion_equivariance_and_no_mid_frame_leak():
    body = _body(8, seed=1)
    model = DeformationModel(_net().double(), body, N).double()
    rigid, deformed, observed = _window(body)
    Q = rodrigues_to_matrix(torch.tensor([0.7, -2.1, 1.3], dtype=torch.float64))
    shift = torch.tensor([300.0, -150.0, 40.0], dtype=torch.float64)
    out = model(rigid, deformed, observed)
    out2 = model(rigid @ Q.T + shift, deformed @ Q.T + shift, observed)
    assert torch.allclose(out2, out @ Q.T + shift, atol=1e-8)
    d2 = deformed.clone()
    d2[:, N] += 10.0
    o2 = observed.clone()
    o2[:, N] = True
    assert torch.equal(model(rigid, d2, o2), model(rigid, deformed, observed.clone()))


def test_rest_features_identify_parts_by_place_and_side():
    M = torch.tensor(np.array(default_mouse().points), dtype=torch.float64)[None]
    f = rest_features(M)
    assert torch.allclose(rest_features(2.5 * M + 7.0), f, atol=1e-9)  # size and place free
    parts = default_mouse().parts
    left, right = parts.index("left_ear"), parts.index("right_ear")
    nose = parts.index("nose_tip")
    assert f[0, left, 4] < -0.5 and f[0, right, 4] > 0.5 and abs(f[0, nose, 4]) < 1e-9
    assert torch.allclose(f[0, left, 3], f[0, right, 3])  # the same distance from the midline


def test_for_body_shares_the_net_and_index_nets_refuse():
    body8, body15 = _body(8), _body(15, seed=4)
    model = DeformationModel(_net(), body8, N, {"_target_": "deformnet.nets.PartTransformer"})
    moved = model.for_body(body15)
    assert moved.net is model.net and moved.body.parts == body15.parts and moved.part_agnostic
    lstm = DeformationModel(LSTMPredictor(8, N, hidden=8, embed=8), body8, N)
    assert lstm.for_body(_body(8, seed=9)).num_parts == 8  # same parts: fine
    with pytest.raises(ValueError, match="by index"):
        lstm.for_body(body15, "deformation=default")


def test_part_net_checkpoint_round_trip_on_another_skeleton(tmp_path):
    assert NETS["deformnet.nets.PartTransformer"] is PartTransformer
    cfg = {"_target_": "deformnet.nets.PartTransformer", "num_parts": 8, "half_window": N,
           "d_model": 16, "heads": 2, "layers": 1, "ff": 32, "hidden": 32}  # fmt: skip
    net = build_net(cfg)
    with torch.no_grad():
        net.out.weight.normal_(0, 0.3)
    model = DeformationModel(net.eval(), _body(8), N, cfg)
    model.save(tmp_path / "m.pt")
    back = DeformationModel.from_checkpoint(tmp_path / "m.pt")
    body = _body(34, seed=2)
    r, d, o = (x.float() if x.is_floating_point() else x for x in _window(body))
    assert torch.equal(back.for_body(body)(r, d, o), model.for_body(body)(r, d, o))


def test_train_fine_tunes_a_part_net_on_another_skeleton(tmp_path):
    from deformnet.confutil import compose
    from deformnet.train import build_model

    cfg_net = {"_target_": "deformnet.nets.PartTransformer", "num_parts": 8, "half_window": N,
               "d_model": 16, "heads": 2, "layers": 1, "ff": 32, "hidden": 32}  # fmt: skip
    pre = DeformationModel(build_net(cfg_net), _body(8), N, cfg_net)
    body = _body(15, seed=6)
    lit, got, _ = build_model(compose("train", ["net=lstm_small"]), body, pre)
    assert got.parts == body.parts and isinstance(lit.model.net, PartTransformer)
    for (k, a), b in zip(lit.model.net.state_dict().items(), pre.net.state_dict().values()):
        assert torch.equal(a, b), k
    lstm = DeformationModel(LSTMPredictor(8, N, hidden=8, embed=8), _body(8), N,
                            {"_target_": "deformnet.nets.LSTMPredictor", "num_parts": 8,
                             "half_window": N, "hidden": 8, "embed": 8})  # fmt: skip
    with pytest.raises(ValueError, match="train from scratch"):
        build_model(compose("train", ["net=lstm_small"]), body, lstm)


def test_mixed_skeleton_fit_learns_a_shared_deformation():
    """Two skeletons whose parts lag their rigid points by the same place-dependent offset:
    one fit on both predicts the mid frame better than the rigid model on a third, unseen one."""
    from deformnet.heldout import heldout_errors
    from deformnet.pretrained.fit import FitConfig, fit_sessions
    from deformnet.sessions import SessionTokens

    def session(K: int, seed: int, T: int = 300) -> SessionTokens:
        body = _body(K, seed)
        g = torch.Generator().manual_seed(seed)
        t = torch.arange(T, dtype=torch.float64)[:, None]
        poses = torch.cat((0.02 * t * torch.tensor([[0.0, 0.0, 1.0]]),
                           torch.cat((t, 0.5 * t, 0 * t), 1)), 1)  # fmt: skip
        M = torch.tensor(np.array(body.points), dtype=torch.float64)
        rigid = transform_points(poses, M.expand(T, K, 3))
        sway = torch.sin(0.2 * t)[:, :, None] * M[None, :, 1:2] / 10.0  # a body-place wave
        deformed = rigid + sway * torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
        observed = (torch.rand(T, K, generator=g) > 0.2).numpy()
        r, d = rigid.float().numpy(), deformed.float().numpy()
        return SessionTokens(r, d, observed, tuple(body.parts), np.array(body.points), "b")

    cfg = FitConfig(net={"_target_": "deformnet.nets.PartTransformer", "half_window": N,
                         "d_model": 16, "heads": 2, "layers": 1, "ff": 32, "hidden": 32},
                    steps=150, batch_size=32, lr=3e-3, warmup_steps=10, log_every=0)  # fmt: skip
    model, facts = fit_sessions([session(8, 1), session(22, 2)], cfg, seed=0)
    assert [s["parts"] for s in facts["skeletons"]] == [8, 22]
    unseen = session(15, 3)

    h = heldout_errors(model.for_body(unseen.body_model()), unseen, windows=256)
    rigid = float(np.sqrt(np.nanmean(np.square(h["rigid_mm"]))))
    assert h["net_all_mm"] < 0.8 * rigid  # measured 0.70x
