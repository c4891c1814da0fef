"""The default pretrained deformation net that ships with the package.

``real_mouse_parts.pt``: a `PartTransformer` (conf/net/parts.yaml: a part is identified by where
it sits on the body, its rest coordinates and side, not by an index, so the one net runs on 8,
22, 34 parts or a skeleton it has never seen) trained on a real mouse's motion: frames 0-2399
of ``shared/data/real-mouse-motion-3d`` filmed through simulated rigs (2-4 cameras, 8 / 22 / 34
parts, several detector seeds), tracked by adjust-track's defaults, with `deformation=self`'s
self-supervised objective on the tracks' tokens. `adjust.pretrain_real` reproduces it from its
seed, bit for bit on the kind of CPU that built it (elsewhere other float kernels give other
bits and a net as good)::

    python -m adjust.pretrain_real   # make pretrained: deformnet/pretrained/real_mouse_parts.pt

`adjust-track deformation=default` uses it as it is, on the session's own body
(`DeformationModel.for_body`), ``deformation=self`` fine-tunes it on the recording,
`deformnet-train pretrained=default` on a lab's sessions. Loading needs no Lightning
(`DeformationModel.from_checkpoint`).

``mouse_lstm_small.pt`` (`SIM_CHECKPOINT`): the earlier default, an `LSTMPredictor` for the
default mouse's 8 parts trained on the simulator only (`deformnet.pretrained.build`); kept for
comparison (``deformation=`` or ``pretrained=`` its path).
"""

from __future__ import annotations

from pathlib import Path

from deformnet.deformation import DeformationModel
from deformnet.paths import regular_file

__all__ = [
    "DEFAULT_CHECKPOINT",
    "SIM_CHECKPOINT",
    "default_checkpoint",
    "load_default",
    "load_net",
    "net_spec",
]

DEFAULT_CHECKPOINT = Path(__file__).resolve().parent / "real_mouse_parts.pt"
SIM_CHECKPOINT = Path(__file__).resolve().parent / "mouse_lstm_small.pt"


def default_checkpoint() -> Path:
    """The shipped checkpoint's path (ValueError if the installation lacks it)."""
    if not DEFAULT_CHECKPOINT.is_file():
        raise ValueError(
            f"the default pretrained net {DEFAULT_CHECKPOINT} is missing from this installation; "
            "rebuild it with `python -m adjust.pretrain_real` (make pretrained)"
        )
    return DEFAULT_CHECKPOINT


def load_default():
    """The shipped net as a `DeformationModel` (eval mode, float32, CPU)."""
    return DeformationModel.from_checkpoint(default_checkpoint())


def net_spec(value) -> str | None:
    """A net setting's value (``deformnet-train pretrained=``, ``adjust-track
    adapt.pretrained=``): None for null or the text "", "none" or "null" (from scratch), else
    the text (``default`` or a checkpoint path)."""
    if value is None or str(value).lower() in ("", "none", "null"):
        return None
    return str(value)


def load_net(spec, setting: str) -> DeformationModel | None:
    """The net a setting names (``deformnet-train pretrained=``, ``adjust-track
    adapt.pretrained=``): None -> None (from scratch), ``default`` -> the shipped net
    (`load_default`), else a checkpoint path (`net_spec`: "none" and "null" are None too). A
    missing path, or one that is not a regular file (a folder, FIFO or device), is a
    ValueError naming ``<setting>=<spec>``."""
    spec = net_spec(spec)
    if spec is None:
        return None
    if spec.lower() == "default":
        return load_default()
    p = Path(spec)
    if not p.exists():
        raise ValueError(f"{setting}={spec}: no such checkpoint")
    regular_file(p, f"{setting}={spec}: the checkpoint")
    return DeformationModel.from_checkpoint(p)
