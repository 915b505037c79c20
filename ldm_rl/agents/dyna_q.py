"""Dyna-Q: FC-DQN whose updates also learn from transitions imagined by the LDM from replayed states.

Each :meth:`DynaQAgent.update` on a replayed batch of B transitions:

1. trains the LDM (focal loss, :class:`~ldm_rl.objectives.LDMLoss`) and the reward head of the V CNN
   (``R(s') → r`` and ``R(f(s, a)) → r``; the value head is not used by this agent);
2. imagines ``M = round(imagined_ratio · B)`` transitions in :class:`~ldm_rl.world_model.LDMImaginedEnv`:
   start states are the batch's own states ``s`` (rows ``0, 1, …, B−1, 0, 1, …``), actions are drawn by the
   exploring policy (one ``softmax(Q/τ)`` draw, :class:`~ldm_rl.planning.q_map.QMapPolicy`), the next state
   is ``f(s, a)`` and the reward ``R(f(s, a))`` from the reward head; an imagined transition is terminal
   when that reward exceeds ``terminal_reward`` (rewards are 0 except on success);
3. takes one DQN step (:class:`~ldm_rl.objectives.SpatialDQNLoss`) on the B real and M imagined
   transitions together (imagined rows with importance weight 1); the new priorities are the real rows'.

Imagination uses the online networks in eval mode without gradients (the models' train/eval flags and
BatchNorm statistics are left as they were). The target Q network, its ``TargetSync`` and the Q
optimiser are FC-DQN's.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from ldm_rl import keys
from ldm_rl.agents.base import TargetNetworkAgent
from ldm_rl.objectives import LDMLoss, SpatialDQNLoss
from ldm_rl.objectives.reward_head import predicted_next_state, reward_head_loss
from ldm_rl.planning.q_map import QMapPolicy

__all__ = ["DynaQAgent", "TRANSITION_KEYS"]

STATE = (keys.HEIGHTMAP, keys.IN_HAND, keys.HOLDING)
# what the DQN loss reads of a transition, real or imagined
TRANSITION_KEYS = (*STATE, keys.ACTION, *((keys.NEXT, key) for key in (*STATE, keys.REWARD, keys.TERMINATED)))


class DynaQAgent(TargetNetworkAgent):
    """The Dyna-Q baseline (see the module docstring). ``lr`` / ``weight_decay``: dicts with ``q``,
    ``value`` (the reward head) and ``dynamics`` entries.

    Args:
        policy: FC-DQN's policy (its Q network is the one trained).
        loss: FC-DQN's DQN loss.
        dynamics_loss: the LDM's focal loss (``write_logits=True`` saves the reward head's second LDM pass).
        value_network: the V CNN whose reward head gives imagined rewards.
        imagined_ratio: imagined transitions per replayed one (0 = FC-DQN with a model trained beside it).
        terminal_reward: an imagined transition with a predicted reward above this ends its episode.
        reward_on_prediction: also fit the reward head on ``f(s, a)``, the kind of state it scores here.
    """

    name = "dynaq"

    def __init__(
        self,
        policy: QMapPolicy,
        loss: SpatialDQNLoss,
        dynamics_loss: LDMLoss,
        value_network: nn.Module,
        *,
        imagined_ratio: float = 1.0,
        terminal_reward: float = 0.5,
        reward_on_prediction: bool = True,
        q_grad_clip: float | None = 1.0,
        **kwargs,
    ) -> None:
        dynamics = dynamics_loss.dynamics
        super().__init__(policy, loss, {"q": policy.q_network, "value": value_network, "dynamics": dynamics},
                         q_grad_clip=q_grad_clip, **kwargs)
        number = isinstance(imagined_ratio, (int, float)) and not isinstance(imagined_ratio, bool)
        if not number or not 0 <= imagined_ratio <= 16:
            raise ValueError(f"imagined_ratio must be a number in [0, 16], got {imagined_ratio!r}")
        self.dynamics_loss, self.value_network = dynamics_loss, value_network
        self.imagined_ratio, self.reward_on_prediction = float(imagined_ratio), bool(reward_on_prediction)
        from ldm_rl.world_model import ImaginedReward

        reward_model = TensorDictModule(ImaginedReward(value_network, terminal_reward),
                                        in_keys=[keys.HEIGHTMAP, keys.IN_HAND],
                                        out_keys=[keys.REWARD, keys.DONE, keys.TERMINATED])
        object.__setattr__(self, "reward_model", reward_model)  # shares value_network: kept out of state_dict

    @property
    def dynamics(self) -> nn.Module:
        return self.dynamics_loss.dynamics

    def imagined_env(self, device: torch.device):
        """The :class:`~ldm_rl.world_model.LDMImaginedEnv` on ``device`` (built once per device; kept out
        of the module tree, so it adds nothing to ``state_dict``)."""
        from ldm_rl.world_model import LDMImaginedEnv

        env = self.__dict__.get("_imagined_env")
        if env is None or torch.device(env.device) != torch.device(device):
            env = LDMImaginedEnv(self.dynamics, reward_module=self.reward_model, device=device)
            object.__setattr__(self, "_imagined_env", env)
        return env

    @torch.no_grad()
    def imagine(self, batch: TensorDictBase) -> TensorDictBase | None:
        """``round(imagined_ratio · B)`` imagined transitions ``[M]`` (keys :data:`TRANSITION_KEYS`) from the
        batch's states, or None when M = 0."""
        size = batch.batch_size[0]
        count = int(round(self.imagined_ratio * size))
        if count == 0:
            return None
        device = batch.get(keys.HEIGHTMAP).device
        start = batch.select(*STATE)[torch.arange(count, device=device) % size]
        env = self.imagined_env(device)
        td = env.reset(start)
        with set_exploration_type(ExplorationType.RANDOM):
            action = self.planner(td.select(*STATE).copy()).get(keys.ACTION)
        td.set(keys.ACTION, action)
        return env.step(td).select(*TRANSITION_KEYS)

    def _model_losses(self, batch: TensorDictBase):
        dyn = self.dynamics_loss(batch)
        predicted = predicted_next_state(self.dynamics, batch) if self.reward_on_prediction else None
        return dyn, reward_head_loss(self.value_network, batch, predicted)

    def pretrain_update(self, batch: TensorDictBase) -> dict[str, float]:
        """The parts that need no targets, before acting: the LDM and the reward head."""
        self._train_mode()
        dyn, loss_reward = self._model_losses(batch)
        self._step(dyn["loss_dynamics"] + loss_reward, count=False)
        return {"loss_dynamics": float(dyn["loss_dynamics"].detach()), "loss_reward": float(loss_reward.detach()),
                "pixel_accuracy": float(dyn["pixel_accuracy"])}

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        self._train_mode()
        imagined = self.imagine(batch)  # first: with the networks as they were before this batch's training pass
        dyn, loss_reward = self._model_losses(batch)
        real = batch.select(*TRANSITION_KEYS)
        size, device = batch.batch_size[0], batch.get(keys.HEIGHTMAP).device
        if self.loss.expert_margin_weight:  # the margin term reads the real rows' flag; imagined ones are no expert's
            real.set("is_expert", batch.get("is_expert").reshape(size, 1).bool())
            if imagined is not None:
                imagined.set("is_expert", torch.zeros(imagined.batch_size[0], 1, dtype=torch.bool, device=device))
        if self.loss.return_lower_bound:  # imagined transitions collected no real return: no bound for them
            real.set("return_to_go", batch.get("return_to_go"))
            if imagined is not None:
                imagined.set("return_to_go", torch.full((imagined.batch_size[0], 1), -math.inf, device=device))
        weight = batch.get("priority_weight", None)
        real.set("priority_weight", torch.ones(size, device=device) if weight is None
                 else weight.reshape(-1).to(device=device, dtype=torch.float32))
        if imagined is not None:
            imagined.set("priority_weight", torch.ones(imagined.batch_size[0], device=device))
            combined = torch.cat([real, imagined])
        else:
            combined = real
        out = self.loss(combined)
        batch.set("td_error", combined.get("td_error")[:size])
        self._step(dyn["loss_dynamics"] + loss_reward + out["loss_q"])
        metrics = {key: float(value.detach()) for key, value in out.items()}
        metrics.update(loss_dynamics=float(dyn["loss_dynamics"].detach()), pixel_accuracy=float(dyn["pixel_accuracy"]),
                       loss_reward=float(loss_reward.detach()), td_error=float(batch.get("td_error").mean()),
                       imagined=0.0, imagined_reward=0.0)
        if imagined is not None:
            metrics.update(imagined=float(imagined.batch_size[0]),
                           imagined_reward=float(imagined.get((keys.NEXT, keys.REWARD)).mean()))
        return metrics
