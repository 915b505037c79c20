"""Random Shooting (RS): random actions near objects, each scored through the LDM by ``R + γ·V``.

No Q network exists in this agent. Conventions (different from the LDM agent's V, because RS scores with
the reward head explicitly): ``R(s)`` is the reward received on arriving in ``s`` and ``V(s)`` the
discounted value of what follows ``s`` (no arrival reward, 0 after a terminal step), so

    score(s, a) = R(f(s, a)) + γ·V(f(s, a))   estimates   Q(s, a) = r + γ·(1 − d)·V(s').

* Policy (:class:`RandomShootingPlanner`): N candidates drawn uniformly near objects
  (:func:`~ldm_rl.planning.random_shooting.sample_near_objects`), one batched LDM → (V, R) pass; a draw
  from ``softmax(score/τ_v)`` while exploring, the best score under DETERMINISTIC (the candidates stay
  random: RS's greedy policy is stochastic by construction).
* Loss (:class:`RandomShootingLoss`): for a replayed ``(s, a, r, s', d)``, ``y_V = (1 − d)·max_{a' ∈ C(s')}
  [R⁻ + γ·V⁻](f⁻(s', a'))`` over ``num_target_candidates`` fresh RS candidates ``C(s')`` scored by the
  target networks; Huber losses ``V(s') → y_V``, ``R(s') → r`` and (``value_on_prediction``) the same
  two on the LDM's prediction ``f(s, a)``, the kind of state RS scores. Priority: ``|R(s') + γ·V(s') −
  (r + γ·y_V)|``, the error of the taken action's score on the real next state.
* Agent (:class:`RandomShootingAgent`): the LDM focal loss and this loss on the same batches, two Adam
  optimisers (``value``: V and its reward head; ``dynamics``: the LDM), StepLR, ``TargetSync`` of the
  target V and LDM every ``target_update_interval`` updates.
"""

from __future__ import annotations


import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from torch import nn

from ldm_rl import keys
from ldm_rl.objectives.transition_loss import TransitionLoss
from ldm_rl.agents.fc_dqn import StatePolicy, TargetNetworkAgent
from ldm_rl.objectives import LDMLoss
from ldm_rl.planning.lookahead import lookahead
from ldm_rl.planning.planner import ScheduleLike
from ldm_rl.planning.random_shooting import sample_near_objects
from ldm_rl.runtime import eval_mode

__all__ = ["RandomShootingPlanner", "RandomShootingLoss", "RandomShootingAgent", "shooting_scores", "reward_head_loss",
           "predicted_next_state"]


def shooting_scores(dynamics, value_network, heightmap, in_hand, holding, candidates, *, gamma: float,
                    chunk_size: int = 64) -> torch.Tensor:
    """``R(f(s, a)) + γ·V(f(s, a))`` ``[B, N]`` of ``candidates`` ``[B, N, 3]`` (eval mode, no gradients)."""
    out = lookahead(dynamics, value_network, heightmap, in_hand, holding, candidates, chunk_size=chunk_size,
                    with_reward=True)
    return out.rewards + gamma * out.values


class _CandidateRule:
    """The RS candidate rule with its settings (see :mod:`ldm_rl.planning.random_shooting`)."""

    def __init__(self, num_rotations: int, height_threshold: float, dilation: int) -> None:
        self.num_rotations, self.dilation = int(num_rotations), int(dilation)
        self.height_threshold = float(height_threshold)
        sample_near_objects(torch.zeros(1, 1, 8, 8), 1, num_rotations=self.num_rotations,
                            height_threshold=self.height_threshold, dilation=self.dilation)  # validates the settings

    def __call__(self, heightmap: torch.Tensor, num: int) -> torch.Tensor:
        return sample_near_objects(heightmap, num, num_rotations=self.num_rotations,
                                   height_threshold=self.height_threshold, dilation=self.dilation)


