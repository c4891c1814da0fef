"""``deformation=self``'s gate (``adapt.require_better``): the adapted net is checked against
the interpolation the tracks would otherwise get (``deformation=interp``'s kriging,
`adjust.net_gate.kriged_mid`) on held-out windows of the recording's tokens; a net no better
leaves the tracks to the interpolation and summary.json says ``deformation.mode: interp`` with
the reason. The fine-tuning itself is replaced by a given net (`adjust.adapt.adapt_net`)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from adjust.lsq.stochastic import OffsetCovariance, krige_offsets
from adjust.net_gate import beyond_share, kriged_mid, net_vs_kriging
from deformnet.body import default_mouse
from deformnet.confutil import compose
from deformnet.deformation import DeformationModel
from deformnet.sessions import SessionTokens
from deformnet.so3 import transform_points

torch.set_num_threads(1)


def _cov(K: int, sill: float = 100.0) -> OffsetCovariance:
    """A covariance under which two neighbours' kriging is their linear interpolation."""
    lags = np.array([1.0, 2.0, 4.0, 8.0])
    gamma = np.broadcast_to(0.01 * lags, (K, 3, 4)).copy()
    return OffsetCovariance(
        np.zeros((K, 3)), np.full((K, 3), sill), np.full((K, 3), 1e-4), lags, gamma, np.ones(K)
    )


def test_kriged_mid_krieges_body_frame_offsets_of_each_window():
    """Offsets linear in time in body axes on a turning body: kriging is exact across a gap
    (positions interpolated linearly are not); with nothing on one side the offset is held;
    the result is `krige_offsets` on each window's body-frame offsets."""
    body = default_mouse()
    K, W, mid = body.num_parts, 9, 4
    t = torch.arange(W, dtype=torch.float64)
    poses = torch.zeros(2, W, 6, dtype=torch.float64)
    poses[..., 2] = 0.3 * t  # turning 17 degrees a frame
    poses[..., 3] = 40.0 * t
    B = torch.tensor(np.array(body.points))
    rigid = transform_points(poses, B.expand(2, W, K, 3))
    off = torch.stack((t, -2 * t, 0.5 * t), -1)[None, :, None, :].expand(2, W, K, 3)
    rot = torch.cat((poses[..., :3], torch.zeros_like(poses[..., 3:])), -1)
    deformed = rigid + transform_points(rot, off.contiguous())
    observed = torch.ones(2, W, K, dtype=torch.bool)
    observed[:, 2:7, 0] = False  # part 0: neighbours 1 and 7
    observed[0, mid:, 1] = False  # window 0, part 1: nothing after mid -> frame 3 held
    observed[:, mid] = False
    batch = {"rigid": rigid, "deformed": deformed, "observed": observed}
    cov = _cov(K)
    pred = kriged_mid(batch, body.points, cov, mid)
    torch.testing.assert_close(pred[:, 0], deformed[:, mid, 0])
    torch.testing.assert_close(pred[1, 2:], deformed[1, mid, 2:])
    held = rigid[0, mid, 1] + transform_points(rot[0, mid], off[0, 3, 1][None])[0]
    torch.testing.assert_close(pred[0, 1], held)
    # the same as krige_offsets on window 0's body-frame offsets
    o = off[0].numpy()
    k, _ = krige_offsets(o, observed[0].numpy(), cov)
    expect = rigid[0, mid] + transform_points(rot[0, mid], torch.as_tensor(k[mid]))
    torch.testing.assert_close(pred[0], expect)
    # token steps: the covariance's lags are in frames
    far = _cov(K, sill=0.02)  # var > sill beyond a lag of 1 frame: the mean (0)
    assert torch.allclose(kriged_mid(batch, body.points, far, mid, step=8)[:, 0], rigid[:, mid, 0])


