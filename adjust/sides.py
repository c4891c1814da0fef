"""Left and right: find a camera whose detections name left/right parts the other way round from
the other cameras, and swap them back.

    det, report = check_sides(cameras, det, mode, reference=None)

A pose estimator trained for one camera with its labels given by the image's left and right (a
view from below, a view through a mirror), or a file whose columns were mislabelled, reports the
animal's left paw as ``right_*`` in that camera only, for every pair or for some. Unnoticed
(before stop 59), two cameras tracked 2.7-3.8x worse with exit 0 (the paired parts lie about 10 px
from each other's epipolar lines, below the camera check's 25 px); with three or four, the
camera was excluded as "detections or intrinsics inconsistent", its other parts lost too.

The left/right pairs are named by `deformnet.windows.mirror_permutation` (``left_*``, ``*_R``,
``L1A``, ...). For each camera pair, the median symmetric epipolar distance of the paired parts
is measured as labelled and with one camera's pairs crossed (`adjust.sync.epipolar_medians`). A
pair of cameras *crosses* where crossed is `BETTER` times closer and within `PLAUSIBLE_PX` (or
twice the rig's least unpaired parts' median: a rig with noisier detections), and is *as
labelled* the other way round; other camera pairs tell nothing. The cameras' labelling (which
are swapped) is the one that explains every telling camera pair (`labelling`), with the fewest
cameras swapped. This is done for every left/right pair at once (a whole camera the other way
round), then for each pair on its own (some of its pairs). Where labellings tie (two cameras, or
two of four), the geometry does not tell which camera is the other way round: the first camera
of the calibration keeps its labels, unless the body model's own left and right tell where one
is given (`reference`, a named body such as the default mouse): the ties are judged jointly, the
labelling whose triangulated parts are turned the body's way (`handedness`: the tetrahedra of 4
parts whose sign the pairs' exchange changes) chosen, and each tie kept where its own pairs'
tetrahedra are turned its way in `HANDED` of them over `MIN_FRAMES` frames or more (said in the
warning either way). Runs in the camera check after the pixel and frame-rate checks, before the
sync and move checks (a camera the other way round confuses them), and again after them (a
camera out of step or turned has its pairs told only once it is put right)
(`adjust.camera_check`; `combine`); ``input.camera_check=error`` stops instead,
``input.side_check=false`` does not look.
Detections: ``Detections`` (T, K, C, 2) px."""

from __future__ import annotations

import dataclasses
import itertools
import logging
from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import torch

from adjust.camera import Camera, CameraTensors
from adjust.io import Detections, InputError
from adjust.sync import epipolar_medians, normalised_points, spread_rows
from adjust.triangulate import triangulate
from deformnet.windows import mirror_permutation

log = logging.getLogger(__name__)

BETTER = 2.0  #: crossed pairs must lie this many times closer to the lines (or farther)
PLAUSIBLE_PX = 5.0  #: ... and within this median distance (or twice the rig's least unpaired)
MIN_PAIRS = 20  #: part-frames a camera pair needs, as labelled and crossed
MAX_ROWS = 3_000  #: rows measured (spread over the session)
MAX_CAMERAS = 12  #: labellings are enumerated (2^C)
HANDED = 0.6  #: a tie is decided by the body where a labelling is turned its way this often
MIN_FRAMES = 3  #: ... over this many frames at least (`_tells_hand`)
MAX_COMBOS = 256  #: tied labellings judged jointly by the body (more: the first camera's)
MIN_VOLUME = 0.2  #: a reference tetrahedron counts from this volume (x6) over its radius cubed


def side_pairs(parts: Sequence[str]) -> list[tuple[int, int]]:
    """The left/right pairs of `parts` as index pairs (i < j), by
    `deformnet.windows.mirror_permutation`'s naming rules; [] where none."""
    perm = mirror_permutation(parts)
    return [] if perm is None else [(i, j) for i, j in enumerate(perm) if i < j]


def swap(det: Detections, pairs: Mapping[str, Iterable[Sequence[str]]]) -> Detections:
    """The detections with each named camera's pairs of parts ``pairs[camera]`` = [(left,
    right), ...] swapped (its left and right named the other way round); the others as they
    are (`det` itself where nothing is to be swapped)."""
    pairs = {name: list(its) for name, its in pairs.items()}
    if not any(pairs.values()):
        return det
    xy, lk = det.xy.copy(), det.likelihood.copy()
    parts = list(det.parts)
    for name, its in pairs.items():
        c = det.cameras.index(name)
        for p, q in its:
            i, j = parts.index(p), parts.index(q)
            xy[:, [i, j], c] = det.xy[:, [j, i], c]
            lk[:, [i, j], c] = det.likelihood[:, [j, i], c]
    return dataclasses.replace(det, xy=xy, likelihood=lk)


