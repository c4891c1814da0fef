"""The default pretrained deformation net that ships with the package.

``mouse_lstm_small.pt``: an `LSTMPredictor` (conf/net/lstm_small.yaml, half-window 16) trained
on the default simulator's mice (Table 1 body) by `deformnet.pretrained.build`, which reproduces
it from its seed, bit for bit on the kind of CPU that built it (elsewhere other float kernels
give other bits and a net as good)::

    python -m deformnet.pretrained.build   # writes deformnet/pretrained/mouse_lstm_small.pt

`adjust-track deformation=default` uses it as it is, ``deformation=self`` fine-tunes it on the
recording, `deformnet-train pretrained=default` on a lab's sessions. Loading needs no
Lightning (`DeformationModel.from_checkpoint`).
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["DEFAULT_CHECKPOINT", "default_checkpoint", "load_default"]

DEFAULT_CHECKPOINT = Path(__file__).resolve().parent / "mouse_lstm_small.pt"


def default_checkpoint() -> Path:
    """The shipped checkpoint's path (ValueError if the installation lacks it)."""
    if not DEFAULT_CHECKPOINT.is_file():
        raise ValueError(
            f"the default pretrained net {DEFAULT_CHECKPOINT} is missing from this installation; "
            "rebuild it with `python -m deformnet.pretrained.build`"
        )
    return DEFAULT_CHECKPOINT


def load_default():
    """The shipped net as a `DeformationModel` (eval mode, float32, CPU)."""
    from deformnet.deformation import DeformationModel

    return DeformationModel.from_checkpoint(default_checkpoint())
