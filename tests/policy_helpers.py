"""Tiny real networks and transitions for the planner, objective and agent tests."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from ldm_rl.models.q_fcn import build_q_network
from ldm_rl.models.v_cnn import build_value_network
from dyn_helpers import block_scenes
from ldm_rl.world_model import build_dynamics_model

MAX_HEIGHT = 0.25


def tiny_networks(seed: int = 0):
    """(q, dynamics, value) with random weights: a lite LDM(64) at width 1/16, Q and V at width 1/8."""
    torch.manual_seed(seed)
    dynamics = build_dynamics_model({"name": "ldm", "preset": "lite", "width": 0.0625, "crop_size": 64}, MAX_HEIGHT)
    q = build_q_network("lite", max_height=MAX_HEIGHT, width=0.125)
    value = build_value_network("lite", max_height=MAX_HEIGHT, width=0.125)
    return q, dynamics, value


def scenes(batch: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """``batch`` random block scenes (``dyn_helpers.block_scenes``), every second one holding an object."""
    heightmap = block_scenes(batch, seed)
    holding = (torch.arange(batch) % 2 == 1).view(batch, 1)
    in_hand = torch.where(holding.view(batch, 1, 1, 1), torch.full((batch, 1, 24, 24), 0.04), torch.zeros(batch, 1, 24, 24))
    return {"heightmap": heightmap, "in_hand": in_hand, "holding": holding}


def transitions(batch: int, seed: int = 0, terminated=None) -> TensorDict:
    """A flat batch of transitions between random scenes (rewards 0/1)."""
    now, nxt = scenes(batch, seed), scenes(batch, seed + 1)
    g = torch.Generator().manual_seed(seed + 2)
    action = torch.stack([torch.randint(16, 112, (batch,), generator=g), torch.randint(16, 112, (batch,), generator=g),
                          torch.randint(0, 8, (batch,), generator=g)], -1)
    if terminated is None:
        terminated = torch.rand(batch, 1, generator=g) < 0.3
    reward = terminated.float()
    return TensorDict({**now, "action": action,
                       "next": {**nxt, "reward": reward, "terminated": terminated, "truncated": torch.zeros_like(terminated),
                                "done": terminated.clone()}}, batch_size=[batch])


def quarter_turn_maps(q, grad: bool = False, seed: int = 1, max_layers: int = 4):
    """``(maps, plus, minus)`` of Q network ``q`` on 4 :func:`q_states` scenes, as they are and turned by ±90°
    (``[4, R, 128, 128]`` each, the quarter-turn tests' inputs), with or without gradients."""
    import math

    from ldm_rl import geometry

    scene, in_hand, holding = q_states(4, seed=seed, max_layers=max_layers)
    with torch.set_grad_enabled(grad):
        return (q(scene, in_hand, holding), q(geometry.rotate(scene, math.pi / 2), in_hand, holding),
                q(geometry.rotate(scene, -math.pi / 2), in_hand, holding))


def q_states(n: int, seed: int = 0, max_layers: int = 4):
    """Block scenes on a noisy floor ``[n, 1, 128, 128]`` m (up to ``max_layers`` 4 cm layers per block: 4 reaches
    above the Q tests' max_height), random in-hand images ``[n, 1, 24, 24]`` m, holding alternating ``[n, 1]``."""
    gen = torch.Generator().manual_seed(seed)
    heights = torch.rand(n, 1, 128, 128, generator=gen) * 0.02
    for i in range(n):
        for _ in range(4):
            r, c = torch.randint(4, 110, (2,), generator=gen).tolist()
            h, w = torch.randint(6, 18, (2,), generator=gen).tolist()
            heights[i, 0, r : r + h, c : c + w] += 0.04 * int(torch.randint(1, max_layers + 1, (1,), generator=gen))
    in_hand = torch.rand(n, 1, 24, 24, generator=gen) * 0.08
    return heights, in_hand, (torch.arange(n) % 2 == 1).unsqueeze(-1)
