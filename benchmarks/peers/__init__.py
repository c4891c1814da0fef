"""Peers run side by side in the benchmarks (each in its own environment where it must be)."""

import logging


def wanted(skip: bool, installed: bool, missing: str) -> bool:
    """Whether a benchmark runs a peer: not skipped (its ``--no-...`` flag) and `installed`;
    the warning `missing` when it is wanted but not installed."""
    if skip:
        return False
    if not installed:
        logging.getLogger("benchmarks").warning(missing)
    return installed
