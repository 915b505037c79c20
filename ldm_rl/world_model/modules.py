"""TensorDict wrappers of the dynamics model (keys: ``ldm_rl.keys``)."""

from __future__ import annotations

from typing import Sequence

from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

from ldm_rl.keys import ACTION, FORESIGHT_KEYS, HEIGHTMAP, HOLDING, IN_HAND, NEXT_LOGITS, next_key
from ldm_rl.torch_utils import eval_mode
from ldm_rl.world_model.core import DynamicsModel

__all__ = ["DynamicsPredictor", "make_dynamics_module", "STATE_KEYS", "PREDICTED_KEYS", "NEXT_KEYS", "FORESIGHT_KEYS",
           "ROOT_KEYS"]

# the model's inputs: the state *and the action* (``ldm_rl.keys.STATE_KEYS`` is the state alone = ROOT_KEYS)
STATE_KEYS: tuple[NestedKey, ...] = (HEIGHTMAP, IN_HAND, HOLDING, ACTION)
# out_keys choices of make_dynamics_module:
#   PREDICTED_KEYS (default): beside the real transition, ("next", "pred_heightmap"|...) + next_logits: never clobbers
#   NEXT_KEYS: in place of the next state, ("next", "heightmap"|...) + next_logits: for imagined data only
#   ROOT_KEYS: over the state itself (the imagined env steps this way)
PREDICTED_KEYS: tuple[NestedKey, ...] = (*FORESIGHT_KEYS, NEXT_LOGITS)
NEXT_KEYS: tuple[NestedKey, ...] = (next_key(HEIGHTMAP), next_key(IN_HAND), next_key(HOLDING), NEXT_LOGITS)
ROOT_KEYS: tuple[NestedKey, ...] = (HEIGHTMAP, IN_HAND, HOLDING)


class DynamicsPredictor(nn.Module):
    """``(heightmap, in_hand, holding, action) -> (heightmap', in_hand', holding'[, logits])``.

    Adapts :meth:`DynamicsModel.predict` to a tuple-returning module for ``TensorDictModule``. Every
    prediction runs under ``ldm_rl.torch_utils.eval_mode(model)``: eval mode (BatchNorm uses and keeps its
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
    out_keys: Sequence[NestedKey] = PREDICTED_KEYS,
    in_keys: Sequence[NestedKey] = STATE_KEYS,
) -> TensorDictModule:
    """Wrap ``model`` as a TensorDictModule (predictions in eval mode, no gradients; see :class:`DynamicsPredictor`).

    ``in_keys``: (heightmap, in_hand, holding, action). ``out_keys``: 3 keys (heightmap', in_hand',
    holding') or 4 (+ frame logits ``[*B, K, S, S]``). The default, :data:`PREDICTED_KEYS`, writes
    ``("next", "pred_heightmap")``, ``("next", "pred_in_hand")``, ``("next", "pred_holding")`` and
    ``next_logits``: beside a real transition's ``("next", "heightmap")``, never over it (the keys the
    :class:`~ldm_rl.world_model.ForesightTransform` writes). :data:`NEXT_KEYS` writes the prediction as the
    next state (imagined data only); :data:`ROOT_KEYS` overwrites the state (the imagined env). A missing
    input key raises ``KeyError`` naming it; an empty batch raises ``ValueError``.
    """
    in_keys, out_keys = list(in_keys), list(out_keys)
    if len(in_keys) != 4 or len(out_keys) not in (3, 4):
        raise ValueError(f"need 4 in_keys and 3 or 4 out_keys, got {in_keys} -> {out_keys}")
    predictor = DynamicsPredictor(model, return_logits=len(out_keys) == 4)
    return TensorDictModule(predictor, in_keys=in_keys, out_keys=out_keys, strict=True)
