"""`DeformationModel`: a trained net as a differentiable function in global coordinates.

    model = DeformationModel.from_checkpoint("runs/train/.../checkpoints/best.ckpt")
    pred = model(rigid, deformed, observed)   # (..., W, K, 3) x2, (..., W, K) -> (..., K, 3)

All in global mm. The model canonicalises internally (mid pose by Kabsch of the mid frame's rigid
points onto its body model; or, for a net trained with a world up direction (`up`), that
pose's heading frame, `deformnet.tokens.canonicalize`), runs the net, and maps the prediction
back. It ignores the mid frame's deformed input, is differentiable in `rigid` and `deformed`
with plain reverse-mode autograd over batched independent windows (nn.LSTM does not support
torch.func vmap-Jacobians, and CPU scaled-dot-product attention has no forward-mode AD), and
supports `.double()`.

Checkpoints are data, never code: `from_checkpoint` reads them with ``weights_only=True``
(`deformnet.checkpoint.load_checkpoint`), builds the net they name only from the allow-list of
this project's nets with plain keyword values (`build_net`), and never imports Lightning (a
deformnet-train checkpoint holds only tensors and plain data).
"""

from __future__ import annotations

import io
import logging
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from deformnet.atomic import atomic_path
from deformnet.body import BodyModel
from deformnet.checkpoint import load_checkpoint, plain_kwargs
from deformnet.nets import NETS, is_part_agnostic
from deformnet.so3 import kabsch
from deformnet.tokens import canonicalize, check_window, uncanonicalize

log = logging.getLogger(__name__)

__all__ = [
    "DeformationModel",
    "build_net",
    "check_up",
    "frame_up",
    "check_world_up",
    "check_track_up",
    "CHECKPOINT_KEY",
]

CHECKPOINT_KEY = "deformation_model"  # extra entry the Lightning module adds to its checkpoints


def build_net(config: Mapping[str, Any], source: str = "") -> nn.Module:
    """A net from its config: a mapping with a `_target_` naming one of this project's nets
    (`deformnet.nets.NETS`, as in conf/net/*.yaml or a checkpoint's `net_config`) and plain
    keyword values (numbers, strings, bools, lists of those: `plain_kwargs`). Nothing a config
    names is imported or instantiated (no `hydra.utils.instantiate`): another `_target_`, a
    nested config (one carrying a `_target_` too) or any other value is a ValueError naming
    ``source`` (the checkpoint file), as is a net its arguments cannot build."""
    where = f"{source}: net_config" if source else "net config"
    if not isinstance(config, Mapping):
        raise ValueError(f"{where}: refused: a {type(config).__name__}, not a config mapping")
    target = config.get("_target_")
    if target is None or target == "":
        keys = sorted(str(k) for k in config)
        raise ValueError(f"{where} needs a '_target_' (a net class), got keys {keys}")
    if not isinstance(target, str) or target not in NETS:
        raise ValueError(
            f"{where}: refused: '_target_' {str(target)[:200]!r} is not one of this project's "
            f"nets ({', '.join(NETS)})"
        )
    kwargs = plain_kwargs(config, where, skip=("_target_",))
    try:
        return NETS[target](**kwargs)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"{where}: cannot build net '{target}': {_first_line(exc)}") from None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return (text.splitlines()[0] if text else type(exc).__name__)[:200]


def check_up(up: Sequence[float] | None) -> tuple[float, float, float] | None:
    """A world up direction: None, or 3 finite numbers, not all zero (returned unit length);
    ValueError otherwise."""
    if up is None:
        return None
    try:
        v = np.asarray(list(up), dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"up must be 3 numbers (the world's up direction), got {up!r}") from None
    if v.shape != (3,) or not np.isfinite(v).all() or not np.linalg.norm(v) > 0:
        raise ValueError(f"up must be 3 finite numbers, not all zero, got {list(v.ravel())}")
    v = v / np.linalg.norm(v)
    return (float(v[0]), float(v[1]), float(v[2]))


def frame_up(configured, pretrained=None, source: str = "") -> tuple[float, float, float] | None:
    """The world up a net reads its windows in: a pretrained net's own (`DeformationModel.up`;
    a configured up that differs is a ValueError naming `source`, its checkpoint: the net keeps
    its checkpoint's frame), else the configured one (`check_up`; None: the body frame)."""
    up = check_up(configured)
    if pretrained is None:
        return up
    if configured is not None and up != pretrained.up:
        raise ValueError(
            f"up={list(configured)} but the pretrained net {source or '(no path)'} reads "
            + ("the body frame" if pretrained.up is None else f"up={list(pretrained.up)}")
            + ": a pretrained net keeps its checkpoint's frame (leave up unset)"
        )
    return pretrained.up


MAX_UP_DEG = 60.0  # a mouse stands on its floor most of the time (median tilt far less; a
#                   world whose up is another axis: about 90 or 180)