class _ShiftNet(nn.Module):
    """The rigid mid point moved by 10 mm: far worse than interpolation."""

    def __init__(self, half_window: int) -> None:
        super().__init__()
        self.mid = half_window

    def forward(self, rigid_c, deformed_c, observed):
        out = rigid_c[:, self.mid].clone()
        out[..., 0] += 10.0
        return out


class _Oracle(DeformationModel):
    """A net that knows the recording: the mid frame's measured points (found by the rigid
    mid points' centroid), the rigid mid point where none was measured. Beats any
    interpolation on held-out tokens."""

    def __init__(self, body, tokens) -> None:
        super().__init__(_ShiftNet(4), body, 4)
        self.centroids = torch.as_tensor(tokens.rigid, dtype=torch.float64).mean(-2)
        self.measured = torch.as_tensor(tokens.deformed, dtype=torch.float64)

    def forward(self, rigid, deformed, observed):
        mid = rigid[..., self.half_window, :, :]
        c = mid.double().mean(-2).reshape(-1, 3)
        f = torch.cdist(c, self.centroids).argmin(-1)
        X = self.measured[f].reshape(mid.shape)
        return torch.where(torch.isfinite(X), X, mid.double()).to(rigid.dtype)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A default-mouse scene: the shipped net's own kind of mouse."""
    from adjust.apps.simulate import run

    out = tmp_path_factory.mktemp("selfgate") / "scene"
    run(compose("scene", [f"output.dir={out}", "num_frames=600", "seed=7"]))
    return out


