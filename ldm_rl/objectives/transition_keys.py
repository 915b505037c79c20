"""The input keys every transition loss of the agents reads (TorchRL ``_AcceptedKeys`` convention)."""

from __future__ import annotations

from dataclasses import dataclass

from tensordict.utils import NestedKey

from ldm_rl import keys

__all__ = ["TransitionKeys"]


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
