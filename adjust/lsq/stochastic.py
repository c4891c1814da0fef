"""Stochastic model estimated from the data: detector noise, per-part deformation, interpolation.

Nothing here is a fixed constant: every variance is estimated from the session itself.

- `detector_sigma`: the detector's pixel noise from the reprojection residuals of the robustly
  triangulated part-frames (sum of squared residuals over their degrees of freedom, 2n - 3 for
  n views, trimmed against mis-detections), per camera and pooled.
- `OffsetCovariance`: how a part's position in body coordinates, o_t = R_t^T (X_t - tau_t) - B,
  varies in time: per part and body axis its mean, its variance (the deformation variance: a
  hind paw strays from the rigid body far more than an ear), the triangulation noise on it
  (the nugget) and its empirical semivariogram gamma(h) = E |o_{t+h} - o_t|^2 / 2 over lags h
  in frames, estimated from the part-frames triangulated from >= 2 cameras.
- `krige_offsets`: each part-frame's offset predicted from the nearest observed frames before
  and after it, *excluding the frame itself*: linear interpolation across a gap (held at the
  ends), its error variance from the semivariogram (or the part's mean where that is the
  better guess). On a gap this is the interpolation of the offsets; on an observed frame it is
  the prediction from its neighbours, an independent prior to fuse with the frame's own
  detections. The variance is what makes the reported uncertainty calibrated.

Shapes: T frames, K parts, C cameras. Units: px, mm, frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: lags (frames) at which the semivariogram is estimated; linear in between, the sill beyond
DEFAULT_LAGS = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512)


def all_last(b: np.ndarray) -> np.ndarray:
    """``b.all(-1)`` of a bool array (..., n): for n = 3 (points) by its three slices, which
    numpy does an order of magnitude faster than a reduction over a short last axis."""
    b = np.asarray(b, dtype=bool)
    if b.ndim and b.shape[-1] == 3:
        return b[..., 0] & b[..., 1] & b[..., 2]
    return b.all(-1)


def detector_sigma(
    view_error: np.ndarray, used: np.ndarray, trim: float = 4.0, floor: float = 0.05
) -> tuple[float, np.ndarray]:
    """Detector noise (px) from triangulation residuals.

    view_error: (T, K, C) reprojection error px of each view of a triangulated point (NaN where
    none); used: (T, K, C) bool, the views the point rests on. A point from n >= 2 views leaves
    2n - 3 degrees of freedom in its 2n residual coordinates, so sigma^2 = sum |e|^2 / sum(2n - 3)
    (pooled), and per camera sigma_c^2 = sum_c |e|^2 / sum_c (2n - 3)/n. Residuals beyond
    ``trim`` sigma are dropped and the estimate repeated (mis-detections are not noise).
    Returns (pooled sigma, (C,) per-camera sigma; NaN where a camera has no data).
    """
    e = np.asarray(view_error, dtype=np.float64)
    u = np.asarray(used, dtype=bool) & np.isfinite(e)
    if e.ndim != 3 or u.shape != e.shape:
        raise ValueError(f"view_error and used must be (T, K, C), got {e.shape}, {u.shape}")
    C = e.shape[-1]
    n = u.sum(-1, keepdims=True)
    ok = u & (n >= 2)
    if not ok.any():
        return float("nan"), np.full(C, np.nan)
    dof = np.where(ok, (2.0 * n - 3.0) / np.maximum(n, 1), 0.0)  # each view's share
    e2 = np.where(ok, e * e, 0.0)
    keep = ok
    sigma2 = e2.sum() / max(dof.sum(), 1e-12)
    for _ in range(5):  # trimmed re-estimation (a clean Gaussian loses ~0.03% beyond 4 sigma)
        keep = ok & (e2 <= (trim * trim) * sigma2)
        new = (e2 * keep).sum() / max((dof * keep).sum(), 1e-12)
        if abs(new - sigma2) <= 1e-6 * sigma2:
            sigma2 = new
            break
        sigma2 = new
    # the trimmed sum misses the Gaussian tail beyond `trim` sigma (2D: exp(-trim^2/2))
    sigma2 /= 1.0 - (1.0 + trim * trim / 2.0) * math.exp(-trim * trim / 2.0)
    per = np.full(C, np.nan)
    for c in range(C):
        d = (dof[..., c] * keep[..., c]).sum()
        if d > 10:
            per[c] = math.sqrt((e2[..., c] * keep[..., c]).sum() / d)
    return max(math.sqrt(sigma2), floor), per


def body_offsets(poses_R: np.ndarray, poses_t: np.ndarray, X: np.ndarray, body: np.ndarray):
    """Offsets of global points from the rigid model in body coordinates.

    poses_R (T, 3, 3), poses_t (T, 3): model -> global; X (T, K, 3) global mm (NaN missing);
    body (K, 3) -> (T, K, 3) o = R^T (X - t) - B (NaN where X is).
    """
    c = np.einsum("tji,tkj->tki", poses_R, X - poses_t[:, None, :])
    return c - body[None]


@dataclass
class OffsetCovariance:
    """Per part and body axis: mean (K, 3) mm, sill = variance (K, 3) mm^2, nugget (K, 3) mm^2
    (noise of a single observation), the semivariogram gamma (K, 3, L) mm^2 at ``lags`` (L,)
    frames (of the noise-free offsets), and the observation counts (K,)."""

    mean: np.ndarray
    sill: np.ndarray
    nugget: np.ndarray
    lags: np.ndarray
    gamma: np.ndarray
    counts: np.ndarray

    @property
    def sigma_mm(self) -> np.ndarray:
        """(K,) 3D rms deformation of each part about its mean position: sqrt(sum of sills)."""
        return np.sqrt(self.sill.sum(-1))

    def covariance(self, h: np.ndarray) -> np.ndarray:
        """C(h) = sill - gamma(h) of the noise-free offsets: lags h (T, K) frames (>= 0;
        C(0) = sill) -> (T, K, 3) mm^2."""
        h = np.asarray(h, dtype=np.float64)
        K = self.sill.shape[0]
        if h.ndim != 2 or h.shape[1] != K:
            raise ValueError(f"lags must be (T, {K}), got {h.shape}")
        top = float(self.lags[-1]) + 1.0
        if h.shape[0] > top and (h >= 0).all():
            whole = np.minimum(h, top).astype(np.int64)
            if (whole == np.minimum(h, top)).all():  # whole lags: tabulated
                return self.lag_covariance(whole)
        return self._interpolated(h)

    def _interpolated(self, h: np.ndarray) -> np.ndarray:
        """`covariance` at lags h (T, K) float: every part and axis's semivariogram
        interpolated at once, by np.interp's arithmetic (the same values: between two lags
        slope * (h - lag_j) + g_j with slope = (g_{j+1} - g_j) / (lag_{j+1} - lag_j); at a lag
        its value; before the first 0, beyond the last the sill)."""
        T, K = h.shape
        lag = np.concatenate(([0.0], self.lags.astype(np.float64)))  # (L + 1,)
        n = lag.size
        g = np.concatenate((np.zeros((K, 3, 1)), self.gamma), -1)  # (K, 3, L + 1)
        g = np.ascontiguousarray(np.swapaxes(g, 1, 2))  # (K, L + 1, 3)
        sill = np.broadcast_to(self.sill[None], (T, K, 3))
        if n == 1:  # one lag (0): 0 there, the sill beyond
            v = np.where((h > lag[0])[..., None], sill, 0.0)
            return np.maximum(sill - v, 0.0)
        slope = (g[:, 1:] - g[:, :-1]) / (lag[1:] - lag[:-1])[None, :, None]  # (K, L, 3)
        j = np.clip(np.searchsorted(lag, h, side="right") - 1, 0, n - 2)  # (T, K)
        rows = j + n * np.arange(K)
        gj = np.take(g.reshape(K * n, 3), rows, axis=0)
        gj1 = np.take(g.reshape(K * n, 3), rows + 1, axis=0)
        sj = np.take(slope.reshape(K * (n - 1), 3), j + (n - 1) * np.arange(K), axis=0)
        x = h[..., None]
        lj = lag[j][..., None]
        v = sj * (x - lj) + gj
        v = np.where(x == lj, gj, v)
        v = np.where(x == lag[-1], gj1, v)  # (j is then n - 2: the last lag's value)
        v = np.where(x < lag[0], g[:, 0][None], v)
        v = np.where(x > lag[-1], sill, v)
        v = np.where(np.isnan(x), x, v)
        return np.maximum(sill - v, 0.0)

    def lag_covariance(self, h: np.ndarray) -> np.ndarray:
        """`covariance` at whole lags h (T, K) int >= 0, the same values: with more frames than
        lags tabulated at the lags 0..last + 1 (by the same np.interp, each lag's value is
        np.interp's at that lag) and looked up, without a loop over the frames."""
        h = np.asarray(h, dtype=np.int64)
        K = self.sill.shape[0]
        top = int(self.lags[-1]) + 1  # every lag beyond the last is the sill's (interp's right)
        if h.shape[0] <= top:  # fewer frames than lags: interpolated directly
            return self._interpolated(h.astype(np.float64))
        table = self._interpolated(np.broadcast_to(np.arange(top + 1.0)[:, None], (top + 1, K)))
        rows = np.minimum(h, top) * K + np.arange(K)  # (the table is (top + 1, K, 3))
        return np.take(table.reshape((top + 1) * K, 3), rows, axis=0)

    @classmethod
    def estimate(
        cls,
        offsets: np.ndarray,
        observed: np.ndarray,
        lags=DEFAULT_LAGS,
        min_pairs: int = 20,
        floor_mm: float = 0.3,
        nugget: np.ndarray | None = None,
        few_var: np.ndarray | None = None,
    ) -> OffsetCovariance:
        """From offsets (T, K, 3) observed where ``observed`` (T, K) (>= 2 views, gated).

        The sample semivariogram at each lag is the mean half squared difference over the
        pairs both observed; the nugget (K, 3) (the noise of one observation, e.g. the mean
        triangulation variance per body axis) is given, or else extrapolated to lag 0 as for a
        smooth (quadratic near 0) motion, (4 g(1) - g(2)) / 3; it is removed from every lag.
        gamma is made non-decreasing and capped at the sill. A part with too few pairs at
        a lag uses the sill there (no temporal information is claimed where none was seen); a
        part observed fewer than ``min_pairs`` times gets mean 0 and 4x the largest second
        moment of the others (it is barely known), or its ``few_var`` (K, 3) mm^2 where that is
        finite (its spread known otherwise, e.g. from its single views, `place_from_rays`).
        """
        o = np.asarray(offsets, dtype=np.float64)
        m = np.asarray(observed, dtype=bool) & all_last(np.isfinite(o))
        if o.ndim != 3 or o.shape[-1] != 3 or m.shape != o.shape[:2]:
            raise ValueError(f"offsets (T, K, 3) and observed (T, K), got {o.shape}, {m.shape}")
        T, K, _ = o.shape
        lags = np.asarray([h for h in lags if h < max(T, 2)], dtype=np.int64)
        if lags.size == 0:
            lags = np.array([1])
        counts = m.sum(0)
        z = np.where(m[..., None], o, 0.0)
        mean = z.sum(0) / np.maximum(counts, 1)[:, None]
        var = (np.where(m[..., None], (o - mean) ** 2, 0.0)).sum(0) / np.maximum(counts - 1, 1)[
            :, None
        ]
        raw = np.full((K, 3, lags.size), np.nan)
        buf = np.empty_like(z)  # the squared differences of one lag, 0 where not both seen
        mt = np.ascontiguousarray(m.T)  # (K, T): the pairs counted along contiguous rows
        for i, h in enumerate(lags):
            n = np.count_nonzero(mt[:, h:] & mt[:, :-h], axis=1)
            both = np.repeat((m[h:] & m[:-h])[..., None], 3, axis=-1)
            d = buf[: T - h]  # (z: o where observed, so o's differences where both are)
            np.subtract(z[h:], z[:-h], out=d)
            np.multiply(d, d, out=d)
            np.multiply(d, both, out=d)
            d2 = d.sum(0)
            g = 0.5 * d2 / np.maximum(n, 1)[:, None]
            raw[:, :, i] = np.where((n >= min_pairs)[:, None], g, np.nan)
        # nugget: quadratic extrapolation to 0 from lags 1 and 2 (or a linear one from lag 1)
        g1 = raw[:, :, 0]
        g2 = raw[:, :, 1] if lags.size > 1 and lags[1] == 2 else np.full_like(g1, np.nan)
        nug = np.where(np.isfinite(g2), (4.0 * g1 - g2) / 3.0, 0.5 * g1)
        nug = np.clip(np.nan_to_num(nug, nan=0.0), 0.0, np.nan_to_num(g1, nan=0.0))
        if nugget is not None:  # ... but never more than the lag-1 semivariogram it is part of
            given = np.broadcast_to(np.asarray(nugget, dtype=np.float64), (K, 3))
            nug = np.where(np.isfinite(g1), np.minimum(given, np.nan_to_num(g1)), given)
        sill = np.maximum(var - nug, floor_mm**2)
        few = counts < min_pairs  # too few 3D observations to say how the part moves
        if few.any():
            known = ~few
            wide = 4.0 * (sill[known] + mean[known] ** 2).max(0) if known.any() else 100.0
            sill[few] = wide
            if few_var is not None:
                fv = np.broadcast_to(np.asarray(few_var, dtype=np.float64), (K, 3))
                sill = np.where(few[:, None] & np.isfinite(fv), fv, sill)
            mean[few] = 0.0
            raw[few] = np.nan
        gamma = raw - nug[..., None]
        gamma = np.where(np.isfinite(gamma), gamma, sill[..., None])
        gamma = np.clip(np.maximum.accumulate(gamma, axis=-1), 0.0, sill[..., None])
        return cls(mean, sill, nug, lags, gamma, counts)


def neighbours(observed: np.ndarray, skip_self: bool) -> tuple[np.ndarray, np.ndarray]:
    """Index of the previous and next observed frame (T, K) (-1 / T where none); with
    ``skip_self`` strictly before / after t, else t itself where observed."""
    T, K = observed.shape
    t = np.arange(T)[:, None]
    idx = np.where(observed, t, -1)
    prev_incl = np.maximum.accumulate(idx, axis=0)
    idx2 = np.where(observed, t, T)
    next_incl = np.minimum.accumulate(idx2[::-1], axis=0)[::-1]
    if not skip_self:
        return prev_incl, next_incl
    prev = np.vstack([np.full((1, K), -1), prev_incl[:-1]])
    nxt = np.vstack([next_incl[1:], np.full((1, K), T)])
    return prev, nxt


def count_within(mask: np.ndarray, w: int) -> np.ndarray:
    """(T, K) int: for each frame t and part, how many of the part's frames flagged in mask
    (T, K) lie within w frames of t (t included)."""
    m = np.asarray(mask, dtype=bool)
    T, K = m.shape
    cs = np.concatenate([np.zeros((1, K), np.int64), np.cumsum(m, axis=0, dtype=np.int64)])
    t = np.arange(T)
    return cs[np.minimum(t + w + 1, T)] - cs[np.maximum(t - w, 0)]


def krige_offsets(
    offsets: np.ndarray,
    observed: np.ndarray,
    cov: OffsetCovariance,
    skip_self: bool = True,
    noise: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Predict every part-frame's offset from its nearest observed neighbours in time.

    offsets (T, K, 3) (any value where not observed), observed (T, K) -> prediction (T, K, 3)
    mm and its variance (T, K, 3) mm^2 per body axis. Between the previous and the next
    observed frame (strictly before / after t with ``skip_self``) the offset is interpolated
    linearly (the ordinary-kriging weights of two neighbours under a power-law semivariogram;
    exact for a part moving linearly in body coordinates), beyond the last one it is held. Its
    error variance follows from the semivariogram of the noise-free offsets and the nugget of
    the observations: for weights l_p + l_n = 1 at lags d_p, d_n,
    2 (l_p g(d_p) + l_n g(d_n)) - 2 l_p l_n g(d_p + d_n) + (l_p^2 + l_n^2) nugget.
    Where that exceeds the part's variance about its mean (far from any observation), the mean
    is the better prediction and is used, with variance = sill; so is it with no neighbour.
    noise (T, K, 3) mm^2, optional: each observation's own noise variance per body axis (e.g.
    a part-frame seen by one camera, `InterpObservation.anchored`), in place of the nugget:
    l_p^2 noise_p + l_n^2 noise_n.
    """
    o = np.asarray(offsets, dtype=np.float64)
    m = np.asarray(observed, dtype=bool) & all_last(np.isfinite(o))
    prev, nxt = neighbours(m, skip_self)
    return krige_between(o, prev, nxt, cov, noise)


def krige_between(
    o: np.ndarray,
    prev: np.ndarray,
    nxt: np.ndarray,
    cov: OffsetCovariance,
    noise: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """`krige_offsets` from given neighbours: offsets o (T, K, 3), the previous and next
    observed frame of each part-frame (T, K) (-1 / T where none) -> prediction (T, K, 3) mm and
    its variance (T, K, 3) mm^2."""
    T, K, _ = o.shape
    t = np.arange(T)[:, None]
    has_p, has_n = prev >= 0, nxt < T
    dpi = np.where(has_p, t - prev, 0)  # whole lags (frames)
    dni = np.where(has_n, nxt - t, 0)
    dp, dn = dpi.astype(np.float64), dni.astype(np.float64)
    # the neighbours' rows of (T, K, ...) arrays flattened to (T K, ...): gathered by np.take
    rp = np.clip(prev, 0, T - 1) * K + np.arange(K)
    rn = np.clip(nxt, 0, T - 1) * K + np.arange(K)
    flat = np.ascontiguousarray(o).reshape(T * K, 3)
    op = np.where(has_p[..., None], np.take(flat, rp, axis=0), 0.0)
    on = np.where(has_n[..., None], np.take(flat, rn, axis=0), 0.0)
    both = has_p & has_n
    span = np.where(both, dp + dn, 1.0)
    lp = np.where(both, dn / span, has_p.astype(np.float64))  # weight of the previous frame
    ln = np.where(both, dp / span, has_n.astype(np.float64))
    sill = cov.sill[None]
    gp = sill - cov.lag_covariance(dpi)  # noise-free semivariogram at the lags, (T, K, 3)
    gn = sill - cov.lag_covariance(dni)
    gpn = sill - cov.lag_covariance(dpi + dni)
    lp3, ln3 = lp[..., None], ln[..., None]
    pred = lp3 * op + ln3 * on
    if noise is None:
        obs_var = (lp3**2 + ln3**2) * cov.nugget[None]
    else:
        nz = np.asarray(noise, dtype=np.float64)
        nz = np.ascontiguousarray(np.broadcast_to(nz, (T, K, nz.shape[-1]))).reshape(T * K, -1)
        n_p = np.where(has_p[..., None], np.take(nz, rp, axis=0), 0.0)
        n_n = np.where(has_n[..., None], np.take(nz, rn, axis=0), 0.0)
        obs_var = lp3**2 * n_p + ln3**2 * n_n
    var = 2 * (lp3 * gp + ln3 * gn) - 2 * lp3 * ln3 * gpn + obs_var
    use_mean = ~(has_p | has_n)[..., None] | (var > sill)
    pred = np.where(use_mean, cov.mean[None], pred)
    var = np.where(use_mean, np.broadcast_to(sill, var.shape), var)
    return pred, np.maximum(var, 1e-6)
