"""One way to set torch's number of intra-op threads: for the rest of the process
(`set_torch_threads`) or for a block, restoring the previous setting (`torch_threads`)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import torch

#: the most threads a setting may ask for: more is no speed-up, and torch crashes on absurd
#: counts (threads=100000 segfaults)
MAX_THREADS = 4 * (os.cpu_count() or 1)


def check_threads(n, name: str = "threads") -> int | None:
    """`n` as an int (None stays None), or a ValueError naming the setting when it is not an
    integer or above `MAX_THREADS`."""
    if n is None:
        return None
    try:
        value = int(n)
        if isinstance(n, bool) or value != float(n):
            raise ValueError
    except (TypeError, ValueError):
        raise ValueError(f"{name}={n!r} is not valid: {name} accepts an integer") from None
    if value > MAX_THREADS:
        raise ValueError(
            f"{name}={n!r} is not valid: {name} accepts an integer from 1 to {MAX_THREADS} "
            f"(4 x this machine's {os.cpu_count()} CPUs)"
        )
    return value


def set_torch_threads(n: int | None) -> int:
    """Use `n` torch threads from now on (None or <= 0: unchanged; above `MAX_THREADS`: a
    ValueError); returns the previous count."""
    old = torch.get_num_threads()
    n = check_threads(n)
    if n is not None and n > 0:
        torch.set_num_threads(n)
    return old


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run with `n` torch threads (None or <= 0: unchanged), restoring the previous setting."""
    n = check_threads(n)
    if n is None or n <= 0:
        yield
        return
    old = set_torch_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)
