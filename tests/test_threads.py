"""deformnet.threads: the one way to set torch's intra-op thread count."""

import torch

from deformnet.threads import set_torch_threads, torch_threads


def test_set_and_restore_torch_threads():
    before = torch.get_num_threads()
    try:
        assert set_torch_threads(1) == before and torch.get_num_threads() == 1
        for unchanged in (None, 0, -1):
            assert set_torch_threads(unchanged) == 1 and torch.get_num_threads() == 1
        with torch_threads(2):
            assert torch.get_num_threads() == 2
        assert torch.get_num_threads() == 1
        with torch_threads(None):
            assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
