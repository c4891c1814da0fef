"""``adjust-track deformation=``: how the body deforms, one object per choice.

- `RigidMode` (``rigid``): the rigid body model only.
- `InterpMode` (``interp``, the default): each part's body-frame offset interpolated (kriged)
  from its own 3D observations across its gaps (`adjust.lsq.observation.InterpObservation`).
- `NetMode`: a deformation net (`adjust.lsq.net_observation.NetObservation`) after rigid ->
  interp; its three sources are `CheckpointNet` (a deformnet-train checkpoint, ``net``),
  `DefaultNet` (the shipped pretrained net, ``default``) and `SelfNet` (that net fine-tuned on
  this recording's own tokens, ``self``, `adjust.adapt`). A net that does not beat the
  interpolation on the recording's held-out parts (`adjust.net_gate`) leaves the tracks to
  the interpolation, and summary.json says ``mode: interp`` with the reason.

`mode_from_config` picks the object once from ``deformation=``; `adjust.pipeline` then asks it
what it needs (`needs_consensus`, `checkpoint_body`, `prepare`) and lets it adjust the session
after the rigid adjustment (`adjust`, on an `Adjusting`): it returns the result and its facts,
summary.json's ``deformation`` block.
"""

from __future__ import annotations

from adjust.deformation_modes.base import (
    Adjusting,
    DeformationMode,
    InterpMode,
    RigidMode,
    deform_step,
    far_steps,
    interp_facts,
)
from adjust.deformation_modes.net import (
    CheckpointNet,
    DefaultNet,
    NetDecision,
    NetMode,
    SelfNet,
    load_deformation,
    make_deformable_observation,
)
from adjust.track_config import MEASURED

__all__ = [
    "MEASURED",
    "Adjusting",
    "CheckpointNet",
    "DefaultNet",
    "DeformationMode",
    "InterpMode",
    "NetDecision",
    "NetMode",
    "RigidMode",
    "SelfNet",
    "deform_step",
    "far_steps",
    "interp_facts",
    "load_deformation",
    "make_deformable_observation",
    "mode_from_config",
]


def mode_from_config(deformation) -> DeformationMode:
    """``deformation=``: null / ``rigid`` (the rigid model), ``interp`` (each part's body-frame
    offset interpolated from its own observations, `InterpObservation`), ``default`` (the
    shipped pretrained net, `deformnet.pretrained`), ``self`` (that net fine-tuned on this
    recording's own tokens, `adapt_net`), else a checkpoint (``net``)."""
    key = "" if deformation is None else str(deformation).lower()
    if key in ("", "none", "null", "rigid"):
        return RigidMode()
    if key == "interp":
        return InterpMode()
    if key == "default":
        return DefaultNet()
    if key == "self":
        return SelfNet()
    return CheckpointNet(str(deformation))
