"""Held-out-camera validation of the prior that measured part-frames are fused with.

A part-frame that two or more cameras see is fused from its own detections and a prior
(`adjust.lsq.fusion.fuse_points`). Two priors are at hand: the part's prediction from its
neighbouring frames (``deformation=interp``'s kriging; the temporal prior) and the rigid model
point (the shape prior). On real recordings neither is always better. The detections of a part
are biased in ways that persist over many frames (a detector that places a knuckle a few pixels
off in one view, a slightly wrong camera pose): the neighbours' triangulations carry the same
bias as the frame's own, so the temporal prior cannot average it out, while the rigid model,
estimated over all frames and all view combinations, can. Which of the two predicts better is
a property of the recording, and the recording can say: hold out one camera, fuse each
part-frame that the other cameras still see from the prior and those views only, and measure
the held-out camera's reprojection error. The temporal prior is rebuilt without the held-out
camera (its neighbours' triangulations would otherwise carry that camera's own bias and
favour it); the rigid model moves less with one camera (it rests on all frames).

`choose_measured_prior` does this for every camera and picks the prior with the lower median
held-out error. With fewer than 3 cameras no part-frame is seen by two cameras besides the
held-out one, and the temporal prior cannot be rebuilt without it (a temporal prior that kept
the held-out camera would carry its bias and always look better): without that evidence the
choice is the rigid model, the one prior independent of the two views' persistent errors (a
two-view triangulation has one redundant coordinate, so a consensus cannot check them), and
the facts say why. Shapes: T frames, K parts, C cameras; mm, px.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from adjust.estimate import consensus
from adjust.lsq.fusion import held_out_view_errors
from adjust.lsq.observation import InterpObservation, RigidObservation

log = logging.getLogger(__name__)


def choose_measured_prior(
    poses: np.ndarray,
    xy: np.ndarray,
    weight: np.ndarray,
    accepted: np.ndarray,
    cams,
    body_points: np.ndarray,
    rigid_var: np.ndarray,
    sigma_px: float,
    consensus_kwargs: dict | None = None,
    few_var: torch.Tensor | None = None,
    max_frames: int = 3000,
) -> tuple[str, dict]:
    """``"rigid"`` or ``"interp"``: which prior of the measured part-frames predicts held-out
    cameras better on this recording (module doc; ``"rigid"`` where that cannot be measured).

    poses (T, 6) model -> global; xy (T, K, C, 2) px (NaN missing); weight (T, K, C) (0 =
    missing or dropped); accepted (T, K, C) bool, the detections the tracked points rest on;
    body_points (K, 3) mm; rigid_var (K, 3) mm^2 the rigid model's per-axis spread;
    consensus_kwargs: `adjust.estimate.consensus`'s settings (as the tracking used them);
    few_var: `InterpObservation`'s. A longer session is validated on its middle ``max_frames``
    frames (the cost stays bounded; thousands of held-out detections decide). Returns the
    choice and facts (median held-out errors, the number of held-out detections, per camera,
    the frames used)."""

    T, K, C, _ = xy.shape
    if C < 3:
        return "rigid", {
            "choice": "rigid",
            "reason": f"{C} cameras: held-out validation needs >= 3 (two to fuse, one held out); "
            "the rigid model, independent of the views' persistent errors",
        }
    a, b = 0, T
    if max_frames and T > max_frames:  # the middle block of frames
        a = (T - max_frames) // 2
        b = a + max_frames
        poses, xy, weight, accepted = (np.asarray(x)[a:b] for x in (poses, xy, weight, accepted))
    dt = torch.float64
    P = torch.as_tensor(poses, dtype=dt)
    B = torch.as_tensor(np.asarray(body_points), dtype=dt)
    eye = 1e-6 * torch.eye(3, dtype=dt)
    rigid = RigidObservation(B, torch.as_tensor(np.asarray(rigid_var), dtype=dt))
    Xr, _ = rigid.rigid_points(P)
    Pr = rigid.deformation_cov(P) + eye
    xy_t = torch.as_tensor(np.nan_to_num(np.asarray(xy, dtype=np.float64)))
    acc = torch.as_tensor(np.asarray(accepted, dtype=bool))
    kw = dict(consensus_kwargs or {})
    kw.setdefault("sigma_det_px", sigma_px)

    def temporal_without(c: int):
        w = np.array(weight, dtype=np.float64, copy=True)
        w[..., c] = 0.0
        cons = consensus(np.asarray(xy), w, cams, **kw)
        obs = InterpObservation(
            B,
            torch.as_tensor(cons.points),
            torch.as_tensor(cons.observed),
            torch.as_tensor(cons.noise_var),
            few_var,
        )
        obs.prepare(P)
        X, _ = obs.points(P, jacobian=False)
        return X, obs.deformation_cov(P) + eye

    with torch.no_grad():
        e_rigid = held_out_view_errors(Xr, Pr, xy_t, acc, cams, sigma_px, min_others=2)
        e_temp = held_out_view_errors(
            Xr, Pr, xy_t, acc, cams, sigma_px, min_others=2, prior_without=temporal_without
        )
    both = torch.isfinite(e_rigid) & torch.isfinite(e_temp)
    n = int(both.sum())
    if n < 30:
        return "rigid", {
            "choice": "rigid",
            "reason": f"only {n} detections can be held out with two other views; the rigid "
            "model, independent of the views' persistent errors",
        }
    med_r = float(e_rigid[both].median())
    med_t = float(e_temp[both].median())
    per_camera = {}
    for c, name in enumerate(cams.names):
        m = both[..., c]
        if int(m.sum()):
            per_camera[name] = {
                "held_out": int(m.sum()),
                "rigid_px": float(e_rigid[..., c][m].median()),
                "interp_px": float(e_temp[..., c][m].median()),
            }
    choice = "rigid" if med_r < med_t else "interp"
    log.info(
        "held-out cameras: the measured part-frames' prior predicts a held-out view to %.2f px "
        "(rigid model) vs %.2f px (neighbouring frames), %d detections: %s",
        med_r,
        med_t,
        n,
        "the rigid model" if choice == "rigid" else "the neighbouring frames",
    )
    return choice, {
        "choice": choice,
        "held_out_detections": n,
        "rigid_median_px": med_r,
        "interp_median_px": med_t,
        "per_camera": per_camera,
        "frames": [a, b],
    }
