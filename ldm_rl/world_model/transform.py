"""``ForesightTransform``: the LDM's prediction of every real transition, written beside it.

On a ``TransformedEnv`` each step writes ``pred_heightmap``, ``pred_in_hand``, ``pred_holding`` into
the step's ``next`` data, i.e. the rollout holds ``("next", "pred_heightmap")`` beside
``("next", "heightmap")``; after ``step_mdp`` they also appear at the root, so ``reset`` writes zeros
("no prediction yet") under the same keys. On a replay buffer (``rb.append_transform(...)``) every
sampled transition gets the same ``("next", pred_*)`` entries. Predictions run under
``ldm_rl.torch_utils.eval_mode(model)`` (eval mode, no gradient; the model's train/eval flags are given back
afterwards, so foresight during training leaves the BatchNorm running statistics untouched), and
the ``eval()`` TorchRL applies to a transform when it joins an env or a replay buffer does not reach the
model (see :meth:`ForesightTransform.train`).
"""

from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Binary, Composite, Unbounded
from torchrl.envs.transforms import Transform

from ldm_rl.keys import NEXT, PRED_KEYS, require_keys
from ldm_rl.torch_utils import eval_mode
from ldm_rl.world_model.core import DynamicsModel
from ldm_rl.world_model.modules import STATE_KEYS

__all__ = ["ForesightTransform"]


class ForesightTransform(Transform):
    """Runs ``model.predict`` on (heightmap, in_hand, holding, action) and stores the next state under
    ``out_keys`` (default ``pred_heightmap``, ``pred_in_hand``, ``pred_holding``).

    The action read is the base-env action ``[*B, 3]`` (row, col, rot bin): TorchRL calls ``_step`` with
    the input after all inverse transforms, so place this transform where that holds.
    """

    def __init__(
        self,
        model: DynamicsModel,
        *,
        in_keys: Sequence[NestedKey] = STATE_KEYS,
        out_keys: Sequence[NestedKey] = PRED_KEYS,
    ) -> None:
        in_keys, out_keys = list(in_keys), list(out_keys)
        if len(in_keys) != 4 or len(out_keys) != 3:
            raise ValueError(f"need 4 in_keys (heightmap, in_hand, holding, action) and 3 out_keys, got {in_keys}, {out_keys}")
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        self.model = model

    def train(self, mode: bool = True) -> "ForesightTransform":
        """Set the transform's own train/eval flag but leave the model's flags as they are.

        TorchRL calls ``transform.eval()`` when a transform joins a ``TransformedEnv`` or a replay buffer
        (``append_transform``); ``nn.Module.eval`` would recurse into the shared model and silently switch
        the model being trained to eval mode. Predictions run in eval mode anyway (``_predict``).
        """
        flags = [(m, m.training) for m in self.model.modules()]
        super().train(mode)
        for m, training in flags:
            m.training = training
        return self

    def _predict(self, tensordict: TensorDictBase) -> dict:
        require_keys(tensordict, self.in_keys, "ForesightTransform")
        with eval_mode(self.model):
            pred = self.model.predict(*(tensordict.get(k) for k in self.in_keys))
        return dict(zip(self.out_keys, pred[:3]))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Replay-buffer path: add ``("next", pred_*)`` to a batch of transitions."""
        for key, value in self._predict(tensordict).items():
            tensordict.set((NEXT, key), value)
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.update(self._predict(tensordict))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        for source, key in zip(self.in_keys[:3], self.out_keys):
            value = tensordict_reset.get(source)
            if key == self.out_keys[2]:
                value = torch.zeros((*value.shape[: tensordict_reset.batch_dims], 1), dtype=torch.bool, device=value.device)
            tensordict_reset.set(key, torch.zeros_like(value))
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        heightmap_key, hand_key = self.in_keys[0], self.in_keys[1]
        batch = observation_spec.shape
        for source, key in ((heightmap_key, self.out_keys[0]), (hand_key, self.out_keys[1])):
            spec = observation_spec[source]
            observation_spec[key] = Unbounded(shape=spec.shape, dtype=spec.dtype, device=spec.device)
        observation_spec[self.out_keys[2]] = Binary(n=1, shape=(*batch, 1), dtype=torch.bool, device=observation_spec.device)
        return observation_spec
