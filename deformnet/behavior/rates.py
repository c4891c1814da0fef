"""Behavior sessions at another frame rate: resampled to the classifier's rate (low-passed
first when the rate falls) and the results taken back to the track's own frames; which rates a
trained classifier resamples between (`frame_rates`)."""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np

from deformnet.behavior.tracks import Session
from deformnet.confutil import check_fps

log = logging.getLogger(__name__)

__all__ = ["same_fps", "lowpass_in_time", "resample_session", "to_track_frames", "frame_rates"]


def same_fps(a: float, b: float) -> bool:
    """Whether two frame rates (Hz, > 0) are the same one (to 1e-6 relative): no resampling."""
    return abs(float(a) - float(b)) <= 1e-6 * max(float(a), float(b))


def _rate_times(fnum: np.ndarray, fps: float, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """A track's frame times (T,) (s, from its first frame: fnum / fps, gaps in the frame
    numbers kept) and those of the same span at `rate` (T',)."""
    t = (np.asarray(fnum, np.float64) - float(fnum[0])) / fps
    n = int(np.floor(t[-1] * rate + 1e-9)) + 1
    return t, np.arange(n) / rate


#: resampling to a lower rate low-passes first: a Gaussian of this many output frame periods (sd)
ANTIALIAS_SIGMA = 0.5


def lowpass_in_time(
    points: np.ndarray, observed: np.ndarray, fnum: np.ndarray, sigma: float
) -> np.ndarray:
    """Points (T, K, 3) smoothed in time with Gaussian weights of sd `sigma` frames (of the
    frame numbers fnum (T,), gaps in them kept as gaps in time), each part over its observed
    (T, K) frames only: a local linear fit (weighted least squares of a line in time about each
    frame, within 3 sd), which in the middle of the data is the Gaussian filter and at the ends
    of the data and of its gaps does not pull a moving part back (a one-sided mean would, by
    the slope times about 0.8 sd). Unobserved part-frames are returned as they are."""
    from scipy.ndimage import correlate1d

    P = np.asarray(points, np.float64)
    obs = np.asarray(observed, bool)
    g = np.asarray(fnum, np.int64) - int(fnum[0])
    n = int(g[-1]) + 1
    w = np.zeros((n, P.shape[1]))
    w[g] = obs
    x = np.zeros((n, *P.shape[1:]))
    x[g] = np.where(obs[..., None], P, 0.0)
    r = max(1, int(np.ceil(3.0 * sigma)))
    u = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (u / sigma) ** 2)

    def corr(a: np.ndarray, m: int) -> np.ndarray:  # sum_j a_j k(j - i) (j - i)^m
        return correlate1d(a, k * u**m, axis=0, mode="constant")[g]

    s0, s1, s2 = (corr(w, m) for m in range(3))
    t0, t1 = corr(x, 0), corr(x, 1)
    det = s0 * s2 - s1**2
    lin = det > 1e-6 * np.maximum(s0 * s2, 1e-300)  # a line is determined (>= 2 frames)
    with np.errstate(invalid="ignore", divide="ignore"):
        line = (s2[..., None] * t0 - s1[..., None] * t1) / np.where(lin, det, 1.0)[..., None]
        mean = t0 / np.where(s0 > 0, s0, 1.0)[..., None]
    est = np.where(lin[..., None], line, mean)
    return np.where((obs & (s0 > 0))[..., None], est, P)


