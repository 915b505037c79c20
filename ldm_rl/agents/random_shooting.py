"""Random Shooting (RS): random actions near objects, each scored through the LDM by ``R + γ·V``.

Policy :class:`~ldm_rl.planning.random_shooting.RandomShootingPlanner`, losses :class:`~ldm_rl.objectives.LDMLoss` and
:class:`~ldm_rl.objectives.RandomShootingLoss` (targets and conventions there) on the same batches; two Adam
optimisers (``value``: V and its reward head; ``dynamics``: the LDM), StepLR, ``TargetSync`` of the target V
and LDM every ``target_update_interval`` updates. No Q network.
"""

from __future__ import annotations

from tensordict import TensorDictBase

from ldm_rl.agents.base import TargetNetworkAgent
from ldm_rl.objectives import LDMLoss
from ldm_rl.objectives.random_shooting import RandomShootingLoss
from ldm_rl.objectives.reward_head import predicted_next_state, reward_head_loss
from ldm_rl.planning.random_shooting import RandomShootingPlanner

__all__ = ["RandomShootingAgent"]


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