def swap_all(det: Detections, cameras: Iterable[str]) -> Detections:
    """`swap` of every left/right pair (`side_pairs`) in the named cameras."""
    named = [(det.parts[i], det.parts[j]) for i, j in side_pairs(det.parts)]
    return swap(det, {c: named for c in cameras})


def _flipped(x: np.ndarray, flips: Mapping[int, set], pairs: Sequence[tuple[int, int]]):
    """x (N, K, C, ...) with camera c's pairs ``flips[c]`` (indices into `pairs`) swapped."""
    out = x.copy()
    for c, its in flips.items():
        for p in its:
            i, j = pairs[p]
            out[:, [i, j], c] = x[:, [j, i], c]
    return out


def telling(same: np.ndarray, crossed: np.ndarray, alone: np.ndarray) -> dict:
    """{(a, b): True (the pair crosses) or False (as labelled)} for the camera pairs whose
    medians tell (see the module doc). `alone`: the unpaired parts' medians (C, C); the rig's
    least of them sets how close "close" is (a camera disturbed otherwise, e.g. turned
    mid-session, has its own pairs' medians raised: not a measure of the rig's noise)."""
    out = {}
    C = same.shape[0]
    finite = alone[np.isfinite(alone)]
    plausible = max(PLAUSIBLE_PX, 2.0 * float(finite.min())) if finite.size else PLAUSIBLE_PX
    for a, b in itertools.combinations(range(C), 2):
        s, x = same[a, b], crossed[a, b]
        if not (np.isfinite(s) and np.isfinite(x)):
            continue
        if s >= BETTER * x and x <= plausible:
            out[(a, b)] = True
        elif x >= BETTER * s and s <= plausible:
            out[(a, b)] = False
    return out


def combine(first: dict, then: dict) -> dict:
    """Two `check_sides` reports of one session (the second on the first's output) as one: a
    camera's pairs swapped by both are swapped by neither."""
    out = {n: dict(v, pairs=[list(p) for p in v["pairs"]]) for n, v in first["swapped"].items()}
    for name, v in then["swapped"].items():
        if name not in out:
            out[name] = v
            continue
        had = {tuple(p) for p in out[name]["pairs"]}
        pairs = had ^ {tuple(p) for p in v["pairs"]}
        by = sorted(set(out[name]["decided_by"]) | set(v["decided_by"]))
        out[name] = dict(v, pairs=sorted(list(p) for p in pairs), decided_by=by)
    return {"swapped": {n: v for n, v in out.items() if v["pairs"]}}


def labelling(C: int, tells: dict) -> list[tuple[int, ...]]:
    """The labellings (one bool per camera: swapped) that explain every telling pair with the
    fewest cameras swapped (several where they tie); [] where none explains them all (a
    camera pair crossing that no swap per camera gives: nothing is swapped)."""
    if C > MAX_CAMERAS:
        return []
    best: list[tuple[int, ...]] = []
    fewest = C + 1
    for s in itertools.product((0, 1), repeat=C):
        if any(bool(s[a] ^ s[b]) != cross for (a, b), cross in tells.items()):
            continue
        n = sum(s)
        if n < fewest:
            best, fewest = [s], n
        elif n == fewest:
            best.append(s)
    return best


