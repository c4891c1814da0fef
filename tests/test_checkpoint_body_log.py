"""``deformation=PATH`` (`adjust.deformation_modes.net.CheckpointNet`): the checkpoint's body
model replaces the ``body`` group's, and that is said once per session, not once per chunk of a
long session (the chunks reuse the mode the sample chose)."""

from __future__ import annotations

import logging

import numpy as np
from helpers import tiny_deformation_model

from adjust.deformation_modes.net import CheckpointNet
from deformnet.body import BodyModel
from deformnet.confutil import compose


def test_the_checkpoints_body_is_said_once_per_session(tmp_path, caplog):
    model = tiny_deformation_model()
    body = model.body
    model.body = BodyModel(body.parts, np.asarray(body.points) * 1.1, body.aliases, "bigger")
    path = tmp_path / "net.ckpt"
    model.save(path)
    body_cfg = compose("track", []).body
    mode = CheckpointNet(str(path))
    with caplog.at_level(logging.WARNING):
        got = [mode.checkpoint_body(body_cfg) for _ in range(3)]  # the sample, then two chunks
    assert caplog.text.count("using the checkpoint's body model 'bigger'") == 1, caplog.text
    for b in got:  # every call still gives the checkpoint's model
        assert b.name == "bigger"
        np.testing.assert_allclose(b.points, np.asarray(body.points) * 1.1, rtol=1e-6)
