"""Memory of long sessions: the heap freed by a processed chunk handed back to the OS (used by
the chunked initialisation, `adjust.lsq.init`, and the chunked solver, `adjust.lsq.solver`)."""

from __future__ import annotations

import ctypes

__all__ = ["release_freed_memory"]

_malloc_trim = None


def release_freed_memory() -> None:
    """Hand the heap memory freed by a chunk back to the OS (glibc ``malloc_trim``; elsewhere a
    no-op). Without it the chunks' freed temporaries stay resident, fragmented between longer
    lived allocations, and the resident size of a long session grows by ~0.6 KB per frame."""
    global _malloc_trim
    if _malloc_trim is None:
        try:
            _malloc_trim = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):  # not glibc
            _malloc_trim = False
    if _malloc_trim:
        _malloc_trim(0)
