"""``SpatialDQNLoss``: DQN on a spatial Q map (the FC-DQN and Dyna-Q baselines' loss).

A TorchRL ``LossModule`` in ``DQNLoss``'s style: Huber between ``Q(s, a)`` and ``y = r + γ·(1 − d)·max_{a'}
Q⁻(s', a')``, weighted by the importance weights; writes ``td_error = |Q(s, a) − y|`` (the replay adds ε and
the expert bonus). TorchRL's ``DQNLoss`` is not used: it evaluates the whole ``R·H·W`` map of ``s`` with
gradients (R× the trunk passes of :meth:`~ldm_rl.models.q_fcn.QFCN.action_values`, which runs only the taken
rotation) and squares the TD error.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from torch import nn

from ldm_rl import keys
from ldm_rl.objectives.q_scale import QScale
from ldm_rl.objectives.transition_loss import TransitionLoss
from ldm_rl.torch_utils import eval_mode, swapped_parameters

__all__ = ["SpatialDQNLoss"]


class SpatialDQNLoss(TransitionLoss):
    """DQN on a spatial Q map: ``Q(s, a) ← r + γ·(1 − terminated)·max_{a'} Q⁻(s', a')``.

    Args:
        q_network: ``(heightmap, in_hand, holding) -> [B, R, H, W]`` with ``action_values(..., action) -> [B]``.
        gamma: discount in [0, 1].
        return_lower_bound: raise ``y`` to the batch's ``return_to_go`` where it is higher
            (:meth:`~ldm_rl.objectives.TransitionLoss.lower_bounded`; not in the paper).
        q_log_floor: None (Q regresses ``y``) or ε in (0, 1): Q regresses ``log(max(y, ε))`` and ``max Q⁻`` is
            read back as ``exp`` (:class:`~ldm_rl.objectives.q_scale.QScale`; ``y`` itself is unchanged).
        expert_margin_weight, expert_margin, expert_margin_rows, expert_margin_temperature: λ (0 = off, the
            paper), l, the row cap and the soft max's τ (0 = the hard max) of DQfD's large-margin term on the
            expert rows, added to ``loss_q`` as λ times it and reported as ``expert_margin``
            (:meth:`~ldm_rl.objectives.TransitionLoss.expert_margin_loss`; not in the paper).

    The target network is ``target_q_network_params`` (TorchRL ``convert_to_functional``), synced by a
    target updater (:class:`~ldm_rl.objectives.TargetSync`); targets run in eval mode without gradients,
    terminal rows skip the target pass. Writes ``td_error`` ``[B]`` = ``|Q(s, a) − y|`` (on Q's scale) into the input. Losses are Huber,
    weighted by ``priority_weight`` when present.
    """

    q_network: nn.Module
    q_network_params: TensorDictParams
    target_q_network_params: TensorDictParams
    def __init__(self, q_network: nn.Module, *, gamma: float = 0.95, return_lower_bound: bool = False,
                 q_log_floor: float | None = None, expert_margin_weight: float = 0.0, expert_margin: float = 0.1,
                 expert_margin_rows: int = 4, expert_margin_temperature: float = 0.0) -> None:
        super().__init__()
        self.q_scale = QScale(q_log_floor)
        self.set_expert_margin(expert_margin_weight, expert_margin, expert_margin_rows, expert_margin_temperature)
        self.return_lower_bound = bool(return_lower_bound)
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma!r}")
        self.convert_to_functional(q_network, "q_network", create_target_params=True)
        self.gamma = float(gamma)

    @property
    def out_keys(self) -> list[str]:
        return ["loss_q", "q_target", keys.CHOSEN_ACTION_VALUE, "td_error",
                *(["expert_margin"] if self.expert_margin_weight else [])]

    @torch.no_grad()
    def targets(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``y`` ``[B, 1]`` float32 with the target network."""
        k = self.tensor_keys
        reward = tensordict.get(k.reward).reshape(-1, 1).float()
        live = ~tensordict.get(k.terminated).reshape(-1).bool()
        q_next = torch.zeros_like(reward)
        rows = live.nonzero().squeeze(1)
        if rows.numel():
            state = [tensordict.get((keys.NEXT, key)).index_select(0, rows) for key in (k.heightmap, k.in_hand)]
            holding = tensordict.get((keys.NEXT, k.holding)).reshape(-1, 1).bool().index_select(0, rows)
            with swapped_parameters(self.q_network, self.target_q_network_params), eval_mode(self.q_network):
                q_next[rows] = self.q_scale.decode(self.q_network(*state, holding).flatten(1).amax(1, keepdim=True))
        return self.lower_bounded(reward + self.gamma * q_next, tensordict)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        self.check_batch(tensordict)
        k = self.tensor_keys
        target = self.targets(tensordict)
        weight = self.importance_weights(tensordict, target)
        state = [tensordict.get(key) for key in (k.heightmap, k.in_hand)]
        holding = tensordict.get(k.holding).reshape(-1, 1).bool()
        q_pred = self.q_network.action_values(*state, holding, tensordict.get(k.action)).reshape(-1, 1)
        fitted = self.q_scale.encode(target)
        td_error = (q_pred.detach() - fitted).abs().reshape(-1)
        tensordict.set(k.priority, td_error)
        out = {
            "loss_q": (F.smooth_l1_loss(q_pred, fitted, reduction="none") * weight).mean(),
            "q_target": target.mean(),
            keys.CHOSEN_ACTION_VALUE: self.q_scale.decode(q_pred.detach()).mean(),
            "td_error": td_error.mean(),
        }
        margin = self.expert_margin_loss(self.q_network, tensordict)
        if margin is not None:
            out["loss_q"] = out["loss_q"] + self.expert_margin_weight * margin
            out["expert_margin"] = margin.detach()
        return TensorDict(out, batch_size=[])
