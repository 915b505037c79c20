"""Shared helpers of the tests/test_dyn_*.py files: tiny models and synthetic block scenes."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from ldm_rl.world_model import build_dynamics_model

MAX_HEIGHT = 0.15
TINY = {"name": "ldm", "preset": "lite", "width": 0.125, "crop_size": 64, "num_depth_classes": 21, "num_rotations": 8}


def tiny_model(**overrides):
    """A small random-weight dynamics model (eval mode)."""
    torch.manual_seed(0)
    return build_dynamics_model({**TINY, **overrides}, MAX_HEIGHT).eval()


def block_scenes(n: int, seed: int = 0) -> torch.Tensor:
    """[n,1,128,128] float32 heightmaps with a few 12-px blocks of 4 or 8 cm."""
    g = torch.Generator().manual_seed(seed)
    scenes = torch.zeros(n, 1, 128, 128)
    for i in range(n):
        for _ in range(3):
            r, c = torch.randint(8, 108, (2,), generator=g).tolist()
            scenes[i, 0, r : r + 12, c : c + 12] = 0.04 * int(torch.randint(1, 3, (1,), generator=g))
    return scenes


def transitions(n: int, seed: int = 0) -> TensorDict:
    """A batch of synthetic transitions with the demo-data keys (half picks, half places)."""
    g = torch.Generator().manual_seed(seed)
    scenes = block_scenes(n, seed)
    holding = (torch.arange(n) % 2 == 1).unsqueeze(-1)
    action = torch.stack(
        (torch.randint(10, 118, (n,), generator=g), torch.randint(10, 118, (n,), generator=g), torch.randint(0, 8, (n,), generator=g)), -1
    )
    nxt = scenes.clone()
    nxt[:, :, 60:70, 60:70] += 0.04  # some change the model can learn
    in_hand = torch.where(holding.view(n, 1, 1, 1), torch.full((n, 1, 24, 24), 0.04), torch.zeros(n, 1, 24, 24))
    return TensorDict(
        {
            "heightmap": scenes,
            "in_hand": in_hand,
            "holding": holding,
            "action": action,
            "next": {"heightmap": nxt, "in_hand": torch.zeros(n, 1, 24, 24), "holding": ~holding},
        },
        batch_size=[n],
    )


class one_thread:
    """Run a block with one torch thread (training loops in tests stay fast on a shared 2-core box,
    where 2 spinning OpenMP threads per process oversubscribe the CPU)."""

    def __enter__(self):
        self.threads = torch.get_num_threads()
        torch.set_num_threads(1)

    def __exit__(self, *exc):
        torch.set_num_threads(self.threads)


@pytest.fixture
def one_torch_thread():
    """Fixture form of :class:`one_thread` (the test_dyn_* modules use it for every test)."""
    with one_thread():
        yield
