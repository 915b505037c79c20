"""``FailedPickMemory``: the picks that came up empty since the scene last changed, as an observation.

A greedy policy is a deterministic function of the observation. A pick that closes on nothing leaves the
hand empty and the scene (nearly) as it was, so the same policy picks at the same spot again, and again,
until the step limit: the world model promised a grasp that the world refused, and nothing in the state
records it. This transform records it. After every step it writes ``failed_picks`` ``[*B, M, 3]`` int64:
the ``(row, col, rot)`` of the last ``M`` picks that left the hand empty, most recent first, ``-1`` rows
for none; any step that changes the hand (a pick that holds, any place) and every reset clear it. The
Q-map policies (:mod:`ldm_rl.planning`) leave those actions out of their proposals
(:func:`~ldm_rl.planning.sampling.mask_actions`). It adds a key and changes no dynamics, so an agent
trained without it plays with it, and replay ignores the key.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded
from torchrl.envs.transforms import Transform

from ldm_rl import keys

__all__ = ["FailedPickMemory"]


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
