"""What every transition loss of the agents shares: its input keys (TorchRL ``_AcceptedKeys``) and ``in_keys``."""

from __future__ import annotations

from dataclasses import dataclass

from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from ldm_rl import keys

__all__ = ["TransitionKeys", "TransitionLoss"]


@dataclass
class TransitionKeys:
    """State, action, reward, termination, and the replay's priority keys; change them with
    ``loss.set_keys(...)``. A loss that reads more subclasses it (``class _AcceptedKeys(TransitionKeys)``)."""

    heightmap: NestedKey = keys.HEIGHTMAP
    in_hand: NestedKey = keys.IN_HAND
    holding: NestedKey = keys.HOLDING
    action: NestedKey = keys.ACTION
    reward: NestedKey = (keys.NEXT, keys.REWARD)
    terminated: NestedKey = (keys.NEXT, keys.TERMINATED)
    priority: NestedKey = "td_error"
    priority_weight: NestedKey = "priority_weight"


class TransitionLoss(LossModule):
    """Base of the agents' losses over flat batches of transitions: declares the keys and the inputs.

    ``in_keys`` = the state, the action, the next state, the reward and the termination flag.
    """

    _AcceptedKeys = TransitionKeys
    default_keys = TransitionKeys
    tensor_keys: TransitionKeys

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        k = self.tensor_keys
        state = [k.heightmap, k.in_hand, k.holding]
        return [*state, k.action, *[(keys.NEXT, key) for key in state], k.reward, k.terminated]
