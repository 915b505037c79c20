"""``RandomShootingLoss``: the V and reward-head losses of the Random Shooting agent.

Conventions (different from the LDM agent's V, because RS scores with the reward head explicitly): ``R(s)``
is the reward received on arriving in ``s`` and ``V(s)`` the discounted value of what follows ``s`` (no
arrival reward, 0 after a terminal step), so ``score(s, a) = R(f(s, a)) + γ·V(f(s, a))`` estimates
``Q(s, a) = r + γ·(1 − d)·V(s')``. For a replayed ``(s, a, r, s', d)``: ``y_V = (1 − d)·max_{a' ∈ C(s')}
[R⁻ + γ·V⁻](f⁻(s', a'))`` over ``num_target_candidates`` fresh RS candidates ``C(s')`` scored by the target
networks; Huber losses ``V(s') → y_V``, ``R(s') → r`` and (``value_on_prediction``) the same two on the
LDM's prediction ``f(s, a)``, the kind of state RS scores. Priority: ``|R(s') + γ·V(s') − (r + γ·y_V)|``,
the error of the taken action's score on the real next state.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from torch import nn

from ldm_rl import keys
from ldm_rl.objectives.reward_head import predicted_next_state
from ldm_rl.objectives.transition_loss import TransitionLoss
from ldm_rl.planning.lookahead import shooting_scores
from ldm_rl.planning.sampling import NearObjectSampler
from ldm_rl.torch_utils import swapped_parameters

__all__ = ["RandomShootingLoss"]


class RandomShootingLoss(TransitionLoss):
    """V and reward-head losses of the RS agent (see the module docstring for the targets).

    Args:
        dynamics: the LDM (only its target copy is used here; its own loss is :class:`LDMLoss`).
        value_network: the V CNN with its reward head.
        gamma: discount.
        num_target_candidates: RS candidates of ``s'`` in the target's max.
        height_threshold, dilation: the candidate rule.
        value_on_prediction: also fit ``V``/``R`` on ``f(s, a)`` (from ``next_logits`` when present).
        chunk_size: state-candidate pairs per LDM/V pass of the targets.
        return_lower_bound: raise ``y_V`` to the return the episode collected from the *next* step on
            (``("next", "return_to_go")``: this V excludes the arrival reward; not in the paper).
    """

    value_network: nn.Module
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams
    dynamics: nn.Module
    dynamics_params: TensorDictParams
    target_dynamics_params: TensorDictParams
    out_keys = ["loss_value", "loss_reward", "value_target", "state_value", "td_error"]

    def __init__(
        self,
        dynamics: nn.Module,
        value_network: nn.Module,
        *,
        gamma: float = 0.95,
        num_target_candidates: int = 10,
        height_threshold: float = 0.01,
        dilation: int = 8,
        value_on_prediction: bool = True,
        chunk_size: int = 64,
        return_lower_bound: bool = False,
    ) -> None:
        super().__init__()
        self.return_lower_bound = bool(return_lower_bound)
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma!r}")
        if not isinstance(num_target_candidates, int) or num_target_candidates < 1:
            raise ValueError(f"num_target_candidates must be a positive int, got {num_target_candidates!r}")
        self.convert_to_functional(value_network, "value_network", create_target_params=True)
        self.convert_to_functional(dynamics, "dynamics", create_target_params=True)
        self.gamma, self.num_target_candidates = float(gamma), num_target_candidates
        self.rule = NearObjectSampler(dynamics.num_rotations, height_threshold, dilation)
        self.value_on_prediction, self.chunk_size = bool(value_on_prediction), int(chunk_size)

    @torch.no_grad()
    def targets(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``y_V`` ``[B, 1]``: 0 on terminal rows, else the best target score of fresh RS candidates of s'."""
        k = self.tensor_keys
        live = ~tensordict.get(k.terminated).reshape(-1).bool()
        target = torch.zeros(live.shape[0], 1, device=live.device)
        rows = live.nonzero().squeeze(1)
        if rows.numel():
            heightmap = tensordict.get((keys.NEXT, k.heightmap)).index_select(0, rows)
            in_hand = tensordict.get((keys.NEXT, k.in_hand)).index_select(0, rows)
            holding = tensordict.get((keys.NEXT, k.holding)).reshape(-1, 1).bool().index_select(0, rows)
            candidates = self.rule(heightmap, self.num_target_candidates)
            with swapped_parameters(self.value_network, self.target_value_network_params), \
                    swapped_parameters(self.dynamics, self.target_dynamics_params):
                scores = shooting_scores(self.dynamics, self.value_network, heightmap, in_hand, holding, candidates,
                                         gamma=self.gamma, chunk_size=self.chunk_size)
            target[rows] = scores.amax(1, keepdim=True)
        return self.lower_bounded(target, tensordict, key=(keys.NEXT, self.tensor_keys.return_to_go))

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        self.check_batch(tensordict)
        k = self.tensor_keys
        v_target = self.targets(tensordict)
        reward = tensordict.get(k.reward).reshape(-1, 1).float()
        weight = self.importance_weights(tensordict, reward)

        def huber(pred, target):
            return (F.smooth_l1_loss(pred, target, reduction="none") * weight).mean()

        next_in_hand = tensordict.get((keys.NEXT, k.in_hand))
        v_real, r_real = self.value_network.value_and_reward(tensordict.get((keys.NEXT, k.heightmap)), next_in_hand)
        loss_value, loss_reward = huber(v_real, v_target), huber(r_real, reward)
        if self.value_on_prediction:
            predicted = predicted_next_state(self.dynamics, tensordict)
            v_pred, r_pred = self.value_network.value_and_reward(predicted.heightmap, predicted.in_hand)
            loss_value = loss_value + huber(v_pred, v_target)
            loss_reward = loss_reward + huber(r_pred, reward)
        score = (r_real + self.gamma * v_real).detach()
        td_error = (score - (reward + self.gamma * v_target)).abs().reshape(-1)
        tensordict.set(k.priority, td_error)
        return TensorDict(
            {
                "loss_value": loss_value,
                "loss_reward": loss_reward,
                "value_target": v_target.mean(),
                "state_value": v_real.detach().mean(),
                "td_error": td_error.mean(),
            },
            batch_size=[],
        )
