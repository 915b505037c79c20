"""FC-DQN: the Q FCN alone, acting on its Q map and trained with DQN targets (the paper's model-free baseline).

* Policy (:class:`QMapPolicy`): greedy ``argmax`` of the ``[R, 128, 128]`` Q map of the current primitive
  under ``ExplorationType.DETERMINISTIC`` (first index on ties, flat order ``rot·H·W + row·W + col``);
  while exploring, one draw from ``softmax(Q/τ)`` over the whole map, τ the LDM agent's proposal
  temperature schedule (``cfg.planner.tau``): the LDM agent's proposal distribution with N = 1 and no
  lookahead.
* Loss (:class:`SpatialDQNLoss`, a TorchRL ``LossModule`` in ``DQNLoss``'s style): Huber between
  ``Q(s, a)`` and ``y = r + γ·(1 − d)·max_{a'} Q⁻(s', a')``, weighted by the importance weights; writes
  ``td_error = |Q(s, a) − y|`` (the replay adds ε and the expert bonus). TorchRL's ``DQNLoss`` is not used:
  it evaluates the whole ``R·H·W`` map of ``s`` with gradients (R× the trunk passes of
  :meth:`~ldm_rl.models.q_fcn.QFCN.action_values`, which runs only the taken rotation) and squares the TD
  error.
* Agent (:class:`FCDQNAgent`): one Adam optimiser with StepLR, the Q gradient clamp and a
  :class:`~ldm_rl.objectives.TargetSync` every ``target_update_interval`` updates, as the LDM agent's Q.
"""

from __future__ import annotations


import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.objectives import LossModule

from ldm_rl import keys
from ldm_rl.objectives.target_sync import TargetSync
from ldm_rl.objectives.transition_loss import TransitionLoss
from ldm_rl.agents.base import Agent
from ldm_rl.planning.planner import ScheduleLike, as_schedule, is_greedy
from ldm_rl.planning.sampling import sample_candidates
from ldm_rl.runtime import eval_mode, make_adam

__all__ = ["StatePolicy", "QMapPolicy", "SpatialDQNLoss", "TargetNetworkAgent", "FCDQNAgent", "CHOSEN_ACTION_VALUE",
           "flat_to_action"]

CHOSEN_ACTION_VALUE = "chosen_action_value"  # [*B, 1] Q of the action taken (TorchRL's QValueActor key)


