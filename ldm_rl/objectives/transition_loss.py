"""What every transition loss of the agents shares: its input keys (TorchRL ``_AcceptedKeys``) and ``in_keys``."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
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
    return_to_go: NestedKey = "return_to_go"
    index: NestedKey = "index"  # the replay's row index (a TorchRL replay sample's "index"): cache key


class TransitionLoss(LossModule):
    """Base of the agents' losses over flat batches of transitions: declares the keys and the inputs.

    ``in_keys`` = the state, the action, the next state, the reward and the termination flag.
    """

    _AcceptedKeys = TransitionKeys
    default_keys = TransitionKeys
    tensor_keys: TransitionKeys

    #: raise a target to the return the episode actually collected from the transition on (set by subclasses)
    return_lower_bound: bool = False

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def lower_bounded(self, target: torch.Tensor, tensordict: TensorDictBase, key=None) -> torch.Tensor:
        """``max(target, return_to_go)`` ``[B, 1]`` when ``return_lower_bound`` is on, else ``target``.

        ``return_to_go`` ``[B, 1]`` is ``Σ_k γ^k r_{t+k}`` of the transition's own episode (``-inf`` where the
        episode was truncated): written by :class:`~ldm_rl.data.FrameReplay` built with ``return_gamma = γ``.
        A return some policy collected is a lower bound of the optimal value, so the bootstrapped target
        cannot sink below what the agent (or the expert) actually reached (He et al. 2017, "optimality
        tightening"); it can still rise above it. ``key``: read the bound elsewhere, e.g. ``("next",
        "return_to_go")`` (the return from the *next* step on, for a value that excludes the arrival reward).
        """
        if not self.return_lower_bound:
            return target
        key = self.tensor_keys.return_to_go if key is None else key
        bound = tensordict.get(key, None)
        if bound is None:
            raise KeyError(f"{type(self).__name__}(return_lower_bound=True) needs {key!r} "
                           "in the batch: sample from FrameReplay(return_gamma=gamma)")
        return torch.maximum(target, bound.reshape(-1, 1).to(target))

    def check_batch(self, tensordict: TensorDictBase) -> None:
        """The input is a flat, non-empty batch of transitions with every in-key (one ``ValueError`` otherwise)."""
        keys.require_keys(tensordict, self.in_keys, type(self).__name__)
        if tensordict.batch_dims != 1 or tensordict.batch_size[0] == 0:
            raise ValueError(f"{type(self).__name__} needs a flat, non-empty batch of transitions, got batch_size "
                             f"{tuple(tensordict.batch_size)}")

    def importance_weights(self, tensordict: TensorDictBase, like: torch.Tensor) -> torch.Tensor:
        """``[B, 1]`` prioritized-replay importance weights (``priority_weight``), ones without them; as ``like``."""
        weight = tensordict.get(self.tensor_keys.priority_weight, None)
        return torch.ones_like(like) if weight is None else weight.reshape(-1, 1).to(like)

    @property
    def in_keys(self) -> list[NestedKey]:
        k = self.tensor_keys
        state = [k.heightmap, k.in_hand, k.holding]
        return [*state, k.action, *[(keys.NEXT, key) for key in state], k.reward, k.terminated]
