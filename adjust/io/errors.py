"""The error type of `adjust.io`: bad input, naming the file (and camera, part, frame)."""

from __future__ import annotations


class InputError(ValueError):
    """An input file is missing, malformed or inconsistent; the message names what and where."""


class UnknownPartsError(InputError):
    """A detection file names parts that the body model does not know (even through its
    aliases); ``parts``: those names."""

    def __init__(self, message: str, parts=()):
        super().__init__(message)
        self.parts = tuple(parts)
