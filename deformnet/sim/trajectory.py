"""Behavior episodes and the planar body track (origin x, y and heading per frame).

A Markov chain over the behaviors draws episodes with durations from the configured ranges.
`walk` episodes follow a random curve (log-normal speed with stops, curvature noise, folded into
the walkable rectangle by reflection and Gaussian-smoothed so the wall turns are round); before
a reach the mouse walks to the mechanism's standing spot along a Hermite curve (labelled `walk`).
All other behaviors happen at rest. Vectorised within each episode; one Python step per episode.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import lfilter

from deformnet.sim.config import BEHAVIORS, SimConfig
from deformnet.sim.scene import Scene

WALK, SCAN, REAR, GROOM = 0, 1, 2, 3
FIRST_MECH = 4
MIN_SPEED = 1.0  # mm/s below which the heading is held (not read from the path)
HEADING_SMOOTH = 0.2  # s: Gaussian smoothing of the heading read from the path at low speed
TURN_SPEED = 20.0  # mm/s: from this speed on, the heading is exactly the path's direction
TURN_RATE = 2 * np.pi  # rad/s: turning on the spot before setting off in another direction
WALL_TURN = 30.0  # mm of path over which the mouse turns away from a wall ahead
MAX_WALL_TURNS = 12  # wall turns computed per walk; beyond, the path is folded at the walls


@dataclass(frozen=True)
class Plan:
    xy: np.ndarray  # (T, 2) body origin on the plane
    heading: np.ndarray  # (T,) rad, direction of the body's forward axis (unwrapped)
    labels: np.ndarray  # (T,) int64
    ep_start: np.ndarray  # (E,) episode start frames (behavior episodes, approach walks included)
    ep_len: np.ndarray  # (E,)
    ep_label: np.ndarray  # (E,)
    ep_pitch: np.ndarray  # (E,) rad, peak body pitch (rear, groom, reach), else 0


def smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def ou_noise(rng: np.random.Generator, n: int, tau_frames: float) -> np.ndarray:
    """Stationary unit-variance AR(1) (Ornstein-Uhlenbeck) noise with correlation time tau."""
    a = float(np.exp(-1.0 / max(tau_frames, 1e-9)))
    e = rng.standard_normal(n)
    b = np.sqrt(1.0 - a * a)
    x0 = rng.standard_normal()
    out, _ = lfilter([b], [1.0, -a], e, zi=[a * x0])
    return out


def fold(v: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Reflect points into [lo, hi] per coordinate (billiard folding of an unbounded path)."""
    span = np.maximum(hi - lo, 1e-9)
    u = np.mod(v - lo, 2.0 * span)
    return lo + np.where(u > span, 2.0 * span - u, u)


def smooth_heading(
    h: np.ndarray, xy: np.ndarray, p0: np.ndarray, h0: float, sigma: float, fps: float
) -> np.ndarray:
    """Gaussian-smooth an unwrapped heading (sigma in frames) where the body is slow, keeping its
    start at h0: setting off in another direction (or reversing at a wall while nearly still)
    becomes a turn on the spot. At speeds >= TURN_SPEED the heading is the path's direction."""
    n = len(h)
    if sigma <= 0 or n < 2:
        return h
    hs = gaussian_filter1d(h, sigma, mode="nearest")
    u = np.arange(n, dtype=np.float64)
    pin = 1.0 - smoothstep(u / max(1.0, min(3.0 * sigma, n / 2.0)))
    hs = hs + (h0 - hs[0]) * pin
    speed = np.hypot(*np.diff(np.concatenate([p0[None], xy]), axis=0).T) * fps
    w = 1.0 - np.clip(speed / TURN_SPEED, 0.0, 1.0)
    return w * hs + (1.0 - w) * h


def heading_from_path(xy: np.ndarray, p0: np.ndarray, h0: float, fps: float) -> np.ndarray:
    """Direction of motion per frame (from the previous frame), held where the body is still;
    unwrapped to continue from h0."""
    d = np.diff(np.concatenate([p0[None], xy]), axis=0)
    moving = np.hypot(d[:, 0], d[:, 1]) * fps > MIN_SPEED
    ang = np.arctan2(d[:, 1], d[:, 0])
    last = np.maximum.accumulate(np.where(moving, np.arange(len(xy)), -1))
    ang = np.where(last >= 0, ang[np.maximum(last, 0)], h0)
    dh = np.diff(np.concatenate([[h0], ang]))
    dh = (dh + np.pi) % (2 * np.pi) - np.pi
    return h0 + np.cumsum(dh)


