"""Bout features: what a frame's whole session says about it, without labels (`BoutFeatures`).
Some behaviors differ only in duration or sequence: a short nose contact with a mechanism is
sniffing, a long one operating it; a walk that ends at a mechanism is an approach. Per frame:
for each distance in `near`, how long the run of frames the chosen parts are that near each
mechanism lasts, and the time since the last and until the next such contact; how long the
current moving or still run of the body (its rigid model's centroid) lasts, how far into it the
frame is, and the nearest mechanism's distance just after it ends and just before it began
(SimBA's bout features, over the session instead of a window). Shapes: T frames, M mechanisms,
F features; times in s, capped at `cap`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from deformnet.confutil import checked_fields

__all__ = ["BoutSettings", "bout_settings", "run_spans", "BoutFeatures"]


@dataclass
class BoutSettings:
    """The ``bouts`` block of conf/classify.yaml (see there)."""

    enabled: bool = True
    near: list[float] = field(default_factory=lambda: [10.0, 30.0])  # mm
    moving: float = 25.0  # mm/s: the body moves faster than this ...
    smooth: float = 0.3  # s: ... its speed averaged over this
    after: float = 0.5  # s: where a run ends: the distance this long after it
    cap: float = 10.0  # s: longer times are this


def bout_settings(cfg) -> dict | None:
    """The checked ``bouts`` block as a plain dict, or None when ``bouts.enabled`` is false."""
    s = BoutSettings(**checked_fields(BoutSettings, cfg, "bouts"))
    if not isinstance(s.enabled, bool):
        raise ValueError(f"bouts.enabled must be true or false, got {s.enabled!r}")
    if not s.enabled:
        return None
    s.near = [float(r) for r in (s.near or [])]
    vals = {"moving": s.moving, "smooth": s.smooth, "cap": s.cap}
    bad = {k: v for k, v in vals.items() if not float(v) > 0}
    if bad or not float(s.after) >= 0 or not all(r > 0 for r in s.near):
        raise ValueError(f"bouts.near, moving, smooth and cap must be > 0 and bouts.after >= 0, "
                         f"got {asdict(s)}")  # fmt: skip
    return asdict(s)


def run_spans(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame of a boolean (T,): the first and last frame (T,), (T,) of the run of equal
    values it lies in."""
    mask = np.asarray(mask, bool)
    T = len(mask)
    change = np.r_[True, mask[1:] != mask[:-1]]
    starts = np.flatnonzero(change)
    stops = np.r_[starts[1:] - 1, T - 1]
    run = np.cumsum(change) - 1
    return starts[run], stops[run]


def _since_until(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames (T,), (T,) since the last and until the next True of a boolean (T,) (0 on one;
    inf where there is none)."""
    t = np.arange(len(mask), dtype=np.float64)
    last = np.maximum.accumulate(np.where(mask, t, -np.inf))
    nxt = np.minimum.accumulate(np.where(mask, t, np.inf)[::-1])[::-1]
    return t - last, nxt - t


def _mean(x: np.ndarray, n: int) -> np.ndarray:
    """The centred running mean (T,) over n frames of x (T,) (fewer at the ends)."""
    k = np.ones(n)
    return np.convolve(x, k, "same") / np.convolve(np.ones(len(x)), k, "same")


class BoutFeatures:
    """A session's bout features (module doc) at ``fps`` Hz; settings as `bout_settings` gives
    them; mechanisms: the classifier's `MechanismFeatures` (their positions and chosen parts),
    or None (the moving / still runs only).

    __call__(rigid, deformed (T, K, 3) global mm, observed (T, K) bool) -> (T, dim) float32.
    """

    def __init__(self, settings: dict, fps: float, mechanisms=None) -> None:
        self.settings, self.fps = dict(settings), float(fps)
        self.mechanisms = mechanisms
        M = 0 if mechanisms is None else int(mechanisms.positions.shape[0])
        self.dim = 4 + (len(self.settings["near"]) * (M + 2) + 2 if M else 0)

    def _seconds(self, frames: np.ndarray) -> np.ndarray:
        return np.minimum(frames / self.fps, float(self.settings["cap"]))

    def __call__(self, rigid: np.ndarray, deformed: np.ndarray, observed: np.ndarray):
        s, T = self.settings, len(rigid)
        rigid = np.asarray(rigid, np.float64)
        body = rigid.mean(1)  # the posed rigid model's centroid (T, 3)
        step = np.linalg.norm(np.diff(body, axis=0, prepend=body[:1]), axis=-1) * self.fps
        n = max(1, int(round(s["smooth"] * self.fps)))
        moving = _mean(step, n) > s["moving"]
        a, b = run_spans(moving)
        t = np.arange(T)
        length = b - a + 1
        out = [np.where(moving, length, 0), np.where(moving, 0, length), b - t, t - a]
        if self.mechanisms is not None:
            seen = np.where(np.asarray(observed, bool)[..., None], deformed, rigid)
            p = seen[:, self.mechanisms.parts.numpy()]  # (T, P, 3)
            pos = self.mechanisms.positions.double().numpy()  # (M, 3)
            d = np.linalg.norm(p[:, :, None] - pos, axis=-1).min(1)  # (T, M) nearest part
            d = np.stack([_mean(x, n) for x in d.T], 1)  # a contact does not flicker
            nearest = d.min(1)
            lag = int(round(s["after"] * self.fps))
            for r in s["near"]:
                for m in range(d.shape[1]):
                    na, nb = run_spans(d[:, m] < r)
                    out.append(np.where(d[:, m] < r, nb - na + 1, 0))
                out += list(_since_until(nearest < r))
        feats = [self._seconds(np.asarray(f, np.float64)) for f in out]
        if self.mechanisms is not None:
            scale = float(self.mechanisms.scale)
            feats += [nearest[np.minimum(b + lag, T - 1)] / scale,
                      nearest[np.maximum(a - lag, 0)] / scale]  # fmt: skip
        return np.nan_to_num(np.stack(feats, 1), nan=0.0).astype(np.float32)

    def of(self, sessions: Sequence) -> list[np.ndarray]:
        """Each `Session`'s features (T, dim)."""
        return [self(x.rigid, x.deformed, x.observed) for x in sessions]
