"""``LDMAgent``: Q proposals, LDM lookahead, V scores (paper §3.3–3.4), trained online.

Each ``update(batch)`` takes one step of three Adam optimizers (Q, V with its reward head, LDM) on:
the LDM focal loss (:class:`~ldm_rl.objectives.LDMLoss`, whose frame logits also give the predicted next
state V is fitted on), the Q loss and the V/reward losses with lookahead targets
(:class:`~ldm_rl.objectives.LookaheadLoss`). Target networks (weights and BatchNorm statistics) are copied
every ``target_update_interval`` updates by :class:`~ldm_rl.objectives.TargetSync`, and by
:meth:`~ldm_rl.agents.base.Agent.sync_targets`; the LRs decay ×``lr_decay`` every ``lr_decay_every`` updates.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from ldm_rl.agents.base import Agent
from ldm_rl.objectives import LDMLoss, LookaheadLoss, TargetSync
from ldm_rl.planning.planner import LookaheadPlanner
from ldm_rl.runtime import make_adam

__all__ = ["LDMAgent"]

NETWORKS = ("q", "value", "dynamics")


class LDMAgent(Agent):
    """The paper's agent. ``lr`` / ``weight_decay``: dicts keyed by ``q``, ``value``, ``dynamics``."""

    name = "ldm"

    def __init__(
        self,
        planner: LookaheadPlanner,
        loss: LookaheadLoss,
        dynamics_loss: LDMLoss,
        *,
        lr: dict[str, float],
        weight_decay: dict[str, float] | None = None,
        lr_decay: float = 0.95,
        lr_decay_every: int = 2000,
        target_update_interval: int = 100,
        q_grad_clip: float | None = 1.0,
        autocast: str | None = None,
    ) -> None:
        super().__init__()
        if target_update_interval < 1 or lr_decay_every < 1 or not 0 < lr_decay <= 1:
            raise ValueError(f"need target_update_interval >= 1, lr_decay_every >= 1, lr_decay in (0, 1]; got "
                             f"{target_update_interval}, {lr_decay_every}, {lr_decay}")
        self.planner, self.loss, self.dynamics_loss = planner, loss, dynamics_loss
        modules = {"q": planner.q_network, "value": planner.value_network, "dynamics": planner.dynamics}
        weight_decay = weight_decay or {}
        for name in NETWORKS:
            if name not in lr or not lr[name] > 0:
                raise ValueError(f"lr.{name} must be a positive number, got {lr.get(name)!r}")
            self.optimizers[name] = make_adam(modules[name].parameters(), lr=lr[name],
                                              weight_decay=weight_decay.get(name, 0.0))
            self.lr_schedulers[name] = torch.optim.lr_scheduler.StepLR(self.optimizers[name], lr_decay_every, lr_decay)
        self.target_updater = TargetSync(loss, interval=target_update_interval)
        self.q_grad_clip = q_grad_clip
        if autocast not in (None, "bf16"):
            raise ValueError(f"autocast must be None or 'bf16', got {autocast!r}")
        self.autocast = autocast

    @property
    def policy(self) -> LookaheadPlanner:
        return self.planner

    def _train_mode(self) -> None:
        for module in (self.planner.q_network, self.planner.value_network, self.planner.dynamics):
            module.train()

    def pretrain_update(self, batch: TensorDictBase) -> dict[str, float]:
        """An LDM-only step (the model needs no targets): used on the expert data before acting."""
        self._train_mode()
        out = self.dynamics_loss(batch)
        opt = self.optimizers["dynamics"]
        opt.zero_grad(set_to_none=True)
        out["loss_dynamics"].backward()
        opt.step()
        return {"loss_dynamics": float(out["loss_dynamics"].detach()), "pixel_accuracy": float(out["pixel_accuracy"])}

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        self._train_mode()
        device = batch.device.type if batch.device is not None else "cpu"
        with torch.autocast(device, dtype=torch.bfloat16, enabled=self.autocast == "bf16"):
            dyn = self.dynamics_loss(batch)
            out = self.loss(batch)
        total = dyn["loss_dynamics"] + out["loss_q"] + out["loss_value"] + out["loss_reward"]
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)
        total.backward()
        if self.q_grad_clip:
            torch.nn.utils.clip_grad_value_(self.planner.q_network.parameters(), self.q_grad_clip)
        for name in NETWORKS:
            self.optimizers[name].step()
            self.lr_schedulers[name].step()
        self.target_updater.step()
        self.updates += 1
        self.planner.set_step(self.updates)
        metrics = {key: float(value.detach()) for key, value in out.items()}
        metrics.update(loss_dynamics=float(dyn["loss_dynamics"].detach()), pixel_accuracy=float(dyn["pixel_accuracy"]))
        if self.loss.bootstrap_cache is not None:
            metrics["bootstrap_hit_rate"] = self.loss.bootstrap_cache.hit_rate
        return metrics

    def training_state(self) -> dict:
        return {**super().training_state(), "target_updater_counter": self.target_updater.counter}

    def load_training_state(self, state: dict) -> None:
        super().load_training_state(state)
        self.target_updater.counter = int(state["target_updater_counter"])
        self.planner.set_step(self.updates)
