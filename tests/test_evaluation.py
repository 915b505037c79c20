"""ldm_rl.evaluation's per-episode counts, on hand-built rollouts."""

import pytest
import torch
from tensordict import TensorDict

from ldm_rl.evaluation import pick_counts


def rollout(holding: list[int], next_holding: list[int]) -> TensorDict:
    """A ``[T]`` rollout with only what :func:`pick_counts` reads: ``holding`` and ``("next", "holding")`` ``[T, 1] bool``."""
    steps = len(holding)
    as_bool = lambda values: torch.tensor(values, dtype=torch.bool).reshape(steps, 1)  # noqa: E731
    return TensorDict({"holding": as_bool(holding), "next": {"holding": as_bool(next_holding)}}, batch_size=[steps])


def test_pick_counts_counts_empty_hand_steps_and_those_that_held():
    # pick (held), place, pick (empty), pick (held), place, pick (held, episode ends holding)
    episode = rollout([0, 1, 0, 0, 1, 0], [1, 0, 0, 1, 0, 1])
    assert pick_counts(episode) == (4, 3)
    assert pick_counts(rollout([0, 0, 0], [0, 0, 0])) == (3, 0)  # three empty picks
    assert pick_counts(rollout([1], [0])) == (0, 0)  # a place alone is no pick


def test_pick_counts_refuses_what_is_not_one_episode_with_the_hand_state():
    with pytest.raises(ValueError, match=r"missing \[\('next', 'holding'\)\]"):
        pick_counts(TensorDict({"holding": torch.zeros(3, 1, dtype=torch.bool)}, batch_size=[3]))
    batched = torch.stack([rollout([0, 1], [1, 0]), rollout([0, 1], [1, 0])])  # [2, T]: two episodes
    with pytest.raises(ValueError, match=r"got batch shape \(2, 2\)"):
        pick_counts(batched)
