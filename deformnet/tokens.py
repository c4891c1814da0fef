"""Tokens and windows: canonicalisation, token features, masks, baselines.

A token pairs one body part's rigid-model position and its observed deformed position,
T(t, i) = (X̄(t, i), X̃(t, i)) (paper, eq. "token"). A sample is the window of frames t-n..t+n
(W = 2n + 1). The deformed half of the mid frame's tokens is masked; the net predicts the mid
frame's deformed positions. Elsewhere deformed positions that were not observed are masked too
(the boolean `observed` flags are inputs).

Every window is expressed in the mid frame's rigid-model coordinates ("canonical"): the mid pose
(R, t) is recovered by Kabsch of the mid frame's rigid points onto the body model (exact for rigid
points), and X_c = R^T (X - t). The prediction then does not depend on where the mouse is or which
way it faces.

Or, with a world ``up`` direction, the mid frame's *heading* frame: the same origin t, rotated by
R_h, the rotation nearest R whose Z axis is the world's up (R's pitch and roll removed, its yaw
kept: R_h = Q R, Q the smallest rotation taking the body's up axis R e_z onto up). The window is
then invariant to where the mouse is and which way it faces, but not to its pitch and roll,
which gravity makes meaningful (a rearing mouse stands up against gravity, a walking one does
not): the net sees them in its inputs. The body's up axis pointing straight down (upside down)
is the one singular pose; there Q is the half-turn about the body's X axis.

Shapes: B batch (any leading dims where stated), W window, K parts. Points in mm. All functions
are pure torch, batched and differentiable (reverse mode) in the point inputs.
"""

from __future__ import annotations

import torch
from torch import Tensor

from deformnet.so3 import kabsch, skew

__all__ = [
    "kabsch",
    "canonicalize",
    "uncanonicalize",
    "heading_rotation",
    "token_features",
    "check_window",
    "NUM_FEATURES",
    "PRIOR_FEATURES",
    "POS_SCALE",
    "OFFSET_SCALE",
    "masked_mse",
    "linear_baseline",
    "offset_baseline",
]

NUM_FEATURES = 7  # rigid_c (3), deformation offset in the frame's own body frame (3), observed (1)
POS_SCALE = 30.0  # mm: the default divisor of canonical positions in the token features
OFFSET_SCALE = 10.0  # mm: the default divisor of deformation offsets (features and net outputs)


def heading_rotation(R: Tensor, up: Tensor) -> Tensor:
    """The heading part of body rotations: R_h = Q R, Q the smallest rotation taking the body's
    up axis R e_z onto ``up`` (so R_h e_z = up, and R_h keeps R's heading about up).

    R: (..., 3, 3) rotations (model -> world); up: (3,) world up direction (any length > 0).
    Returns (..., 3, 3). Differentiable except where R e_z = -up (upside down), where Q is the
    half-turn about R e_x.
    """
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {tuple(R.shape)}")
    if tuple(up.shape) != (3,):
        raise ValueError(f"up must have shape (3,), got {tuple(up.shape)}")
    norm = torch.linalg.vector_norm(up)
    if not bool(norm > 0):
        raise ValueError("up must be a non-zero direction")
    b = (up / norm).to(R.dtype).expand(R.shape[:-2] + (3,))
    a = R[..., :, 2]  # the body's up axis in the world
    v = torch.linalg.cross(a, b)
    c = (a * b).sum(-1)
    vx = skew(v)
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    flip = c < -1.0 + 1e-6
    denom = torch.where(flip, torch.ones_like(c), 1.0 + c)
    Q = eye + vx + vx @ vx / denom[..., None, None]  # Rodrigues: a -> b
    x = R[..., :, 0]
    half_turn = 2.0 * x[..., :, None] * x[..., None, :] - eye  # about the body's X axis
    Q = torch.where(flip[..., None, None], half_turn, Q)
    return Q @ R


