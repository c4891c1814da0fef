"""Body model: ordered part names, rigid 3D coordinates (mm) in the model frame, name aliases.

Model frame: right-handed, X right, Y forward (towards the nose), Z up; origin at the body's
reference point (for the default mouse, the paper's Table 1 origin). A pose (r, tau) maps
model points to global ones, X_g = R(r) X_m + tau (see `deformnet.so3`).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from deformnet.confutil import to_plain
from deformnet.paths import CONF_DIR
from deformnet.so3 import kabsch

log = logging.getLogger(__name__)


def part_key(name: str) -> str:
    """A part name as `BodyModel.resolve` compares it loosely: lower case, without ``_``, ``-``,
    ``.`` and spaces (``Left_Front-Paw`` -> ``leftfrontpaw``)."""
    return re.sub(r"[\s_.\-]+", "", str(name)).lower()


@dataclass(frozen=True)
class BodyModel:
    """A rigid body model.

    parts: K part names in model order; points: (K, 3) float64 model coordinates in mm;
    aliases: other names (e.g. a user's DeepLabCut names such as ``snout``) -> part name.
    """

    parts: tuple[str, ...]
    points: np.ndarray
    aliases: Mapping[str, str] = field(default_factory=dict)
    name: str = "body"

    def __post_init__(self) -> None:
        parts = tuple(str(p) for p in self.parts)
        pts = np.asarray(self.points, dtype=np.float64)
        if pts.shape != (len(parts), 3):
            raise ValueError(
                f"body model '{self.name}': points must have shape ({len(parts)}, 3) for parts "
                f"{list(parts)}, got {pts.shape}"
            )
        if len(set(parts)) != len(parts):
            raise ValueError(f"body model '{self.name}': duplicate part names in {list(parts)}")
        if not np.all(np.isfinite(pts)):
            bad = [parts[i] for i in np.flatnonzero(~np.isfinite(pts).all(1))]
            raise ValueError(f"body model '{self.name}': non-finite coordinates for parts {bad}")
        aliases = {str(k): str(v) for k, v in dict(self.aliases).items()}
        for alias, target in aliases.items():
            if target not in parts:
                raise ValueError(
                    f"body model '{self.name}': alias '{alias}' points to unknown part '{target}'"
                )
        pts = pts.copy()
        pts.flags.writeable = False
        object.__setattr__(self, "parts", parts)
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "aliases", aliases)

    @property
    def num_parts(self) -> int:
        return len(self.parts)

    def index(self, name: str) -> int:
        """Index of a part by its name or one of its aliases, matched as `resolve` does (raises
        KeyError naming the part)."""
        key = self.resolve(name)
        try:
            return self.parts.index(key)
        except ValueError:
            raise KeyError(
                f"body part '{name}' is not in body model '{self.name}' (parts: "
                f"{', '.join(self.parts)}; aliases: {', '.join(sorted(self.aliases)) or 'none'})"
            ) from None

    def resolve(self, name: str) -> str | None:
        """The model's part name for `name` (a part name or alias), or None if unknown.

        An exact part name or alias first; else the same ignoring case and the separators ``_``,
        ``-``, ``.`` and spaces (`part_key`: ``Nose``, ``Left_Ear``, ``tail-base`` and
        ``TailBase`` all match), when that names a single part."""
        key = self.aliases.get(name, name)
        if key in self.parts:
            return key
        want = part_key(name)
        hits = {p for n, p in self._loose_names() if n == want}
        return hits.pop() if len(hits) == 1 else None

    def match(self, names: Sequence[str]) -> tuple[dict[str, int], list[str]]:
        """The model's parts named in `names` (by name or alias, `resolve`) -> the index of the
        name that names each, and the names that name no part. Two names of one part: a
        ValueError naming both."""
        found: dict[str, int] = {}
        unknown: list[str] = []
        for k, name in enumerate(names):
            part = self.resolve(name)
            if part is None:
                unknown.append(name)
            elif part in found:
                raise ValueError(
                    f"parts '{names[found[part]]}' and '{name}' both map to body part '{part}' "
                    f"of model '{self.name}' (keep one, or rename the other)"
                )
            else:
                found[part] = k
        return found, unknown

    def _loose_names(self) -> list[tuple[str, str]]:
        """(part_key of a part name or alias, the part) for every part and alias."""
        return [(part_key(p), p) for p in self.parts] + [
            (part_key(a), p) for a, p in self.aliases.items()
        ]

    def with_aliases(self, aliases: Mapping[str, str] | None, where: str = "aliases") -> BodyModel:
        """This model with more aliases (a user's part names -> this model's parts, e.g.
        ``{Snout: nose_tip}``); a target that is not a part is a ValueError naming `where`."""
        if not aliases:
            return self
        extra = {str(k): str(v) for k, v in dict(aliases).items()}
        bad = {k: v for k, v in extra.items() if self.resolve(v) is None}
        if bad:
            raise ValueError(
                f"{where}: {bad} name(s) no part of body model '{self.name}' (parts: "
                f"{list(self.parts)})"
            )
        extra = {k: self.resolve(v) for k, v in extra.items()}
        return BodyModel(self.parts, self.points, {**self.aliases, **extra}, self.name)

    @property
    def centroid(self) -> np.ndarray:
        """(3,) mean of the model points."""
        return self.points.mean(axis=0)

    @property
    def extent(self) -> np.ndarray:
        """(3,) size of the axis-aligned bounding box of the model points (mm)."""
        return self.points.max(axis=0) - self.points.min(axis=0)

    # --- config round trip -------------------------------------------------------------
    @classmethod
    def from_mapping(
        cls,
        parts: Mapping[str, Sequence[float]],
        aliases: Mapping[str, str] | None = None,
        name: str = "body",
    ) -> BodyModel:
        """From ``{part: [x, y, z]}`` (ordered) as in ``conf/body/*.yaml``."""
        names = [str(k) for k in parts]
        pts = np.array([[float(c) for c in parts[k]] for k in parts], dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1:] != (3,):
            raise ValueError(f"body model '{name}': every part needs [x, y, z] in mm")
        return cls(tuple(names), pts, dict(aliases or {}), str(name))

    def to_mapping(self) -> dict:
        """Plain dict that `from_mapping(**d)` turns back into this model."""
        return {
            "name": self.name,
            "parts": {p: [float(c) for c in xyz] for p, xyz in zip(self.parts, self.points)},
            "aliases": dict(self.aliases),
        }

    @classmethod
    def from_config(cls, cfg) -> BodyModel:
        """From a Hydra/OmegaConf node or dict with keys parts and optionally aliases, name
        (absent: `from_mapping`'s defaults; other keys, such as the fit's settings in
        adjust-track's ``body`` group, are not the model's)."""
        cfg = dict(to_plain(cfg))
        return cls.from_mapping(**{k: cfg[k] for k in ("parts", "aliases", "name") if k in cfg})

    def scaled(self, scale: float) -> BodyModel:
        """The same model with every coordinate multiplied by `scale` (> 0)."""
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"body model '{self.name}': scale must be > 0, got {scale}")
        return BodyModel(self.parts, self.points * float(scale), self.aliases, self.name)

    def estimate_scale(
        self, points: np.ndarray, min_parts: int = 4, rigid: np.ndarray | None = None
    ) -> tuple[float, int]:
        """The scale that fits this model to 3D observations of it.

        points: (T, K, 3) mm, NaN missing, in model part order. Per frame with >= `min_parts`
        parts, the ratio of the rms radius of the observed parts about their centroid to that
        of the same model parts (rotation-free, exact for a scaled rigid body); the median
        over frames. Given the posed model, rigid (T, K, 3) (this model moved by each frame's
        pose, e.g. a track's), instead the least-squares scale of the observed parts about the
        posed model's centroid c_t (sum (p - c_t).(r - c_t) / sum |r - c_t|^2 over them):
        unbiased by zero-mean deformations, which inflate the rms radius. Returns (scale,
        frames used); (nan, 0) without usable frames.
        """
        X = np.asarray(points, dtype=np.float64)
        if X.shape[1:] != (self.num_parts, 3):
            raise ValueError(f"points must be (T, {self.num_parts}, 3), got {X.shape}")
        seen = np.isfinite(X).all(-1)
        if rigid is not None:
            R = np.asarray(rigid, dtype=np.float64)
            if R.shape != X.shape:
                raise ValueError(f"rigid must be {X.shape} like points, got {R.shape}")
            c = R.mean(1, keepdims=True)
            r, p = R - c, np.where(seen[..., None], X - c, 0.0)
            den = np.where(seen, (r * r).sum(-1), 0.0).sum(1)
            use = (seen.sum(1) >= max(3, int(min_parts))) & (den > 1e-9)
            if not use.any():
                return float("nan"), 0
            return float(np.median((p * r).sum((1, 2))[use] / den[use])), int(use.sum())
        use = seen.sum(1) >= max(3, int(min_parts))
        if not use.any():
            return float("nan"), 0
        w = seen[use].astype(np.float64)[..., None]
        Xu = np.where(w > 0, X[use], 0.0)
        n = w.sum(1)
        cx = (Xu * w).sum(1) / n
        B = np.broadcast_to(self.points, Xu.shape)
        cb = (B * w).sum(1) / n
        rx = ((Xu - cx[:, None]) ** 2 * w).sum((1, 2))
        rb = ((B - cb[:, None]) ** 2 * w).sum((1, 2))
        ok = rb > 1e-9
        ratio = np.sqrt(rx[ok] / rb[ok])
        return (float(np.median(ratio)) if ratio.size else float("nan")), int(ratio.size)

    def in_frame_of(self, ref: BodyModel, min_parts: int = 3) -> tuple[BodyModel, dict]:
        """This model moved rigidly (its size and shape kept) into `ref`'s model frame: the
        similarity fit ``ref ~ s R self + t`` over the parts `ref` knows (by name or alias,
        `resolve`), then ``self -> R self + t / s``. An estimated body so keeps a prior model's
        conventions (the mouse's X right, Y forward, Z up). With fewer than `min_parts` shared
        parts, or collinear ones, the model is returned as it is. Returns (model, facts: the
        shared parts, the scale s, the rms distance (mm) of the moved parts from ref / s)."""
        pairs = [(i, ref.parts.index(r)) for i, p in enumerate(self.parts)
                 if (r := ref.resolve(p)) is not None]  # fmt: skip
        facts: dict = {"frame_of": ref.name, "shared_parts": [self.parts[i] for i, _ in pairs]}
        if len(pairs) < max(3, int(min_parts)):
            facts["aligned"] = False
            return self, facts
        a = torch.as_tensor(self.points[[i for i, _ in pairs]])
        b = torch.as_tensor(ref.points[[j for _, j in pairs]])
        R, _, S = kabsch(b, a, spread=True)  # b ~ R a + t
        if not bool(S[1] > 1e-6 * S[0]):
            facts["aligned"] = False
            return self, facts
        ac, bc = a - a.mean(0), b - b.mean(0)
        scale = float((bc * (ac @ R.T)).sum() / (ac * ac).sum())
        Rn = R.numpy()
        t = b.mean(0).numpy() / scale - Rn @ a.mean(0).numpy()
        moved = self.points @ Rn.T + t
        idx = [i for i, _ in pairs]
        rms = float(np.sqrt(np.mean(np.sum((moved[idx] - b.numpy() / scale) ** 2, -1))))
        facts.update(aligned=True, scale=scale, rms_mm=rms)
        return BodyModel(self.parts, moved, self.aliases, self.name), facts

    # --- estimation ---------------------------------------------------------------------
    @classmethod
    def from_observations(
        cls,
        points: np.ndarray,
        parts: Sequence[str] | None = None,
        min_parts: int | None = None,
        iterations: int = 20,
        max_frames: int = 20000,
        name: str = "auto",
    ) -> BodyModel:
        """Estimate a rigid model from 3D observations by generalized Procrustes analysis.

        points: (T, K, 3) in mm with NaN for missing; no frame needs all parts. Every frame
        with at least `min_parts` (default and minimum 3) observed parts contributes. The
        shape starts from the frame with the most parts; a part it lacks is placed from the
        frames that see it together with >= 3 already placed parts (aligned on those); then
        generalized Procrustes with missing data: each frame aligned rigidly (no scale) on its
        own parts to the mean shape, each part's position the mean over the frames that saw
        it, until the shape stops changing.
        The model frame: origin at the centroid, axes along the principal directions (largest
        spread -> Y, smallest -> Z), right-handed.
        """
        X = np.asarray(points, dtype=np.float64)
        if X.ndim != 3 or X.shape[-1] != 3:
            raise ValueError(f"points must have shape (T, K, 3), got {X.shape}")
        T, K, _ = X.shape
        names = tuple(parts) if parts is not None else tuple(f"part{i}" for i in range(K))
        if len(names) != K:
            raise ValueError(f"{len(names)} part names for {K} parts")
        seen = np.isfinite(X).all(-1)
        need = 3 if min_parts is None else max(3, int(min_parts))
        usable = seen.sum(1) >= need
        if usable.sum() < 2:
            raise ValueError(
                f"cannot estimate a body model: only {int(usable.sum())} frames have >= {need} "
                f"of the {K} parts observed"
            )
        frames = np.flatnonzero(usable)
        if frames.size > max_frames:
            frames = frames[np.linspace(0, frames.size - 1, max_frames).astype(int)]
        S = seen[frames]
        Xf = np.where(S[..., None], X[frames], 0.0)
        # incremental placement: start from the frame with the most parts, then place the
        # parts still missing from the frames that see them with >= 3 already placed parts
        ref = int(np.argmax(S.sum(1)))
        placed = S[ref].copy()
        mean = np.where(placed[:, None], Xf[ref], 0.0)
        while not placed.all():
            known = S & placed[None]
            cand = (known.sum(1) >= 3) & (S & ~placed[None]).any(1)
            if not cand.any():
                # no frame relates these parts rigidly to the placed ones: place each by the
                # mean translation from the placed parts it was seen with (no rotation known),
                # loudly; a tracker then gives them a large deformation variance
                rough = [i for i in np.flatnonzero(~placed)]
                never = []
                for i in rough:
                    with_placed = S[:, i] & (S & placed[None]).any(1)
                    if not with_placed.any():
                        never.append(names[i])
                        continue
                    f = np.flatnonzero(with_placed)
                    wp = (S[f] & placed[None]).astype(np.float64)
                    cen_frame = (Xf[f] * wp[..., None]).sum(1) / wp.sum(1, keepdims=True)
                    cen_model = (wp @ mean) / wp.sum(1, keepdims=True)
                    mean[i] = np.mean(Xf[f, i] - cen_frame + cen_model, axis=0)
                if never:  # nothing relates them to the rest: at the centre, said loudly
                    idx = [names.index(n) for n in never]
                    mean[idx] = mean[placed].mean(0)
                    log.warning(
                        "body model: parts %s are never observed in 3D together with another "
                        "part; placed at the body's centre (their model positions are unknown)",
                        ", ".join(never),
                    )
                log.warning(
                    "body model: parts %s are never seen together with >= 3 other placed parts; "
                    "placed by translation only (their positions are rough)",
                    ", ".join(names[i] for i in rough),
                )
                placed[:] = True
                break
            al = _align_to(Xf[cand], known[cand].astype(np.float64), mean)
            new = S[cand] & ~placed[None]
            tot = new.sum(0)
            add = tot > 0
            mean[add] = (al * new[..., None]).sum(0)[add] / tot[add, None]
            placed |= add
        # generalized Procrustes with missing data: each frame aligned on its own parts
        w = S.astype(np.float64)
        aligned = Xf
        for _ in range(iterations):
            aligned = _align_to(Xf, w, mean)
            new_mean = _masked_mean_shape(aligned, w, fill=mean)
            new_mean -= new_mean.mean(0)
            if np.abs(new_mean - mean).max() < 1e-9:
                mean = new_mean
                break
            mean = new_mean
        good = frames
        # principal axes: largest spread -> Y (forward), next -> X, smallest -> Z
        centred = mean - mean.mean(0)
        _, _, vt = np.linalg.svd(centred, full_matrices=False)
        y_axis, x_axis = vt[0], vt[1]
        z_axis = np.cross(x_axis, y_axis)
        basis = np.stack([x_axis, y_axis, z_axis])  # rows: model axes in old coordinates
        model = centred @ basis.T
        spread = np.sqrt(np.mean(np.sum((aligned - mean) ** 2 * w[..., None], -1)))
        log.info("estimated body model from %d frames; rms deviation %.3f mm", len(good), spread)
        return cls(names, model, {}, name)


def _masked_mean_shape(X: np.ndarray, w: np.ndarray, fill: np.ndarray) -> np.ndarray:
    """Per-part weighted mean of (F, K, 3), weights (F, K); `fill` where a part has no weight."""
    tot = w.sum(0)
    m = (X * w[..., None]).sum(0) / np.maximum(tot, 1e-12)[:, None]
    return np.where(tot[:, None] > 0, m, fill)


def _align_to(X: np.ndarray, w: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Rigidly align each frame of X (F, K, 3), weights w (F, K), onto ref (K, 3) (Kabsch)."""
    Xt, wt, rt = (torch.from_numpy(np.require(a, np.float64, "W")) for a in (X, w, ref))
    R, t = kabsch(rt, Xt, wt)  # ref ~ X R^T + t, per frame
    return (Xt @ R.transpose(-1, -2) + t[:, None, :]).numpy()


def default_mouse() -> BodyModel:
    """The default mouse (Table 1, left/right X negated), from conf/body/mouse.yaml."""
    import yaml

    with open(CONF_DIR / "body" / "mouse.yaml", encoding="utf-8") as fh:
        return BodyModel.from_config(yaml.safe_load(fh))
