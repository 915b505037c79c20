"""Episode memories written as observations: ``FailedPickMemory`` (the picks that came up empty since the scene
last changed) and ``SceneMemory`` (the scenes seen with an empty hand since the reset).

A greedy policy is a deterministic function of the observation. A pick that closes on nothing leaves the
hand empty and the scene (nearly) as it was, so the same policy picks at the same spot again, and again,
until the step limit: the world model promised a grasp that the world refused, and nothing in the state
records it. This transform records it. After every step it writes ``failed_picks`` ``[*B, M, 3]`` int64:
the ``(row, col, rot)`` of the last ``M`` picks that left the hand empty, most recent first, ``-1`` rows
for none; any step that changes the hand (a pick that holds, any place) and every reset clear it. The
Q-map policies (:mod:`ldm_rl.planning`) leave those actions out of their proposals
(:func:`~ldm_rl.planning.sampling.mask_actions`). It adds a key and changes no dynamics, so an agent
trained without it plays with it, and replay ignores the key.

``SceneMemory`` writes ``visited_scenes`` ``[*B, M, 1, 128, 128]`` float32 m: the last ``M`` heightmaps observed
with an empty hand since the reset (the reset's own first), most recent first, ``-1`` for none; a scene that differs
from the newest one by more than ``changed`` m in at most ``same_pixels`` pixels (an empty pick: a cube's edge may
flicker) is not stored twice. The LDM agent's planner with
``revisits_last`` ranks a place last whose predicted scene is one of them
(:func:`~ldm_rl.planning.planner.rank_revisits_last`): under deterministic dynamics a policy that comes back to a
state it left has spent those steps for nothing (a 2-cycle: pick a block, put it back, pick it again). Like the
picks' memory it adds a key and changes no dynamics; it weighs 64 KB per remembered scene in every step's TensorDict.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded
from torchrl.envs.transforms import Transform

from ldm_rl import keys

__all__ = ["FailedPickMemory", "SceneMemory"]


class FailedPickMemory(Transform):
    """Writes ``failed_picks`` ``[*B, size, 3]`` (see the module docstring); ``size`` picks are remembered."""

    def __init__(self, size: int = 8) -> None:
        if not isinstance(size, int) or isinstance(size, bool) or size < 1:
            raise ValueError(f"size must be a positive int (picks remembered), got {size!r}")
        super().__init__(in_keys=[], out_keys=[keys.FAILED_PICKS])
        self.size = size

    def _empty(self, batch_size, device) -> torch.Tensor:
        return torch.full((*batch_size, self.size, 3), -1, dtype=torch.int64, device=device)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        tensordict_reset.set(keys.FAILED_PICKS, self._empty(tensordict_reset.batch_size, tensordict_reset.device))
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        memory = tensordict.get(keys.FAILED_PICKS, None)
        if memory is None:
            memory = self._empty(next_tensordict.batch_size, next_tensordict.device)
        empty_before = ~tensordict.get(keys.HOLDING).bool().reshape(*tensordict.batch_size, 1)
        empty_after = ~next_tensordict.get(keys.HOLDING).bool().reshape(*next_tensordict.batch_size, 1)
        failed = (empty_before & empty_after).unsqueeze(-1)  # [*B, 1, 1]
        pushed = torch.cat([tensordict.get(keys.ACTION).unsqueeze(-2).to(torch.int64), memory[..., :-1, :]], -2)
        next_tensordict.set(keys.FAILED_PICKS, torch.where(failed, pushed, torch.full_like(pushed, -1)))
        return next_tensordict

    def transform_observation_spec(self, observation_spec):
        batch = observation_spec.shape
        observation_spec[keys.FAILED_PICKS] = Bounded(
            -1, torch.iinfo(torch.int64).max, shape=(*batch, self.size, 3), dtype=torch.int64,
            device=observation_spec.device)
        return observation_spec


class SceneMemory(Transform):
    """Writes ``visited_scenes`` ``[*B, size, 1, H, W]`` (see the module docstring); ``size`` scenes are remembered;
    two scenes with at most ``same_pixels`` pixels more than ``changed`` m apart are one."""

    def __init__(self, size: int = 8, changed: float = 0.015, same_pixels: int = 32) -> None:
        if not isinstance(size, int) or isinstance(size, bool) or size < 1:
            raise ValueError(f"size must be a positive int (scenes remembered), got {size!r}")
        if isinstance(changed, bool) or not isinstance(changed, (int, float)) or not changed > 0:
            raise ValueError(f"changed must be a number > 0 (metres), got {changed!r}")
        if not isinstance(same_pixels, int) or isinstance(same_pixels, bool) or same_pixels < 0:
            raise ValueError(f"same_pixels must be an int >= 0, got {same_pixels!r}")
        super().__init__(in_keys=[], out_keys=[keys.VISITED_SCENES])
        self.size, self.changed, self.same_pixels = size, float(changed), same_pixels

    def _pushed(self, memory: torch.Tensor, heightmap: torch.Tensor, push: torch.Tensor) -> torch.Tensor:
        """``memory`` ``[*B, M, 1, H, W]`` with ``heightmap`` ``[*B, 1, H, W]`` in front where ``push`` ``[*B]`` and it
        differs from the newest entry."""
        new = ((heightmap - memory[..., 0, :, :, :]).abs() > self.changed).flatten(-3).sum(-1) > self.same_pixels
        push = (push & new).reshape(*push.shape, 1, 1, 1, 1)
        shifted = torch.cat([heightmap.unsqueeze(-4).to(memory.dtype), memory[..., :-1, :, :, :]], -4)
        return torch.where(push, shifted, memory)

    def _empty(self, heightmap: torch.Tensor) -> torch.Tensor:
        return torch.full((*heightmap.shape[:-3], self.size, *heightmap.shape[-3:]), -1.0, dtype=torch.float32,
                          device=heightmap.device)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        heightmap = tensordict_reset.get(keys.HEIGHTMAP)
        empty = ~tensordict_reset.get(keys.HOLDING).bool().reshape(heightmap.shape[:-3])
        tensordict_reset.set(keys.VISITED_SCENES, self._pushed(self._empty(heightmap), heightmap, empty))
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        heightmap = next_tensordict.get(keys.HEIGHTMAP)
        memory = tensordict.get(keys.VISITED_SCENES, None)
        if memory is None:
            memory = self._empty(heightmap)
        empty = ~next_tensordict.get(keys.HOLDING).bool().reshape(heightmap.shape[:-3])
        next_tensordict.set(keys.VISITED_SCENES, self._pushed(memory, heightmap, empty))
        return next_tensordict

    def transform_observation_spec(self, observation_spec):
        batch = observation_spec.shape
        scene = observation_spec[keys.HEIGHTMAP].shape[len(batch):]
        observation_spec[keys.VISITED_SCENES] = Bounded(
            -1.0, float(torch.finfo(torch.float32).max), shape=(*batch, self.size, *scene), dtype=torch.float32,
            device=observation_spec.device)
        return observation_spec