def flat_to_action(index: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Flat indices ``rot·H·W + row·W + col`` ``[B]`` -> actions ``[B, 3]`` int64 (row, col, rot)."""
    rot, rem = index.div(height * width, rounding_mode="floor"), index.remainder(height * width)
    return torch.stack((rem.div(width, rounding_mode="floor"), rem.remainder(width), rot), dim=-1)


class StatePolicy(TensorDictModuleBase):
    """A TensorDict policy over states (``heightmap``, ``in_hand``, ``holding``) of any batch shape
    (unbatched, ``[B]``, ``[B1, B2]``, ...): subclasses implement :meth:`decide` on a flat batch.

    Schedules (floats or ``step -> float``) are evaluated at ``self.step`` (:meth:`set_step`)."""

    in_keys = [keys.HEIGHTMAP, keys.IN_HAND, keys.HOLDING]

    def __init__(self, **schedules: ScheduleLike) -> None:
        super().__init__()
        self.schedules = {name: as_schedule(value, name) for name, value in schedules.items()}
        self.step = 0

    def set_step(self, step: int) -> None:
        """Advance the schedules to training step ``step``."""
        if not isinstance(step, int) or step < 0:
            raise ValueError(f"step must be a non-negative int, got {step!r}")
        self.step = step

    def hyperparameters(self) -> dict[str, float]:
        """The schedules' current values."""
        return {name: float(schedule(self.step)) for name, schedule in self.schedules.items()}

    def decide(self, heightmap, in_hand, holding, *, greedy: bool) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys.require_keys(tensordict, self.in_keys, type(self).__name__)
        unbatched = tensordict.batch_dims == 0
        td = tensordict.unsqueeze(0) if unbatched else tensordict
        batch = td.batch_size
        flat = td.reshape(-1)
        holding = flat.get(keys.HOLDING).reshape(-1, 1).bool()
        decision = self.decide(flat.get(keys.HEIGHTMAP), flat.get(keys.IN_HAND), holding, greedy=is_greedy())
        for name, value in decision.items():
            value = value.reshape(*batch, *value.shape[1:])
            tensordict.set(name, value.squeeze(0) if unbatched else value)
        return tensordict


class QMapPolicy(StatePolicy):
    """Acts on the Q map: argmax under DETERMINISTIC (or MODE/MEAN), one ``softmax(Q/τ)`` draw otherwise.

    Args:
        q_network: ``(heightmap, in_hand, holding) -> [B, R, H, W]``.
        tau: temperature in Q units (a float or a schedule of the update count).
        write_action_value: also write the ``[*B, R, H, W]`` map under ``action_value``.

    Writes ``action`` ``[*B, 3]``, ``chosen_action_value`` ``[*B, 1]`` and ``action_value``.
    """

    def __init__(self, q_network: nn.Module, *, tau: ScheduleLike = 0.1, write_action_value: bool = True) -> None:
        super().__init__(tau=tau)
        self.q_network, self.write_action_value = q_network, bool(write_action_value)
        self.out_keys = [keys.ACTION, CHOSEN_ACTION_VALUE] + ([keys.ACTION_VALUE] if write_action_value else [])

    def decide(self, heightmap, in_hand, holding, *, greedy: bool) -> dict[str, torch.Tensor]:
        with eval_mode(self.q_network):
            q_map = self.q_network(heightmap, in_hand, holding)
        flat = q_map.flatten(1)
        if greedy:
            index = flat.argmax(1)
            action = flat_to_action(index, *q_map.shape[-2:])
        else:  # one draw of softmax(Q/τ): sample_candidates with N = 1 (no inhibition is applied after the last draw)
            action = sample_candidates(q_map, 1, tau=self.hyperparameters()["tau"], beta=0.0, mode="softmax")[:, 0]
            index = (action[:, 2] * q_map.shape[-2] + action[:, 0]) * q_map.shape[-1] + action[:, 1]
        out = {keys.ACTION: action, CHOSEN_ACTION_VALUE: flat.gather(1, index[:, None])}
        if self.write_action_value:
            out[keys.ACTION_VALUE] = q_map
        return out


class SpatialDQNLoss(TransitionLoss):
    """DQN on a spatial Q map: ``Q(s, a) ← r + γ·(1 − terminated)·max_{a'} Q⁻(s', a')``.

    Args:
        q_network: ``(heightmap, in_hand, holding) -> [B, R, H, W]`` with ``action_values(..., action) -> [B]``.
        gamma: discount in [0, 1].
        return_lower_bound: raise ``y`` to the batch's ``return_to_go`` where it is higher
            (:meth:`~ldm_rl.objectives.TransitionLoss.lower_bounded`; not in the paper).

    The target network is ``target_q_network_params`` (TorchRL ``convert_to_functional``), synced by a
    target updater (:class:`~ldm_rl.objectives.TargetSync`); targets run in eval mode without gradients,
    terminal rows skip the target pass. Writes ``td_error`` ``[B]`` = ``|Q(s, a) − y|`` into the input. Losses are Huber,
    weighted by ``priority_weight`` when present.
    """


    q_network: nn.Module
    q_network_params: TensorDictParams
    target_q_network_params: TensorDictParams
    out_keys = ["loss_q", "q_target", CHOSEN_ACTION_VALUE, "td_error"]

    def __init__(self, q_network: nn.Module, *, gamma: float = 0.95, return_lower_bound: bool = False) -> None:
        super().__init__()
        self.return_lower_bound = bool(return_lower_bound)
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma!r}")
        self.convert_to_functional(q_network, "q_network", create_target_params=True)
        self.gamma = float(gamma)

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
            with self.target_q_network_params.to_module(self.q_network, preserve_module_state=False), \
                    eval_mode(self.q_network):
                q_next[rows] = self.q_network(*state, holding).flatten(1).amax(1, keepdim=True)
        return self.lower_bounded(reward + self.gamma * q_next, tensordict)

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        keys.require_keys(tensordict, self.in_keys, type(self).__name__)
        if tensordict.batch_dims != 1 or tensordict.batch_size[0] == 0:
            raise ValueError(f"{type(self).__name__} needs a flat, non-empty batch of transitions, got batch_size "
                             f"{tuple(tensordict.batch_size)}")
        k = self.tensor_keys
        target = self.targets(tensordict)
        weight = tensordict.get(k.priority_weight, None)
        weight = torch.ones_like(target) if weight is None else weight.reshape(-1, 1).to(target)
        state = [tensordict.get(key) for key in (k.heightmap, k.in_hand)]
        holding = tensordict.get(k.holding).reshape(-1, 1).bool()
        q_pred = self.q_network.action_values(*state, holding, tensordict.get(k.action)).reshape(-1, 1)
        td_error = (q_pred.detach() - target).abs().reshape(-1)
        tensordict.set(k.priority, td_error)
        return TensorDict(
            {
                "loss_q": (F.smooth_l1_loss(q_pred, target, reduction="none") * weight).mean(),
                "q_target": target.mean(),
                CHOSEN_ACTION_VALUE: q_pred.detach().mean(),
                "td_error": td_error.mean(),
            },
            batch_size=[],
        )


class TargetNetworkAgent(Agent):
    """What the baselines share: one Adam optimiser and StepLR per trained network (``lr`` /
    ``weight_decay`` dicts keyed by network name), the Q gradient clamp, :class:`~ldm_rl.objectives.TargetSync` of
    ``loss``'s target networks (weights and buffers) every ``target_update_interval`` updates, the planner's schedules
    following the update count, and the target updater's counter in :meth:`training_state`.

    ``networks``: name -> module of every network trained here (the optimisers' order)."""

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

    @property
    def policy(self) -> StatePolicy:
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
            self.updates += 1
            self.planner.set_step(self.updates)

    def training_state(self) -> dict:
        return {**super().training_state(), "target_updater_counter": self.target_updater.counter}

    def load_training_state(self, state: dict) -> None:
        super().load_training_state(state)
        self.target_updater.counter = int(state["target_updater_counter"])
        self.planner.set_step(self.updates)


class FCDQNAgent(TargetNetworkAgent):
    """The FC-DQN baseline: :class:`QMapPolicy` trained by :class:`SpatialDQNLoss`. ``lr`` /
    ``weight_decay``: dicts with a ``q`` entry (other entries are not used)."""

    name = "fcdqn"

    def __init__(self, policy: QMapPolicy, loss: SpatialDQNLoss, *, q_grad_clip: float | None = 1.0, **kwargs) -> None:
        super().__init__(policy, loss, {"q": policy.q_network}, q_grad_clip=q_grad_clip, **kwargs)

    def pretrain_update(self, batch: TensorDictBase) -> dict[str, float]:
        """Nothing to pretrain: FC-DQN has no model, and its Q network learns in :meth:`update` only, as
        the LDM agent's Q does (``schedule.pretrain_updates`` trains the LDM agent's model alone)."""
        return {}

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        self._train_mode()
        out = self.loss(batch)
        self._step(out["loss_q"])
        return {key: float(value.detach()) for key, value in out.items()}
