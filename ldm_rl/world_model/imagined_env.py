"""``LDMImaginedEnv``: a batch-free TorchRL env that steps with the dynamics model (Dyna / planners)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.data import Binary, Composite, MultiCategorical, Unbounded
from torchrl.envs.model_based import ModelBasedEnvBase

from ldm_rl.keys import DONE, HEIGHTMAP, HOLDING, IN_HAND, REWARD, TERMINATED, require_keys
from ldm_rl.world_model.core import HAND_SIZE, HEIGHTMAP_SIZE, DynamicsModel
from ldm_rl.world_model.modules import ROOT_KEYS, STATE_KEYS, make_dynamics_module

__all__ = ["LDMImaginedEnv"]


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

    Batch-free (``batch_size == ()``): ``reset(start_td)`` accepts any batch of start states (a
    TensorDict with heightmap, in_hand, holding) and ``rollout(n, policy, tensordict=start,
    auto_reset=False)`` runs them all. Rewards come from ``reward_module`` (a TensorDictModule reading the
    predicted next state at the root and writing ``reward`` [*B, 1]), else 0; episodes never end unless
    that module also writes ``done``/``terminated``. The dynamics model predicts in eval mode without
    gradients and keeps its own train/eval flags (``DynamicsPredictor``), so imagining during training
    leaves its BatchNorm running statistics untouched; ``reward_module`` runs as given.
    """

    def __init__(self, model: DynamicsModel, reward_module: TensorDictModuleBase | None = None, *, device="cpu") -> None:
        parts = [make_dynamics_module(model, out_keys=ROOT_KEYS, in_keys=STATE_KEYS)]
        if reward_module is not None:
            parts.append(reward_module)
        parts.append(_RewardAndDone())
        super().__init__(TensorDictSequential(*parts), device=device, batch_size=None)
        self.observation_spec = Composite(
            {
                HEIGHTMAP: Unbounded((1, HEIGHTMAP_SIZE, HEIGHTMAP_SIZE)),
                IN_HAND: Unbounded((1, HAND_SIZE, HAND_SIZE)),
                HOLDING: Binary(n=1, shape=(1,), dtype=torch.bool),
            }
        )
        # the state is also an input of reset/step, so wrappers (TransformedEnv) pass it through
        self.state_spec = self.observation_spec.clone()
        self.action_spec = MultiCategorical(nvec=[HEIGHTMAP_SIZE, HEIGHTMAP_SIZE, model.num_rotations], shape=(3,), dtype=torch.int64)
        self.reward_spec = Unbounded((1,))
        self.done_spec = Composite(
            {DONE: Binary(n=1, shape=(1,), dtype=torch.bool), TERMINATED: Binary(n=1, shape=(1,), dtype=torch.bool)}
        )
        self.model = model

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        if tensordict is None:
            raise ValueError(f"LDMImaginedEnv.reset needs a tensordict with the start state {list(ROOT_KEYS)}")
        require_keys(tensordict, ROOT_KEYS, "LDMImaginedEnv.reset (start state)")
        out = tensordict.select(*ROOT_KEYS).copy()
        holding = out.get(HOLDING)
        if holding.shape == out.batch_size:
            out.set(HOLDING, holding.unsqueeze(-1))
        out.set(HOLDING, out.get(HOLDING).bool())
        out.update(self.full_done_spec.zero(out.shape))
        return out
