"""What every agent offers the training loop (``recipes/train_policy.py``) and the evaluator, and the
target-network trainer every agent of this package is.

An agent owns its networks, losses, optimizers, LR schedules and target updater; the recipe owns the
loop (collect → replay → ``agent.update(batch)`` → evaluate → checkpoint) in plain view.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from torchrl.objectives import LossModule

from ldm_rl.objectives.target_sync import TargetSync
from ldm_rl.planning.policy import StatePolicy
from ldm_rl.torch_utils import make_adam

__all__ = ["Agent", "TargetNetworkAgent", "is_target_entry", "tail_ema_multi_avg_fn"]


def tail_ema_multi_avg_fn(decay: float, tail: float):
    """An ``AveragedModel`` ``multi_avg_fn``: an exponential moving average whose n-th update (n ≥ 1 earlier
    averages) uses decay ``min(decay, 1 − 1/max(1, tail·n))``, i.e. it spans ≈ the last ``tail`` fraction of the
    updates, at most ≈ ``1/(1 − decay)`` of them. ``tail`` in (0, 1]."""
    if isinstance(tail, bool) or not isinstance(tail, (int, float)) or not 0 < tail <= 1:
        raise ValueError(f"greedy_ema_tail must be a number in (0, 1] (a fraction of the updates), got {tail!r}")

    @torch.no_grad()
    def update(averaged: list[torch.Tensor], current: list[torch.Tensor], num_averaged: torch.Tensor) -> None:
        d = min(decay, 1.0 - 1.0 / max(1.0, tail * float(num_averaged)))
        if averaged[0].is_floating_point():
            torch._foreach_lerp_(averaged, current, 1.0 - d)
        else:  # integer buffers (BatchNorm's batch counts), as torch's own EMA treats them
            for a, c in zip(averaged, current, strict=True):
                a.copy_(a * d + c * (1.0 - d))

    return update


def is_target_entry(key: str) -> bool:
    """Whether a ``state_dict`` key belongs to a target network's copy (a loss's ``target_<net>_params``)."""
    return any(part.startswith("target_") and part.endswith("_params") for part in key.split("."))


class Agent(nn.Module):
    """Base class: ``policy`` (a TensorDict module for collectors and ``env.rollout``), ``update``,
    ``training_state`` / ``load_training_state`` (optimizers, schedules, counters) beside ``state_dict``.
    """

    name = "agent"

    def __init__(self) -> None:
        super().__init__()
        self.updates = 0
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.lr_schedulers: dict[str, torch.optim.lr_scheduler.LRScheduler] = {}

    @property
    def policy(self) -> TensorDictModuleBase:
        raise NotImplementedError

    @property
    def greedy_policy(self) -> TensorDictModuleBase:
        """The policy evaluations play (greedily, under ``set_exploration_type(DETERMINISTIC)``); the
        exploring ``policy`` unless the agent keeps averaged weights for it."""
        return self.policy

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """One gradient step on a flat batch of transitions; writes ``td_error`` [B] into ``batch``
        (the new replay priorities) and returns scalar diagnostics."""
        raise NotImplementedError

    def pretrain_update(self, batch: TensorDictBase) -> dict[str, float]:
        """An update before any acting (default: a full update)."""
        return self.update(batch)

    def sync_targets(self) -> None:
        """Copy the online networks (weights and buffers) into the target networks now. The training loop
        calls it once the agent is about to act, after any model-only pretraining, so the first targets
        come from the networks that act."""
        updater = getattr(self, "target_updater", None)
        if updater is not None:
            updater.sync()

    def drop_caches(self) -> None:
        """Forget what the losses cache (the bootstrap cache): recomputing gives the same targets, up to the
        last float bits of a different batch composition. The training loop drops them at each checkpoint,
        so a resumed run, which starts without them, computes bit for bit what the uninterrupted one does."""
        cache = getattr(getattr(self, "loss", None), "bootstrap_cache", None)
        if cache is not None:
            cache.clear()

    def policy_state_dict(self) -> dict[str, torch.Tensor]:
        """``state_dict`` less the target networks' copies: what acting needs (``best_policy.pt`` holds it).
        The targets only shape the training targets; :meth:`load_policy_state_dict` re-creates them."""
        return {key: value for key, value in self.state_dict().items() if not is_target_entry(key)}

    def load_policy_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Load a :meth:`state_dict` or a :meth:`policy_state_dict`; without target copies the targets are
        synced from the loaded online networks; cached bootstraps are dropped. Any other missing or unexpected
        key is an error."""
        result = self.load_state_dict(state, strict=False)
        missing = [key for key in result.missing_keys if not is_target_entry(key)]
        if missing or result.unexpected_keys:
            raise RuntimeError(f"{self.name} agent state does not fit: {len(missing)} missing keys (first "
                               f"{missing[:1]}), {len(result.unexpected_keys)} unexpected (first {result.unexpected_keys[:1]})")
        if result.missing_keys:
            self.sync_targets()
        self.drop_caches()

    def learning_rates(self) -> dict[str, float]:
        return {f"lr_{name}": opt.param_groups[0]["lr"] for name, opt in self.optimizers.items()}

    def training_state(self) -> dict[str, Any]:
        """Everything beside the weights that an exact resume needs."""
        return {
            "updates": self.updates,
            "optimizers": {name: opt.state_dict() for name, opt in self.optimizers.items()},
            "lr_schedulers": {name: sched.state_dict() for name, sched in self.lr_schedulers.items()},
        }

    def load_training_state(self, state: dict[str, Any]) -> None:
        self.updates = int(state["updates"])
        for name, opt in self.optimizers.items():
            opt.load_state_dict(state["optimizers"][name])
        for name, sched in self.lr_schedulers.items():
            sched.load_state_dict(state["lr_schedulers"][name])


