"""Initial poses: per-frame fits (Kabsch on parts triangulated by `adjust.triangulate`, or PnP
in one camera), interpolated over the rest; or a constant-velocity Kalman filter + RTS smoother
over them.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from torch import Tensor

from adjust.camera import CameraTensors, project_cameras, undistort_points
from adjust.lsq.geometry import so3_exp, so3_log
from adjust.lsq.memory import release_freed_memory
from adjust.triangulate import triangulate
from deformnet.so3 import kabsch

log = logging.getLogger(__name__)


def triangulated_parts(
    xy: Tensor, valid: Tensor, cams: CameraTensors, max_error_px: float = 15.0
) -> tuple[Tensor, Tensor]:
    """The parts in 3D for the per-frame fits: `adjust.triangulate.triangulate`, robust (its one
    scheme: while the worst used view of a point seen by >= 3 cameras reprojects worse than
    `max_error_px`, the view whose removal leaves the most consistent set is dropped); a point
    that still has a used view worse than `max_error_px`, or lies behind a used camera, is left
    out.

    xy: (T, K, C, 2) px (anything where not valid); valid: (T, K, C) bool -> X (T, K, 3) mm
    (zeros where not ok), ok (T, K) bool.
    """
    if xy.dim() != 4 or valid.shape != xy.shape[:-1]:
        raise ValueError(f"xy (T, K, C, 2), valid (T, K, C); got {tuple(xy.shape)}, "
                         f"{tuple(valid.shape)}")  # fmt: skip
    tri = triangulate(xy, valid.to(xy.dtype), cams, True, max_error_px, num_threads=None)
    ok = (tri.ncams >= 2) & ~(tri.used & (tri.view_error > max_error_px)).any(-1)
    X = torch.where(ok[..., None], tri.points, torch.zeros_like(tri.points))
    zc = torch.einsum("cj,tkj->tkc", cams.R[:, 2], X) + cams.t[:, 2]
    ok = ok & ((zc > 0) | ~tri.used).all(-1)
    return torch.where(ok[..., None], X, torch.zeros_like(X)), ok


def _fit_errors(body: Tensor, X: Tensor, poses: Tensor) -> Tensor:
    Xm = torch.einsum("tij,kj->tki", so3_exp(poses[:, :3]), body) + poses[:, None, 3:]
    return (Xm - X).norm(dim=-1)


def kabsch_robust(
    body: Tensor, X: Tensor, mask: Tensor, max_error_mm: float = 10.0, max_triplets: int = 120
) -> tuple[Tensor, Tensor]:
    """Outlier-resistant `kabsch_poses`: frames whose plain fit leaves a part off by more than
    `max_error_mm` are refitted by RANSAC over the part triplets (all of them, or a fixed random
    `max_triplets` of them for many parts; scored by the number of parts
    within `max_error_mm`, ties by rms), then on the winner's inliers. Frames with fewer than 3
    inliers are not ok. Shapes as `kabsch_poses`."""
    import itertools

    poses, ok = kabsch_poses(body, X, mask)
    err = torch.where(mask, _fit_errors(body, X, poses), torch.zeros_like(X[..., 0]))
    sus = torch.nonzero(ok & (err.max(-1).values > max_error_mm)).ravel()
    if sus.numel():
        Xs, ms = X[sus], mask[sus]
        K = mask.shape[1]
        best = torch.full((sus.numel(),), -1.0, dtype=X.dtype)
        best_in = torch.zeros_like(ms)
        triplets = list(itertools.combinations(range(K), 3))
        if len(triplets) > max_triplets:  # many parts: a fixed random sample (RANSAC proper)
            rng = np.random.default_rng(0)
            pick = rng.choice(len(triplets), max_triplets, replace=False)
            triplets = [triplets[i] for i in sorted(pick)]
        for tri in triplets:
            sel = torch.zeros(K, dtype=torch.bool)
            sel[list(tri)] = True
            use = ms & sel
            p, o = kabsch_poses(body, Xs, use)
            e = _fit_errors(body, Xs, p)
            inl = ms & (e <= max_error_mm) & o[:, None]
            rms = torch.where(inl, e * e, torch.zeros_like(e)).sum(-1) / inl.sum(-1).clamp_min(1)
            score = inl.sum(-1).to(X.dtype) - rms.sqrt() / (max_error_mm + 1.0)
            better = o & (score > best)
            best = torch.where(better, score, best)
            best_in = torch.where(better[:, None], inl, best_in)
        p, o = kabsch_poses(body, Xs, best_in)
        poses[sus] = p
        ok[sus] = o & (best_in.sum(-1) >= 3)
    return torch.where(ok[:, None], poses, torch.zeros_like(poses)), ok


def kabsch_poses(
    body: Tensor, X: Tensor, mask: Tensor, min_parts: int = 3
) -> tuple[Tensor, Tensor]:
    """Rigid fit of the body model to observed 3D parts, per frame (weighted Kabsch, batched).

    body: (K, 3) model points; X: (T, K, 3) global (any value where not mask); mask: (T, K) bool
    -> poses (T, 6) (zeros where not ok), ok (T,) bool (>= min_parts non-collinear parts).
    """
    if X.dim() != 3 or X.shape[1:] != body.shape or mask.shape != X.shape[:2]:
        raise ValueError(
            f"X (T, K, 3), mask (T, K) for body {tuple(body.shape)}; "
            f"got {tuple(X.shape)}, {tuple(mask.shape)}"
        )
    R, tau, S = kabsch(X, body, mask, spread=True)  # model -> global
    ok = mask.sum(1) >= min_parts
    ok = ok & (S[:, 1] > 1e-6 * S[:, 0].clamp_min(1e-300)) & torch.isfinite(S).all(-1)
    poses = torch.cat((so3_log(R), tau), -1)
    return torch.where(ok[:, None], poses, torch.zeros_like(poses)), ok


def pnp_poses(
    xy: np.ndarray,
    valid: np.ndarray,
    cams: CameraTensors,
    body: np.ndarray,
    frames: np.ndarray,
    max_error_px: float = 25.0,
) -> dict[int, np.ndarray]:
    """Single-camera PnP (OpenCV) for the given frames, using the camera with most parts (>= 4).

    xy: (T, K, C, 2); valid: (T, K, C) bool; body (K, 3) -> {frame: pose (6,)} for successes.
    """
    try:
        import cv2
    except ImportError:  # pragma: no cover - opencv is a dependency
        return {}
    K_ = cams.K.detach().cpu().numpy()
    dist = cams.dist.detach().cpu().numpy()
    fish = np.zeros(len(dist), bool) if cams.fisheye is None else cams.fisheye.cpu().numpy()
    Rc = cams.R.detach().cpu().numpy()
    tc = cams.t.detach().cpu().numpy()
    out: dict[int, np.ndarray] = {}
    for t in frames:
        counts = valid[t].sum(0)
        c = int(np.argmax(counts))
        if counts[c] < 4:
            continue
        sel = valid[t, :, c]
        obj = body[sel].astype(np.float64)
        img = xy[t, sel, c].astype(np.float64)
        dc = dist[c]
        if fish[c]:  # OpenCV's PnP knows the pinhole model: its ideal pixels, no distortion
            img = undistort_points(
                torch.as_tensor(img), cams.K[c].detach().cpu(), cams.dist[c].detach().cpu(),
                pixels=True, fisheye=torch.tensor(True),
            ).numpy()  # fmt: skip
            dc = np.zeros(5)
        try:
            okp, rvec, tvec = cv2.solvePnP(obj, img, K_[c], dc, flags=cv2.SOLVEPNP_EPNP)
            if okp:
                okp, rvec, tvec = cv2.solvePnP(
                    obj, img, K_[c], dc, rvec, tvec, True, flags=cv2.SOLVEPNP_ITERATIVE
                )
        except cv2.error:
            continue
        if not okp:
            continue
        Rp = so3_exp(torch.as_tensor(rvec.reshape(3), dtype=torch.float64)).numpy()
        R = Rc[c].T @ Rp
        tau = Rc[c].T @ (tvec.reshape(3) - tc[c])
        Xc = obj @ Rp.T + tvec.reshape(3)
        if np.any(Xc[:, 2] <= 0):
            continue
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K_[c], dc)
        if np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, -1))) > max_error_px:
            continue
        r = so3_log(torch.as_tensor(R)).numpy()
        out[int(t)] = np.concatenate([r, tau])
    return out


def _angle_deg(Ra: Tensor, Rb: Tensor) -> Tensor:
    """Rotation angle (degrees) of Ra^T Rb, batched over leading dims: (..., 3, 3) -> (...)."""
    c = ((Ra * Rb).sum((-1, -2)) - 1.0) / 2.0
    return torch.rad2deg(torch.arccos(c.clamp(-1.0, 1.0)))


def consistent_fits(
    poses: Tensor, ok: Tensor, strong: Tensor, max_deg: float = 45.0, window: int = 5
) -> tuple[Tensor, dict]:
    """Per-frame fits that agree with their neighbours in time (a mouse does not turn by tens
    of degrees between two frames, but a rigid model fitted to three parts of a deforming body,
    or PnP in one camera, can flip).

    poses (T, 6) model -> global, ok (T,) bool: the fits; strong (T,) bool: the fits to trust
    first (Kabsch on >= 4 triangulated parts). A strong fit is kept when it is within
    `max_deg` (``max_deg * d / 2`` for a fit d > 2 frames away: a steady turn of 17 degrees a
    frame is kept) of at least half of the strong fits within `window` frames on either side
    (or has none);
    a weak fit (3 parts, PnP) when it is within `max_deg` of the kept strong fits' rotation
    slerp-interpolated to its frame (`interpolate_poses`). O(T window). The window is short (5
    frames: 0.17 s at 30 fps) so that a fast real turn is not taken for a flip (15 frames cost
    3% RMSE on a 30 fps scene and gained nothing at 100 fps). Returns the kept fits
    (T,) bool and facts (counts of dropped strong and weak fits). Without strong fits nothing
    is dropped."""
    T = poses.shape[0]
    strong = strong & ok
    facts = {"dropped_strong": 0, "dropped_weak": 0}
    if T < 2 or not bool(strong.any()):
        return ok.clone(), facts
    R = so3_exp(poses[:, :3])
    agree = torch.zeros(T, dtype=torch.long)
    near = torch.zeros(T, dtype=torch.long)
    for d in range(1, min(window, T - 1) + 1):
        both = strong[:-d] & strong[d:]
        # a body turning steadily moves away from its neighbours: more leeway farther out
        close = both & (_angle_deg(R[:-d], R[d:]) <= max_deg * max(1.0, d / 2))
        near[:-d] += both
        near[d:] += both
        agree[:-d] += close
        agree[d:] += close
    keep_strong = strong & ((near == 0) | (2 * agree >= near))
    if not bool(keep_strong.any()):
        return ok.clone(), facts
    ref = so3_exp(interpolate_poses(poses, keep_strong)[:, :3])
    weak = ok & ~strong
    keep_weak = weak & (_angle_deg(ref, R) <= max_deg)
    facts = {
        "dropped_strong": int((strong & ~keep_strong).sum()),
        "dropped_weak": int((weak & ~keep_weak).sum()),
    }
    return keep_strong | keep_weak, facts


def interpolate_poses(poses: Tensor, ok: Tensor) -> Tensor:
    """Fill frames that are not ok: slerp of rotations (R = exp(a log(R_b R_a^T)) R_a) and linear
    translations between the nearest ok frames; constant beyond the first/last; zeros if none.

    poses: (T, 6); ok: (T,) bool -> (T, 6).
    """
    T = poses.shape[0]
    if T == 0 or bool(ok.all()):
        return poses.clone()
    if not bool(ok.any()):
        return torch.zeros_like(poses)
    okn = ok.cpu().numpy()
    prev = np.where(okn, np.arange(T), -1)
    prev = np.maximum.accumulate(prev)
    nxt = np.where(okn, np.arange(T), T)
    nxt = np.minimum.accumulate(nxt[::-1])[::-1]
    prev = np.where(prev < 0, nxt, prev)
    nxt = np.where(nxt >= T, prev, nxt)
    out = poses.clone()  # fitted frames keep their poses; only the others are computed,
    fill = np.flatnonzero(~okn)  # in blocks (bounded memory on long sessions)
    for s in range(0, fill.size, 100_000):
        f = fill[s : s + 100_000]
        idx = torch.as_tensor(f)
        a, b = torch.as_tensor(prev[f]), torch.as_tensor(nxt[f])
        span = (b - a).clamp_min(1).to(poses.dtype)
        alpha = torch.where(b > a, (idx - a).to(poses.dtype) / span, torch.zeros_like(span))
        alpha = alpha[:, None]
        Ra, Rb = so3_exp(poses[a, :3]), so3_exp(poses[b, :3])
        rel = so3_log(Rb @ Ra.transpose(-1, -2))
        R = so3_exp(alpha * rel) @ Ra
        tau = (1 - alpha) * poses[a, 3:] + alpha * poses[b, 3:]
        out[idx] = torch.cat((so3_log(R), tau), -1)
    return out


def unwrap_rotations(r: np.ndarray) -> np.ndarray:
    """Continuous rotation vectors: per row, of r + 2 pi k r/|r| (k = -1, 0, 1, ...) the one
    nearest the previous row.  (T, 3) -> (T, 3)."""
    out = r.copy()
    for t in range(1, len(r)):
        th = np.linalg.norm(r[t])
        if th < 1e-12:
            cands = [r[t]]
        else:
            ax = r[t] / th
            base = out[t - 1] @ ax  # nearest angle along this axis
            k = np.round((base - th) / (2 * np.pi))
            cands = [r[t] + 2 * np.pi * (k + j) * ax for j in (-1, 0, 1)]
        out[t] = min(cands, key=lambda c: float(np.sum((c - out[t - 1]) ** 2)))
    return out


def kalman_smooth(
    z: np.ndarray, ok: np.ndarray, meas_std: np.ndarray, accel_std: np.ndarray
) -> np.ndarray:
    """Constant-velocity Kalman filter + RTS smoother, independently per column.

    z: (T, P) measurements (ignored where not ok); ok: (T,) bool; meas_std, accel_std: (P,)
    -> smoothed values (T, P). State (value, velocity), dt = 1 frame, white acceleration.
    """
    T, P = z.shape
    if T == 0:
        return z.copy()
    first = int(np.argmax(ok)) if ok.any() else 0
    q = accel_std**2
    Q = np.stack([np.stack([q / 4, q / 2], -1), np.stack([q / 2, q], -1)], -2)  # (P, 2, 2)
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    r2 = meas_std**2
    x = np.zeros((P, 2))
    x[:, 0] = z[first] if ok.any() else 0.0
    Pm = np.zeros((P, 2, 2))  # a diffuse initial state: the data alone decide
    Pm[:, 0, 0] = 1e8
    Pm[:, 1, 1] = 1e8
    xs_f = np.zeros((T, P, 2))
    Ps_f = np.zeros((T, P, 2, 2))
    xs_p = np.zeros((T, P, 2))
    Ps_p = np.zeros((T, P, 2, 2))
    for t in range(T):
        if t > 0:
            x = x @ F.T
            Pm = F @ Pm @ F.T + Q
        xs_p[t], Ps_p[t] = x, Pm
        if ok[t]:
            S = Pm[:, 0, 0] + r2
            Kg = Pm[:, :, 0] / S[:, None]  # (P, 2)
            x = x + Kg * (z[t] - x[:, 0])[:, None]
            Pm = Pm - Kg[:, :, None] * Pm[:, None, 0, :]
        xs_f[t], Ps_f[t] = x, Pm
    xs = xs_f.copy()
    for t in range(T - 2, -1, -1):
        G = Ps_f[t] @ F.T @ np.linalg.inv(Ps_p[t + 1])
        xs[t] = xs_f[t] + np.einsum("pij,pj->pi", G, xs[t + 1] - xs_p[t + 1])
    return xs[..., 0]


def initial_poses(
    xy: Tensor,
    valid: Tensor,
    cams: CameraTensors,
    body: Tensor,
    method: str = "fit",
    accel_std: tuple[float, float] = (0.2, 50.0),
) -> tuple[Tensor, Tensor]:
    """Initial poses from the detections.

    xy: (T, K, C, 2) px (anything where not valid); valid: (T, K, C) bool; body: (K, 3).
    method 'fit': Kabsch on parts triangulated from >= 2 cameras (>= 3 parts), else PnP in the
    camera with >= 4 parts, slerp-interpolated over frames without a fit; 'kalman': the same
    per-frame fits smoothed (and gaps bridged) by a constant-velocity Kalman filter + RTS
    smoother on unwrapped rotation vectors and translations.
    Returns poses (T, 6) and fitted (T,) bool (frames that had their own fit).
    """
    T, K, C, _ = xy.shape
    dt = body.dtype
    if T == 0:
        return xy.new_zeros((0, 6)), torch.zeros(0, dtype=torch.bool)
    fits = []
    for a in range(0, T, 10000):  # per-frame fits in blocks of frames (cache-friendly)
        X, mask = triangulated_parts(xy[a : a + 10000], valid[a : a + 10000], cams)
        fits.append((*kabsch_robust(body, X, mask), mask.sum(1) >= 4))
        del X, mask
        if T > 10000:
            release_freed_memory()
    poses = torch.cat([f[0] for f in fits], 0)
    ok = torch.cat([f[1] for f in fits], 0)
    strong = ok & torch.cat([f[2] for f in fits], 0)
    need = np.flatnonzero(~ok.cpu().numpy() & (valid.sum(1) >= 4).any(-1).cpu().numpy())
    if need.size:
        fits = pnp_poses(xy.cpu().numpy(), valid.cpu().numpy(), cams, body.cpu().numpy(), need)
        for t, p in fits.items():
            poses[t] = torch.as_tensor(p, dtype=dt)
            ok[t] = True
        log.debug(
            "PnP initialised %d of %d frames without a triangulated fit", len(fits), need.size
        )
    ok, dropped = consistent_fits(poses, ok, strong)
    if dropped["dropped_strong"] or dropped["dropped_weak"]:
        log.info(
            "initial fits: %d of 4+-part fits and %d of 3-part / one-camera fits turn by > 45 "
            "degrees from their neighbours in time; interpolated instead",
            dropped["dropped_strong"],
            dropped["dropped_weak"],
        )
    log.info("initial fits in %d of %d frames", int(ok.sum()), T)
    if method == "fit" or not bool(ok.any()):
        return interpolate_poses(poses, ok), ok
    if method != "kalman":
        raise ValueError(f"unknown init method {method!r} (fit, kalman)")
    okn = ok.cpu().numpy()
    filled = interpolate_poses(poses, ok).cpu().numpy()
    z = filled.copy()
    z[:, :3] = unwrap_rotations(filled[:, :3])
    meas = np.array([0.05] * 3 + [2.0] * 3)
    acc = np.array([accel_std[0]] * 3 + [accel_std[1]] * 3)
    sm = kalman_smooth(z, okn, meas, acc)
    sm_t = torch.as_tensor(sm, dtype=dt)
    r = so3_log(so3_exp(sm_t[:, :3]))
    return torch.cat((r, sm_t[:, 3:]), -1), ok


def reprojection_rms(
    poses: Tensor, body: Tensor, xy: Tensor, valid: Tensor, cams: CameraTensors
) -> float:
    """RMS reprojection error (px) of the rigid model at the poses over the valid detections."""
    X = torch.einsum("tij,kj->tki", so3_exp(poses[:, :3]), body) + poses[:, None, 3:]
    e = project_cameras(X, cams) - xy
    e2 = torch.where(valid, (e * e).sum(-1), torch.zeros_like(e[..., 0]))
    n = int(valid.sum())
    return float((e2.sum() / max(n, 1)).sqrt())
