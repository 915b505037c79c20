"""``QMapPolicy``: acting on the Q map alone (the FC-DQN and Dyna-Q baselines' policy).

Greedy (``ExplorationType.DETERMINISTIC``, MODE or MEAN): the argmax of the ``[R, 128, 128]`` Q map of the
current primitive (first index on ties, flat order ``rot·H·W + row·W + col``). Exploring: one draw from
``softmax(Q/τ)`` over the whole map — the LDM planner's proposal distribution with N = 1 and no lookahead.
"""

from __future__ import annotations

import torch
from torch import nn

from ldm_rl import keys
from ldm_rl.geometry import action_to_flat, flat_to_action
from ldm_rl.planning.policy import ScheduleLike, StatePolicy
from ldm_rl.planning.sampling import mask_actions, sample_candidates
from ldm_rl.torch_utils import eval_mode

__all__ = ["QMapPolicy"]


class QMapPolicy(StatePolicy):
    """Acts on the Q map: argmax when greedy, one ``softmax(Q/τ)`` draw otherwise.

    Args:
        q_network: ``(heightmap, in_hand, holding) -> [B, R, H, W]``.
        tau: temperature in Q units (a float or a schedule of the update count).
        write_action_value: also write the ``[*B, R, H, W]`` map under ``action_value``.

    Reads ``failed_picks`` if present (never taken again: :class:`~ldm_rl.envs.memory.FailedPickMemory`).
    Writes ``action`` ``[*B, 3]``, ``chosen_action_value`` ``[*B, 1]`` and ``action_value``.
    """

    def __init__(self, q_network: nn.Module, *, tau: ScheduleLike = 0.1, write_action_value: bool = True) -> None:
        super().__init__(tau=tau)
        self.q_network, self.write_action_value = q_network, bool(write_action_value)
        self.out_keys = [keys.ACTION, keys.CHOSEN_ACTION_VALUE] + ([keys.ACTION_VALUE] if write_action_value else [])

    def decide(self, heightmap, in_hand, holding, *, greedy: bool, avoid=None, visited=None) -> dict[str, torch.Tensor]:
        with eval_mode(self.q_network):
            q_map = self.q_network(heightmap, in_hand, holding)
        flat = (q_map if avoid is None else mask_actions(q_map, avoid)).flatten(1)
        height, width = q_map.shape[-2:]
        if greedy:
            index = flat.argmax(1)
            action = flat_to_action(index, height, width)
        else:  # one draw of softmax(Q/τ): sample_candidates with N = 1 (no inhibition is applied after the last draw)
            action = sample_candidates(flat.view_as(q_map), 1, tau=self.hyperparameters()["tau"], beta=0.0, mode="softmax")[:, 0]
            index = action_to_flat(action, height, width)
        out = {keys.ACTION: action, keys.CHOSEN_ACTION_VALUE: flat.gather(1, index[:, None])}
        if self.write_action_value:
            out[keys.ACTION_VALUE] = q_map
        return out