class TargetNetworkAgent(Agent):
    """The trainer every agent is: one Adam optimiser and StepLR per trained network (``lr`` / ``weight_decay``
    dicts keyed by network name), the Q gradient clamp, :class:`~ldm_rl.objectives.TargetSync` of ``loss``'s
    target networks (weights and buffers) every ``target_update_interval`` updates, the planner's schedules
    following the update count, and the target updater's counter in :meth:`training_state`. A subclass
    builds its losses in ``update`` / ``pretrain_update`` and hands their sum to :meth:`_step`.

    ``networks``: name -> module of every network trained here (the optimisers' order).
    ``greedy_ema_decay``: when set (in (0, 1)), :attr:`greedy_policy` is a copy of the planner whose weights and
    BatchNorm statistics are an exponential moving average of the online ones over the updates
    (``torch.optim.swa_utils.AveragedModel``; its first update copies); training, exploration and the targets
    are unchanged. None: the greedy policy plays the online weights. ``greedy_ema_tail`` (in (0, 1], with a
    decay): the average spans at most that fraction of the updates so far — the n-th average uses
    ``min(decay, 1 − 1/max(1, tail·n))`` — so a long average (0.999: ≈ 1000 updates) does not carry the first,
    untrained weights into the early evaluations (:func:`tail_ema_multi_avg_fn`). ``greedy_ema_model=False``
    (agents that plan with a model): the average covers every network but the model, whose online weights the
    greedy policy plans with (the LDM averaged over ≈ 1000 updates predicted so badly that the greedy block
    stacking fell from 89 to 7 / 100 on one training)."""

    def __init__(
        self,
        planner: StatePolicy,
        loss: LossModule,
        networks: dict[str, nn.Module],
        *,
        lr: dict[str, float],
        weight_decay: dict[str, float] | None = None,
        lr_decay: float = 0.95,
        lr_decay_every: int = 2000,
        target_update_interval: int = 100,
        q_grad_clip: float | None = None,
        greedy_ema_decay: float | None = None,
        greedy_ema_tail: float | None = None,
        greedy_ema_model: bool = True,
    ) -> None:
        super().__init__()
        if target_update_interval < 1 or lr_decay_every < 1 or not 0 < lr_decay <= 1:
            raise ValueError(f"need target_update_interval >= 1, lr_decay_every >= 1, lr_decay in (0, 1]; got "
                             f"{target_update_interval}, {lr_decay_every}, {lr_decay}")
        self.planner, self.loss = planner, loss
        self.trained = dict(networks)  # a plain dict: the modules are registered through planner and loss
        weight_decay = weight_decay or {}
        for name, module in self.trained.items():
            if name not in lr or not lr[name] > 0:
                raise ValueError(f"lr.{name} must be a positive number, got {lr.get(name)!r}")
            self.optimizers[name] = make_adam(module.parameters(), lr=lr[name], weight_decay=weight_decay.get(name, 0.0))
            self.lr_schedulers[name] = torch.optim.lr_scheduler.StepLR(self.optimizers[name], lr_decay_every, lr_decay)
        self.q_grad_clip = q_grad_clip
        self.target_updater = TargetSync(loss, interval=target_update_interval)
        self.averaged_planner = None
        if greedy_ema_decay is not None:
            if isinstance(greedy_ema_decay, bool) or not isinstance(greedy_ema_decay, (int, float)) \
                    or not 0 < greedy_ema_decay < 1:
                raise ValueError(f"greedy_ema_decay must be a number in (0, 1) or None, got {greedy_ema_decay!r}")
            average = get_ema_multi_avg_fn(float(greedy_ema_decay)) if greedy_ema_tail is None \
                else tail_ema_multi_avg_fn(float(greedy_ema_decay), greedy_ema_tail)
            self.averaged_planner = AveragedModel(planner, multi_avg_fn=average, use_buffers=True)
            self.averaged_planner.requires_grad_(False)
        elif greedy_ema_tail is not None:
            raise ValueError(f"greedy_ema_tail={greedy_ema_tail!r} needs greedy_ema_decay (the longest average)")
        if not greedy_ema_model:
            if self.averaged_planner is None:
                raise ValueError("greedy_ema_model=False needs greedy_ema_decay (it leaves the model out of the average)")
            if not isinstance(getattr(planner, "dynamics", None), nn.Module):
                raise ValueError(f"greedy_ema_model=False: {type(planner).__name__} plans with no model (dynamics)")
        self.greedy_ema_model = bool(greedy_ema_model)

    @property
    def policy(self) -> StatePolicy:
        return self.planner

    @property
    def greedy_policy(self) -> StatePolicy:
        """The planner over the averaged weights once an update has been averaged (else the online planner),
        at the online planner's schedule step."""
        averaged = self.averaged_planner
        if averaged is None or int(averaged.n_averaged) == 0:
            return self.planner
        averaged.module.set_step(self.planner.step)
        return averaged.module

    def evaluation_policy(self, online_weights: bool = False) -> StatePolicy:
        """What an evaluation plays: :attr:`greedy_policy`, or with ``online_weights`` the online planner of an
        agent built with ``greedy_ema_decay`` (the same training played the other way; greedy under
        ``ExplorationType.DETERMINISTIC``). ValueError for ``online_weights`` without averaged weights."""
        if not online_weights:
            return self.greedy_policy
        if self.averaged_planner is None:
            raise ValueError("needs a run trained with agent.greedy_ema_decay; this agent has no averaged weights "
                             "(its greedy policy already plays the online ones)")
        return self.planner

    def _train_mode(self) -> None:
        for module in self.trained.values():
            module.train()

    def _step(self, total: torch.Tensor, *, count: bool = True) -> None:
        """Backward ``total``, clamp the Q gradients, step the optimisers; with ``count`` (an update, not a
        pretraining step) also the LR schedules, the target updater, the update count and the schedules."""
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)
        total.backward()
        if self.q_grad_clip and "q" in self.trained:
            grads = [p for p in self.trained["q"].parameters() if p.grad is not None]  # none in a model-only step
            if grads:
                torch.nn.utils.clip_grad_value_(grads, self.q_grad_clip)
        for name in self.trained:
            self.optimizers[name].step()
            if count:
                self.lr_schedulers[name].step()
        if count:
            self.target_updater.step()
            if self.averaged_planner is not None:
                self.averaged_planner.update_parameters(self.planner)
                if not self.greedy_ema_model:  # the greedy policy plans with the online model
                    self.averaged_planner.module.dynamics.load_state_dict(self.planner.dynamics.state_dict())
            self.updates += 1
            self.planner.set_step(self.updates)

    def training_state(self) -> dict:
        return {**super().training_state(), "target_updater_counter": self.target_updater.counter}

    def load_training_state(self, state: dict) -> None:
        super().load_training_state(state)
        self.target_updater.counter = int(state["target_updater_counter"])
        self.planner.set_step(self.updates)
