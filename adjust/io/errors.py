"""The error type of `adjust.io`: bad input, naming the file (and camera, part, frame)."""

from __future__ import annotations


class InputError(ValueError):
    """An input file is missing, malformed or inconsistent; the message names what and where."""
