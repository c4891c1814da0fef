"""The simulator engine, `simulate`: the deformable-mouse simulator (the paper's "Simulated
Data", extended with behaviors). Everything per frame is vectorised with NumPy; see the package
docstring."""

from __future__ import annotations

import logging
import time as _time
from typing import Any

import numpy as np
from scipy.ndimage import gaussian_filter1d

from deformnet.body import BodyModel, default_mouse
from deformnet.sim.config import BEHAVIORS, MECHANISMS, SimConfig
from deformnet.sim.dataset import SimData
from deformnet.sim.scene import Scene, build_scene
from deformnet.sim.trajectory import (
    FIRST_MECH,
    GROOM,
    REAR,
    SCAN,
    WALK,
    make_plan,
    ou_noise,
    smoothstep,
)

log = logging.getLogger(__name__)

TAIL_FLOOR = 1.0  # mm: the deformed tail root never goes below this height
LIFT_SPEED = 20.0  # mm/s: below this gait speed the swing paws are lifted proportionally less


def _resolve(cfg: Any, num_frames: int | None, seed: int | None, body: BodyModel | None):
    """Accept a SimConfig, a sim node/mapping, or a whole app config with a `sim` key."""
    top = None
    if not isinstance(cfg, SimConfig) and cfg is not None:
        try:
            has_sim = "sim" in cfg
        except TypeError:
            has_sim = False
        if has_sim:
            top, cfg = cfg, cfg["sim"]
    sim = SimConfig.from_config(cfg)
    if top is not None:
        if num_frames is None and top.get("num_frames") is not None:
            num_frames = top.get("num_frames")
        if seed is None and top.get("seed") is not None:
            seed = top.get("seed")
        if body is None and top.get("body") is not None:
            body = BodyModel.from_config(top.get("body"))
    changes = {}
    if num_frames is not None:
        changes["num_frames"] = num_frames
    if seed is not None:
        changes["seed"] = seed
    if changes:
        for k, v in changes.items():
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise ValueError(f"{k}: expected an integer, got {v!r}")
        sim = sim.replace(**{k: int(v) for k, v in changes.items()})
    return sim, (body if body is not None else default_mouse())


def _envelopes(plan, T: int, fps: float, ramp_s: float):
    """Per frame: episode id, local frame index, and the rise-hold-fall envelope of its episode
    (0 at the episode's first and last frame)."""
    ep = np.repeat(np.arange(len(plan.ep_start)), plan.ep_len)[:T]
    u = np.arange(T) - plan.ep_start[ep]
    n = plan.ep_len[ep]
    r = np.maximum(1.0, np.minimum(ramp_s * fps, (n - 1) / 3.0))
    env = np.minimum(smoothstep(u / r), smoothstep((n - 1 - u) / r))
    return ep, u, env


def _tri(x: np.ndarray) -> np.ndarray:
    """Triangle wave 0 -> 1 -> 0 with period 1."""
    return 1.0 - np.abs(2.0 * np.mod(x, 1.0) - 1.0)


