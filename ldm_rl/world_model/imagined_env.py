"""``LDMImaginedEnv``: a TorchRL env that steps with the dynamics model (Dyna, planners, RandomPolicy, collectors),
and ``ImaginedReward``, a reward for it from a V CNN's reward head."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.data import Binary, Composite, MultiCategorical, Unbounded
from torchrl.envs.model_based import ModelBasedEnvBase

from ldm_rl.keys import DONE, HEIGHTMAP, HOLDING, IN_HAND, REWARD, TERMINATED, require_keys
from ldm_rl.torch_utils import eval_mode
from ldm_rl.world_model.core import HAND_SIZE, HEIGHTMAP_SIZE, DynamicsModel
from ldm_rl.world_model.modules import ROOT_KEYS, STATE_KEYS, make_dynamics_module

__all__ = ["LDMImaginedEnv", "ImaginedReward"]


class _RewardAndDone(TensorDictModuleBase):
    """Writes ``reward`` = 0 (unless a reward module already wrote one) and never-done flags, all [*B, 1]."""

    in_keys = [HEIGHTMAP]
    out_keys = [REWARD, DONE, TERMINATED]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = (*tensordict.batch_size, 1)
        device = tensordict.get(HEIGHTMAP).device
        if REWARD not in tensordict.keys():
            tensordict.set(REWARD, torch.zeros(shape, device=device))
        for key in (DONE, TERMINATED):
            if key not in tensordict.keys():
                tensordict.set(key, torch.zeros(shape, dtype=torch.bool, device=device))
        return tensordict


class LDMImaginedEnv(ModelBasedEnvBase):
    """Imagined transitions ``s' = f(s, a)`` with the keys of ``ldm_rl.keys``.

    Two ways to run it:

    * **batch-free** (default, ``batch_size == ()``, what TorchRL's planners need): ``reset(start)``
      accepts any batch ``[*B]`` of start states (a TensorDict with heightmap, in_hand, holding) and
      ``rollout(n, policy, tensordict=env.reset(start), auto_reset=False)`` runs them all; the policy must
      follow the input's batch (our planners, ``env.rand_action``).
    * **over a fixed batch of start states** (``start_states=td`` ``[*B]``): the env's ``batch_size`` is
      ``[*B]``, its specs are ``[*B, ...]``, and ``reset()`` with no argument restarts from ``td``, so
      ``env.rollout(n, RandomPolicy(env.action_spec))`` and a TorchRL ``Collector`` drive it as any env.
      ``batch_size=[*B]`` alone fixes the batch without default start states.

    Rewards come from ``reward_module`` (a TensorDictModule reading the predicted next state at the root
    and writing ``reward`` [*B, 1]), else 0; episodes never end unless that module also writes
    ``done``/``terminated``. The dynamics model predicts in eval mode without gradients and keeps its own
    train/eval flags (``DynamicsPredictor``), so imagining during training leaves its BatchNorm running
    statistics untouched; ``reward_module`` runs as given.
    """

    def __init__(
        self,
        model: DynamicsModel,
        reward_module: TensorDictModuleBase | None = None,
        *,
        start_states: TensorDictBase | None = None,
        batch_size=None,
        device="cpu",
    ) -> None:
        if start_states is not None:
            if not isinstance(start_states, TensorDictBase):
                raise ValueError(f"start_states must be a TensorDict with {list(ROOT_KEYS)}, got {type(start_states).__name__}")
            require_keys(start_states, ROOT_KEYS, "LDMImaginedEnv(start_states=...)")
            if batch_size is not None and torch.Size(batch_size) != start_states.batch_size:
                raise ValueError(f"batch_size {list(batch_size)} differs from the start_states' {list(start_states.batch_size)}")
            batch_size = start_states.batch_size
        batch = torch.Size(batch_size if batch_size is not None else ())
        if 0 in batch:
            raise ValueError(f"batch_size must not be empty, got {list(batch)}")
        parts = [make_dynamics_module(model, out_keys=ROOT_KEYS, in_keys=STATE_KEYS)]
        if reward_module is not None:
            parts.append(reward_module)
        parts.append(_RewardAndDone())
        super().__init__(TensorDictSequential(*parts), device=device, batch_size=batch)
        flag = Binary(n=1, shape=(*batch, 1), dtype=torch.bool)
        self.observation_spec = Composite(
            {
                HEIGHTMAP: Unbounded((*batch, 1, HEIGHTMAP_SIZE, HEIGHTMAP_SIZE)),
                IN_HAND: Unbounded((*batch, 1, HAND_SIZE, HAND_SIZE)),
                HOLDING: flag.clone(),
            },
            shape=batch,
        )
        # the state is also an input of reset/step, so wrappers (TransformedEnv) pass it through
        self.state_spec = self.observation_spec.clone()
        nvec = [HEIGHTMAP_SIZE, HEIGHTMAP_SIZE, model.num_rotations]
        self.action_spec = MultiCategorical(nvec=nvec, shape=(3,), dtype=torch.int64).expand(*batch, 3)
        self.reward_spec = Unbounded((*batch, 1))
        self.done_spec = Composite({DONE: flag.clone(), TERMINATED: flag.clone()}, shape=batch)
        self.model = model
        self.start_states = None if start_states is None else self._start(start_states, "start_states")

    def _start(self, tensordict: TensorDictBase, who: str) -> TensorDictBase:
        """The checked start state: heightmap, in_hand, holding ``[*B, 1]`` bool, on the env's device."""
        require_keys(tensordict, ROOT_KEYS, f"LDMImaginedEnv {who}")
        if self.batch_size and tensordict.batch_size != self.batch_size:
            raise ValueError(f"LDMImaginedEnv {who}: batch_size {list(tensordict.batch_size)} must equal the env's "
                             f"{list(self.batch_size)}")
        out = tensordict.select(*ROOT_KEYS).copy()
        holding = out.get(HOLDING)
        if holding.shape == out.batch_size:
            out.set(HOLDING, holding.unsqueeze(-1))
        out.set(HOLDING, out.get(HOLDING).bool())
        return out.to(self.device) if self.device is not None else out

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        if tensordict is not None and any(key in tensordict.keys() for key in ROOT_KEYS):
            out = self._start(tensordict, "reset (start state)")
        elif self.start_states is not None:
            out = self.start_states.clone()
        else:
            raise ValueError(f"LDMImaginedEnv.reset needs a tensordict with the start state {list(ROOT_KEYS)} (or build the "
                             "env with start_states=...)")
        out.update(self.full_done_spec.zero(out.shape[: out.batch_dims - len(self.batch_size)]))  # specs hold batch_size
        return out


class ImaginedReward(nn.Module):
    """``(heightmap, in_hand)`` of an imagined next state -> ``(reward, done, terminated)``, each ``[*B, 1]``:
    the reward head of ``value_network`` (eval mode, no gradients), terminal when ``reward > terminal_reward``."""

    def __init__(self, value_network: nn.Module, terminal_reward: float = 0.5) -> None:
        super().__init__()
        if not 0.0 < terminal_reward <= 1.0:
            raise ValueError(f"terminal_reward must be in (0, 1], got {terminal_reward!r}")
        self.value_network, self.terminal_reward = value_network, float(terminal_reward)

    def forward(self, heightmap: torch.Tensor, in_hand: torch.Tensor):
        with eval_mode(self.value_network):
            _, reward = self.value_network.value_and_reward(heightmap, in_hand)
        done = reward > self.terminal_reward
        return reward, done, done.clone()