def check_world_up(
    R, up: Sequence[float] | None, where: str, max_deg: float = MAX_UP_DEG
) -> float | None:
    """Whether a session's world has the up a heading-frame net assumes.

    R: (T, 3, 3) the session's body rotations (model -> world; non-finite frames ignored); up:
    the net's world up (None: a body-frame net, nothing to check). Returns the median angle
    (degrees) between the body's up axis (model Z, R e_z) and up; ValueError naming `where`
    when it is over `max_deg` (the world of that calibration is not up)."""
    if up is None:
        return None
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    R = R[np.isfinite(R).all((1, 2))]
    if not len(R):
        return None
    cos = np.clip(R[:, :, 2] @ np.asarray(up, dtype=float), -1.0, 1.0)
    angle = float(np.median(np.degrees(np.arccos(cos))))
    if angle > max_deg:
        raise ValueError(
            f"{where}: the deformation net reads windows in the heading frame of world up "
            f"{list(up)}, but this session's mouse has its up axis a median {angle:.0f} deg "
            f"away from it: the calibration's world is not up={list(up)}; use a net trained "
            "with up=null (the body frame, e.g. the default) or one trained with this world's up"
        )
    return angle


def check_track_up(rigid, body_points, up: Sequence[float] | None, where: str) -> float | None:
    """`check_world_up` for a track's rigid points (T, K, 3) mm (frames with a non-finite
    value ignored) of the body model `body_points` (K, 3): its rotations by Kabsch."""
    if up is None:
        return None

    rigid = np.array(rigid, dtype=float)  # a writable copy
    ok = np.isfinite(rigid).all((1, 2))
    if not ok.any():
        return None
    R, _ = kabsch(torch.as_tensor(rigid[ok]), torch.as_tensor(np.array(body_points, float)))
    return check_world_up(R.numpy(), up, where)