def resample_session(session: Session, fps: float, rate: float, antialias: bool = True) -> Session:
    """The session recorded at `fps` (frame times fnum / fps) as it would be at `rate` (Hz):
    rigid and deformed points linearly interpolated in time at every 1 / rate s of its span, a
    part observed where both frames around it are (its deformed point the rigid one
    elsewhere), labels and frame numbers (0, 1, ...) at the new rate, the nearest frame's
    label. To a lower rate with `antialias`, the points are low-passed first
    (`lowpass_in_time`, sd `ANTIALIAS_SIGMA` / rate s: motion the new rate cannot carry, such
    as tracking jitter, is not folded into slower motion). The classifier of another frame
    rate labels the session so (`deformnet.behavior.model.predict_session`), its results taken back
    by `to_track_frames`."""
    fps, rate = check_fps(fps, "fps"), check_fps(rate, "rate")
    if fps is None or rate is None:
        raise ValueError("resample_session needs both frame rates")
    fnum = np.asarray(session.fnum)
    if len(fnum) == 0 or np.any(np.diff(fnum) <= 0):
        raise ValueError(f"{session.name}: frame numbers must increase to be resampled in time")
    rigid, deformed = session.rigid, session.deformed
    obs = np.asarray(session.observed, bool)
    if antialias and rate < fps and len(fnum) > 1:
        sigma = ANTIALIAS_SIGMA * fps / rate  # source frames
        rigid = lowpass_in_time(rigid, np.ones_like(obs), fnum, sigma)
        deformed = lowpass_in_time(deformed, obs, fnum, sigma)
    t, tn = _rate_times(fnum, fps, rate)
    T = len(t)
    if T == 1:
        i0, i1, w = np.zeros(1, int), np.zeros(1, int), np.zeros(1)
    else:
        i0 = np.clip(np.searchsorted(t, tn, side="right") - 1, 0, T - 2)
        i1 = i0 + 1
        w = np.clip((tn - t[i0]) / (t[i1] - t[i0]), 0.0, 1.0)
    wv = w[:, None, None]

    def lerp(x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, np.float64)
        return ((1 - wv) * x[i0] + wv * x[i1]).astype(np.float32)

    observed = np.where(
        w[:, None] == 0, obs[i0], np.where(w[:, None] == 1, obs[i1], obs[i0] & obs[i1])
    )
    rigid = lerp(rigid)
    deformed = np.where(observed[..., None], lerp(deformed), rigid)
    nearest = np.where(w > 0.5, i1, i0)
    return Session(
        session.name,
        rigid,
        deformed,
        observed,
        np.arange(len(tn), dtype=np.int64),
        np.asarray(session.labels)[nearest],
        scale=session.scale,
        pose=session.pose,
    )


def to_track_frames(
    values: np.ndarray, fnum: np.ndarray, fps: float, rate: float, kind: str = "nearest"
) -> np.ndarray:
    """Per-frame results (T', ...) of a session resampled to `rate` (`resample_session`) back
    at the track's own frames fnum (T,) recorded at `fps`: "nearest" (labels, flags: the
    nearest resampled frame's) or "linear" (probabilities: interpolated in time)."""
    t, tn = _rate_times(np.asarray(fnum), fps, rate)
    values = np.asarray(values)
    if len(values) != len(tn):
        raise ValueError(
            f"values must have the resampled session's {len(tn)} frames, got {len(values)}"
        )
    if kind == "nearest":
        return values[np.clip(np.rint(t * rate).astype(np.int64), 0, len(tn) - 1)]
    if kind != "linear":
        raise ValueError(f"kind must be 'nearest' or 'linear', got {kind!r}")
    flat = values.reshape(len(tn), -1).astype(np.float64)
    out = np.stack([np.interp(t, tn, flat[:, j]) for j in range(flat.shape[1])], -1)
    return out.reshape((len(t),) + values.shape[1:])


#: BORIS's aggregated events export: the behavior, its start and stop (s; "Image index" columns,


def frame_rates(fps, meta: Mapping, name: str) -> tuple[float, float] | None:
    """The rates `predict_session` resamples a track `name` recorded at `fps` (Hz, or None:
    unknown) between, for a classifier whose meta stores its training rate ("fps", None
    where unknown): (fps, the classifier's) where both are known and differ, else None
    (logged: the track taken to be at the classifier's rate, or not resampled)."""
    fps = check_fps(fps, "fps")
    rate = check_fps(meta.get("fps"), "the classifier's fps")
    if fps is None:
        if rate is None:
            log.info("%s: no fps= given, and the classifier knows no frame rate", name)
        else:  # the data cannot tell: another animal moves 0.7-1.8x the mm per frame
            log.warning(
                "%s: no fps= given: the track is taken to be at the classifier's frame rate, "
                "%g Hz; at another rate its windows and speeds mean other times than the "
                "classifier learnt (give fps=, the track's rate, to have it resampled)",
                name,
                rate,
            )
        return None
    if rate is None:
        log.warning(
            "%s: the classifier does not know the frame rate it was trained at (trained "
            "without fps=): the track (%g Hz) is labelled frame by frame as it is; if the rates "
            "differ its windows and speeds mean other times than the classifier learnt",
            name,
            fps,
        )
        return None
    if same_fps(fps, rate):
        return None
    log.info("%s: %g Hz, labelled resampled to the classifier's %g Hz", name, fps, rate)
    return fps, rate