def handedness(
    cameras: Sequence[Camera],
    det: Detections,
    reference,
    pairs: Sequence[Sequence[str]] | None = None,
) -> tuple[float, int]:
    """How often the triangulated parts are turned the reference body's way, as told by the
    left/right `pairs` ([(left, right), ...] of `det`'s parts; None: every pair): over the
    frames and the reference's tetrahedra of 4 parts that change their volume's sign when the
    pairs' left and right are exchanged (each volume at least `MIN_VOLUME` of the body's radius
    cubed), the fraction whose 4 triangulated parts have its volume's sign; and the number of
    frames with one or more counted. Left and right named the other way round give about 1 -
    f (a tetrahedron with a part near the midline and other parts about it keeps its sign under
    the exchange: it tells nothing and is not counted); a bending, stretching body changes the
    sign of thin tetrahedra only. `reference`: a body model (``parts``, ``points`` (K', 3))."""
    ref_parts = list(reference.parts)
    idx = [i for i, p in enumerate(det.parts) if p in ref_parts]
    if len(idx) < 4:
        return float("nan"), 0
    Y = np.asarray(reference.points, dtype=np.float64)[[ref_parts.index(det.parts[i]) for i in idx]]
    radius = float(np.sqrt(((Y - Y.mean(0)) ** 2).sum(-1).mean()))
    if pairs is None:
        pairs = [(det.parts[i], det.parts[j]) for i, j in side_pairs(det.parts)]
    local = {det.parts[i]: k for k, i in enumerate(idx)}
    twin = np.arange(len(idx))
    for a, b in pairs:
        if a in local and b in local:
            twin[local[a]], twin[local[b]] = local[b], local[a]
    quads = np.array(list(itertools.combinations(range(len(idx)), 4)))
    vol, exchanged = _volumes(Y[quads]), _volumes(Y[twin[quads]])
    big = MIN_VOLUME * radius**3
    keep = (np.abs(vol) >= big) & (np.abs(exchanged) >= big) & (np.sign(vol) != np.sign(exchanged))
    quads, sign = quads[keep], np.sign(vol[keep])
    if not quads.size:
        return float("nan"), 0
    rows = spread_rows(det.num_frames, MAX_ROWS)
    ct = CameraTensors.from_cameras(list(cameras), dtype=torch.float64)
    with torch.no_grad():
        X = triangulate(
            torch.as_tensor(det.xy[rows][:, idx]), torch.as_tensor(det.weight()[rows][:, idx]),
            ct, robust=len(cameras) >= 3,
        ).points.numpy()  # fmt: skip
    P = X[:, quads]  # (T, Q, 4, 3)
    V = np.full(P.shape[:2], np.nan)
    seen = np.isfinite(P).all((-1, -2))
    V[seen] = _volumes(P[seen])
    ok = np.isfinite(V) & (V != 0)
    frames = int(ok.any(1).sum())
    if not frames:
        return float("nan"), 0
    return float((np.sign(V[ok]) == np.broadcast_to(sign, V.shape)[ok]).mean()), frames


def _tells_hand(h: tuple[float, int]) -> bool:
    """A `handedness` (fraction, frames) that decides: `HANDED` or more, over `MIN_FRAMES`
    frames or more (weaker evidence still beats the coin that the first camera's labels are)."""
    f, n = h
    return bool(n >= MIN_FRAMES and f >= HANDED)


def _volumes(P: np.ndarray) -> np.ndarray:
    """Signed volumes (x6) of tetrahedra P (..., 4, 3)."""
    e = P[..., 1:, :] - P[..., :1, :]
    return np.linalg.det(e)


def _say(msg: str, mode: str) -> None:
    if mode == "error":
        raise InputError(
            msg + "; swap its left and right columns (or rename them) and run again "
            "(input.camera_check=warn swaps them)"
        )
    log.warning("%s; its left and right parts SWAPPED (input.camera_check=warn)", msg)


