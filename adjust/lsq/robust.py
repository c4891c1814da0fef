"""Stochastic model: two-Gaussian mixture (EM responsibilities) and robust kernels (IRLS).

Each accepted detection's pixel residual e (2,) is modelled as a mixture of two isotropic
Gaussians: the detector's accuracy sigma_det (px) and unmodelled body deformation sigma_def
(mm), projected per detection to px as sigma_def * f / z (f focal length, z the part's depth).
With the responsibility gamma of the narrow component (E-step), the detection gets the
inverse-variance weight gamma / sigma_det^2 + (1 - gamma) / sigma_def_px^2 (the M-step of the
scale-mixture EM), and the mixing share is re-estimated as the weighted mean responsibility.
On the whitened residual norm u = |e| sqrt(weight) a robust kernel (Huber, Cauchy) multiplies
the weight down for mis-detections. The detection's own weight (e.g. a DeepLabCut likelihood)
multiplies everything.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


class Kernel:
    """A robust kernel on whitened residual norms u >= 0: ``cost(u2)`` = rho(u^2) / 2 and the
    IRLS ``weight(u)`` = rho'(u) / u (pypose's `optim/kernel.py` in spirit). A new kernel is a
    new subclass registered in `KERNELS`."""

    def __init__(self, scale: float = 1.0) -> None:
        self.scale = float(scale)

    def weight(self, u: Tensor) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def cost(self, u2: Tensor) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError


class NoKernel(Kernel):
    """Plain least squares."""

    def weight(self, u: Tensor) -> Tensor:
        return torch.ones_like(u)

    def cost(self, u2: Tensor) -> Tensor:
        return 0.5 * u2


class Huber(Kernel):
    """Quadratic up to ``scale``, linear beyond."""

    def weight(self, u: Tensor) -> Tensor:
        return torch.where(u <= self.scale, torch.ones_like(u), self.scale / u.clamp_min(1e-300))

    def cost(self, u2: Tensor) -> Tensor:
        u, c = u2.sqrt(), self.scale
        return torch.where(u <= c, 0.5 * u2, c * u - 0.5 * c * c)


class Cauchy(Kernel):
    """rho = c^2 log(1 + u^2 / c^2): mis-detections far out weigh almost nothing."""

    def weight(self, u: Tensor) -> Tensor:
        return 1.0 / (1.0 + (u / self.scale) ** 2)

    def cost(self, u2: Tensor) -> Tensor:
        c2 = self.scale * self.scale
        return 0.5 * c2 * torch.log1p(u2 / c2)


#: the kernels by their config name (`solver.robust`)
KERNELS: dict[str, type[Kernel]] = {"none": NoKernel, "huber": Huber, "cauchy": Cauchy}


def make_kernel(kind: str, scale: float) -> Kernel:
    """The kernel named `kind` (a key of `KERNELS`) with its scale."""
    try:
        return KERNELS[kind](scale)
    except KeyError:
        raise ValueError(f"unknown robust kernel {kind!r} ({', '.join(KERNELS)})") from None


def kernel_weight(u: Tensor, kind: str, scale: float) -> Tensor:
    """IRLS weight rho'(u)/u of the kernel `kind` on whitened residual norms u >= 0."""
    return make_kernel(kind, scale).weight(u)


def kernel_cost(u2: Tensor, kind: str, scale: float) -> Tensor:
    """rho(u^2)/2 per residual (the robust cost; = u^2/2 without kernel).  u2 (...) -> (...)."""
    return make_kernel(kind, scale).cost(u2)


def mixture_weights(
    e2: Tensor,
    base: Tensor,
    sigma_det: float,
    sigma_def_px: Tensor | None,
    share: float,
    em_steps: int = 10,
) -> tuple[Tensor, Tensor, float]:
    """EM of the two-Gaussian model at fixed residuals (`em_steps` share updates, warm-started
    from `share`, so the outer Gauss-Newton iterations need not wait for the slow EM drift).

    e2: (...) squared residual norms px^2; base: (...) detection weights (0 = not a detection);
    sigma_def_px: (...) projected deformation std (px) or None (single Gaussian).
    Returns (inverse-variance weight (...) px^-2, responsibility of the narrow component (...),
    new share).
    """
    inv_det = 1.0 / sigma_det**2
    if sigma_def_px is None:
        return torch.full_like(e2, inv_det), torch.ones_like(e2), 1.0
    s2 = sigma_def_px.clamp_min(sigma_det * 1.0001) ** 2
    # log-density ratio of the two 2D isotropic Gaussians, without the shares
    dl = math.log(1.0 / sigma_det**2) + torch.log(s2) - 0.5 * e2 * (inv_det - 1.0 / s2)
    tot = float(base.sum())
    for _ in range(max(em_steps, 1)):
        gamma = torch.sigmoid(dl + math.log(share) - math.log(1.0 - share))
        if tot <= 0:
            break
        new = min(max(float((gamma * base).sum()) / tot, 0.02), 0.98)
        done = abs(new - share) < 1e-5
        share = new
        if done:
            break
    gamma = torch.sigmoid(dl + math.log(share) - math.log(1.0 - share))
    w = gamma * inv_det + (1.0 - gamma) / s2
    return w, gamma, share
