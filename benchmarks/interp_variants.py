"""Imputation and uncertainty variants of ``deformation=interp`` on the real motion (issue 45).

The defaults' uncertainty is calibrated when pooled but not part by part on the real mouse's
occluded part-frames, and another detector seed moves their RMSE by > 10% at 3 cameras (the
error is on parts no camera sees, in gaps of up to 300 frames). This script tries, on
`real_motion.py`'s scenes (the validation segment by default), the variants that were proposed
for both, without changing the library: each is patched into one process around
`adjust-track`'s defaults.

- ``base``: the defaults before issue 45's stop (``deform.single_views=false``).
- ``cv_calibration``: the kriging variance of the unobserved part-frames scaled per part by the
  recording's own cross-validation (`calibrate_kriging`: observed stretches hidden in blocks
  whose lengths follow the session's real gap lengths, the held-out error against the
  predicted variance, shrunk towards the pooled ratio).
- ``shape_drift``: each part's offset kriged about its prediction from the other parts seen in
  the same frame (`PartCovariance`, the body's shape space learned from the frames where the
  parts are seen: a Gaussian conditional), so that a long gap reverts to the shape space's
  prediction instead of the part's mean.
- ``shape_fused``: the kriging and the shape space's prediction fused (product of Gaussians)
  on the unobserved part-frames only.
- ``no_mean``: inside a gap the interpolation between its ends, never the part's mean (the
  kriging's fallback where the interpolation's variance exceeds the sill).
- ``blend``: inside a gap the interpolation and the mean fused as independent Gaussians.
- ``single_views``: the defaults since issue 45's stop (``deform.single_views=true``): interp
  solved twice, the second time with the part-frames one camera saw (at the first pass's fused
  points, their fused variance as noise) among the observations the gaps are interpolated from
  (`InterpObservation.anchored`). Every other variant runs with ``deform.single_views=false``
  (the defaults before).
- ``inflation_clip9``, ``inflation_clip16``, ``inflation_median``: the solver's per-part
  inflation of the prior from the single views (`adjust.lsq.fusion.prior_inflation`: the
  mean squared Mahalanobis distance, each clipped at 30, at most 2) with each distance clipped
  at 9 or 16 (the target scaled to the clipped chi-square mean), or the median at most the
  chi-square median: swapped or outlying single views count less.
- ``rays1``, ``rays3``, ``rays6``, ``rays12``: ``single_views`` with each anchor read as its
  camera's ray and every part's offsets smoothed over the session (``deform.anchors=rays``,
  `adjust.lsq.smoother`), the views' sd across their rays 1, 3, 6, 12 x the detector's
  (``deform.ray_sd_factor``).
- (``gap_sigma_leave_runs_out``, ``gap_sigma_anchors_out``, stop 47: the reported sigma of
  the gaps from a held-out check; ``deform.gap_sigma`` was deleted at stop 54, it did not
  calibrate 2 cameras: run them on a checkout before it.) The occluded calibration is also
  split by the cameras that saw a part-frame: none / one (``calib_no_view``,
  ``calib_one_view``).

Metrics per scene (`real_motion.evaluate`, `real_motion.calibration`): RMSE all / seen >= 2 /
occluded, the pooled calibration ratios, how many parts' occluded ratios are within 0.8-1.25;
per variant the mean over the scenes and the seed change at 3 cameras (seeds 0 and 100,
|b - a| / mean, as `real_motion.py`'s stability table).

    .venv/bin/python benchmarks/interp_variants.py [--split val] [--scenes 3x0,3x1,3x100,2x0,4x0]
        [--variants base,cv_calibration,...] [--out runs/benchmarks/interp_variants_val.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import real_motion as rm  # noqa: E402
from common import emit, start  # noqa: E402
from tracking import run_track  # noqa: E402

import adjust.lsq.observation as observation  # noqa: E402
from adjust.lsq import fusion  # noqa: E402
from adjust.lsq.geometry import so3_exp  # noqa: E402
from adjust.lsq.stochastic import OffsetCovariance, krige_offsets, neighbours  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RAY_SD_FACTORS = (1, 3, 6, 12)
VARIANTS = (
    "base",
    "cv_calibration",
    "shape_drift",
    "shape_fused",
    "no_mean",
    "blend",
    "single_views",
    "inflation_clip9",
    "inflation_clip16",
    "inflation_median",
    *(f"rays{f}" for f in RAY_SD_FACTORS),
)
#: variants that are the defaults with these settings (else ``deform.single_views=false``)
OVERRIDES = {
    "single_views": ["deform.anchors=fused"],
    **{f"rays{f}": ["deform.anchors=rays", f"deform.ray_sd_factor={f}"] for f in RAY_SD_FACTORS},
}


@dataclass
class PartCovariance:
    """How the parts' body-frame offsets vary together within a frame (the body's shape space):
    mean (K, 3) mm and the joint covariance (3K, 3K) mm^2 of the offsets of all parts (part k's
    axes at rows 3k..3k+2), estimated from the part-frames triangulated from >= 2 cameras
    (pairwise: each block from the frames where both parts were seen, shrunk towards 0 where
    those are few; made positive definite). It predicts a part from the other parts seen in the
    same frame (`condition`): the nose tip from the ears, a paw from the other paws."""

    mean: np.ndarray
    cov: np.ndarray

    @classmethod
    def estimate(
        cls,
        offsets: np.ndarray,
        observed: np.ndarray,
        shrink_pairs: float = 50.0,
        min_pairs: int = 20,
        floor_mm: float = 0.3,
    ) -> PartCovariance:
        """From offsets (T, K, 3) observed where ``observed`` (T, K). The block of parts i, j is
        the mean product of their centred offsets over the frames both are seen in, times
        n / (n + shrink_pairs) (few common frames: little claimed dependence; none below
        ``min_pairs``); the matrix is then made positive definite (eigenvalues >= floor^2)."""
        o = np.asarray(offsets, dtype=np.float64)
        m = np.asarray(observed, dtype=bool) & np.isfinite(o).all(-1)
        T, K, _ = o.shape
        n = m.sum(0)
        mean = np.where(m[..., None], o, 0.0).sum(0) / np.maximum(n, 1)[:, None]
        z = np.where(m[..., None], o - mean, 0.0).reshape(T, 3 * K)
        w = np.repeat(m, 3, axis=1).astype(np.float64)
        both = w.T @ w  # (3K, 3K) frames both seen
        cov = (z.T @ z) / np.maximum(both, 1.0)
        factor = np.where(both >= min_pairs, both / (both + shrink_pairs), 0.0)
        diag = np.kron(np.eye(K), np.ones((3, 3))).astype(bool)
        cov = np.where(diag, cov, cov * factor)
        few = np.repeat(n < min_pairs, 3)
        cov[few, :] = 0.0
        cov[:, few] = 0.0
        big = 4.0 * max(float(np.diag(cov).max()), floor_mm**2)
        cov[few, few] = big  # barely known: wide, independent, mean 0 (as `OffsetCovariance`)
        mean[n < min_pairs] = 0.0
        cov = 0.5 * (cov + cov.T)
        val, vec = np.linalg.eigh(cov)
        cov = (vec * np.maximum(val, floor_mm**2)) @ vec.T
        return cls(mean, 0.5 * (cov + cov.T))

    def condition(self, offsets: np.ndarray, observed: np.ndarray, batch: int = 256):
        """Each part-frame's offset predicted from the *other* parts seen in the same frame
        (the Gaussian conditional mean; a seen part's own observation left out).

        offsets (T, K, 3) (any value where not observed), observed (T, K) -> prediction
        (T, K, 3) mm and its variance (T, K, 3) mm^2 per body axis (the conditional
        covariance's diagonal). A frame with no other part seen gets the mean and the
        marginal variance. Frames are grouped by which parts are seen."""
        o = np.asarray(offsets, dtype=np.float64)
        m = np.asarray(observed, dtype=bool) & np.isfinite(o).all(-1)
        T, K, _ = o.shape
        D = 3 * K
        x = np.where(m[..., None], o - self.mean[None], 0.0).reshape(T, D)
        pred = np.broadcast_to(self.mean[None], (T, K, 3)).copy().reshape(T, D)
        var = np.broadcast_to(np.diag(self.cov).reshape(1, D), (T, D)).copy()
        S_all = self.cov
        patterns, inverse = np.unique(m, axis=0, return_inverse=True)
        inverse = np.asarray(inverse).reshape(-1)
        for p, seen in enumerate(patterns):
            if not seen.any():
                continue
            rows = np.nonzero(inverse == p)[0]
            s = np.repeat(seen, 3)
            si, ui = np.nonzero(s)[0], np.nonzero(~s)[0]
            Q = np.linalg.inv(S_all[np.ix_(si, si)])  # precision of the seen block
            Qx = x[np.ix_(rows, si)] @ Q  # (n, |S|)
            if ui.size:
                A = S_all[np.ix_(ui, si)]
                pred[np.ix_(rows, ui)] += Qx @ A.T
                var[np.ix_(rows, ui)] = np.diag(S_all[np.ix_(ui, ui)] - A @ Q @ A.T)[None]
            # a seen part from the others: o_k - Q_kk^-1 (Q x)_k (leave-one-out)
            ks = np.nonzero(seen)[0]
            for j, k in enumerate(ks):
                b = slice(3 * j, 3 * j + 3)
                Ckk = np.linalg.inv(Q[b, b])
                cols = slice(3 * k, 3 * k + 3)
                pred[rows, cols] = o[rows, k] - Qx[:, b] @ Ckk.T
                var[rows, cols] = np.diag(Ckk)[None]
        return pred.reshape(T, K, 3), np.maximum(var, 1e-6).reshape(T, K, 3)


def gap_lengths(observed: np.ndarray) -> list[np.ndarray]:
    """Per part, the lengths (frames) of its runs of unobserved frames between observed ones
    (the interior gaps; a session's ends are not gaps between observations): observed (T, K)
    -> K arrays of ints."""
    m = np.asarray(observed, dtype=bool)
    out = []
    for k in range(m.shape[1]):
        idx = np.nonzero(m[:, k])[0]
        d = np.diff(idx) - 1 if idx.size >= 2 else np.zeros(0, dtype=np.int64)
        out.append(d[d > 0])
    return out


@dataclass
class KrigingCalibration:
    """Per part, the factor (K,) on the kriging variance of its unobserved part-frames that
    makes the prediction's error agree with its variance on the recording's own held-out
    observations (`calibrate_kriging`): raw (K,) the held-out ratios before shrinkage, blocks
    (K,) how many held-out blocks each rests on, pooled the ratio over all parts."""

    factor: np.ndarray
    raw: np.ndarray
    blocks: np.ndarray
    pooled: float


def calibrate_kriging(
    offsets: np.ndarray,
    observed: np.ndarray,
    predict,
    nugget: np.ndarray,
    rounds: int = 4,
    hide: float = 0.15,
    prior_blocks: float = 10.0,
    clip: tuple[float, float] = (0.2, 8.0),
    seed: int = 0,
) -> KrigingCalibration:
    """Calibrate a predictor's variance across gaps by cross-validation on the recording itself.

    offsets (T, K, 3) observed where ``observed`` (T, K); predict(offsets, observed) ->
    (prediction (T, K, 3), variance (T, K, 3)), the predictor the tracks use (e.g.
    `krige_offsets`); nugget (K, 3) mm^2 the noise of one observation. In each of ``rounds``
    rounds, blocks of observed frames are hidden in every part (about ``hide`` of its observed
    frames), their lengths drawn from the session's real gap lengths (the part's own where it
    has >= 5 gaps, else all parts'), and the hidden observations predicted from the rest: the
    ratio of the squared errors to the predicted variance plus the nugget, summed over the
    part's hidden part-frames, is the part's factor, shrunk in log towards the pooled one with
    weight blocks / (blocks + ``prior_blocks``) (held-out frames of one block are not
    independent), and clipped to ``clip``. Deterministic (``seed``)."""
    o = np.asarray(offsets, dtype=np.float64)
    m = np.asarray(observed, dtype=bool) & np.isfinite(o).all(-1)
    T, K, _ = o.shape
    rng = np.random.default_rng(seed)
    gaps = gap_lengths(m)
    pool = np.concatenate([g for g in gaps]) if any(g.size for g in gaps) else np.array([1])
    num = np.zeros(K)
    den = np.zeros(K)
    nblocks = np.zeros(K)
    nug = np.asarray(nugget, dtype=np.float64).sum(-1)  # (K,) 3D
    for _ in range(rounds):
        hidden = np.zeros_like(m)
        for k in range(K):
            idx = np.nonzero(m[:, k])[0]
            if idx.size < 20:
                continue
            lengths = gaps[k] if gaps[k].size >= 5 else pool
            budget = hide * idx.size
            taken = 0
            for _try in range(200):
                if taken >= budget:
                    break
                L = int(rng.choice(lengths))
                s = int(rng.integers(0, T))
                blk = slice(s, min(s + L, T))
                # a block starts at an observed frame and leaves observations on both sides
                if not m[s, k] or hidden[max(s - 1, 0) : blk.stop + 1, k].any():
                    continue
                if not m[:s, k].any() or not m[blk.stop :, k].any():
                    continue
                hidden[blk, k] = m[blk, k]
                taken += int(m[blk, k].sum())
                nblocks[k] += 1
        if not hidden.any():
            break
        pred, var = predict(o, m & ~hidden)
        e2 = ((o - pred) ** 2).sum(-1)
        v = var.sum(-1) + nug[None]
        num += np.where(hidden, e2, 0.0).sum(0)
        den += np.where(hidden, v, 0.0).sum(0)
    ok = den > 0
    raw = np.where(ok, num / np.where(ok, den, 1.0), np.nan)
    pooled = float(num[ok].sum() / den[ok].sum()) if ok.any() else 1.0
    w = np.where(ok, nblocks / (nblocks + prior_blocks), 0.0)
    logf = w * np.log(np.where(ok, raw, 1.0).clip(1e-6)) + (1.0 - w) * math.log(max(pooled, 1e-6))
    factor = np.clip(np.exp(logf), *clip)
    return KrigingCalibration(factor, raw, nblocks, pooled)


# --- the variants, patched into this process -------------------------------------------------


def _krige_cv(offsets, observed, cov, skip_self=True):
    """`krige_offsets`, its variance on unobserved part-frames times `calibrate_kriging`'s
    per-part factor."""
    pred, var = krige_offsets(offsets, observed, cov, skip_self=skip_self)
    m = np.asarray(observed, dtype=bool) & np.isfinite(offsets).all(-1)

    def predict(o, mm):
        return krige_offsets(o, mm, OffsetCovariance.estimate(o, mm, nugget=cov.nugget))

    cal = calibrate_kriging(offsets, m, predict, cov.nugget)
    return pred, np.where(m[..., None], var, var * cal.factor[None, :, None])


def _krige_drift(offsets, observed, cov, skip_self=True):
    """Kriging about the shape space's prediction from the frame's other parts."""
    m = np.asarray(observed, dtype=bool) & np.isfinite(offsets).all(-1)
    drift, _ = PartCovariance.estimate(offsets, m).condition(offsets, m)
    e = offsets - drift
    rcov = OffsetCovariance.estimate(e, m, nugget=cov.nugget)
    pe, var = krige_offsets(e, m, rcov, skip_self=skip_self)
    return drift + pe, var


def _krige_fused(offsets, observed, cov, skip_self=True):
    """On unobserved part-frames, the kriging and the shape space fused as independent."""
    m = np.asarray(observed, dtype=bool) & np.isfinite(offsets).all(-1)
    pk, vk = krige_offsets(offsets, observed, cov, skip_self=skip_self)
    pd, vd = PartCovariance.estimate(offsets, m).condition(offsets, m)
    w = vd / (vk + vd)
    g = m[..., None]
    return np.where(g, pk, w * pk + (1 - w) * pd), np.where(g, vk, vk * vd / (vk + vd))


def _krige_no_mean(offsets, observed, cov, skip_self=True):
    """Inside a gap (an observation on both sides) the interpolation between its ends, never
    the part's mean (its variance the interpolation's, beyond the sill in long gaps): a part
    hidden away from its usual place is nearer its gap's ends than its mean."""
    pred, var = krige_offsets(offsets, observed, cov, skip_self=skip_self)
    wide = dataclasses.replace(cov, sill=np.full_like(cov.sill, 1e12))
    p2, v2 = krige_offsets(offsets, observed, wide, skip_self=skip_self)
    m = np.asarray(observed, dtype=bool) & np.isfinite(offsets).all(-1)
    prev, nxt = neighbours(m, skip_self)
    inside = ((prev >= 0) & (nxt < m.shape[0]))[..., None]
    return np.where(inside, p2, pred), np.where(inside, v2, var)


def _krige_blend(offsets, observed, cov, skip_self=True):
    """Inside a gap the interpolation between its ends and the part's mean fused as
    independent Gaussians (variances: the interpolation's, the sill): a smooth version of the
    kriging's switch to the mean where the interpolation's variance exceeds the sill."""
    pred, var = krige_offsets(offsets, observed, cov, skip_self=skip_self)
    wide = dataclasses.replace(cov, sill=np.full_like(cov.sill, 1e12))
    p2, v2 = krige_offsets(offsets, observed, wide, skip_self=skip_self)
    sill = cov.sill[None]
    pb = (sill * p2 + v2 * cov.mean[None]) / (sill + v2)
    vb = sill * v2 / (sill + v2)
    m = np.asarray(observed, dtype=bool) & np.isfinite(offsets).all(-1)
    prev, nxt = neighbours(m, skip_self)
    inside = ((prev >= 0) & (nxt < m.shape[0]))[..., None]
    return np.where(inside, pb, pred), np.where(inside, vb, var)


def _inflation(stat):
    """`fusion.prior_inflation` with another statistic of the single views' squared
    Mahalanobis distances d2 (stat(d2) <= 2 is the target)."""

    def prior_inflation(X_prior, prior_cov, xy, use, cams, sigma_px, min_count=30):
        uv, J, _ = fusion.project_with_jacobian(X_prior, cams)
        JPJ = J @ prior_cov[..., None, :, :] @ J.transpose(-1, -2)
        e = torch.where(use[..., None], xy - uv, torch.zeros_like(uv))
        out = torch.ones(use.shape[1], dtype=X_prior.dtype)
        eye = torch.eye(2, dtype=JPJ.dtype)
        for k in range(use.shape[1]):
            mk = use[:, k]
            if int(mk.sum()) < min_count:
                continue
            Pk, ek = JPJ[:, k][mk], e[:, k][mk]
            best = None
            for a in fusion.INFLATIONS:
                S = a * Pk + sigma_px**2 * eye
                d2 = (ek[..., None, :] @ torch.linalg.solve(S, ek[..., None]))[..., 0, 0]
                best = a
                if stat(d2) <= 2.0:
                    break
            out[k] = best
        return out

    return prior_inflation


def _clipped(c: float):
    return lambda d2: float(d2.clamp_max(c).mean()) / (1.0 - math.exp(-c / 2.0))


def _median(d2) -> float:
    return float(d2.median()) / math.log(2.0)  # chi-square (2 dof) median: 2 ln 2


def patch(variant: str) -> None:
    """Put `variant` in place (and undo any other: ``base`` restores the library's)."""
    krige = {"cv_calibration": _krige_cv, "shape_drift": _krige_drift,
             "shape_fused": _krige_fused, "no_mean": _krige_no_mean,
             "blend": _krige_blend}.get(
                 variant, krige_offsets)  # fmt: skip
    observation.krige_offsets = krige
    infl = {
        "inflation_clip9": _inflation(_clipped(9.0)),
        "inflation_clip16": _inflation(_clipped(16.0)),
        "inflation_median": _inflation(_median),
    }.get(variant, fusion.prior_inflation)
    for name, mod in list(sys.modules.items()):  # wherever the solver imported it from
        if name.startswith("adjust.lsq") and name != "adjust.lsq.fusion":
            if getattr(mod, "prior_inflation", None) is not None:
                mod.prior_inflation = infl


# --- what the tracker's stochastic model sees, against the truth -----------------------------


class Recorder:
    """Keeps the last `InterpObservation` prepared (with its poses) and the solver's last
    per-part prior inflation, for `gap_diagnosis`."""

    def __init__(self) -> None:
        self.obs = self.poses = self.alpha = None
        self._prepare = observation.InterpObservation.prepare
        self._inflation = None

    def install(self) -> None:
        rec = self

        def prepare(obs, poses):
            rec._prepare(obs, poses)
            rec.obs, rec.poses = obs, poses.detach().clone()

        observation.InterpObservation.prepare = prepare
        for name, mod in list(sys.modules.items()):
            if name.startswith("adjust.lsq") and name != "adjust.lsq.fusion":
                inner = getattr(mod, "prior_inflation", None)
                if inner is not None:

                    def infl(*a, inner=inner, **k):
                        out = inner(*a, **k)
                        rec.alpha = out.detach().cpu().numpy().copy()
                        return out

                    mod.prior_inflation = infl

    def uninstall(self) -> None:
        observation.InterpObservation.prepare = self._prepare


def gap_diagnosis(rec: Recorder, truth: np.ndarray, parts: list[str]) -> dict:
    """Per part, in the tracker's body frame (its final poses): the rms distance (mm) of the
    *true* offset from the part's estimated mean offset on the part-frames with a 3D observation
    and on the others (the gaps the kriging fills), the estimated spread (sqrt of the summed
    sills), the rms kriging sd on the gaps and the solver's prior inflation from the single
    views. Where the gaps' distance exceeds the observed frames' the occlusion is not at random:
    a part is hidden when it is away from where it usually is."""
    obs = rec.obs
    P = rec.poses
    R = so3_exp(P[:, :3]).cpu().numpy().astype(np.float64)
    t = P[:, 3:].cpu().numpy().astype(np.float64)
    B = obs.body.cpu().numpy().astype(np.float64)
    o_true = np.einsum("tji,tkj->tki", R, truth - t[:, None]) - B[None]
    good = obs.observed.cpu().numpy() & ~obs.outliers.cpu().numpy()
    var = obs._var.cpu().numpy()
    if var.ndim == 4:  # full body-axis covariances (``anchors=rays``): their diagonal
        var = np.diagonal(var, axis1=-2, axis2=-1)
    d = np.sqrt(((o_true - obs.cov.mean[None]) ** 2).sum(-1))
    out = {}
    for k, p in enumerate(parts):
        g, m = ~good[:, k], good[:, k]
        out[p] = {
            "observed_mm": float(np.sqrt(np.mean(d[m, k] ** 2))) if m.any() else None,
            "gap_mm": float(np.sqrt(np.mean(d[g, k] ** 2))) if g.any() else None,
            "spread_mm": float(np.sqrt(obs.cov.sill[k].sum())),
            "kriging_sd_gap_mm": float(np.sqrt(var[g, k].sum(-1).mean())) if g.any() else None,
            "inflation": None if rec.alpha is None else float(rec.alpha[k]),
        }
    return out


def ray_diagnosis(rec: Recorder, truth: np.ndarray) -> dict | None:
    """``anchors=rays``: on the part-frames one camera saw, the prior's error (the smoother's
    prediction without the frame's own view, against the truth, in the tracker's body frame)
    along the view's ray and across it, rms error (mm), rms predicted sd (mm) and their ratio
    (1: calibrated); and on the part-frames no view saw. None without rays."""
    obs = rec.obs
    if obs is None or obs.rays is None:
        return None
    P = rec.poses
    R = so3_exp(P[:, :3]).cpu().numpy().astype(np.float64)
    t = P[:, 3:].cpu().numpy().astype(np.float64)
    err = np.einsum("tji,tkj->tki", R, truth - t[:, None]) - obs._M.cpu().numpy()
    var = obs._var.cpu().numpy()
    one = obs.anchors.cpu().numpy() & ~obs.outliers.cpu().numpy()
    u = np.einsum("tji,tkj->tki", R, obs.rays.cpu().numpy())[one]
    e, V = err[one], var[one]
    along = (e * u).sum(-1)
    v_along = np.einsum("ni,nij,nj->n", u, V, u)
    across2 = (e**2).sum(-1) - along**2
    v_across = np.trace(V, axis1=-2, axis2=-1) - v_along
    none = ~obs.observed.cpu().numpy()
    e0, v0 = (err[none] ** 2).sum(-1), np.trace(var[none], axis1=-2, axis2=-1)

    def row(e2, v):
        re, rs = float(np.sqrt(np.mean(e2))), float(np.sqrt(np.mean(v)))
        return {"rms_err_mm": re, "rms_sd_mm": rs, "ratio": re / rs}

    return {
        "one_view_along": row(along**2, v_along),
        "one_view_across": row(across2, v_across),
        "no_view": row(e0, v0) if none.any() else None,
    }


def calibration_by_views(points_csv: Path, est, truth, nviews, parts) -> dict:
    """The occluded part-frames' pooled calibration (rms error / rms sigma) split by how many
    cameras saw them: none (``calib_no_view``: the tracks are the model's alone) and one
    (``calib_one_view``: fused with that view)."""
    extra = rm.read_points3d(points_csv)["extra"]
    sig = np.stack([np.asarray(extra[f"{p}_sigma"], float) for p in parts], 1)
    err = np.linalg.norm(est - truth, axis=-1)
    return {
        "calib_no_view": rm._ratio(err, sig, nviews == 0),
        "calib_one_view": rm._ratio(err, sig, nviews == 1),
    }


# --- runs -----------------------------------------------------------------------------------


def run_variant(variant: str, scenes: list[tuple[int, int]], args, motion, work: Path) -> dict:
    patch(variant)
    start_frame = rm.SPLITS[args.split]
    rows = {}
    for cams, seed in scenes:
        key = rm.scene_key(args.split, start_frame, args.frames, cams, 8, seed)
        scene = rm.film_scene(
            work / "scenes" / key, motion, start_frame, args.frames, cams, 8, seed
        )
        tr = np.load(scene / "truth.npz")
        truth, nv = tr["points"], tr["nviews"]
        parts = [str(p) for p in tr["parts"]]
        out = work / "runs" / variant / key
        t0 = time.perf_counter()
        rec = Recorder()
        rec.install()
        try:
            ov = OVERRIDES.get(variant, ["deform.single_views=false"])
            est, _, summ = run_track(scene, out, [f"threads={args.threads}", *ov])
        finally:
            rec.uninstall()
        est = rm.align(est, summ["parts"], parts)
        row = {**rm.evaluate(est, truth, nv), "seconds": round(time.perf_counter() - t0, 2)}
        row.update(rm.calibration(out / "points3d.csv", est, truth, nv, parts))
        row.update(calibration_by_views(out / "points3d.csv", est, truth, nv, parts))
        row["parts_calibrated"] = rm.calibrated_parts(row["calib_per_part"])
        if rec.obs is not None:
            row["gaps"] = gap_diagnosis(rec, truth, parts)
            row["rays"] = ray_diagnosis(rec, truth)
        rows[key] = row
        print(
            f"{variant:<18} {key:<26} all {row['rmse_all']:6.3f}  >=2 {row['rmse_seen2']:6.3f}  "
            f"occl {row['rmse_occluded']:6.3f}  cal >=2 {row['calib_seen']:5.2f}  occl "
            f"{row['calib_occluded']:5.2f}  parts occl in range "
            f"{row['parts_calibrated']['occluded'][0]}/{row['parts_calibrated']['occluded'][1]}"
            f"  (no camera {row['calib_no_view']:4.2f}, one {row['calib_one_view']:4.2f})"
            + (
                "  prior / truth, one view: along the ray {:.2f}, across {:.2f}".format(
                    row["rays"]["one_view_along"]["ratio"], row["rays"]["one_view_across"]["ratio"]
                )
                if row.get("rays")
                else ""
            ),
            flush=True,
        )
    patch("base")
    return rows


def summarize(rows: dict, args) -> dict:
    start_frame = rm.SPLITS[args.split]
    vals = list(rows.values())
    s = {
        c: float(np.mean([r[c] for r in vals]))
        for c in ("rmse_all", "rmse_seen2", "rmse_occluded", "calib_seen", "calib_occluded")
    }
    lo, hi = rm.CALIBRATED
    s["pooled_occluded_in_range"] = sum(lo <= r["calib_occluded"] <= hi for r in vals)
    s["parts_occluded_in_range"] = sum(r["parts_calibrated"]["occluded"][0] for r in vals)
    s["parts_occluded_measured"] = sum(r["parts_calibrated"]["occluded"][1] for r in vals)
    a = rows.get(rm.scene_key(args.split, start_frame, args.frames, 3, 8, rm.STABILITY_SEED))
    b = rows.get(rm.scene_key(args.split, start_frame, args.frames, 3, 8, rm.OTHER_DETECTOR_SEED))
    if a and b:
        s["seed_change_3cams"] = abs(b["rmse_all"] - a["rmse_all"]) / (
            0.5 * (a["rmse_all"] + b["rmse_all"])
        )
    return s


def _num(v) -> str:
    return f"{v:6.2f}" if isinstance(v, float) and math.isfinite(v) else f"{'-':>6}"


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", choices=sorted(rm.SPLITS), default="val")
    ap.add_argument("--frames", type=int, default=rm.SEGMENT_FRAMES)
    ap.add_argument("--scenes", default="3x0,3x1,3x100,2x0,4x0",
                    help="cameras x detector seed, 8 parts")  # fmt: skip
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--data", default=str(rm.DATA))
    ap.add_argument("--work", default=str(ROOT / "runs" / "benchmarks" / "interp_variants"))
    ap.add_argument("--out", default=None)
    args = start(ap, argv)
    try:
        scenes = [tuple(int(x) for x in s.split("x")) for s in args.scenes.split(",") if s]
    except ValueError:
        ap.error(f"--scenes: comma list of CAMERASxSEED, got {args.scenes!r}")
    variants = [v for v in args.variants.split(",") if v]
    bad = [v for v in variants if v not in VARIANTS]
    if bad:
        ap.error(f"--variants: unknown {bad}; choose from {','.join(VARIANTS)}")
    motion = rm.Motion(Path(args.data))
    work = Path(args.work) / motion.tag
    res = {v: run_variant(v, scenes, args, motion, work) for v in variants}
    summary = {v: summarize(rows, args) for v, rows in res.items()}
    print(f"\n{args.split} segment, scenes {args.scenes}: mean over scenes")
    cols = ("rmse_all", "rmse_seen2", "rmse_occluded", "calib_seen", "calib_occluded",
            "seed_change_3cams")  # fmt: skip
    print(f"{'variant':<18}" + "".join(f"{c:>18}" for c in cols) + "  parts occl in range")
    for v, s in summary.items():
        print(
            f"{v:<18}" + "".join(f"{s.get(c, float('nan')):>18.3f}" for c in cols)
            + f"  {s['parts_occluded_in_range']}/{s['parts_occluded_measured']}"
            + f" (pooled {s['pooled_occluded_in_range']}/{len(scenes)})"
        )  # fmt: skip
    for v, rows in res.items():
        if v != "base":
            continue
        print(
            "\nbase: the true offset's rms distance (mm) from the part's estimated mean, on "
            "frames with a 3D observation / on the gaps; the estimated spread; the kriging sd "
            "on the gaps; the solver's prior inflation (single views)"
        )
        for key, r in rows.items():
            print(f"  {key}")
            for p, g in (r.get("gaps") or {}).items():
                print(
                    f"    {p:<18} observed {_num(g['observed_mm'])}  gaps {_num(g['gap_mm'])}"
                    f"  spread {_num(g['spread_mm'])}  kriging sd {_num(g['kriging_sd_gap_mm'])}"
                    f"  inflation {_num(g['inflation'])}"
                )
    out = args.out or str(ROOT / "runs" / "benchmarks" / f"interp_variants_{args.split}.json")
    return emit({"split": args.split, "scenes": args.scenes, "summary": summary,
                 "rows": res}, out)  # fmt: skip


if __name__ == "__main__":
    main()
