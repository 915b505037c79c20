"""``LDMAgent``: Q proposals, LDM lookahead, V scores (paper §3.3–3.4), trained online.

Each ``update(batch)`` takes one step of three Adam optimizers (Q, V with its reward head, LDM) on:
the LDM focal loss (:class:`~ldm_rl.objectives.LDMLoss`, whose frame logits also give the predicted next
state V is fitted on), the Q loss and the V/reward losses with lookahead targets
(:class:`~ldm_rl.objectives.LookaheadLoss`). Target networks (weights and BatchNorm statistics) are copied
every ``target_update_interval`` updates by :class:`~ldm_rl.objectives.TargetSync`, and by
:meth:`~ldm_rl.agents.base.Agent.sync_targets`; the LRs decay ×``lr_decay`` every ``lr_decay_every`` updates
(the trainer is :class:`~ldm_rl.agents.base.TargetNetworkAgent`, as for every baseline).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from ldm_rl.agents.base import TargetNetworkAgent
from ldm_rl.objectives import LDMLoss, LookaheadLoss
from ldm_rl.planning.planner import LookaheadPlanner
from ldm_rl.world_model.training import dynamics_update

__all__ = ["LDMAgent"]


class LDMAgent(TargetNetworkAgent):
    """The paper's agent. ``lr`` / ``weight_decay``: dicts keyed by ``q``, ``value``, ``dynamics``."""

    name = "ldm"

    def __init__(
        self,
        planner: LookaheadPlanner,
        loss: LookaheadLoss,
        dynamics_loss: LDMLoss,
        *,
        q_grad_clip: float | None = 1.0,
        autocast: str | None = None,
        **kwargs,
    ) -> None:
        if autocast not in (None, "bf16"):
            raise ValueError(f"autocast must be None or 'bf16', got {autocast!r}")
        networks = {"q": planner.q_network, "value": planner.value_network, "dynamics": planner.dynamics}
        super().__init__(planner, loss, networks, q_grad_clip=q_grad_clip, **kwargs)
        self.dynamics_loss, self.autocast = dynamics_loss, autocast

    def pretrain_update(self, batch: TensorDictBase) -> dict[str, float]:
        """An LDM-only step (the model needs no targets): used on the expert data before acting."""
        self._train_mode()
        out = dynamics_update(self.dynamics_loss, self.optimizers["dynamics"], batch)
        return {"loss_dynamics": float(out["loss_dynamics"].detach()), "pixel_accuracy": float(out["pixel_accuracy"])}

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        self._train_mode()
        device = batch.device.type if batch.device is not None else "cpu"
        with torch.autocast(device, dtype=torch.bfloat16, enabled=self.autocast == "bf16"):
            dyn = self.dynamics_loss(batch)
            out = self.loss(batch)
        total = dyn["loss_dynamics"] + out["loss_q"] + out["loss_value"] + out["loss_reward"]
        self._step(total + out["loss_termination"] if "loss_termination" in out.keys() else total)
        metrics = {key: float(value.detach()) for key, value in out.items()}
        metrics.update(loss_dynamics=float(dyn["loss_dynamics"].detach()), pixel_accuracy=float(dyn["pixel_accuracy"]))
        if self.loss.bootstrap_cache is not None:
            metrics["bootstrap_hit_rate"] = self.loss.bootstrap_cache.hit_rate
        return metrics