def _rot_body(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """R = Rz(yaw) Rx(pitch), (T, 3, 3)."""
    c, s = np.cos(yaw), np.sin(yaw)
    ct, st = np.cos(pitch), np.sin(pitch)
    R = np.empty(yaw.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = c, -s * ct, s * st
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = s, c * ct, -c * st
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = 0.0, st, ct
    return R


def _half_cycles(d: np.ndarray, ep: np.ndarray, stride: float):
    """Gait distance s (T,), the half-cycle boundaries (H + 1,) on it, and (H + 1,) flags for
    the boundaries that start a moving episode.

    d: (T,) gait distance covered from frame t-1 to t (d[0] = 0); ep: (T,) episode per frame.
    Each episode that moves is split into a whole number of half cycles of at most `stride`, so a
    mouse that stops at an episode's end has just put its swinging paws down.
    """
    s = np.cumsum(d)
    n_ep = int(ep.max()) + 1 if ep.size else 0
    total = np.bincount(ep, weights=d, minlength=n_ep)
    first = np.searchsorted(ep, np.arange(n_ep), side="left")
    last = np.searchsorted(ep, np.arange(n_ep), side="right") - 1
    bounds, starts = [np.zeros(1)], [np.zeros(1, dtype=bool)]
    for e in np.flatnonzero(total > 1e-9):
        start = s[first[e] - 1] if first[e] > 0 else 0.0
        n = max(1, int(np.ceil(total[e] / stride - 1e-9)))
        bounds.append(np.linspace(start, s[last[e]], n + 1)[1:])
        starts.append(np.arange(n) == n - 1)  # the boundary after this one starts an episode
    bounds = np.concatenate(bounds)
    starts = np.concatenate(starts)
    starts[0] = True
    keep = np.concatenate([[True], np.diff(bounds) > 1e-12])
    # starts[i]: the half cycle beginning at bounds[i] is the first of a moving episode
    return s, bounds[keep], starts[keep]


def _pose_at(s: np.ndarray, xy: np.ndarray, yaw: np.ndarray, values: np.ndarray):
    """Body origin (n, 2) and yaw (n,) where the gait distance first reaches `values`."""
    T = len(s)
    j = np.clip(np.searchsorted(s, values, side="left"), 0, T - 1)
    i = np.clip(j - 1, 0, T - 1)
    den = s[j] - s[i]
    f = np.where(den > 0, np.clip((values - s[i]) / np.where(den > 0, den, 1.0), 0.0, 1.0), 0.0)
    return xy[i] + f[:, None] * (xy[j] - xy[i]), yaw[i] + f * (yaw[j] - yaw[i])


def _rotvec_z_x(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """Rodrigues vectors (T, 3) of Rz(yaw) Rx(pitch), |pitch| < pi / 2 (via the quaternion
    (ca cb, ca sb, sa sb, sa cb), a = yaw / 2, b = pitch / 2)."""
    a = 0.5 * ((yaw + np.pi) % (2 * np.pi) - np.pi)
    b = 0.5 * pitch
    ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
    w = ca * cb  # >= 0
    v = np.stack([ca * sb, sa * sb, sa * cb], -1)
    n = np.linalg.norm(v, axis=-1)
    small = n < 1e-12
    scale = np.where(
        small, 2.0 / np.maximum(w, 1e-300), 2.0 * np.arctan2(n, w) / np.where(small, 1.0, n)
    )
    return v * scale[:, None]


def _euler_zxy(ang: np.ndarray) -> np.ndarray:
    """R = Rz(yaw) Rx(pitch) Ry(roll) (T, 3, 3) from (T, 3) radians (yaw, pitch, roll)."""
    cz, sz = np.cos(ang[:, 0]), np.sin(ang[:, 0])
    cx, sx = np.cos(ang[:, 1]), np.sin(ang[:, 1])
    cy, sy = np.cos(ang[:, 2]), np.sin(ang[:, 2])
    R = np.empty((len(ang), 3, 3))
    R[:, 0, 0] = cz * cy - sz * sx * sy
    R[:, 0, 1] = -sz * cx
    R[:, 0, 2] = cz * sy + sz * sx * cy
    R[:, 1, 0] = sz * cy + cz * sx * sy
    R[:, 1, 1] = cz * cx
    R[:, 1, 2] = sz * sy - cz * sx * cy
    R[:, 2, 0] = -cx * sy
    R[:, 2, 1] = sx
    R[:, 2, 2] = cx * cy
    return R


def _gait(scene: Scene, cfg: SimConfig, xy, yaw, d, ep, parity0: int, flat):
    """Paw positions (T, 4, 3) in PAWS order for the paper's pace: pair A (right front + left
    hind) stands on even half cycles while pair B swings, then they swap.

    A stance paw stays where it was put down: in half cycle k (gait distance b_k .. b_{k+1},
    stride L_k) at G_k = P((b_k + b_{k+1}) / 2), P = the paw's rigid ground position, so it goes
    from half a stride ahead of its rigid position to half a stride behind. In the first half
    cycle of a walk (after a rest) G_k = P(b_k) + L_k / 2 * forward instead, which needs no
    look-ahead past the rest. A swing paw goes from G_{k-1} to G_{k+1}, two strides while the
    body covers one: it moves by twice its rigid position's displacement (twice the body's
    speed), plus a correction linear in gait distance that is zero on straight stretches.
    flat: (T, 4, 3) rigid paw ground positions (pose without pitch).
    """
    s, b, first = _half_cycles(d, ep, cfg.gait.stride)
    T, H = len(s), len(b) - 1
    pm = scene.model[scene.paws]  # (4, 3)

    def place(values: np.ndarray, ahead: np.ndarray) -> np.ndarray:
        base, yb = _pose_at(s, xy, yaw, values)
        c, sn = np.cos(yb), np.sin(yb)
        G = np.empty((len(values), 4, 3))
        G[..., 0] = c[:, None] * pm[:, 0] - sn[:, None] * pm[:, 1] + base[:, :1]
        G[..., 1] = sn[:, None] * pm[:, 0] + c[:, None] * pm[:, 1] + base[:, 1:]
        G[..., 2] = pm[:, 2] + scene.ground
        fwd = np.stack([-sn, c], -1)  # model +Y in the plane
        G[..., :2] += (ahead[:, None] * fwd)[:, None]
        return G

    if H < 1:  # never moves: all paws where the rigid model has them
        G = place(np.zeros(T) + s[0], np.zeros(T))
        return G, np.ones((T, 4), dtype=bool)
    L = np.diff(b)  # (H,)
    # G[k + 1] for k = -1 .. H: before the first and after the last half cycle, same stride
    fh = first[:H]
    values = np.concatenate([[b[0]], np.where(fh, b[:H], b[:H] + 0.5 * L), [b[H]]])
    ahead = 0.5 * np.concatenate([[-L[0]], np.where(fh, L, 0.0), [L[-1]]])
    G = place(values, ahead)
    k = np.clip(np.searchsorted(b, s, side="right") - 1, 0, H - 1)
    frac = np.clip((s - b[k]) / L[k], 0.0, 1.0)
    parity = np.array([0, 0, 1, 1]) + parity0
    stance = (k[:, None] + parity[None]) % 2 == 0  # (T, 4)
    paw = np.arange(4)[None]
    stance_pos = G[(k + 1)[:, None], paw]
    prev = G[k[:, None], paw]
    nxt = G[(k + 2)[:, None], paw]
    # swing: twice the rigid paw's own displacement since lift-off, plus a share (linear in
    # gait distance) of what is left to reach G_{k+1}; zero on straight stretches
    Pb = place(b, np.zeros(H + 1))  # rigid paw ground positions at the boundaries
    p0, p1 = Pb[k[:, None], paw], Pb[(k + 1)[:, None], paw]
    rest = nxt - prev - 2.0 * (p1 - p0)
    swing_pos = prev + 2.0 * (flat - p0) + frac[:, None, None] * rest
    swing_pos[..., 2] = prev[..., 2]
    # lift the swinging paws only while stepping: at rest all four paws stand on the ground
    speed = np.concatenate([d[1:2], d[1:]]) * cfg.fps if T > 1 else np.zeros(T)
    lift = np.sin(np.pi * frac) * np.clip(speed / LIFT_SPEED, 0.0, 1.0)
    swing_pos[..., 2] += cfg.gait.swing_height * lift[:, None]
    return np.where(stance[..., None], stance_pos, swing_pos), stance


def _smooth_noise(rng: np.random.Generator, T: int, tau_frames: float, dims: int) -> np.ndarray:
    """(T, dims) smooth random motion: unit-variance OU noise, Gaussian-smoothed over tau / 5."""
    x = np.stack([ou_noise(rng, T, tau_frames) for _ in range(dims)], -1)
    sigma = tau_frames / 5.0
    return gaussian_filter1d(x, sigma, axis=0, mode="nearest") if sigma >= 0.5 and T > 1 else x


def _rear_extras(cfg: SimConfig, scene: Scene, R, rear, deformed, rng) -> None:
    """Rearing on extended legs (`RearConfig.lift`), a stretched trunk (`stretch`) and free front
    paws (`paw_motion`), scaled by the rear envelope `rear` (T,); edits `deformed` (T, K, 3)."""
    rc = cfg.rear
    if not (rc.lift > 0 or rc.stretch > 0 or rc.paw_motion > 0):
        return
    K = len(scene.model)
    low = np.zeros(K, dtype=bool)
    low[[i for i in scene.paws if i not in scene.front]] = True  # the hind paws
    if scene.tail >= 0:
        low[scene.tail] = True
    upper = np.flatnonzero(~low)
    if rc.stretch > 0:  # parts ahead of the hind paws move forward along the body
        ahead = np.maximum(scene.model[upper, 1] - scene.pitch_pivot[1], 0.0)  # (U,)
        fwd = R[:, :, 1]  # (T, 3) the body's forward axis
        deformed[:, upper] += (
            (rc.stretch * rear)[:, None, None] * ahead[None, :, None] * fwd[:, None]
        )
    if rc.lift > 0:
        deformed[:, upper, 2] += rc.lift * rear[:, None]
    if rc.paw_motion > 0:
        T = len(rear)
        noise = _smooth_noise(rng, T, cfg.deform.paw_tau * cfg.fps, 3 * len(scene.front))
        noise = noise.reshape(T, len(scene.front), 3)
        move = np.einsum("tij,tpj->tpi", R, rc.paw_motion * noise)
        deformed[:, scene.front] += rear[:, None, None] * move


def _spine_bend(cfg: SimConfig, scene: Scene, yaw, R, tau, deformed, rng) -> None:
    """Bend the parts behind `DeformConfig.spine_pivot` about the body's vertical axis through
    it (see `DeformConfig`); edits `deformed` (T, K, 3)."""
    dfc = cfg.deform
    if not (dfc.spine_bend > 0 or dfc.spine_wiggle > 0):
        return
    T, fps = len(yaw), cfg.fps
    pivot = dfc.spine_pivot * cfg.body_scale
    y = scene.model[:, 1]
    span = pivot - float(y.min())
    if span <= 0:
        return
    w = np.clip((pivot - y) / span, 0.0, 1.0)  # (K,)
    lag = max(1, int(round(dfc.spine_lag * fps)))
    past = np.concatenate([np.full(min(lag, T), yaw[0]), yaw[: max(T - lag, 0)]])
    lim = np.radians(dfc.spine_max)
    theta = np.clip(dfc.spine_bend * (past - yaw), -lim, lim)
    theta = gaussian_filter1d(theta, 0.05 * fps, mode="nearest") if T > 1 else theta
    if dfc.spine_wiggle > 0:
        theta = (
            theta
            + np.radians(dfc.spine_wiggle) * _smooth_noise(rng, T, dfc.spine_tau * fps, 1)[:, 0]
        )
    ang = theta[:, None] * w[None]  # (T, K)
    local = np.einsum("tji,tkj->tki", R, deformed - tau[:, None])  # model frame
    c, s = np.cos(ang), np.sin(ang)
    x, yy = local[..., 0].copy(), local[..., 1] - pivot
    local[..., 0] = c * x - s * yy
    local[..., 1] = s * x + c * yy + pivot
    deformed[:] = np.einsum("tij,tkj->tki", R, local) + tau[:, None]


def _masks(cfg: SimConfig, T: int, K: int, rng: np.random.Generator) -> np.ndarray:
    m = cfg.missing
    missing = rng.random((T, K)) < m.dropout
    n_ep = rng.poisson(m.occlusion_rate * T / cfg.fps, K)
    if n_ep.sum():
        part = np.repeat(np.arange(K), n_ep)
        start = rng.integers(0, T, part.size)
        length = np.maximum(1, np.round(rng.uniform(*m.occlusion_duration, part.size) * cfg.fps))
        stop = np.minimum(start + length.astype(np.int64), T)
        delta = np.zeros((K, T + 1), dtype=np.int64)
        np.add.at(delta, (part, start), 1)
        np.add.at(delta, (part, stop), -1)
        missing |= (np.cumsum(delta[:, :T], axis=1) > 0).T
    return ~missing


def simulate(
    cfg: Any = None,
    num_frames: int | None = None,
    seed: int | None = None,
    body: BodyModel | None = None,
) -> SimData:
    """Simulate a deformable mouse in the lock-box arena.

    cfg: a `SimConfig`, a sim config node/mapping (``conf/sim/*.yaml``), a whole app config with
    keys ``sim`` (and optionally ``num_frames``, ``seed``, ``body``), or None for the defaults.
    num_frames, seed: override the config's. body: the rigid body model (default: the app
    config's ``body``, else `default_mouse()`); it must have the mouse's 8 parts (aliases ok).
    Deterministic for a seed.
    """
    t_start = _time.perf_counter()
    cfg, body = _resolve(cfg, num_frames, seed, body)
    if cfg.body_scale != 1.0:
        body = body.scaled(cfg.body_scale)
    scene = build_scene(cfg, body)
    T, fps, K = cfg.num_frames, cfg.fps, body.num_parts
    ss = np.random.SeedSequence(cfg.seed)
    rng_plan, rng_head, rng_jit, rng_mask, rng_gait = (
        np.random.default_rng(s) for s in ss.spawn(5)
    )
    rng_extra = np.random.default_rng(ss.spawn(1)[0])  # `cfg.deform` and the rear extras only
    dfc = cfg.deform

    plan = make_plan(cfg, scene, T, rng_plan)
    xy, heading, labels = plan.xy, plan.heading, plan.labels
    ep, u, env = _envelopes(plan, T, fps, cfg.reach.ramp)
    lab_ep = plan.ep_label[ep]
    env = np.where(np.isin(lab_ep, [WALK, SCAN]), 0.0, env)
    pitch = plan.ep_pitch[ep] * env

    # --- rigid pose: yaw about the origin, pitch about the hind paws' midpoint -----------------
    yaw = heading - np.pi / 2  # model +Y (forward) along the heading
    R = _rot_body(yaw, pitch)
    Rz = _rot_body(yaw, np.zeros_like(yaw))
    P = scene.pitch_pivot
    ct, st = np.cos(pitch), np.sin(pitch)
    RxP = np.stack([np.full(T, P[0]), ct * P[1] - st * P[2], st * P[1] + ct * P[2]], -1)
    tau = np.einsum("tij,tj->ti", Rz, P - RxP)
    tau[:, :2] += xy
    tau[:, 2] += scene.ground
    rvec = _rotvec_z_x(yaw, pitch)
    poses = np.concatenate([rvec, tau], -1)
    model = scene.model
    rigid = np.matmul(model, R.transpose(0, 2, 1)) + tau[:, None]
    deformed = rigid.copy()

    # --- paws: pace gait (ground contact), expressed as offsets from the unpitched rigid paws ---
    # gait distance: path length plus turning (a mouse turning on the spot steps too)
    turn_r = float(np.linalg.norm(model[scene.paws, :2], axis=1).mean())
    d = np.zeros(T)
    d[1:] = np.hypot(*np.diff(xy, axis=0).T) + turn_r * np.abs(np.diff(yaw))
    flat = np.matmul(model[scene.paws], Rz.transpose(0, 2, 1))
    flat[..., :2] += xy[:, None]
    flat[..., 2] += scene.ground
    gait, _ = _gait(scene, cfg, xy, yaw, d, ep, int(rng_gait.integers(2)), flat)
    deformed[:, scene.paws] += gait - flat

    # --- head triangle: rotation about the ear midpoint, linear back and forth -----------------
    t = np.arange(T) / fps
    walk_w = (labels == WALK).astype(np.float64)
    scan_w = (labels == SCAN).astype(np.float64)
    if cfg.head.blend > 0:
        walk_w = gaussian_filter1d(walk_w, cfg.head.blend * fps, mode="nearest")
        scan_w = gaussian_filter1d(scan_w, cfg.head.blend * fps, mode="nearest")
    angles = np.zeros((T, 3))  # yaw, pitch, roll in deg
    for grp, wgt in ((cfg.head, walk_w), (cfg.scan, scan_w)):
        phase = rng_head.random(3)
        for a, key in enumerate(("yaw", "pitch", "roll")):
            lo, hi = getattr(grp, key)
            angles[:, a] += wgt * (lo + (hi - lo) * _tri(t / grp.period[a] + phase[a]))
    head_std = np.array([dfc.head_yaw, dfc.head_pitch, dfc.head_roll])
    if np.any(head_std > 0):  # a head moving on its own, in every behavior
        angles += head_std * _smooth_noise(rng_extra, T, dfc.head_tau * fps, 3)
    # yaw about model Z, pitch about model X, roll about model Y: R_h = Rz(yaw) Rx(pitch) Ry(roll)
    Rh = _euler_zxy(np.radians(angles))
    hp = scene.head_pivot
    head_m = np.matmul(model[scene.head] - hp, Rh.transpose(0, 2, 1)) + hp
    if dfc.head_shift > 0:  # the neck: the head triangle moves relative to the trunk
        head_m += dfc.head_shift * _smooth_noise(rng_extra, T, dfc.head_tau * fps, 3)[:, None]
    deformed[:, scene.head] = np.matmul(head_m, R.transpose(0, 2, 1)) + tau[:, None]

    # --- rear: front paws tucked to the chest (the body pitch is in the pose) ------------------
    rear = np.where(labels == REAR, env, 0.0)
    tuck = np.einsum("tij,j->ti", R, np.asarray(cfg.rear.tuck))
    deformed[:, scene.front] += (rear[:, None] * tuck)[:, None]
    _rear_extras(cfg, scene, R, rear, deformed, rng_extra)

    # --- groom: front paws at the snout, stroking ----------------------------------------------
    g = np.where(labels == GROOM, env, 0.0)
    if np.any(g > 0):
        off = np.asarray(cfg.groom.paw_offset, dtype=np.float64)
        stroke = cfg.groom.stroke_amplitude * np.sin(
            2 * np.pi * cfg.groom.stroke_frequency * u / fps
        )
        nose = deformed[:, scene.head[0]]
        for paw, sign in zip(scene.front, (-1.0, 1.0)):  # left paw mirrored to -X
            o = np.broadcast_to(off * np.array([sign, 1.0, 1.0]), (T, 3)).copy()
            o[:, 2] += stroke
            target = nose + np.einsum("tij,tj->ti", R, o)
            deformed[:, paw] = (1 - g)[:, None] * deformed[:, paw] + g[:, None] * target

    # --- reach: effector brought to the mechanism (a nose reach moves the whole head) ----------
    mech = labels - FIRST_MECH
    reach = np.where(mech >= 0, env, 0.0)
    if np.any(reach > 0):
        jit = cfg.reach.jitter * np.stack([ou_noise(rng_jit, T, 0.2 * fps) for _ in range(3)], -1)
        jit[:, 1] = -np.abs(jit[:, 1])  # never into the box
        mi = np.clip(mech, 0, 3)
        target = scene.mech_pos[mi] + jit
        eff = scene.mech_part[mi]
        rows = np.flatnonzero(reach > 0)
        before = deformed[rows, eff[rows]]
        after = (1 - reach[rows, None]) * before + reach[rows, None] * target[rows]
        delta = after - before
        deformed[rows, eff[rows]] = after
        head_eff = np.isin(eff[rows], scene.head)
        for h in scene.head:  # keep the head triangle rigid: the other head points move along
            sel = head_eff & (eff[rows] != h)
            deformed[rows[sel], h] += delta[sel]

    # --- spine: the rear follows the curved path (and wiggles) ---------------------------------
    _spine_bend(cfg, scene, yaw, R, tau, deformed, rng_extra)
    if dfc.jitter > 0:  # every part's own small motion (skin, fur), in the body frame; the
        # paws keep their gait (a stance paw stays put)
        body_parts = np.setdiff1d(np.arange(K), scene.paws)
        n = len(body_parts)
        wob = _smooth_noise(rng_extra, T, dfc.jitter_tau * fps, 3 * n).reshape(T, n, 3)
        deformed[:, body_parts] += dfc.jitter * np.einsum("tij,tkj->tki", R, wob)

    if scene.tail >= 0:
        np.maximum(deformed[:, scene.tail, 2], TAIL_FLOOR, out=deformed[:, scene.tail, 2])

    observed = _masks(cfg, T, K, rng_mask)
    data = SimData(
        time=t,
        poses=poses,
        rigid=rigid,
        deformed=deformed,
        labels=labels,
        behaviors=BEHAVIORS,
        observed=observed,
        parts=body.parts,
        model=model,
        fps=fps,
        seed=cfg.seed,
        lockbox_corners=scene.corners,
        mechanisms=(MECHANISMS, scene.mech_pos),
        arena_size=scene.arena,
    )
    log.info("simulated %d frames (%.1f s) in %.2f s", T, T / fps, _time.perf_counter() - t_start)
    return data
