"""The behavior classifier's window encoder (plain `nn.Module`s, no Lightning).

`WindowEncoder` runs a deformation net's encoder (`deformnet.nets.LSTMPredictor`,
`TransformerPredictor`: everything before the per-part output layer) on global windows:

    WindowEncoder(net, body_points, half_window)(rigid, deformed, observed) -> (B, D)

    rigid, deformed (B, W, K, 3) global mm, observed (B, W, K) bool; W = 2 half_window + 1;
    optional scale (B,): each window's animal size relative to the rigid model (`normalize_size`).

It canonicalises the window (the mid frame's rigid-model coordinates, `deformnet.tokens`), runs
the net's encoder, and appends what the canonical frame removes but behavior depends on ("frame
features"): the mid pose and the mid frame's own deformation offsets; with a lock box
(`MechanismFeatures`) the distance of chosen parts to each mechanism; with ``measurements`` the
SimBA-style measurements (`pose_measurements`). Given a body scale (the session's,
`deformnet.behavior.tracks.body_scale`) the points are shrunk to the model's size first
(`normalize_size`); the mechanism distances stay those of the real points.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from deformnet.deformation import check_up
from deformnet.nets import LSTMPredictor, TransformerPredictor
from deformnet.so3 import kabsch
from deformnet.windows import window_summary

__all__ = ["MechanismFeatures", "normalize_size", "pose_measurements", "WindowEncoder"]


def normalize_size(rigid: Tensor, points: Tensor, scale: Tensor) -> Tensor:
    """Points (..., K, 3) brought to the rigid model's size: c + (p - c) / scale, about the
    posed rigid model's centroid c = rigid (..., K, 3).mean(-2), scale (...,) > 0 the animal's
    size relative to the model (`deformnet.behavior.tracks.body_scale`). Pose and place are
    kept; the parts' positions relative to the body (offsets, part distances, heights above
    the centroid) are divided by the scale."""
    if rigid.shape != points.shape or rigid.dim() < 2 or rigid.shape[-1] != 3:
        raise ValueError(
            f"rigid / points must be (..., K, 3) alike, got {tuple(rigid.shape)} / "
            f"{tuple(points.shape)}"
        )
    if tuple(scale.shape) != tuple(rigid.shape[:-2]):
        raise ValueError(f"scale must be {tuple(rigid.shape[:-2])}, got {tuple(scale.shape)}")
    c = rigid.mean(-2, keepdim=True)
    return c + (points - c) / scale.to(points.dtype)[..., None, None]


class MechanismFeatures(nn.Module):
    """Where the mouse is relative to a lock box's mechanisms, as frame features: the distance
    of each chosen part to each mechanism and, per mechanism, the nearest of those parts
    (SimBA's ROI distances), divided by ``scale`` mm.

    positions (M, 3) the mechanisms' global positions (mm, the tracks' frame); parts (P,) the
    chosen parts' indices in the body model's part order; names: the mechanisms' names (M,).
    points (B, K, 3) global mm -> (B, M (P + 1)): [part p, mechanism m] at p M + m, then the
    per-mechanism minimum over the parts.
    """

    def __init__(
        self,
        positions: Sequence[Sequence[float]],
        parts: Sequence[int],
        names: Sequence[str] | None = None,
        scale: float = 50.0,
    ) -> None:
        super().__init__()
        pos = np.asarray(positions, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[0] < 1 or pos.shape[1] != 3 or not np.isfinite(pos).all():
            raise ValueError(f"mechanism positions must be (M >= 1, 3) finite mm, got {pos!r}")
        parts = [int(k) for k in parts]
        if not parts or min(parts) < 0:
            raise ValueError(f"mechanism parts must be >= 1 part indices, got {parts}")
        if not float(scale) > 0:
            raise ValueError(f"mechanism scale must be > 0 mm, got {scale}")
        self.names = tuple(str(n) for n in (names or [f"m{i}" for i in range(len(pos))]))
        if len(self.names) != len(pos):
            raise ValueError(f"{len(self.names)} mechanism names for {len(pos)} positions")
        self.scale = float(scale)
        self.register_buffer("positions", torch.tensor(pos, dtype=torch.float32))
        self.register_buffer("parts", torch.tensor(parts, dtype=torch.long))
        self.out_dim = len(pos) * (len(parts) + 1)

    def forward(self, points: Tensor) -> Tensor:
        if points.dim() != 3 or points.shape[-1] != 3:
            raise ValueError(f"points must be (B, K, 3), got {tuple(points.shape)}")
        if int(self.parts.max()) >= points.shape[1]:
            raise ValueError(f"part index {int(self.parts.max())} >= {points.shape[1]} parts")
        p = points[:, self.parts]  # (B, P, 3)
        d = torch.linalg.vector_norm(p[:, :, None] - self.positions.to(p.dtype), dim=-1)
        d = d / self.scale  # (B, P, M)
        return torch.cat((d.flatten(1), d.amin(1)), -1)


def pose_measurements(
    points: Tensor, before: Tensor, scale: float = 50.0, up: Tensor | None = None
) -> Tensor:
    """Hand-made measurements of a frame, as SimBA computes them: every pairwise distance
    between the parts (upper triangle, row-major), each part's speed (its displacement since
    the frame before) and, given the world's unit ``up`` (3,), each part's height along it, all
    divided by ``scale`` mm. Without ``up`` rotation- and translation-invariant.

    points, before (B, K, 3) global mm -> (B, K (K - 1) / 2 + K (+ K with up))."""
    if points.dim() != 3 or points.shape[-1] != 3 or before.shape != points.shape:
        raise ValueError(
            f"points and before must be (B, K, 3) alike, got {tuple(points.shape)}, "
            f"{tuple(before.shape)}"
        )
    if up is not None and tuple(up.shape) != (3,):
        raise ValueError(f"up must be (3,), got {tuple(up.shape)}")
    K = points.shape[1]
    iu = torch.triu_indices(K, K, 1, device=points.device)
    dist = torch.linalg.vector_norm(points[:, iu[0]] - points[:, iu[1]], dim=-1)
    speed = torch.linalg.vector_norm(points - before, dim=-1)
    out = [dist, speed] + ([] if up is None else [points @ up.to(points.dtype)])
    return torch.cat(out, -1) / float(scale)


class WindowEncoder(nn.Module):
    """The encoder of a deformation net, as a window -> feature-vector map (see module doc).

    net: an `LSTMPredictor` or `TransformerPredictor` (its `head`, the per-part output layer, is
    not used); body_points (K, 3) the rigid body model (mm); frame_features: append the mid pose
    and the mid frame's offsets (12 + 4 K values; always the body frame's pose and offsets);
    up: the world's up (3,) when the net was trained in the heading frame, else None;
    mechanisms: a `MechanismFeatures` appended after the frame features (from the mid frame's
    points: observed parts where seen, the rigid model's elsewhere), or None; measurements:
    append hand-made measurements of the mid frame's points (SimBA-style: every pairwise part
    distance, each part's speed since the frame before and, given the world's up, each part's
    height along it: `pose_measurements`); heights_up: that up (3,) for an encoder without one
    (a body-frame net), None: the encoder's ``up`` (none: no heights); a heights_up that
    differs from the encoder's up is a ValueError.
    """

    def __init__(
        self,
        net: nn.Module,
        body_points: Tensor,
        half_window: int,
        frame_features: bool = True,
        up: Sequence[float] | None = None,
        mechanisms: MechanismFeatures | None = None,
        measurements: bool = False,
        heights_up: Sequence[float] | None = None,
    ) -> None:
        super().__init__()
        if not isinstance(net, (LSTMPredictor, TransformerPredictor)):
            raise TypeError(
                f"WindowEncoder needs an LSTMPredictor or TransformerPredictor, got "
                f"{type(net).__name__}"
            )
        if int(half_window) != net.half_window:
            raise ValueError(f"half_window {half_window} != the net's {net.half_window}")
        self.net = net
        self.half_window = net.half_window
        self.window = net.window
        self.num_parts = net.num_parts
        self.frame_features = bool(frame_features)
        self.up = check_up(up)
        self.register_buffer("body_points", torch.tensor(np.array(body_points, dtype=np.float32)))
        self.mechanisms = mechanisms
        self.measurements = bool(measurements)
        if self.measurements and self.half_window < 1:
            raise ValueError("measurements need a window of at least 3 frames (half_window >= 1)")
        hup = check_up(heights_up)
        if hup is not None and self.up is not None and not np.allclose(hup, self.up):
            raise ValueError(
                f"heights_up {list(hup)} differs from the encoder's up {list(self.up)} (the "
                "heading-frame net's; leave heights_up unset)"
            )
        #: the world's up the measurements' part heights are taken along (None: no heights)
        self.heights_up = hup if hup is not None else self.up
        K = self.num_parts
        if mechanisms is not None and int(mechanisms.parts.max()) >= self.num_parts:
            raise ValueError(f"mechanism part index {int(mechanisms.parts.max())} >= the net's "
                             f"{self.num_parts} parts")  # fmt: skip
        self.out_dim = (
            2 * net.encode_dim
            + (12 + 4 * self.num_parts if self.frame_features else 0)
            + (0 if mechanisms is None else mechanisms.out_dim)
            + (
                (K * (K - 1) // 2 + K + (0 if self.heights_up is None else K))
                if self.measurements
                else 0
            )
        )

    def _check(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> None:
        want = (self.window, self.num_parts, 3)
        if rigid.dim() != 4 or tuple(rigid.shape[1:]) != want:
            raise ValueError(f"rigid must have shape (B, {want}), got {tuple(rigid.shape)}")
        if deformed.shape != rigid.shape or tuple(observed.shape) != tuple(rigid.shape[:-1]):
            raise ValueError(
                f"deformed {tuple(deformed.shape)} / observed {tuple(observed.shape)} do not fit "
                f"rigid {tuple(rigid.shape)}"
            )

    def encoder_parameters(self) -> list[nn.Parameter]:
        """The net's parameters this encoder uses (the unused per-part output layer excluded)."""
        return [p for n, p in self.net.named_parameters() if not n.startswith("head.")]

    def forward(
        self, rigid: Tensor, deformed: Tensor, observed: Tensor, scale: Tensor | None = None
    ) -> Tensor:
        self._check(rigid, deformed, observed)
        observed = observed.bool()
        raw = deformed  # the real points: the mechanism distances
        if scale is not None:
            if scale.shape != rigid.shape[:1]:
                raise ValueError(f"scale must be ({rigid.shape[0]},), got {tuple(scale.shape)}")
            deformed = normalize_size(rigid, deformed, scale[:, None].expand(rigid.shape[:2]))
        up = None if self.up is None else rigid.new_tensor(self.up)
        summary, (rigid_c, deformed_c, R, t) = window_summary(
            self.net, self.body_points, rigid, deformed, observed, up
        )
        mid, net, B = self.half_window, self.net, summary.shape[0]

        def seen(i: int, pts: Tensor = deformed) -> Tensor:
            """Frame i's points (B, K, 3): pts where observed, else the rigid model's."""
            return torch.where(observed[:, i, :, None], pts[:, i], rigid[:, i])

        out = [summary]
        if self.frame_features:
            obs_mid = observed[:, mid]
            if up is None:
                off = deformed_c[:, mid] - rigid_c[:, mid]
            else:  # the frame features are the body frame's, whatever frame the net reads
                R, t = kabsch(rigid[:, mid], self.body_points.to(rigid.dtype))
                off = (seen(mid) - rigid[:, mid]) @ R
            off = torch.where(obs_mid[..., None], off / net.offset_scale, torch.zeros_like(off))
            out += [
                R.reshape(B, 9),
                t / (10.0 * net.pos_scale),
                off.reshape(B, -1),
                obs_mid.to(off.dtype),
            ]
        if self.mechanisms is not None:
            out.append(self.mechanisms(seen(mid, raw)))
        if self.measurements:
            hup = None if self.heights_up is None else rigid.new_tensor(self.heights_up)
            out.append(pose_measurements(seen(mid), seen(mid - 1), up=hup))
        return torch.cat(out, -1)
