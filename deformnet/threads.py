"""One way to set torch's number of intra-op threads: for the rest of the process
(`set_torch_threads`) or for a block, restoring the previous setting (`torch_threads`)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


def set_torch_threads(n: int | None) -> int:
    """Use `n` torch threads from now on (None or <= 0: unchanged); returns the previous count."""
    old = torch.get_num_threads()
    if n is not None and int(n) > 0:
        torch.set_num_threads(int(n))
    return old


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run with `n` torch threads (None or <= 0: unchanged), restoring the previous setting."""
    if n is None or int(n) <= 0:
        yield
        return
    old = set_torch_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)
