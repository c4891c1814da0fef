"""The detector model of a simulated scene: DeepLabCut-like 2D detections with occlusions,
misses, left/right swaps, far outliers, pixel noise and likelihoods, vectorised over
(T, K, C) in numpy; deterministic for a seed (`DetectorConfig`, `simulate_scene`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
import torch
from scipy.ndimage import convolve1d
from scipy.special import ndtri

from adjust.camera import Camera, CameraTensors, depth, project_cameras
from adjust.io import Detections
from adjust.scene import occlusion
from adjust.scene._checks import _range
from adjust.scene.occlusion import Ellipsoid
from deformnet.confutil import to_plain
from deformnet.paths import CONF_DIR
from deformnet.windows import mirror_permutation

__all__ = [
    "DEFAULT_OCCLUDERS",
    "DetectorConfig",
    "SceneDetections",
    "detector_config",
    "simulate_scene",
]


#: the default body proxies (mouse model frame, mm), as in ``conf/detector/default.yaml``
DEFAULT_OCCLUDERS = (
    Ellipsoid("trunk", (0.0, -1.0, 3.0), (12.0, 26.0, 10.0)),
    Ellipsoid("head", (0.0, 22.0, 8.0), (7.0, 11.0, 7.0), ("nose_tip", "left_ear", "right_ear")),
)


@dataclass(frozen=True)
class DetectorConfig:
    """The detector model (``conf/detector/default.yaml``); rates are probabilities per
    part-frame-camera.

    dropout_rate: a truly visible part is missed (reported as a low-likelihood guess);
    dropout_correlation_frames: misses come in runs of about this many frames (0: independent);
    swap_rate: per left/right pair, both truly visible: the detector reports each at the
    other's position (high likelihood); swap_correlation_frames likewise;
    outlier_rate: any in-image part-frame-camera becomes a far outlier (random offset of
    outlier_px [min, max] px, high likelihood outlier_likelihood);
    noise_px: Gaussian pixel noise (sigma) on correct detections;
    visible_likelihood / hidden_likelihood: uniform ranges for found / guessed parts;
    guess_px: sigma (px) of the offset of a guess from the true projection;
    out_of_image: 'clip' (report a clipped position with out_of_image_likelihood) or 'nan';
    threshold: likelihood at or above which a detection is accepted (for nviews and fractions);
    occluders: body-proxy ellipsoids in the model frame; lockbox_occludes: the simulator's
    lock box (bounds of ``sim.lockbox_corners``) hides what is behind it; surface_margin: mm of
    the segment ending at the part that is not tested (the part's own surface vicinity).
    """

    dropout_rate: float = 0.34
    dropout_correlation_frames: float = 4.0
    swap_rate: float = 0.01
    swap_correlation_frames: float = 3.0
    outlier_rate: float = 0.01
    outlier_px: tuple[float, float] = (40.0, 250.0)
    outlier_likelihood: tuple[float, float] = (0.6, 1.0)
    noise_px: float = 1.5
    visible_likelihood: tuple[float, float] = (0.9, 1.0)
    hidden_likelihood: tuple[float, float] = (0.01, 0.3)
    guess_px: float = 15.0
    out_of_image: str = "clip"
    out_of_image_likelihood: tuple[float, float] = (0.0, 0.05)
    threshold: float = 0.5
    occluders: tuple[Ellipsoid, ...] = field(default_factory=lambda: DEFAULT_OCCLUDERS)
    lockbox_occludes: bool = True
    surface_margin: float = 3.0

    def __post_init__(self) -> None:
        rates = ("dropout_rate", "swap_rate", "outlier_rate", "threshold")
        sizes = ("dropout_correlation_frames", "swap_correlation_frames", "noise_px", "guess_px",
                 "surface_margin")  # fmt: skip
        for key in (*rates, *sizes):
            v = float(getattr(self, key))
            if key in rates and not 0.0 <= v <= 1.0:
                raise ValueError(f"detector.{key} must be in [0, 1], got {v}")
            if key in sizes and not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"detector.{key} must be >= 0, got {v}")
            object.__setattr__(self, key, v)
        for key in (
            "visible_likelihood",
            "hidden_likelihood",
            "outlier_likelihood",
            "out_of_image_likelihood",
        ):
            object.__setattr__(self, key, _range(getattr(self, key), f"detector.{key}"))
        object.__setattr__(
            self, "outlier_px", _range(self.outlier_px, "detector.outlier_px", 0.0, math.inf)
        )
        if self.out_of_image not in ("clip", "nan"):
            raise ValueError(
                f"detector.out_of_image must be 'clip' or 'nan', got {self.out_of_image!r}"
            )
        if not isinstance(self.lockbox_occludes, bool | np.bool_):
            raise ValueError(
                f"detector.lockbox_occludes must be true/false, got {self.lockbox_occludes!r}"
            )
        object.__setattr__(self, "lockbox_occludes", bool(self.lockbox_occludes))
        occ = self.occluders
        occ = (
            occlusion.ellipsoids_from_config(occ) if isinstance(occ, Mapping) else tuple(occ or ())
        )
        if not all(isinstance(e, Ellipsoid) for e in occ):
            raise ValueError("detector.occluders must be Ellipsoids or {name: {center, radii}}")
        object.__setattr__(self, "occluders", tuple(occ))


def detector_config(cfg: Any = None) -> DetectorConfig:
    """A `DetectorConfig` from a config node/dict (the ``detector`` group or a full scene
    config holding it; keys not given take the dataclass defaults), a `DetectorConfig`
    (returned as is) or None (the shipped ``conf/detector/default.yaml``)."""
    if cfg is None:
        from omegaconf import OmegaConf

        cfg = OmegaConf.load(CONF_DIR / "detector" / "default.yaml")
    if isinstance(cfg, DetectorConfig):
        return cfg
    d = to_plain(cfg)
    if not isinstance(d, Mapping):
        raise ValueError(f"detector config must be a mapping, got {type(d).__name__}")
    if "detector" in d and isinstance(d["detector"], Mapping):
        d = d["detector"]
    d = dict(d)
    known = {f.name for f in fields(DetectorConfig)}
    unknown = set(d) - known
    if unknown:
        raise ValueError(f"unknown detector config keys {sorted(unknown)} (known: {sorted(known)})")
    if "occluders" in d:
        d["occluders"] = tuple(occlusion.ellipsoids_from_config(d["occluders"]))
    return DetectorConfig(**d)


@dataclass(frozen=True)
class SceneDetections:
    """Simulated detections for T frames, K parts, C cameras.

    xy: (T, K, C, 2) reported pixels (NaN only with out_of_image='nan'); likelihood (T, K, C);
    visible: (T, K, C) true visibility (in front, in image, not occluded); in_image (T, K, C);
    occluded (T, K, C) by the body proxy; dropped (T, K, C) visible but missed; swapped and
    outlier (T, K, C): the reported position is not the part's (swap or far outlier);
    truth_xy (T, K, C, 2) noise-free projections; threshold: acceptance likelihood.
    """

    xy: np.ndarray
    likelihood: np.ndarray
    visible: np.ndarray
    outlier: np.ndarray
    swapped: np.ndarray
    dropped: np.ndarray
    occluded: np.ndarray
    in_image: np.ndarray
    truth_xy: np.ndarray
    cameras: tuple[str, ...] = ()
    parts: tuple[str, ...] = ()
    threshold: float = 0.5

    @property
    def accepted(self) -> np.ndarray:
        """(T, K, C) likelihood >= threshold."""
        return self.likelihood >= self.threshold

    @property
    def correct(self) -> np.ndarray:
        """(T, K, C) accepted, and the reported position is the part's own (noisy) projection."""
        return self.accepted & self.visible & ~self.dropped & ~self.outlier

    @property
    def nviews(self) -> np.ndarray:
        """(T, K) number of cameras with an accepted, correct detection."""
        return self.correct.sum(-1)

    @property
    def accepted_xy(self) -> np.ndarray:
        """(T, K, C, 2) reported pixels, NaN below the threshold (as `adjust.io` loads them)."""
        return np.where(self.accepted[..., None], self.xy, np.nan)

    def to_detections(self):
        """The in-memory twin of what `adjust.io.load_detections` reads from the written
        scene folder: an `adjust.io.Detections` (xy NaN below the threshold, no files)."""

        return Detections(
            cameras=tuple(self.cameras),
            parts=tuple(self.parts),
            xy=self.accepted_xy,
            likelihood=np.nan_to_num(self.likelihood, nan=0.0),
            files=(),
            threshold=self.threshold,
        )

    def fractions(self) -> dict[str, float]:
        """Measured fractions of part-frames (and rates over part-frame-cameras)."""
        nv = self.nviews
        acc = self.accepted.sum(-1)
        vis = self.visible
        n_vis = max(int(vis.sum()), 1)
        pair_cand = self.in_image.sum()
        return {
            "ge2_views": float((nv >= 2).mean()),
            "one_view": float((nv == 1).mean()),
            "no_view": float((nv == 0).mean()),
            "ge2_accepted": float((acc >= 2).mean()),
            "no_accepted": float((acc == 0).mean()),
            "visible": float(vis.mean()),
            "occluded": float(self.occluded.mean()),
            "in_image": float(self.in_image.mean()),
            "dropout_given_visible": float(self.dropped.sum() / n_vis),
            "outlier": float((self.outlier & ~self.swapped).sum() / max(int(pair_cand), 1)),
            "swapped": float(self.swapped.mean()),
            "accepted_wrong": float((self.accepted & ~self.correct).mean()),
        }


def _events(
    rng: np.random.Generator, shape: tuple[int, ...], rate: float, corr_frames: float
) -> np.ndarray:
    """Bernoulli(rate) events over `shape` (time first), in runs of about `corr_frames` frames:
    a Gaussian field smoothed along time (unit marginal variance) thresholded at its
    (1 - rate) quantile, so the marginal rate is exact for any correlation length."""
    if rate <= 0.0:
        return np.zeros(shape, dtype=bool)
    if rate >= 1.0:
        return np.ones(shape, dtype=bool)
    z = rng.standard_normal(shape)
    if corr_frames > 0.0 and shape[0] > 1:
        sigma = corr_frames / 2.0
        half = max(1, math.ceil(3 * sigma))
        k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
        k /= np.sqrt((k * k).sum())  # unit variance after smoothing
        z = convolve1d(z, k, axis=0, mode="wrap")
    return z > ndtri(1.0 - rate)


def _uniform(rng: np.random.Generator, lo_hi: tuple[float, float], shape) -> np.ndarray:
    return rng.uniform(lo_hi[0], lo_hi[1], size=shape)


def _lr_partner(parts: Sequence[str]) -> np.ndarray:
    """Index of each part's left/right counterpart (-1 if none), by
    `deformnet.windows.mirror_permutation`'s naming rules (left_x / x_l / Ear_L ...)."""
    perm = mirror_permutation(parts)
    out = np.full(len(parts), -1, dtype=np.int64)
    if perm is not None:
        twin = np.asarray(perm, dtype=np.int64)
        has = twin != np.arange(len(parts))
        out[has] = twin[has]
    return out


def simulate_scene(
    sim: Any,
    cameras: Sequence[Camera],
    detector_cfg: Any = None,
    seed: int | Sequence[int] | None = 0,
) -> SceneDetections:
    """Simulated DeepLabCut-like detections of `sim`'s deformed parts in every camera.

    sim: a ``deformnet.sim.SimData`` (uses ``deformed (T, K, 3)``, ``poses (T, 6)``, ``parts``)
    or anything with those attributes; cameras: the rig; detector_cfg: a `DetectorConfig`, a
    detector config node/dict, or None for the defaults; seed: the detector's random seed (an
    int or a sequence of ints, as numpy's `default_rng` takes).
    """
    cfg = detector_config(detector_cfg)
    X = np.asarray(sim.deformed, dtype=np.float64)
    poses = np.asarray(sim.poses, dtype=np.float64)
    parts = tuple(str(p) for p in sim.parts)
    if X.ndim != 3 or X.shape[-1] != 3:
        raise ValueError(f"sim.deformed must be (T, K, 3), got {X.shape}")
    T, K, _ = X.shape
    if len(parts) != K:
        raise ValueError(f"{len(parts)} part names for {K} parts")
    if poses.shape != (T, 6):
        raise ValueError(f"sim.poses must be ({T}, 6), got {poses.shape}")
    cams = list(cameras)
    if not cams:
        raise ValueError("no cameras given")
    C = len(cams)
    rng = np.random.default_rng(seed)

    ct = CameraTensors.from_cameras(cams)
    Xt = torch.as_tensor(X)
    uv = project_cameras(Xt, ct).numpy()  # (T, K, C, 2)
    z = depth(Xt[..., None, :], ct.R, ct.t).numpy()  # (T, K, C)
    wh = np.array([c.size for c in cams], dtype=np.float64)  # (C, 2)
    if np.any(wh <= 0):
        raise ValueError("every camera needs an image size (width, height) > 0")
    lo, hi = -0.5, wh - 0.5  # pixel-centre origin: the image spans [-0.5, W - 0.5)
    finite = np.isfinite(uv).all(-1)
    in_image = (z > 0) & finite & (uv >= lo).all(-1) & (uv < hi).all(-1)
    centers = np.stack([c.center for c in cams])
    model = getattr(sim, "model", None)
    occluded = occlusion.occluded_by_ellipsoids(
        X, poses, centers, cfg.occluders, cfg.surface_margin, model=model, parts=parts
    )
    if cfg.lockbox_occludes:
        occluded |= occlusion.occluded_by_boxes(
            X, centers, occlusion.lockbox_boxes(sim), cfg.surface_margin
        )
    occluded &= in_image
    visible = in_image & ~occluded

    shape = (T, K, C)
    # detector misses among the visible
    dropped = visible & _events(rng, shape, cfg.dropout_rate, cfg.dropout_correlation_frames)
    found = visible & ~dropped
    # pixel noise on correct detections, guesses for the rest
    noisy = uv + rng.standard_normal(uv.shape) * cfg.noise_px
    guess = uv + rng.standard_normal(uv.shape) * cfg.guess_px
    xy = np.where(found[..., None], noisy, guess)
    lik_found = _uniform(rng, cfg.visible_likelihood, shape)
    lik = np.where(found, lik_found, _uniform(rng, cfg.hidden_likelihood, shape))
    # left/right swaps: both parts of a pair truly found; each reported at the other's place
    partner = _lr_partner(parts)
    swapped = np.zeros(shape, dtype=bool)
    has = np.flatnonzero(partner >= 0)
    if has.size:
        first = has[has < partner[has]]  # one event per pair
        ev = _events(rng, (T, first.size, C), cfg.swap_rate, cfg.swap_correlation_frames)
        both = found[:, first] & found[:, partner[first]]
        ev &= both
        swapped[:, first] = ev
        swapped[:, partner[first]] = ev
        src = np.arange(K)
        src[first] = partner[first]
        src[partner[first]] = first
        xy = np.where(swapped[..., None], noisy[:, src], xy)
    # far outliers: anywhere a detector looks, with a high likelihood
    far = in_image & _events(rng, shape, cfg.outlier_rate, 0.0)
    ang = rng.uniform(0.0, 2 * np.pi, shape)
    rad = _uniform(rng, cfg.outlier_px, shape)
    off = np.stack([np.cos(ang), np.sin(ang)], -1) * rad[..., None]
    far_xy = np.clip(uv + off, lo, hi - 1e-6)
    xy = np.where(far[..., None], far_xy, xy)
    lik = np.where(far, _uniform(rng, cfg.outlier_likelihood, shape), lik)
    outlier = far | swapped
    # outside the image (or behind the camera): missing / low likelihood
    out_lik = _uniform(rng, cfg.out_of_image_likelihood, shape)
    if cfg.out_of_image == "nan":
        xy = np.where(in_image[..., None], xy, np.nan)
        lik = np.where(in_image, lik, np.nan)
    else:
        safe = np.where(finite[..., None], uv, 0.0)
        clipped = np.clip(safe, lo, hi - 1e-6)
        xy = np.where(in_image[..., None], xy, clipped)
        lik = np.where(in_image, lik, out_lik)
    # every reported in-image position stays inside the image
    xy = np.where(in_image[..., None], np.clip(xy, lo, hi - 1e-6), xy)
    return SceneDetections(
        xy=xy,
        likelihood=lik,
        visible=visible,
        outlier=outlier,
        swapped=swapped & ~far,
        dropped=dropped,
        occluded=occluded,
        in_image=in_image,
        truth_xy=uv,
        cameras=tuple(c.name for c in cams),
        parts=parts,
        threshold=cfg.threshold,
    )