class RandomShootingPlanner(StatePolicy):
    """RS policy: random near-object candidates → LDM → ``R + γ·V`` → action.

    Args:
        dynamics: the :class:`~ldm_rl.world_model.DynamicsModel`.
        value_network: ``(heightmap, in_hand) -> [B, 1]`` with ``value_and_reward``.
        num_candidates: N candidates per decision.
        gamma: discount of the score.
        height_threshold, dilation: the candidate rule (metres, pixels).
        tau_value: temperature of the choice among the N scores while exploring (float or schedule).
        chunk_size: state-candidate pairs per LDM/V pass.

    Writes ``action`` ``[*B, 3]``, ``candidate_actions`` ``[*B, N, 3]`` and ``candidate_values``
    ``[*B, N]`` (the scores).
    """

    out_keys = [keys.ACTION, keys.CANDIDATE_ACTIONS, keys.CANDIDATE_VALUES]

    def __init__(
        self,
        dynamics: nn.Module,
        value_network: nn.Module,
        *,
        num_candidates: int = 10,
        gamma: float = 0.95,
        height_threshold: float = 0.01,
        dilation: int = 8,
        tau_value: ScheduleLike = 0.1,
        chunk_size: int = 64,
    ) -> None:
        super().__init__(tau_value=tau_value)
        if not isinstance(num_candidates, int) or isinstance(num_candidates, bool) or num_candidates < 1:
            raise ValueError(f"num_candidates must be a positive int, got {num_candidates!r}")
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma!r}")
        self.dynamics, self.value_network = dynamics, value_network
        self.num_candidates, self.gamma, self.chunk_size = num_candidates, float(gamma), int(chunk_size)
        self.rule = _CandidateRule(dynamics.num_rotations, height_threshold, dilation)

    def decide(self, heightmap, in_hand, holding, *, greedy: bool) -> dict[str, torch.Tensor]:
        candidates = self.rule(heightmap, self.num_candidates)
        scores = shooting_scores(self.dynamics, self.value_network, heightmap, in_hand, holding, candidates,
                                 gamma=self.gamma, chunk_size=self.chunk_size)
        if greedy:
            choice = scores.argmax(-1)
        else:
            choice = torch.multinomial(torch.softmax(scores / self.hyperparameters()["tau_value"], -1), 1).squeeze(-1)
        action = candidates.gather(1, choice.view(-1, 1, 1).expand(-1, 1, 3)).squeeze(1)
        return {keys.ACTION: action, keys.CANDIDATE_ACTIONS: candidates, keys.CANDIDATE_VALUES: scores}


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
        self.rule = _CandidateRule(dynamics.num_rotations, height_threshold, dilation)
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
            with self.target_value_network_params.to_module(self.value_network, preserve_module_state=False), \
                    self.target_dynamics_params.to_module(self.dynamics, preserve_module_state=False):
                scores = shooting_scores(self.dynamics, self.value_network, heightmap, in_hand, holding, candidates,
                                         gamma=self.gamma, chunk_size=self.chunk_size)
            target[rows] = scores.amax(1, keepdim=True)
        return self.lower_bounded(target, tensordict, key=(keys.NEXT, self.tensor_keys.return_to_go))

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        keys.require_keys(tensordict, self.in_keys, type(self).__name__)
        if tensordict.batch_dims != 1 or tensordict.batch_size[0] == 0:
            raise ValueError(f"{type(self).__name__} needs a flat, non-empty batch of transitions, got batch_size "
                             f"{tuple(tensordict.batch_size)}")
        k = self.tensor_keys
        v_target = self.targets(tensordict)
        reward = tensordict.get(k.reward).reshape(-1, 1).float()
        weight = tensordict.get(k.priority_weight, None)
        weight = torch.ones_like(reward) if weight is None else weight.reshape(-1, 1).to(reward)

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



def predicted_next_state(dynamics: nn.Module, tensordict: TensorDictBase):
    """``f(s, a)`` of a batch of transitions with the online model, without gradients: from the frame
    logits the LDM loss wrote under ``next_logits`` when present (no second LDM pass), else one
    eval-mode prediction."""
    args = [tensordict.get(key) for key in (keys.HEIGHTMAP, keys.IN_HAND, keys.HOLDING, keys.ACTION)]
    logits = tensordict.get(keys.NEXT_LOGITS, None)
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


class RandomShootingAgent(TargetNetworkAgent):
    """The RS baseline. ``lr`` / ``weight_decay``: dicts with ``value`` and ``dynamics`` entries (``q`` is
    not used: there is no Q network)."""

    name = "rs"

    def __init__(self, planner: RandomShootingPlanner, loss: RandomShootingLoss, dynamics_loss: LDMLoss,
                 **kwargs) -> None:
        super().__init__(planner, loss, {"value": planner.value_network, "dynamics": planner.dynamics}, **kwargs)
        self.dynamics_loss = dynamics_loss

    def pretrain_update(self, batch: TensorDictBase) -> dict[str, float]:
        """The parts that need no targets, before acting: the LDM and the reward head (on ``s'`` and ``f(s, a)``)."""
        self._train_mode()
        dyn = self.dynamics_loss(batch)
        predicted = predicted_next_state(self.planner.dynamics, batch) if self.loss.value_on_prediction else None
        loss_reward = reward_head_loss(self.planner.value_network, batch, predicted)
        self._step(dyn["loss_dynamics"] + loss_reward, count=False)
        return {"loss_dynamics": float(dyn["loss_dynamics"].detach()), "loss_reward": float(loss_reward.detach()),
                "pixel_accuracy": float(dyn["pixel_accuracy"])}

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        self._train_mode()
        dyn = self.dynamics_loss(batch)
        out = self.loss(batch)
        self._step(dyn["loss_dynamics"] + out["loss_value"] + out["loss_reward"])
        metrics = {key: float(value.detach()) for key, value in out.items()}
        metrics.update(loss_dynamics=float(dyn["loss_dynamics"].detach()), pixel_accuracy=float(dyn["pixel_accuracy"]))
        return metrics
