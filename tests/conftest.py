"""Shared pytest fixtures (shared plain helpers: tests/helpers.py)."""

from __future__ import annotations

import pytest

from deformnet.threads import torch_threads


@pytest.fixture
def one_thread():
    """Run the test with one torch intra-op thread (the previous count restored after it)."""
    with torch_threads(1):
        yield
