"""Lock-box interaction events from 3D tracks: contacts of body parts with mechanisms.

Pure NumPy functions (no I/O; `adjust.apps.events` is the app):

- `contact_intervals(distance, on_mm, off_mm, min_frames, merge_gap)`: frames in contact with
  hysteresis (contact starts when the distance falls to `on_mm` or below and lasts until it rises
  above `off_mm`, so a part jittering around one threshold is one contact), contacts separated by
  fewer than `merge_gap` frames merged, then those shorter than `min_frames` dropped.
- `detect_events(points, parts, mechanisms, ...)`: one event per contact of a chosen part with a
  mechanism: start, stop (frame indices, stop inclusive), part, mechanism, minimum distance, the
  fraction of the event's frames in which a camera saw the part (`{part}_ncams` > 0 and, when
  given, `{part}_sigma` <= max_sigma_mm) and the `inferred` flag when that fraction is below
  `inferred_below` (the contact is decided from the model, not from a detection).
- `operations(events, merge_gap)`: the events of one mechanism (any part) merged into operations;
  `first_operated(events)`: the mechanisms in the order they were first operated.

Shapes: T frames, K parts; points (T, K, 3) mm, NaN = unknown (never in contact).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

__all__ = ["contact_intervals", "detect_events", "operations", "first_operated"]


def contact_intervals(
    distance: np.ndarray,
    on_mm: float,
    off_mm: float | None = None,
    min_frames: int = 1,
    merge_gap: int = 0,
) -> list[tuple[int, int]]:
    """Contact intervals [(start, stop inclusive)] of a distance series (T,) mm (NaN: unknown,
    ends a contact). Hysteresis: enter at d <= on_mm, leave at d > off_mm (off_mm >= on_mm;
    default on_mm). Gaps shorter than `merge_gap` frames between contacts are closed; contacts
    shorter than `min_frames` frames are dropped (after merging)."""
    d = np.asarray(distance, dtype=np.float64)
    if d.ndim != 1:
        raise ValueError(f"distance must have shape (T,), got {d.shape}")
    off = float(on_mm if off_mm is None else off_mm)
    if off < on_mm:
        raise ValueError(f"off_mm ({off}) must be >= on_mm ({on_mm})")
    if d.size == 0:
        return []
    t = np.arange(d.size)
    enter = np.where(d <= on_mm, t, -1)
    leave = np.where(~(d <= off), t, -1)  # NaN leaves too
    contact = np.maximum.accumulate(enter) > np.maximum.accumulate(leave)
    edges = np.diff(np.concatenate(([0], contact.astype(np.int8), [0])))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    runs: list[list[int]] = []
    for a, b in zip(starts.tolist(), stops.tolist()):
        if runs and a - runs[-1][1] - 1 < int(merge_gap):
            runs[-1][1] = b
        else:
            runs.append([a, b])
    return [(a, b) for a, b in runs if b - a + 1 >= int(min_frames)]


def detect_events(
    points: np.ndarray,
    parts: Sequence[str],
    mechanisms: Mapping[str, Sequence[float]],
    use_parts: Sequence[str] | None = None,
    on_mm: float = 8.0,
    off_mm: float = 12.0,
    min_frames: int = 5,
    merge_gap: int = 5,
    ncams: np.ndarray | None = None,
    sigma: np.ndarray | None = None,
    max_sigma_mm: float | None = None,
    inferred_below: float = 0.5,
    mechanism_parts: Mapping[str, Sequence[str]] | None = None,
) -> list[dict]:
    """Contacts of the parts `use_parts` (default all) with each mechanism (name -> [x, y, z]).

    points (T, K, 3) mm in `parts` order; ncams, sigma (T, K) optional. mechanism_parts limits a
    mechanism to some parts (e.g. {lever: [right_front_paw, left_front_paw]}). Returns events
    sorted by start: {start, stop (frame indices, inclusive), frames, part, mechanism,
    min_distance_mm, seen_fraction, inferred}.
    """
    P = np.asarray(points, dtype=np.float64)
    parts = [str(p) for p in parts]
    if P.ndim != 3 or P.shape[1:] != (len(parts), 3):
        raise ValueError(f"points must have shape (T, {len(parts)}, 3), got {P.shape}")
    T, K = P.shape[:2]
    chosen = list(parts if use_parts is None else use_parts)
    unknown = [p for p in chosen if p not in parts]
    if unknown:
        raise ValueError(f"unknown part(s) {unknown}; the tracks have {parts}")
    seen = np.ones((T, K), dtype=bool)
    if ncams is not None:
        nc = np.asarray(ncams, dtype=np.float64)
        if nc.shape != (T, K):
            raise ValueError(f"ncams must have shape {(T, K)}, got {nc.shape}")
        seen &= np.nan_to_num(nc, nan=0.0) > 0
    if sigma is not None and max_sigma_mm is not None:
        sg = np.asarray(sigma, dtype=np.float64)
        if sg.shape != (T, K):
            raise ValueError(f"sigma must have shape {(T, K)}, got {sg.shape}")
        seen &= ~(sg > float(max_sigma_mm))  # NaN sigma: no evidence against the detection
    events = []
    for mech, pos in mechanisms.items():
        m = np.asarray(pos, dtype=np.float64)
        if m.shape != (3,) or not np.isfinite(m).all():
            raise ValueError(f"mechanism '{mech}': position must be 3 finite numbers, got {pos}")
        allowed = chosen
        if mechanism_parts and mech in mechanism_parts:
            allowed = [p for p in chosen if p in set(mechanism_parts[mech])]
        for part in allowed:
            k = parts.index(part)
            d = np.linalg.norm(P[:, k] - m, axis=-1)
            for a, b in contact_intervals(d, on_mm, off_mm, min_frames, merge_gap):
                sf = float(seen[a : b + 1, k].mean())
                events.append(
                    {
                        "start": a,
                        "stop": b,
                        "frames": b - a + 1,
                        "part": part,
                        "mechanism": str(mech),
                        "min_distance_mm": float(np.nanmin(d[a : b + 1])),
                        "seen_fraction": sf,
                        "inferred": bool(sf < float(inferred_below)),
                    }
                )
    events.sort(key=lambda e: (e["start"], e["mechanism"], e["part"]))
    return events


def operations(events: Sequence[Mapping], merge_gap: int = 0) -> list[dict]:
    """Per mechanism, its events (any part) merged where they overlap or are fewer than
    `merge_gap` frames apart: [{mechanism, start, stop, parts}] sorted by start."""
    out: list[dict] = []
    by_mech: dict[str, list[Mapping]] = {}
    for e in events:
        by_mech.setdefault(str(e["mechanism"]), []).append(e)
    for mech, evs in by_mech.items():
        cur = None
        for e in sorted(evs, key=lambda e: e["start"]):
            if cur is not None and e["start"] - cur["stop"] - 1 < max(1, int(merge_gap)):
                cur["stop"] = max(cur["stop"], int(e["stop"]))
                cur["parts"] = sorted(set(cur["parts"]) | {str(e["part"])})
            else:
                cur = {
                    "mechanism": mech,
                    "start": int(e["start"]),
                    "stop": int(e["stop"]),
                    "parts": [str(e["part"])],
                }
                out.append(cur)
    out.sort(key=lambda o: (o["start"], o["mechanism"]))
    return out


def first_operated(events: Sequence[Mapping]) -> list[str]:
    """Mechanisms in the order of their first event."""
    first: dict[str, int] = {}
    for e in events:
        m = str(e["mechanism"])
        first[m] = min(first.get(m, int(e["start"])), int(e["start"]))
    return sorted(first, key=lambda m: (first[m], m))
