"""Bout features (`deformnet.behavior.bouts`): runs of a session without labels, and the
classifier that reads them (the bank path and the window path give the same features)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deformnet.behavior.bouts import BoutFeatures, bout_settings, run_spans
from deformnet.behavior.encoder import MechanismFeatures, WindowEncoder
from deformnet.behavior.features import SessionBank, context_features
from deformnet.behavior.heads import BehaviorClassifier, LinearHead
from deformnet.behavior.tracks import Session
from deformnet.body import default_mouse
from deformnet.deformation import build_net

FPS = 30.0


def _session(T: int = 300):
    """A mouse at rest 100 mm from a mechanism at the origin, walking 2 mm per frame over
    frames 40-69 (1 s), its nose (part 0) on the mechanism over frames 100-129 (1 s)."""
    body = np.asarray(default_mouse().points, np.float64)
    step = np.zeros((T, 3))
    step[40:70, 0] = 2.0
    rigid = body[None] + np.array([100.0, 100.0, 0.0]) + np.cumsum(step, 0)[:, None]
    deformed = rigid.copy()
    deformed[100:130, 0] = 0.0
    return rigid, deformed, np.ones(rigid.shape[:2], bool)


def test_run_spans():
    a, b = run_spans(np.array([0, 0, 1, 1, 1, 0], bool))
    assert a.tolist() == [0, 0, 2, 2, 2, 5] and b.tolist() == [1, 1, 4, 4, 4, 5]


def test_bout_features_measure_a_contact_and_a_walk():
    """The contact's length (about 1 s) on each of its frames, the time until it before and since it
    after; the walk's length (about 1 s) and how far into it a frame is; no contact: 0."""
    settings = bout_settings({"near": [10.0]})
    mech = MechanismFeatures([[0.0, 0.0, 0.0]], [0], ["m"], 50.0)
    bf = BoutFeatures(settings, FPS, mech)
    f = bf(*_session())
    assert f.shape == (300, bf.dim) and bf.dim == 4 + 1 * (1 + 2) + 2
    moving_len, still_len, to_end, from_start, contact, since, until = f[:, :7].T
    # the distance is averaged over 0.3 s first: the contact's run is a few frames shorter
    assert 0.6 <= contact[115] <= 1.0 and np.all(contact[110:120] == contact[115])
    assert contact[:95].max() == 0 and contact[135:].max() == 0
    assert abs(until[60] - 40 / FPS) < 0.2 and abs(since[160] - 31 / FPS) < 0.2
    assert until[115] == since[115] == 0
    assert since[60] == settings["cap"]  # no contact before it
    assert abs(moving_len[55] - 1.0) < 0.25 and still_len[55] == 0 and still_len[200] > 3
    assert to_end[45] > to_end[65] and from_start[45] < from_start[65]
    plain = BoutFeatures(settings, FPS, None)  # no lock box: the moving / still runs only
    assert plain.dim == 4
    np.testing.assert_allclose(plain(*_session()), f[:, :4])
    for bad in ({"near": [0.0]}, {"moving": -1.0}, {"speed": 3}):
        with pytest.raises(ValueError, match="bouts"):
            bout_settings(bad)
    assert bout_settings({"enabled": False}) is None


def test_classifier_reads_bout_features_in_both_paths():
    """A classifier with bout features: its features end with the mid frame's bout features
    (the head's frame columns include them), the same from a bank and from a window batch;
    without them in the batch or the bank: an error."""
    body = default_mouse()
    net = build_net({"_target_": "deformnet.nets.LSTMPredictor", "hidden": 8, "layers": 1,
                     "embed": 8, "num_parts": body.num_parts, "half_window": 2})  # fmt: skip
    mech = MechanismFeatures([[0.0, 0.0, 0.0]], [0], ["m"], 50.0)
    enc = WindowEncoder(net, np.asarray(body.points), 2, True, mechanisms=mech).eval()
    bf = BoutFeatures(bout_settings({}), FPS, mech)
    dim = BehaviorClassifier.feature_dim(enc.out_dim, (5,)) + bf.dim
    model = BehaviorClassifier(enc, LinearHead(dim, 2), (5,), 1, bf).eval()
    assert model.out_dim == dim and int(model.frame_columns()[-1]) == dim - 1
    r, d, o = _session(200)
    s = Session("s", r, d, o, np.arange(200), np.zeros(200, int))
    bank = SessionBank([s], model.half_window, bf)
    idx = torch.arange(0, 200, 7)
    b = bank.batch(idx)
    with torch.no_grad():
        direct = model.features(b["rigid"], b["deformed"], b["observed"], None, b["bouts"])
    banked = context_features(model, bank, idx)
    torch.testing.assert_close(banked, direct)
    torch.testing.assert_close(banked[:, -bf.dim :], torch.from_numpy(bf(r, d, o))[idx])
    with pytest.raises(ValueError, match="bouts must be"):
        model.features(b["rigid"], b["deformed"], b["observed"])
    with pytest.raises(ValueError, match="bout features"):
        context_features(model, SessionBank([s], model.half_window), idx)
