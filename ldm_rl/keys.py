"""TensorDict key names shared by every module (one place), and one check for missing keys.

Root = the current state, ``("next", …)`` = the state after the action, as TorchRL does.

======================  ==============================================  =========================
key                     shape / dtype                                   meaning
======================  ==============================================  =========================
``heightmap``           ``[*B, 1, 128, 128]`` float32, metres           top-down heights
``in_hand``             ``[*B, 1, 24, 24]`` float32, metres             held object's image
``holding``             ``[*B, 1]`` bool                                hand holds an object
``action``              ``[*B, 3]`` int64 (row, col, rot bin)           the primitive's pose
``reward``              ``[*B, 1]`` float32                             (under ``"next"``)
``action_value``        ``[*B, R, 128, 128]`` float32                   Q map, current primitive
``state_value``         ``[*B, 1]`` float32                             V(s)
``chosen_action_value`` ``[*B, 1]`` float32                             Q(s, a) of the action taken
``candidate_actions``   ``[*B, N, 3]`` int64                            the planner's N proposals
``candidate_values``    ``[*B, N]`` float32                             V(f(s, a)) of each
``candidate_entropy``   ``[*B, N]`` float32, nats                       the LDM's uncertainty of each
``candidate_scores``    ``[*B, N]`` float32                             a tree planner's backed-up score
``failed_picks``        ``[*B, M, 3]`` int64, -1 = none                 picks that came up empty here
``visited_scenes``      ``[*B, M, 1, 128, 128]`` float32 m, -1 = none   scenes seen with an empty hand
``next_logits``         ``[*B, K, S, S]`` float32                       LDM frame logits
``pred_heightmap``      as ``heightmap`` (under ``"next"``)             the LDM's foresight of it
``pred_in_hand``        as ``in_hand`` (under ``"next"``)               the LDM's foresight of it
``pred_holding``        as ``holding`` (under ``"next"``)               the LDM's foresight of it
======================  ==============================================  =========================

The ``pred_*`` keys sit beside the real next state, ``("next", "pred_heightmap")`` next to
``("next", "heightmap")`` (:data:`FORESIGHT_KEYS`): every LDM wrapper writes there by default, so a
prediction never overwrites data. ``from ldm_rl import keys`` or ``from ldm_rl import HEIGHTMAP, ...``.
"""

from __future__ import annotations

from typing import Iterable

__all__ = [
    "HEIGHTMAP", "IN_HAND", "HOLDING", "ACTION", "REWARD", "DONE", "TERMINATED", "TRUNCATED", "NEXT",
    "ACTION_VALUE", "STATE_VALUE", "CHOSEN_ACTION_VALUE", "CANDIDATE_ACTIONS", "CANDIDATE_VALUES", "NEXT_LOGITS",
    "CANDIDATE_ENTROPY", "CANDIDATE_SCORES", "FAILED_PICKS", "VISITED_SCENES",
    "PRED_HEIGHTMAP", "PRED_IN_HAND", "PRED_HOLDING", "STATE_KEYS", "PRED_KEYS", "FORESIGHT_KEYS", "next_key",
    "require_keys",
]

HEIGHTMAP, IN_HAND, HOLDING, ACTION = "heightmap", "in_hand", "holding", "action"
REWARD, DONE, TERMINATED, TRUNCATED, NEXT = "reward", "done", "terminated", "truncated", "next"
ACTION_VALUE, STATE_VALUE = "action_value", "state_value"
CHOSEN_ACTION_VALUE = "chosen_action_value"  # TorchRL's QValueActor key
CANDIDATE_ACTIONS, CANDIDATE_VALUES, NEXT_LOGITS = "candidate_actions", "candidate_values", "next_logits"
CANDIDATE_ENTROPY, CANDIDATE_SCORES = "candidate_entropy", "candidate_scores"
FAILED_PICKS = "failed_picks"  # written by ldm_rl.envs.memory.FailedPickMemory, read by the Q-map policies
VISITED_SCENES = "visited_scenes"  # written by ldm_rl.envs.memory.SceneMemory, read by the LDM agent's planner
PRED_HEIGHTMAP, PRED_IN_HAND, PRED_HOLDING = "pred_heightmap", "pred_in_hand", "pred_holding"
STATE_KEYS = (HEIGHTMAP, IN_HAND, HOLDING)
PRED_KEYS = (PRED_HEIGHTMAP, PRED_IN_HAND, PRED_HOLDING)  # the foresight of STATE_KEYS, in the same order
FORESIGHT_KEYS = tuple((NEXT, key) for key in PRED_KEYS)  # where it is written: beside ("next", heightmap) ...


def next_key(key: str) -> tuple[str, str]:
    """``"heightmap" -> ("next", "heightmap")``."""
    return (NEXT, key)


def require_keys(tensordict, keys: Iterable, who: str) -> None:
    """Check the input of ``who`` (a module, loss or env) before any work; raises one ``ValueError``.

    It names every key of ``keys`` missing from ``tensordict`` (nested keys ok), or says the batch is
    empty (a ``batch_size`` with a 0 in it: nothing to compute on).
    """
    present = set(tensordict.keys(include_nested=True))
    missing = [key for key in keys if key not in present]
    if missing:
        raise ValueError(f"{who} input is missing keys {missing}; it has {sorted(map(str, present))}")
    if 0 in tuple(tensordict.batch_size):
        raise ValueError(f"{who} got an empty batch (batch_size {list(tensordict.batch_size)}): it needs at least one "
                         "sample")