def canonicalize(
    rigid: Tensor, deformed: Tensor, body_points: Tensor, mid: int, up: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Express a window in the mid frame's rigid-model coordinates (``up`` None), or in its
    heading frame (``up``: the world's up direction (3,); see the module doc).

    rigid, deformed: (..., W, K, 3) global mm; body_points: (K, 3) model mm; mid: index of the mid
    frame. Returns rigid_c, deformed_c (..., W, K, 3) and the frame R (..., 3, 3), t (..., 3)
    (canonical -> global: X = R X_c + t): the mid pose recovered by Kabsch of
    rigid[..., mid, :, :] onto the body model, or its heading part.
    """
    R, t = kabsch(rigid[..., mid, :, :], body_points)
    if up is not None:
        R = heading_rotation(R, up)
    Rw, tw = R[..., None, :, :], t[..., None, None, :]
    rigid_c = (rigid - tw) @ Rw
    deformed_c = (deformed - tw) @ Rw
    return rigid_c, deformed_c, R, t


def check_window(
    rigid: Tensor,
    deformed: Tensor,
    observed: Tensor,
    window: int,
    num_parts: int,
    *,
    lead: str = "B",
    parts: tuple[str, ...] | None = None,
) -> None:
    """A window's inputs: rigid, deformed (lead, W, K, 3) and observed (lead, W, K), or a
    ValueError naming the one that is off. lead: ``"B"`` = one batch dimension, ``"..."`` = any
    leading dimensions; parts: the body's part names, said in the message."""
    want = (window, num_parts, 3)
    dims_ok = rigid.dim() == 4 if lead == "B" else rigid.dim() >= 3
    if not dims_ok or tuple(rigid.shape[-3:]) != want:
        said = f" (window W = {window}, parts {', '.join(parts)})" if parts else ""
        raise ValueError(
            f"rigid must have shape ({lead}, {', '.join(map(str, want))}){said}, "
            f"got {tuple(rigid.shape)}"
        )
    if deformed.shape != rigid.shape:
        raise ValueError(
            f"deformed shape {tuple(deformed.shape)} != rigid shape {tuple(rigid.shape)}"
        )
    if tuple(observed.shape) != tuple(rigid.shape[:-1]):
        raise ValueError(
            f"observed must have shape {tuple(rigid.shape[:-1])}, got {tuple(observed.shape)}"
        )


def uncanonicalize(points_c: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """Canonical points (..., K, 3) back to global: X = R X_c + t; R (..., 3, 3), t (..., 3)."""
    return points_c @ R.transpose(-1, -2) + t[..., None, :]


def token_features(
    rigid_c: Tensor,
    deformed_c: Tensor,
    observed: Tensor,
    mid: int,
    pos_scale: float = POS_SCALE,
    offset_scale: float = OFFSET_SCALE,
) -> tuple[Tensor, Tensor, Tensor]:
    """Per-token and per-part input features for the nets, from a canonical window.

    rigid_c, deformed_c: (B, W, K, 3) canonical mm; observed: (B, W, K) bool.
    The mid frame's deformed input is always masked here (no leak, whatever the caller passes),
    and unobserved deformed values are zeroed so their content cannot matter.

    Token features (B, W, K, 7): rigid_c / pos_scale; the deformation offset X̃ - X̄ rotated into
    that frame's own body frame (rotation by Kabsch of the frame's rigid points onto the mid
    frame's), / offset_scale, zero where masked; the observed flag.

    Part features (B, K, PRIOR_FEATURES = 26), an interpolation prior for the mid frame built from
    the nearest observed frames before and after it: the body-frame offset interpolated linearly
    (held from the one side that has an observation, zero with none); the canonical deformed
    position interpolated linearly, minus the mid rigid point (the body-frame value where a side
    is missing); the body-frame offsets at the nearest and second-nearest observed frames on each
    side (zero where none) -- all / offset_scale --; the distances to those four frames / (W // 2)
    (2 where none); and their four existence flags.

    Returns (token features, part features, observed with the mid frame masked).
    """
    W = rigid_c.shape[-3]
    keep = torch.ones(W, dtype=torch.bool, device=observed.device)
    keep[mid] = False
    obs = observed.bool() & keep[:, None]
    # rotation of each frame relative to the mid frame (canonical coords): rigid_f ≈ R_f mid + t_f
    R_f, _ = kabsch(rigid_c, rigid_c[..., mid : mid + 1, :, :])
    off = (deformed_c - rigid_c) @ R_f  # offset in the frame's own body frame
    off = torch.where(obs[..., None], off, torch.zeros_like(off))
    feats = torch.cat(
        (rigid_c / pos_scale, off / offset_scale, obs[..., None].to(rigid_c.dtype)), -1
    )
    ib, ia, has_b, has_a = _nearest_observed(obs, mid)
    w = _lerp_weight(ib, ia, mid, rigid_c.dtype)
    ob, oa = _gather_frames(off, ib), _gather_frames(off, ia)
    both = (has_b & has_a)[..., None]
    local = torch.where(both, ob + w * (oa - ob), torch.where(has_b[..., None], ob, oa))
    db, da = _gather_frames(deformed_c, ib), _gather_frames(deformed_c, ia)
    glob = torch.where(both, db + w * (da - db) - rigid_c[..., mid, :, :], local)
    # the second-nearest observations on each side (local slopes / curvature)
    frames = torch.arange(W, device=obs.device)[:, None]
    first = ((frames == ib[..., None, :]) & has_b[..., None, :]) | (
        (frames == ia[..., None, :]) & has_a[..., None, :]
    )
    ib2, ia2, has_b2, has_a2 = _nearest_observed(obs & ~first, mid)
    zero = torch.zeros_like(ob)
    ob2 = torch.where(has_b2[..., None], _gather_frames(off, ib2), zero)
    oa2 = torch.where(has_a2[..., None], _gather_frames(off, ia2), zero)
    ob = torch.where(has_b[..., None], ob, zero)
    oa = torch.where(has_a[..., None], oa, zero)
    half = max(1, W // 2)

    def dist(i: Tensor, has: Tensor) -> Tensor:
        d = (i - mid).abs().to(rigid_c.dtype) / half
        return torch.where(has, d, torch.full_like(d, 2.0))[..., None]

    flags = torch.stack((has_b, has_a, has_b2, has_a2), -1).to(rigid_c.dtype)
    prior = torch.cat(
        (
            local / offset_scale,
            glob / offset_scale,
            ob / offset_scale,
            oa / offset_scale,
            ob2 / offset_scale,
            oa2 / offset_scale,
            dist(ib, has_b),
            dist(ia, has_a),
            dist(ib2, has_b2),
            dist(ia2, has_a2),
            flags,
        ),
        -1,
    )
    return feats, prior, obs


PRIOR_FEATURES = 26


def _nearest_observed(obs: Tensor, mid: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Nearest observed frame before / after `mid` per part (obs (..., W, K), mid excluded):
    indices clamped into the window (..., K) and whether they exist."""
    W = obs.shape[-2]
    idx = torch.arange(W, device=obs.device)
    obs = obs & (idx != mid)[:, None]
    before = torch.where(
        obs & (idx < mid)[:, None], idx[:, None], torch.full_like(idx, -1)[:, None]
    )
    after = torch.where(obs & (idx > mid)[:, None], idx[:, None], torch.full_like(idx, W)[:, None])
    ib = before.max(-2).values
    ia = after.min(-2).values
    return ib.clamp(0, W - 1), ia.clamp(0, W - 1), ib >= 0, ia < W


def _lerp_weight(ib: Tensor, ia: Tensor, mid: int, dtype: torch.dtype) -> Tensor:
    return ((mid - ib).to(dtype) / (ia - ib).clamp_min(1).to(dtype))[..., None]


def _gather_frames(x: Tensor, i: Tensor) -> Tensor:
    """x (..., W, K, 3), i (..., K) frame indices -> (..., K, 3)."""
    index = i[..., None, :, None].expand(*i.shape[:-1], 1, i.shape[-1], x.shape[-1])
    return x.gather(-3, index).squeeze(-3)


def masked_mse(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Mean squared 3D error over the entries where `mask` is true (pred, target (..., K, 3);
    mask (..., K) bool). Entries with mask false contribute neither value nor gradient."""
    m = mask.to(pred.dtype)
    diff = torch.where(mask[..., None], pred - target, torch.zeros_like(pred))
    sq = (diff * diff).sum(-1)
    return (sq * m).sum() / m.sum().clamp_min(1.0)


def linear_baseline(rigid: Tensor, deformed: Tensor, observed: Tensor, mid: int) -> Tensor:
    """Linear-interpolation baseline for the mid frame's deformed positions.

    For each part, the deformed position is interpolated linearly in time between the nearest
    observed frames before and after the mid frame in the window (the mid frame itself is never
    used). Where a side has no observation, the rigid mid point is returned (the rigid baseline).
    rigid, deformed (..., W, K, 3), observed (..., W, K) bool -> (..., K, 3).
    """
    ib, ia, has_b, has_a = _nearest_observed(observed.bool(), mid)
    xb, xa = _gather_frames(deformed, ib), _gather_frames(deformed, ia)
    lin = xb + _lerp_weight(ib, ia, mid, deformed.dtype) * (xa - xb)
    return torch.where((has_b & has_a)[..., None], lin, rigid[..., mid, :, :])


def offset_baseline(rigid: Tensor, deformed: Tensor, observed: Tensor, mid: int) -> Tensor:
    """Offset-interpolation baseline for the mid frame's deformed positions: the rigid mid
    point plus the part's offset from its rigid point (deformed - rigid), interpolated
    linearly in time between the nearest observed frames before and after the mid frame (the
    mid frame itself is never used), in global axes. It is what `adjust-track`'s default
    (``deformation=interp``) does within a window: the rigid model carries the motion, the
    offsets are interpolated (interp kriges them in each frame's body axes, which over a
    window's span turn little). Where a side has no observation, the rigid mid point.
    rigid, deformed (..., W, K, 3), observed (..., W, K) bool -> (..., K, 3).
    """
    ib, ia, has_b, has_a = _nearest_observed(observed.bool(), mid)
    off = deformed - rigid
    ob, oa = _gather_frames(off, ib), _gather_frames(off, ia)
    lerp = ob + _lerp_weight(ib, ia, mid, off.dtype) * (oa - ob)
    mid_rigid = rigid[..., mid, :, :]
    return torch.where((has_b & has_a)[..., None], mid_rigid + lerp, mid_rigid)
