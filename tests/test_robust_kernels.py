"""Robust kernels (adjust/lsq/robust.py): the IRLS weight is the kernel's derivative over u."""

import pytest
import torch

from adjust.lsq.robust import KERNELS, Kernel, make_kernel


@pytest.mark.parametrize("kind", sorted(KERNELS))
def test_weight_is_the_derivative_of_the_cost_over_u(kind):
    k = make_kernel(kind, 2.5)
    assert isinstance(k, Kernel)
    u = torch.linspace(0.05, 12.0, 200, dtype=torch.float64, requires_grad=True)
    c = k.cost(u * u)
    assert c.shape == u.shape and (c >= 0).all()
    (g,) = torch.autograd.grad(c.sum(), u)
    torch.testing.assert_close(g / u, k.weight(u.detach()), rtol=1e-9, atol=1e-12)
    assert torch.autograd.gradcheck(
        lambda x: k.cost(x * x), (u[:20].detach().clone().requires_grad_(),)
    )
    w = k.weight(u.detach())
    assert (w <= 1 + 1e-12).all() and (w[1:] <= w[:-1] + 1e-12).all()  # never up-weights


def test_unknown_kernel_is_refused():
    with pytest.raises(ValueError, match="tukey"):
        make_kernel("tukey", 1.0)
