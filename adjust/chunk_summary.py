"""A long session's summary.json (`adjust.chunks`, issue 46): the chunks' summaries merged
(`merge_summaries`) with what the session's sample estimated once (`session_summary`)."""

from __future__ import annotations

import math
from collections.abc import Sequence

__all__ = ["merge_summaries", "offset_health", "session_summary", "untracked_summary"]

_MAX_KEYS = frozenset({"iterations", "rigid_iterations", "max", "limit_px"})
_STATS_KEYS = frozenset({"count", "median", "mean", "p90", "max"})


def merge_summaries(parts: Sequence[dict], frames: Sequence[int]) -> dict:
    """One summary of the chunks' summaries `parts` (each of its own `frames`, the interior):
    booleans all true, ``iterations`` the largest, other whole numbers summed, costs summed,
    other numbers weighted by frames; error statistics (count, median, mean, p90, max): counts
    summed, means weighted by count, maxima taken, median and p90 the count-weighted means of
    the chunks' (an approximation); ``health`` the worst status with its frames (rows of the
    session); lists of numbers element by element; anything else the first chunk's."""
    return _merge(list(parts), [float(f) for f in frames], "")


def _merge(values: list, weights: list[float], key: str):
    pairs = [(v, w) for v, w in zip(values, weights) if v is not None]
    if not pairs:
        return None
    values, weights = [v for v, _ in pairs], [w for _, w in pairs]
    first = values[0]
    if key == "health":
        return _merge_health(values)
    if key == "cost_history":
        return list(values)
    if isinstance(first, dict):
        if set(first) == _STATS_KEYS:
            return _merge_stats(values)
        keys = dict.fromkeys(k for v in values if isinstance(v, dict) for k in v)
        return {
            k: _merge([v.get(k) for v in values], weights, k)
            for k in keys
            if all(isinstance(v, dict) for v in values)
        }
    if isinstance(first, bool):
        return all(bool(v) for v in values)
    if isinstance(first, (int, float)) and all(isinstance(v, (int, float)) for v in values):
        if key in _MAX_KEYS:
            return max(values)
        if isinstance(first, int) or "cost" in str(key):
            return sum(values)
        finite = [(v, w) for v, w in zip(values, weights) if math.isfinite(v)]
        if not finite:
            return first
        return float(sum(v * w for v, w in finite) / max(sum(w for _, w in finite), 1e-300))
    if (
        isinstance(first, list)
        and first
        and all(isinstance(v, list) and len(v) == len(first) for v in values)
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) for v in values for x in v)
    ):
        columns = [list(c) for c in zip(*values)]
        return [_merge(c, weights, key) for c in columns]
    return first


def _merge_stats(values: list[dict]) -> dict:
    have = [v for v in values if v.get("count")]
    if not have:
        return values[0]
    n = sum(v["count"] for v in have)
    out = {"count": n, "max": max(v["max"] for v in have)}
    for k in ("median", "mean", "p90"):
        out[k] = float(sum(v[k] * v["count"] for v in have) / n)
    return {k: out[k] for k in ("count", "median", "mean", "p90", "max")}


def _merge_health(values: list[dict]) -> dict:
    order = {"ok": 0, "suspect": 1, "failed": 2}
    worst = max(values, key=lambda h: (order.get(h.get("status"), 0), "max_turn_deg" in h))
    out = dict(worst)
    for k in ("bad_frames", "nonfinite_frames", "turn_frames_count", "untracked_frames"):
        out[k] = int(sum(h.get(k, 0) for h in values))
    for k in ("frames", "turn_frames"):
        out[k] = [f for h in values for f in h.get(k, [])][:20]
    out["limit_px"] = max(h["limit_px"] for h in values)
    return out


def offset_health(health: dict, a: int) -> dict:
    """A chunk's health with its frames as rows of the session (the chunk starts at row a)."""
    return {
        **health,
        "frames": [f + a for f in health.get("frames", [])],
        "turn_frames": [f + a for f in health.get("turn_frames", [])],
    }


#: summary.json's ``deformation`` keys of a net mode's choice (`NetDecision`), the sample's
_DECISION_KEYS = frozenset(
    {"mode", "requested", "reason", "checkpoint", "window", "step", "adapt", "world_up", "heldout"}
)


def session_summary(
    summaries: list[dict], frames: list[int], sample: dict, net_mode: bool, T: int
) -> dict:
    """The session's summary: the chunks' merged (`merge_summaries`; a chunk left untracked,
    `untracked_summary`, counts in its frames' completeness and health only), the sample's
    (`sample`, its summary) body model, camera check and detector noise, and with `net_mode`
    the net's choice (`adjust.deformation_modes.NetDecision`, made on the sample)."""
    merged = merge_summaries(summaries, frames)
    tracked = [s for s in summaries if "inputs" in s]
    first = tracked[0]
    for key in ("inputs", "cameras", "parts", "settings", "outputs"):
        merged[key] = first[key]
    merged["body"] = sample["body"]
    merged["camera_check"] = sample["camera_check"]
    if merged.get("stochastic") is not None and sample.get("stochastic") is not None:
        merged["stochastic"]["sigma_det_px"] = sample["stochastic"]["sigma_det_px"]
        merged["stochastic"]["sigma_det_px_per_camera"] = sample["stochastic"][
            "sigma_det_px_per_camera"
        ]
    if net_mode:  # the net's choice, made once on the sample
        chosen = {k: v for k, v in sample["deformation"].items() if k in _DECISION_KEYS}
        merged["deformation"] = {**merged["deformation"], **chosen, "decided_on": "sample"}
    merged["num_frames"] = T
    merged["time_s"] = {
        k: round(sum(s["time_s"].get(k, 0.0) for s in summaries), 3) for k in first["time_s"]
    }
    return merged


def untracked_summary(n: int, usable: dict[str, int], limit_px: float) -> dict:
    """The summary of a chunk of `n` frames left untracked (fewer than two cameras with a usable
    detection; `usable`: {camera: its usable detections in the chunk}): completeness 0, its
    frames counted in ``health.untracked_frames``."""
    return {
        "num_frames": n,
        "completeness": 0.0,
        "usable_per_camera": dict(usable),
        "health": {
            "status": "ok",
            "limit_px": limit_px,
            "bad_frames": 0,
            "nonfinite_frames": 0,
            "frames": [],
            "turn_frames_count": 0,
            "turn_frames": [],
            "untracked_frames": n,
        },
        "time_s": {},
    }