def _self_run(scene: Path, out: Path, monkeypatch, net: str, given=None, extra=()) -> dict:
    """adjust-track deformation=self with the fine-tuning replaced by `net`: ``shift`` (10 mm
    off) or ``oracle`` (`_Oracle`); the second half of the recording held out. given: a dict
    that receives the tokens the fine-tuning was given."""
    from helpers import track_session

    import adjust.adapt

    def adapt_net(tokens, where, adapt_cfg, progress):
        if given is not None:
            given["tokens"] = tokens
        body = default_mouse()
        body = body.__class__(body.parts, tokens.body_points, body.aliases, body.name)
        model = DeformationModel(_ShiftNet(4), body, 4) if net == "shift" else _Oracle(body, tokens)
        T = tokens.num_frames
        return model, {"checkpoint": str(where / "deformation.ckpt"), "data": {
            "split": "by time blocks", "val_blocks": [[T // 2, T]]}}  # fmt: skip

    monkeypatch.setattr(adjust.adapt, "adapt_net", adapt_net)
    return track_session(scene, out, ["deformation=self", *extra])


def test_a_net_no_better_than_kriging_is_reported_as_interp(scene, tmp_path, monkeypatch, caplog):
    with caplog.at_level(logging.WARNING):
        s = _self_run(scene, tmp_path / "bad", monkeypatch, "shift")
    d = s["deformation"]
    assert d["mode"] == "interp" and d["requested"] == "self"
    assert "does not beat interp's kriging by 2%" in d["reason"]
    h = d["heldout"]
    assert h["checked"] and h["net_all_mm"] > h["interp_all_mm"] and h["blocks"] == [[300, 600]]
    assert h["baseline"] == "interp's kriging with single-view anchors"
    assert "net_passes" not in d and d["adapt"]["used"] is False
    assert "summary.json says deformation.mode: interp" in caplog.text


def test_a_net_that_beats_kriging_is_kept(scene, tmp_path, monkeypatch):
    given = {}
    s = _self_run(scene, tmp_path / "good", monkeypatch, "oracle", given)
    # deform.net_anchors: the fine-tuning's windows observe the single views as inputs only
    tok = given["tokens"]
    assert tok.inputs is not None and tok.inputs.any() and not (tok.inputs & tok.observed).any()
    d = s["deformation"]
    h = d["heldout"]
    assert h["checked"] and h["net_all_mm"] < h["interp_all_mm"], h
    assert d["mode"] == "self" and "reason" not in d and d["adapt"]["used"] is True
    assert d["net_passes"] >= 1 and d["net_used_fraction"] > 0


def _anchored_recording(T: int = 400):
    """A still body whose parts sway (x offset 5 sin(2 pi t / 12) mm), measured in 3D on every
    4th frame only and through one view (single-view anchors, exact here) on the others."""
    from adjust.net_gate import Anchors
    from deformnet.sessions import SessionTokens

    body = default_mouse()
    K = body.num_parts
    B = np.array(body.points)
    t = np.arange(T)
    rigid = np.broadcast_to(B, (T, K, 3)).copy()
    truth = rigid.copy()
    truth[..., 0] += 5.0 * np.sin(2 * np.pi * t / 12)[:, None]
    observed = np.broadcast_to((t % 4 == 0)[:, None], (T, K)).copy()
    tokens = SessionTokens(rigid, truth, observed, tuple(body.parts), B, body.name)
    anchors = Anchors(
        torch.as_tensor(truth),
        torch.as_tensor(~observed),
        torch.full((T, K), 0.01, dtype=torch.float64),
    )
    return body, tokens, anchors


def test_the_gate_krieges_from_the_single_view_anchors_of_its_windows_frames():
    """The fallback interp rests on single-view anchors inside the gaps, so the gate's kriging
    must too, each window's anchors taken from its own recording frames (held-out blocks that
    do not start at frame 0 included): with them its error is a fraction of the 3D-only one."""
    from adjust.net_gate import net_vs_kriging

    body, tokens, anchors = _anchored_recording()
    model = DeformationModel(_ShiftNet(4), body, 4)
    cov = _cov(body.num_parts)
    blocks = [[100, 300]]
    plain = net_vs_kriging(model, tokens, cov, blocks, 1, windows=128)
    anch = net_vs_kriging(model, tokens, cov, blocks, 1, windows=128, anchors=anchors)
    assert plain["baseline"] == "interp's kriging"
    assert anch["baseline"] == "interp's kriging with single-view anchors"
    assert anch["targets"] == plain["targets"] and anch["net_all_mm"] == plain["net_all_mm"]
    assert anch["interp_all_mm"] < 0.3 * plain["interp_all_mm"], (anch, plain)
    # a view of the held-out mid frame itself (50 mm off here) is never used
    mid_off = anchors.points.clone()
    mid_off[torch.as_tensor(tokens.observed)] += 50.0
    leak = anchors.__class__(mid_off, torch.ones_like(anchors.mask), anchors.var)
    same = net_vs_kriging(model, tokens, cov, blocks, 1, windows=128, anchors=leak)
    assert same["interp_all_mm"] == pytest.approx(anch["interp_all_mm"])


class _WindowMean(nn.Module):
    """Each part's mean observed deformed position over the window (the rigid mid point where
    none): a stand-in net that reads its inputs."""

    def forward(self, rigid_c, deformed_c, observed):
        o = observed[..., None].to(rigid_c.dtype)
        c = o.sum(-3)
        mid = rigid_c[:, rigid_c.shape[1] // 2]
        return torch.where(c > 0, (deformed_c * o).sum(-3) / c.clamp_min(1), mid)


def test_the_gate_gives_the_net_the_anchors_when_the_tracker_does():
    """``deform.net_anchors``: the gate's net sees the windows' single-view anchors as the
    tracker's does (its error changes: here the window mean of the anchors is the closer one),
    the kriging is the same."""
    from adjust.net_gate import net_vs_kriging

    body, tokens, anchors = _anchored_recording()
    model = DeformationModel(_WindowMean(), body, 4)
    cov = _cov(body.num_parts)
    kw = {"windows": 128, "anchors": anchors}
    plain = net_vs_kriging(model, tokens, cov, [[100, 300]], 1, **kw)
    fed = net_vs_kriging(model, tokens, cov, [[100, 300]], 1, net_anchors=True, **kw)
    assert fed["interp_all_mm"] == plain["interp_all_mm"]
    assert fed["net_all_mm"] < 0.8 * plain["net_all_mm"], (fed, plain)


def test_without_net_anchors_the_fine_tuning_sees_3d_observations_only(
    scene, tmp_path, monkeypatch
):
    given = {}
    _self_run(scene, tmp_path / "plain", monkeypatch, "shift", given, ["deform.net_anchors=false"])
    assert given["tokens"].inputs is None


def test_beyond_share_counts_the_unobserved_frames_out_of_any_observations_reach():
    observed = np.zeros((40, 2), bool)
    observed[[0, 39], 0] = True  # part 0: a 38-frame gap
    observed[::3, 1] = True  # part 1: never more than 2 frames from an observation
    anchors = np.zeros((40, 2), bool)
    share = beyond_share(observed, None, 4, [(0, 40)])
    assert share[0] == pytest.approx(30 / 38) and share[1] == 0.0  # frames 5-34 of 1-38
    anchors[20, 0] = True  # an anchor in the gap's middle: frames 16-24 are within reach
    with_anchor = beyond_share(observed, anchors, 4, [(0, 40)])
    assert with_anchor[0] == pytest.approx(21 / 38)
    assert beyond_share(observed, None, 4, [(0, 20)])[0] == pytest.approx(15 / 19)


class _NearOnly(nn.Module):
    """The window mean of the part's observed tokens (exact for a still part), 20 mm off where
    the part is alone in its window (hidden throughout)."""

    def forward(self, rigid_c, deformed_c, observed):
        o = observed[..., None].to(rigid_c.dtype)
        c = o.sum(-3)
        mid = rigid_c[:, rigid_c.shape[1] // 2]
        return torch.where(c > 0, (deformed_c * o).sum(-3) / c.clamp_min(1), mid + 20.0)


def test_the_gate_judges_the_net_where_the_tracks_use_it_beyond_its_window():
    """A part hidden for long stretches: beyond the window's reach of any observation the
    tracks take the net's prediction from a window without that part. The gate before stop 53
    (``beyond=False``) judged training-like windows only, where a part is rarely alone; with
    ``beyond`` (the default) the windows with the part alone count too, weighed by the share of
    its unobserved frames that lie so far from any observation: a net that errs there loses
    to the kriging, which holds the mean offset (here 0.87 mm off)."""
    body = default_mouse()
    K, T = body.num_parts, 600
    B = np.array(body.points)
    rigid = np.broadcast_to(B, (T, K, 3)).copy()
    truth = rigid + 0.5
    observed = np.zeros((T, K), bool)
    observed[(np.arange(T) % 100) < 40] = True  # 40 frames seen, 60 hidden, in turn
    tokens = SessionTokens(rigid, truth, observed, tuple(body.parts), B, body.name)
    model = DeformationModel(_NearOnly(), body, 12)
    cov = _cov(K)
    near = net_vs_kriging(model, tokens, cov, None, 1, windows=256, beyond=False)
    both = net_vs_kriging(model, tokens, cov, None, 1, windows=256)
    assert "beyond_share" not in near and both["net_near_mm"] == near["net_mm"]
    # 12 frames' reach each side: 36 of each gap's 60 frames, 48 of the last (none after it)
    share = (5 * 36 + 48) / 360
    assert both["beyond_share"] == pytest.approx([share] * K, abs=1e-4)
    assert min(both["net_beyond_mm"]) > 30.0  # 20 mm on each axis
    assert both["interp_beyond_mm"] == pytest.approx([0.5 * 3**0.5] * K)
    for k in range(K):  # each part's errors near and beyond, mixed by its share
        mixed = (1 - share) * near["net_mm"][k] ** 2 + share * both["net_beyond_mm"][k] ** 2
        assert both["net_mm"][k] == pytest.approx(mixed**0.5, rel=1e-3)
    assert both["net_all_mm"] > 10 * near["net_all_mm"] > 0
    assert both["net_all_mm"] > 20 * both["interp_all_mm"]