class DeformationModel(nn.Module):
    """A net plus what is needed to call it in global coordinates.

    net: an nn.Module with forward(rigid_c (B, W, K, 3), deformed_c (B, W, K, 3),
    observed (B, W, K)) -> (B, K, 3) in canonical coordinates; body: the rigid body model
    (K parts); half_window: n (W = 2n + 1); step: frames between the window's tokens (the
    frame step it was trained with: a window covers frames t - n step .. t + n step).
    steps: every token step it was trained with (`deformnet.data.Augment.steps`; default
    (step,)). up: None (canonical frame = the mid frame's body frame) or the world's up
    direction (3,) (the heading frame: the net sees pitch and roll; such a net assumes that its
    windows' world has that up, as the simulator's and the lock box's z up).
    Attributes: body, window, half_window, step, steps, net_config, up (tuple or None).
    """

    def __init__(
        self,
        net: nn.Module,
        body: BodyModel,
        half_window: int,
        net_config: Mapping[str, Any] | None = None,
        step: int = 1,
        steps: Sequence[int] | None = None,
        up: Sequence[float] | None = None,
    ) -> None:
        super().__init__()
        if int(step) < 1:
            raise ValueError(f"step must be >= 1, got {step}")
        self.up = check_up(up)
        self.net = net
        self.body = body
        self.step = int(step)
        # the token steps it was trained with (augmentation: several; the tracker's far steps)
        self.steps = tuple(sorted({int(s) for s in (steps or (self.step,))} | {self.step}))
        self.half_window = int(half_window)
        self.window = 2 * self.half_window + 1
        self.net_config = dict(net_config) if net_config is not None else None
        self.register_buffer(
            "body_points", torch.tensor(np.array(body.points), dtype=torch.float32)
        )

    def up_tensor(self, like: Tensor) -> Tensor | None:
        """`up` as a tensor of `like`'s dtype and device (None for the body frame)."""
        if self.up is None:
            return None
        return torch.tensor(self.up, dtype=like.dtype, device=like.device)

    @property
    def num_parts(self) -> int:
        return self.body.num_parts

    @property
    def part_agnostic(self) -> bool:
        """Whether the net identifies parts by their rest coordinates (`deformnet.nets.
        PartTransformer`): it runs on any skeleton (`for_body`)."""
        return is_part_agnostic(self.net)

    def for_body(self, body: BodyModel, where: str = "") -> DeformationModel:
        """This model on another body model (its parts, points and scale): the same net and
        weights (shared, not copied), window, steps and frame. A part-agnostic net takes any
        skeleton; a net that knows its parts by index only a body with the same parts in the
        same order (ValueError naming `where` otherwise)."""
        if not self.part_agnostic and tuple(body.parts) != tuple(self.body.parts):
            raise ValueError(
                f"{where + ': ' if where else ''}the net knows the parts "
                f"{list(self.body.parts)} by index, this body has {list(body.parts)}; use a "
                "part-agnostic net (net=parts, e.g. the shipped default) or train one for "
                "this skeleton"
            )
        model = DeformationModel(
            self.net, body, self.half_window, self.net_config, self.step, self.steps, self.up
        )
        return model.to(self.body_points.device).train(self.training)

    def _check(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> None:
        check_window(rigid, deformed, observed, self.window, self.num_parts, lead="...",
                     parts=tuple(self.body.parts))  # fmt: skip

    def canonical(
        self, rigid: Tensor, deformed: Tensor, observed: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Canonical prediction (B, K, 3) and the mid pose R (B, 3, 3), t (B, 3) for flat batches
        rigid, deformed (B, W, K, 3) global, observed (B, W, K)."""
        deformed = torch.where(observed[..., None].bool(), deformed, torch.zeros_like(deformed))
        rigid_c, deformed_c, R, t = canonicalize(
            rigid,
            deformed,
            self.body_points.to(rigid.dtype),
            self.half_window,
            self.up_tensor(rigid),
        )
        return self.net(rigid_c, deformed_c, observed.bool()), R, t

    def forward(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> Tensor:
        """Deformed mid-frame positions (..., K, 3), global mm, from windows (..., W, K, 3)."""
        self._check(rigid, deformed, observed)
        lead = rigid.shape[:-3]
        W, K = self.window, self.num_parts
        pred_c, R, t = self.canonical(
            rigid.reshape(-1, W, K, 3), deformed.reshape(-1, W, K, 3), observed.reshape(-1, W, K)
        )
        return uncanonicalize(pred_c, R, t).reshape(*lead, K, 3)

    # --- persistence --------------------------------------------------------------------
    def export(self) -> dict:
        """What a checkpoint needs to rebuild this model (net config, body, window, weights)."""
        if self.net_config is None:
            raise ValueError("cannot export a DeformationModel built without net_config")
        blob = {
            "net_config": dict(self.net_config),
            "body": self.body.to_mapping(),
            "half_window": self.half_window,
            "state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()},
        }
        if self.step != 1:  # (step 1 is what checkpoints without the key mean)
            blob["step"] = self.step
        if self.steps != (self.step,):
            blob["steps"] = list(self.steps)
        if self.up is not None:  # (no key: the body frame, as in every earlier checkpoint)
            blob["up"] = list(self.up)
        return blob

    @classmethod
    def from_export(cls, blob: Mapping[str, Any], source: str = "") -> DeformationModel:
        """The model `export` describes (``source``: the file it came from, for errors); its
        net is built by `build_net` (only this project's nets, plain arguments)."""
        body = BodyModel.from_mapping(
            blob["body"]["parts"], blob["body"].get("aliases"), blob["body"].get("name", "body")
        )
        net = build_net(blob["net_config"], source)
        model = cls(
            net,
            body,
            int(blob["half_window"]),
            blob["net_config"],
            int(blob.get("step", 1)),
            blob.get("steps"),
            blob.get("up"),
        )
        model.load_state_dict(blob["state_dict"])
        return model.eval()

    def save(self, path: str | os.PathLike) -> None:
        """Write a minimal checkpoint (atomic) that `from_checkpoint` reads. The same weights
        give the same bytes (serialised in memory: torch names the archive's records after the
        file it writes, here the atomic write's random temporary name)."""
        buf = io.BytesIO()
        torch.save({CHECKPOINT_KEY: self.export()}, buf)
        with atomic_path(path) as tmp:
            tmp.write_bytes(buf.getvalue())

    @classmethod
    def from_checkpoint(
        cls, path: str | os.PathLike, map_location: str | torch.device = "cpu"
    ) -> DeformationModel:
        """Load from a Lightning checkpoint written by `deformnet-train` (or from `save`).

        Returns the model in eval mode, float32 on `map_location`. Checkpoints are data, not
        code: they are read with ``torch.load(weights_only=True)`` (tensors, numbers, strings,
        lists and dicts only, `deformnet.checkpoint.load_checkpoint`), so a checkpoint that
        carries any other pickled object (which unpickling would run) is refused with a
        ValueError, as is a file that is not a torch checkpoint at all, and its net is built
        only from this project's nets with plain arguments (`build_net`).
        """
        ckpt = load_checkpoint(path, "checkpoint", map_location)
        if not isinstance(ckpt, dict):
            raise ValueError(
                f"{path} is not a deformnet checkpoint (it holds a {type(ckpt).__name__}, not a "
                "dict)"
            )
        if CHECKPOINT_KEY not in ckpt:
            raise ValueError(
                f"{path} is not a deformnet checkpoint (no '{CHECKPOINT_KEY}' entry); write it "
                "with deformnet-train or DeformationModel.save"
            )
        blob = ckpt[CHECKPOINT_KEY]
        if not isinstance(blob, dict):
            raise ValueError(f"{path}: its '{CHECKPOINT_KEY}' entry is not a dict")
        try:
            model = cls.from_export(blob, os.fspath(path))
        except (RuntimeError, KeyError, TypeError, AttributeError) as exc:  # weights that do not
            net_config = blob.get("net_config")  # fit the net, a missing or mistyped entry
            target = net_config.get("_target_") if isinstance(net_config, dict) else None
            raise ValueError(
                f"{path}: the checkpoint does not fit this version's {target or 'net'} "
                f"(written by an older or newer deformnet?); retrain with deformnet-train. "
                f"Detail: {_first_line(exc)}"
            ) from None
        return model.to(map_location)
