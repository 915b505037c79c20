"""The reward head's loss and the predicted next state it (and V) are fitted on.

Shared by the Random Shooting and Dyna-Q agents (their model-only pretraining and updates) and by
:class:`~ldm_rl.objectives.LookaheadLoss` (V on the LDM's prediction).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from torch import nn

from ldm_rl import keys
from ldm_rl.torch_utils import eval_mode

__all__ = ["predicted_next_state", "reward_head_loss"]


def predicted_next_state(dynamics: nn.Module, tensordict: TensorDictBase, *,
                         state_keys=(keys.HEIGHTMAP, keys.IN_HAND, keys.HOLDING, keys.ACTION),
                         logits_key=keys.NEXT_LOGITS):
    """``f(s, a)`` of a batch of transitions with the online model, without gradients: from the frame
    logits the LDM loss wrote under ``logits_key`` when present (no second LDM pass), else one
    eval-mode prediction. ``state_keys``: where the state and the action are (a loss's ``tensor_keys``)."""
    args = [tensordict.get(key) for key in state_keys]
    logits = tensordict.get(logits_key, None)
    if logits is not None:
        return dynamics.next_state_from_logits(*args, logits)
    with eval_mode(dynamics):
        return dynamics.predict(*args)


def reward_head_loss(value_network: nn.Module, tensordict: TensorDictBase, predicted=None) -> torch.Tensor:
    """Huber loss of the reward head: ``R(s') → r`` on the replayed next states and, when ``predicted``
    (a :class:`~ldm_rl.world_model.DynamicsPrediction` of ``f(s, a)``) is given, ``R(f(s, a)) → r``;
    weighted by ``priority_weight`` when present. (The value head runs too and gets no gradient.)"""
    reward = tensordict.get((keys.NEXT, keys.REWARD)).reshape(-1, 1).float()
    weight = tensordict.get("priority_weight", None)
    weight = torch.ones_like(reward) if weight is None else weight.reshape(-1, 1).to(reward)
    states = [(tensordict.get((keys.NEXT, keys.HEIGHTMAP)), tensordict.get((keys.NEXT, keys.IN_HAND)))]
    if predicted is not None:
        states.append((predicted.heightmap, predicted.in_hand))
    return sum((F.smooth_l1_loss(value_network.value_and_reward(h, i)[1], reward, reduction="none") * weight).mean()
               for h, i in states)
