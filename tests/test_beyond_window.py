"""``deform.beyond_window``: where the net's window does not see a part on both sides, the net
(``net``), the interpolation (``interp``) or, with interp's single-view anchors,
the anchored interpolation near an anchor and the net elsewhere (``anchored``); and
``deform.net_anchors``: those anchors among the net's window inputs."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from adjust.lsq.net_observation import NetObservation, _near
from adjust.lsq.observation import InterpObservation
from deformnet.body import default_mouse


class WindowMean(nn.Module):
    """A stand-in net: each part's mean observed deformed position over the window (rigid
    mid point where none)."""

    def __init__(self) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.zeros(()))

    def forward(self, rigid, deformed, observed):
        o = observed[..., None].to(rigid.dtype)
        c = o.sum(-3)
        mid = rigid[..., rigid.shape[-3] // 2, :, :]
        return torch.where(c > 0, (deformed * o).sum(-3) / c.clamp_min(1), mid)


def test_near_marks_the_frames_within_reach_of_a_flag():
    f = torch.zeros(12, 2, dtype=torch.bool)
    f[5, 0] = True
    f[0, 1] = True
    near = _near(f, 2)
    assert near[:, 0].nonzero().flatten().tolist() == [3, 4, 5, 6, 7]
    assert near[:, 1].nonzero().flatten().tolist() == [0, 1, 2]
    assert torch.equal(_near(f, 0), f)


def _scene():
    body = torch.tensor(np.asarray(default_mouse().points), dtype=torch.float64)
    T, K = 80, body.shape[0]
    poses = torch.zeros(T, 6, dtype=torch.float64)
    poses[:, 3] = torch.arange(T, dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    data = body[None] + poses[:, None, 3:] + torch.randn(T, K, 3, generator=g, dtype=torch.float64)
    observed = torch.ones(T, K, dtype=torch.bool)
    observed[30:70, 1] = False  # a 40-frame gap: beyond a 5-frame window
    # part 1 seen by one camera on frame 40: interp's single-view anchor (its fused point)
    ncams = torch.where(observed, 2, 0)
    ncams[40, 1] = 1
    points = data + 5.0 * (~observed)[..., None]  # the anchor 5 mm off the truth per axis
    sd = torch.ones(T, K, dtype=torch.float64)
    anchored = InterpObservation(body, data, observed).anchored(points, sd, ncams)
    return body, poses, data, observed, anchored


def test_anchored_uses_the_anchored_interpolation_near_an_anchor_and_the_net_elsewhere():
    body, poses, data, observed, anchored = _scene()

    def obs(mode, interp=None):
        o = NetObservation(WindowMean(), body, 5, data, observed, 0.0, 4096, "frozen",
                           beyond_window=mode, interp=interp)  # fmt: skip
        o.prepare(poses)
        return o

    net, inside = obs("net"), obs("interp")
    assert net.use_net[30:70, 1].all() and not inside.use_net[32:68, 1].any()
    a = obs("anchored", anchored)
    # within the window's reach (2 frames) of the anchor: the anchored interpolation
    assert not a.use_net[38:43, 1].any()
    assert a.use_net[32:37, 1].all() and a.use_net[44:68, 1].all()
    X, _ = a.points(poses, jacobian=False)
    Xn, _ = net.points(poses, jacobian=False)
    # near the anchor: the anchored interpolation's prediction (a copy of interp's stage)
    assert a.interp is not anchored and a.interp.anchors is not None
    near = a.interp._M[38:43, 1] + poses[38:43, None, 3:]
    torch.testing.assert_close(X[38:43, 1], near[:, 0])
    assert not torch.allclose(Xn[38:43, 1], X[38:43, 1])
    torch.testing.assert_close(X[50, 1], Xn[50, 1])  # far from the anchor: the net
    assert torch.isfinite(a.factor).all()  # the held-out factor on 3D observations only
    torch.testing.assert_close(a.factor, net.factor)
    # a window of the session keeps the anchors
    w = a.window(30, 60)
    w.prepare(poses[30:60])
    assert not w.use_net[8:13, 1].any() and w.use_net[20:28, 1].all()


def test_anchored_without_anchors_is_the_net_and_bad_settings_are_refused():
    body, poses, data, observed, _ = _scene()
    a = NetObservation(WindowMean(), body, 5, data, observed, 0.0, 4096, "frozen",
                       beyond_window="anchored")  # fmt: skip
    a.prepare(poses)
    assert a.use_net[30:70, 1].all()
    with pytest.raises(ValueError, match="beyond_window must be one of net, interp, anchored"):
        NetObservation(WindowMean(), body, 5, data, observed, 0.0, 64, "frozen",
                       beyond_window="both")  # fmt: skip
    with pytest.raises(ValueError, match="interp must observe"):
        NetObservation(WindowMean(), body, 5, data[:10], observed[:10], 0.0, 64, "frozen",
                       interp=InterpObservation(body, data, observed))  # fmt: skip


def test_net_anchors_put_the_single_views_among_the_nets_window_inputs():
    """A part in a 40-frame gap, seen by one camera on frame 40: with net_anchors the net's
    windows around frame 40 observe the anchor's fused point (the stand-in net returns it);
    without, they observe nothing of the part (the rigid point). The 3D observations and the
    held-out factor are the same either way."""
    body, poses, data, observed, anchored = _scene()

    def obs(net_anchors):
        o = NetObservation(WindowMean(), body, 5, data, observed, 0.0, 4096, "frozen",
                           beyond_window="net", interp=anchored,
                           net_anchors=net_anchors)  # fmt: skip
        o.prepare(poses)
        return o

    with_a, without = obs(True), obs(False)
    X, _ = with_a.points(poses, jacobian=False)
    Xo, _ = without.points(poses, jacobian=False)
    anchor = anchored.data[40, 1]  # the fused point, 5 mm off per axis
    for t in range(38, 43):  # every window that holds frame 40
        torch.testing.assert_close(X[t, 1], anchor)
        assert (Xo[t, 1] - anchor).norm() > 5.0
    torch.testing.assert_close(X[50, 1], Xo[50, 1])  # beyond the anchor's windows: the same
    torch.testing.assert_close(X[:, 0], Xo[:, 0])
    torch.testing.assert_close(with_a.factor, without.factor)


def test_with_single_views_adds_one_view_part_frames_only_where_no_3d_one():
    from adjust.lsq.observation import with_single_views

    data = torch.zeros(2, 3, 4, 3, dtype=torch.float64)  # leading dims (2, 3), K = 4
    observed = torch.zeros(2, 3, 4, dtype=torch.bool)
    observed[..., 0] = True
    points = torch.ones(2, 3, 4, 3, dtype=torch.float32)
    views = torch.zeros(2, 3, 4, dtype=torch.bool)
    views[..., :2] = True  # part 0 also has a 3D observation: kept as it is
    d, o, one = with_single_views(data, observed, points, views)
    assert d.dtype == torch.float64 and d.shape == data.shape
    assert one[..., 1].all() and not one[..., [0, 2, 3]].any()
    assert torch.equal(o, observed | one)
    assert (d[..., 1, :] == 1).all() and (d[..., [0, 2, 3], :] == 0).all()