class _Planner:
    def __init__(self, cfg: SimConfig, scene: Scene, rng: np.random.Generator):
        self.cfg, self.scene, self.rng = cfg, scene, rng
        self.fps = cfg.fps

    def free_walk(self, p0: np.ndarray, h0: float, n: int) -> tuple[np.ndarray, np.ndarray]:
        w, fps, rng = self.cfg.walk, self.fps, self.rng
        lo = np.minimum(self.scene.free_lo, p0)
        hi = np.maximum(self.scene.free_hi, p0)
        z = ou_noise(rng, n, w.speed_tau * fps)
        speed = np.minimum(
            w.speed_mean * np.exp(w.speed_sigma * z - 0.5 * w.speed_sigma**2), w.speed_max
        )
        gate = np.ones(n)
        n_stops = rng.poisson(w.stop_rate * n / fps)
        if n_stops:
            starts = rng.integers(0, n, n_stops)
            lens = (rng.uniform(*w.stop_duration, n_stops) * fps).astype(np.int64)
            delta = np.zeros(n + 1)
            np.add.at(delta, starts, 1.0)
            np.add.at(delta, np.minimum(starts + lens, n), -1.0)
            gate = (np.cumsum(delta[:n]) <= 0).astype(np.float64)
            gate = gaussian_filter1d(gate, 0.1 * fps, mode="nearest")
        u = np.arange(n, dtype=np.float64)
        ramp = max(1.0, min(0.3 * fps, n / 3.0))
        taper = smoothstep((u + 1.0) / ramp) * smoothstep((n - 1.0 - u) / ramp)
        ds = speed * gate * taper / fps
        curv = w.curvature_std * ou_noise(rng, n, w.curvature_tau * fps)
        start = h0
        ahead = p0 + WALL_TURN * np.array([np.cos(h0), np.sin(h0)])
        if np.any(ahead < lo) or np.any(ahead > hi):  # facing a wall: set off inwards
            goal = self.scene.free_lo + rng.random(2) * (self.scene.free_hi - self.scene.free_lo)
            start = float(np.arctan2(*(goal - p0)[::-1]))
            start = h0 + (start - h0 + np.pi) % (2 * np.pi) - np.pi
        h = start + np.cumsum(curv * ds)
        raw = self._steer(p0, h, ds, lo, hi)
        xy = fold(raw, lo, hi)  # a guard: the steering normally keeps the path inside
        sigma = w.smooth * fps
        if sigma > 0 and n > 1:
            xy = gaussian_filter1d(xy, sigma, axis=0, mode="nearest")
            # pin the start to p0 (continuity with the previous episode)
            corr = 1.0 - smoothstep(u / max(1.0, min(3.0 * sigma, n / 2.0)))
            xy = xy + (p0 - xy[0]) * corr[:, None]
            xy = np.clip(xy, lo, hi)
        return self._turn_then_go(p0, h0, xy)

    def _steer(self, p0, h, ds, lo, hi) -> np.ndarray:
        """Integrate the path; where it would leave [lo, hi], turn away from the wall (billiard
        reflection plus noise) over the WALL_TURN mm of path before it. A few passes."""
        dist = np.cumsum(ds)
        for _ in range(MAX_WALL_TURNS):
            raw = p0 + np.cumsum(ds[:, None] * np.stack([np.cos(h), np.sin(h)], -1), axis=0)
            out = (raw < lo) | (raw > hi)
            bad = out.any(1)
            if not bad.any():
                break
            e = int(np.argmax(bad))
            normal = np.where(raw[e] < lo, 1.0, 0.0) - np.where(raw[e] > hi, 1.0, 0.0)
            normal /= np.linalg.norm(normal)
            c = np.array([np.cos(h[e]), np.sin(h[e])])
            ref = c - 2.0 * min(float(c @ normal), 0.0) * normal
            want = np.arctan2(ref[1], ref[0]) + self.rng.normal(0.0, 0.3)
            if np.cos(want) * normal[0] + np.sin(want) * normal[1] < 0.3:  # keep it inwards
                want = np.arctan2(normal[1], normal[0]) + self.rng.uniform(-0.8, 0.8)
            delta = (want - h[e] + np.pi) % (2 * np.pi) - np.pi
            h = h + delta * smoothstep((dist - (dist[e] - WALL_TURN)) / WALL_TURN)
        return raw

    def _turn_then_go(self, p0: np.ndarray, h0: float, xy: np.ndarray):
        """Headings for a path starting at p0; if it sets off in a direction other than h0, the
        mouse first turns on the spot (frames prepended). Returns (xy, heading)."""
        fps = self.fps
        far = np.flatnonzero(np.hypot(*(xy - p0).T) > 1.0)
        if far.size:
            v = xy[far[0]] - p0
            delta = (np.arctan2(v[1], v[0]) - h0 + np.pi) % (2 * np.pi) - np.pi
            if abs(delta) > np.radians(20.0):
                m = max(2, int(np.ceil(abs(delta) / TURN_RATE * fps)))
                turn = h0 + delta * smoothstep(np.arange(1, m + 1) / m)
                h1 = h0 + delta
                h = smooth_heading(
                    heading_from_path(xy, p0, h1, fps), xy, p0, h1, HEADING_SMOOTH * fps, fps
                )
                return np.concatenate([np.repeat(p0[None], m, 0), xy]), np.concatenate([turn, h])
        h = heading_from_path(xy, p0, h0, fps)
        return xy, smooth_heading(h, xy, p0, h0, HEADING_SMOOTH * fps, fps)

    def approach(self, p0: np.ndarray, h0: float, target: np.ndarray, h1: float):
        """Walk from (p0, h0) to `target`, arriving with heading h1 (Hermite curve, min-jerk
        speed profile). Returns None if already there."""
        dist = float(np.hypot(*(target - p0)))
        if dist < 0.5:
            return None
        lo = np.minimum(np.minimum(self.scene.free_lo, p0), target)
        hi = np.maximum(np.maximum(self.scene.free_hi, p0), target)
        k = float(np.clip(dist, 10.0, 120.0))
        u = np.linspace(0.0, 1.0, 256)[:, None]
        t0 = np.array([np.cos(h0), np.sin(h0)])
        if t0 @ (target - p0) < 0:  # target behind: turn on the spot first, then go
            t0 = (target - p0) / dist
        t1 = np.array([np.cos(h1), np.sin(h1)])
        curve = (
            (2 * u**3 - 3 * u**2 + 1) * p0
            + (u**3 - 2 * u**2 + u) * k * t0
            + (-2 * u**3 + 3 * u**2) * target
            + (u**3 - u**2) * k * t1
        )
        curve = np.clip(curve, lo, hi)
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(curve, axis=0).T))])
        length = arc[-1]
        n = max(2, int(np.ceil(1.875 * length / self.cfg.walk.approach_speed * self.fps)))
        s = np.arange(n + 1) / n  # the first sample is p0 itself (dropped below)
        s = length * (10 * s**3 - 15 * s**4 + 6 * s**5)
        xy = np.stack([np.interp(s, arc, curve[:, 0]), np.interp(s, arc, curve[:, 1])], -1)[1:]
        xy[-1] = target
        xy, h = self._turn_then_go(p0, h0, xy)
        n = len(h)
        # arrive exactly with heading h1 (mod 2 pi); the curve's end tangent already is h1
        err = (h1 - h[-1] + np.pi) % (2 * np.pi) - np.pi
        h = h + err * smoothstep((np.arange(n) - 0.6 * n) / (0.4 * n - 1 + 1e-9))
        return xy, h

    def plan(self, num_frames: int) -> Plan:
        cfg, rng, fps, sc = self.cfg, self.rng, self.fps, self.scene
        P = np.asarray(cfg.behaviors.transitions, dtype=np.float64)
        cum = np.cumsum(P, axis=1)
        dur = np.asarray(cfg.behaviors.durations, dtype=np.float64)
        pos = sc.free_lo + rng.random(2) * (sc.free_hi - sc.free_lo)
        heading = float(rng.uniform(-np.pi, np.pi))
        state = WALK
        xs, hs, labs = [], [], []
        ep_start, ep_len, ep_label, ep_pitch = [], [], [], []
        total = 0

        def add(xy, h, label, pitch=0.0):
            nonlocal total, pos, heading
            xs.append(xy)
            hs.append(h)
            labs.append(np.full(len(xy), label, dtype=np.int64))
            ep_start.append(total)
            ep_len.append(len(xy))
            ep_label.append(label)
            ep_pitch.append(pitch)
            total += len(xy)
            pos, heading = xy[-1].copy(), float(h[-1])

        def still(n):
            return np.repeat(pos[None], n, 0), np.full(n, heading)

        while total < num_frames:
            n = max(2, int(round(rng.uniform(*dur[state]) * fps)))
            if state == WALK:
                add(*self.free_walk(pos, heading, n), WALK)
            elif state in (SCAN,):
                add(*still(n), state)
            elif state == REAR:
                add(*still(n), state, np.deg2rad(rng.uniform(*cfg.rear.pitch)))
            elif state == GROOM:
                add(*still(n), state, np.deg2rad(rng.uniform(*cfg.groom.pitch)))
            else:
                m = state - FIRST_MECH
                # face +y (the box), keeping the unwrapped heading continuous
                h1 = heading + ((np.pi / 2 - heading + np.pi) % (2 * np.pi) - np.pi)
                path = self.approach(pos, heading, sc.stand_xy[m], h1)
                if path is not None:
                    add(*path, WALK)
                add(*still(n), state, float(sc.stand_pitch[m]))
            state = int(np.searchsorted(cum[state], rng.random() * cum[state, -1], side="right"))
            state = min(state, len(BEHAVIORS) - 1)
        T = num_frames
        ep_start = np.asarray(ep_start, dtype=np.int64)
        keep = ep_start < T
        ep_len_a = np.asarray(ep_len, dtype=np.int64)[keep]
        # the last episode is cut at T: its envelope is computed for its full length
        return Plan(
            xy=np.concatenate(xs)[:T],
            heading=np.concatenate(hs)[:T],
            labels=np.concatenate(labs)[:T],
            ep_start=ep_start[keep],
            ep_len=ep_len_a,
            ep_label=np.asarray(ep_label, dtype=np.int64)[keep],
            ep_pitch=np.asarray(ep_pitch, dtype=np.float64)[keep],
        )


def make_plan(cfg: SimConfig, scene: Scene, num_frames: int, rng: np.random.Generator) -> Plan:
    return _Planner(cfg, scene, rng).plan(num_frames)