def check_sides(
    cameras: Sequence[Camera], det: Detections, mode: str = "warn", reference=None
) -> tuple[Detections, dict]:
    """Find cameras whose left/right parts are named the other way round from the others' and
    swap them (see the module doc): every pair of a camera at once, then each pair on its own
    (a camera with some of its pairs the other way round); a tie is decided by the first
    camera, then the ties are judged jointly by `reference`'s handedness (a body model; None:
    the first camera keeps its labels), each kept where its own pairs' tetrahedra tell.
    Returns the detections and the report (``swapped``: per camera the pairs swapped, the
    pairs' median epipolar distances as labelled and swapped, the cameras that told and what
    decided it)."""
    report: dict = {"swapped": {}}
    pairs = side_pairs(det.parts)
    if not pairs or mode == "off" or len(cameras) < 2:
        return det, report
    C, names, parts = len(cameras), [cam.name for cam in cameras], list(det.parts)
    named = [(parts[i], parts[j]) for i, j in pairs]
    rows = spread_rows(det.num_frames, MAX_ROWS)
    x0 = normalised_points(det.xy[rows], cameras)
    paired = {i for p in pairs for i in p}
    unpaired = [i for i in range(len(parts)) if i not in paired]
    alone = epipolar_medians(cameras, x0, unpaired, unpaired, MIN_PAIRS)
    flips: dict[int, set] = {c: set() for c in range(C)}
    by: dict[tuple[int, int], str] = {}  # (camera, pair): what decided it
    told: dict[int, dict] = {}  # camera: the medians of the crossing camera pairs it is in
    tied: list[tuple] = []  # (group, options, choice) a tie decided: the first camera kept
    for group in [list(range(len(pairs)))] + [[p] for p in range(len(pairs))]:
        x = _flipped(x0, flips, pairs)
        ia = [pairs[p][0] for p in group] + [pairs[p][1] for p in group]
        ib = [pairs[p][1] for p in group] + [pairs[p][0] for p in group]
        same = epipolar_medians(cameras, x, ia, ia, MIN_PAIRS)
        crossed = epipolar_medians(cameras, x, ia, ib, MIN_PAIRS)
        tells = telling(same, crossed, alone)
        if not any(tells.values()):
            continue
        options = labelling(C, tells)
        if not options:
            log.warning(
                "left/right check (%s): camera pairs %s cross these parts and %s do not, which "
                "no swap of whole cameras explains; nothing swapped",
                ", ".join(f"{named[p][0]}/{named[p][1]}" for p in group),
                [f"{names[a]}-{names[b]}" for (a, b), t in tells.items() if t],
                [f"{names[a]}-{names[b]}" for (a, b), t in tells.items() if not t],
            )
            continue
        choice = min(options)  # one; or a tie: the first camera keeps its labels
        if len(options) > 1:
            tied.append((group, options, choice))
        for (a, b), cross in tells.items():
            for c in (a, b) if cross else ():
                t = told.setdefault(c, {"labelled": [], "swapped": [], "against": set()})
                t["labelled"].append(same[a, b])
                t["swapped"].append(crossed[a, b])
                t["against"].add(names[b if c == a else a])
        for c in (c for c in range(C) if choice[c]):
            flips[c] ^= set(group)
            for p in group:
                by[(c, p)] = "the other cameras" if len(options) == 1 else "the first camera"
    hands: dict[int, tuple[float, int]] = {}
    combos = list(itertools.product(*(range(len(o)) for _, o, _ in tied)))
    if reference is not None and tied and len(combos) <= MAX_COMBOS:  # the ties jointly

        def state(combo):  # the flips with the ties decided by `combo`
            trial = {c: set(f) for c, f in flips.items()}
            for (group, options, choice), k in zip(tied, combo):
                for c in (c for c in range(C) if options[k][c] != choice[c]):
                    trial[c] ^= set(group)
            return trial

        whole = [handedness(cameras, _current(det, state(k), pairs, names), reference)[0]
                 for k in combos]  # fmt: skip
        best = list(combos[int(np.nanargmax(whole))]) if np.isfinite(whole).any() else None
        for g, (group, options, choice) in enumerate(tied if best is not None else ()):
            its = [named[p] for p in group]  # each tie kept where its own pairs tell
            h = handedness(cameras, _current(det, state(best), pairs, names), reference, its)
            if not _tells_hand(h):
                best[g] = options.index(choice)
                continue
            for p in group:
                hands[p] = h
        if best is not None:
            flips = state(best)
            for c, p in itertools.product(range(C), hands):
                by[(c, p)] = f"the body model '{reference.name}'"
    for c in sorted(c for c in range(C) if flips[c]):
        its = sorted(flips[c])
        t = told.get(c) or {"labelled": [np.nan], "swapped": [np.nan], "against": set()}
        labelled, swapped = float(np.median(t["labelled"])), float(np.median(t["swapped"]))
        which = (
            "its left and right parts"
            if len(its) == len(pairs)
            else "its " + ", ".join(f"{named[p][0]}/{named[p][1]}" for p in its)
        )
        sources = sorted({by[(c, p)] for p in its})
        note = ""
        if any(p in hands for p in its):
            f = min(hands[p][0] for p in its if p in hands)
            n = min(hands[p][1] for p in its if p in hands)
            note += (
                " (which camera is the other way round the geometry does not tell; the body "
                f"model '{reference.name}' does: so labelled, {100 * f:.0f}% or more of the "
                f"tetrahedra of 4 parts that tell are turned its way, over {n} frames or more)"
            )
        if "the first camera" in sources:
            kept = [names[d] for d in range(C) if not flips[d] & set(its)] or names[:1]
            note += (
                " (which camera is the other way round the geometry does not tell"
                + (" nor, here, the body model" if reference is not None else "")
                + f": camera '{kept[0]}' keeps its labels; if it is the one labelled the other "
                "way round, these parts' left and right are swapped in the output)"
            )
        _say(
            f"camera '{names[c]}' ({det.files[c]}) has {which} the other way round from cameras "
            f"{sorted(t['against'])}: they lie {swapped:.1f} px (median) from their epipolar "
            f"lines swapped, {labelled:.1f} px as labelled (a view from below or through a "
            f"mirror, labelled by the image's sides?){note}",
            mode,
        )
        report["swapped"][names[c]] = {
            "pairs": [list(named[p]) for p in its],
            "labelled_px": labelled,
            "swapped_px": swapped,
            "against": sorted(t["against"]),
            "decided_by": sources,
        }
    return swap(det, {n: v["pairs"] for n, v in report["swapped"].items()}), report


def _current(det, flips, pairs, names) -> Detections:
    """The detections with the swaps decided so far (`flips`: camera -> pair indices)."""
    return swap(det, {names[c]: [(det.parts[pairs[p][0]], det.parts[pairs[p][1]]) for p in its]
                      for c, its in flips.items() if its})  # fmt: skip
