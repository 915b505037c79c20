"""TensorDict wrappers of the dynamics model (keys: ``ldm_rl.keys``)."""

from __future__ import annotations

from typing import Sequence

from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

from ldm_rl.keys import (
    ACTION, HEIGHTMAP, HOLDING, IN_HAND, NEXT_LOGITS, PRED_HEIGHTMAP, PRED_HOLDING, PRED_IN_HAND, next_key,
)
from ldm_rl.runtime import eval_mode
from ldm_rl.world_model.core import DynamicsModel

__all__ = ["DynamicsPredictor", "make_dynamics_module", "STATE_KEYS", "NEXT_KEYS", "FORESIGHT_KEYS", "ROOT_KEYS"]

# the model's inputs: the state *and the action* (``ldm_rl.keys.STATE_KEYS`` is the state alone = ROOT_KEYS)
STATE_KEYS: tuple[NestedKey, ...] = (HEIGHTMAP, IN_HAND, HOLDING, ACTION)
NEXT_KEYS: tuple[NestedKey, ...] = (next_key(HEIGHTMAP), next_key(IN_HAND), next_key(HOLDING), NEXT_LOGITS)
FORESIGHT_KEYS: tuple[NestedKey, ...] = (PRED_HEIGHTMAP, PRED_IN_HAND, PRED_HOLDING)
ROOT_KEYS: tuple[NestedKey, ...] = (HEIGHTMAP, IN_HAND, HOLDING)


class DynamicsPredictor(nn.Module):
    """``(heightmap, in_hand, holding, action) -> (heightmap', in_hand', holding'[, logits])``.

    Adapts :meth:`DynamicsModel.predict` to a tuple-returning module for ``TensorDictModule``. Every
    prediction runs under ``ldm_rl.runtime.eval_mode(model)``: eval mode (BatchNorm uses and keeps its
    running statistics) without gradients, and each submodule gets its train/eval flag back afterwards.
    """

    def __init__(self, model: DynamicsModel, *, return_logits: bool = True) -> None:
        super().__init__()
        self.model, self.return_logits = model, return_logits

    def forward(self, heightmap, in_hand, holding, action):
        with eval_mode(self.model):
            pred = self.model.predict(heightmap, in_hand, holding, action)
        return tuple(pred) if self.return_logits else tuple(pred)[:3]


def make_dynamics_module(
    model: DynamicsModel,
    out_keys: Sequence[NestedKey] = NEXT_KEYS,
    in_keys: Sequence[NestedKey] = STATE_KEYS,
) -> TensorDictModule:
    """Wrap ``model`` as a TensorDictModule (predictions in eval mode, no gradients; see :class:`DynamicsPredictor`).

    ``in_keys``: (heightmap, in_hand, holding, action). ``out_keys``: 3 keys (heightmap', in_hand',
    holding') or 4 (+ frame logits). Defaults write the predicted next state where a real transition
    keeps it, ``("next", ...)``, plus ``next_logits``; pass :data:`FORESIGHT_KEYS` for foresight keys
    beside a real transition or :data:`ROOT_KEYS` to overwrite the state (imagined env).
    """
    in_keys, out_keys = list(in_keys), list(out_keys)
    if len(in_keys) != 4 or len(out_keys) not in (3, 4):
        raise ValueError(f"need 4 in_keys and 3 or 4 out_keys, got {in_keys} -> {out_keys}")
    return TensorDictModule(DynamicsPredictor(model, return_logits=len(out_keys) == 4), in_keys=in_keys, out_keys=out_keys)
