"""ldm_rl.evaluation's per-episode counts, on hand-built rollouts."""

import pytest
import torch
from tensordict import TensorDict

from ldm_rl.evaluation import pick_counts, undone_places


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


def scene(*cubes: tuple[int, int, int]) -> torch.Tensor:
    """A ``[1, 128, 128]`` heightmap (m) with 4 cm cubes of 13 × 13 px at (row, col), ``level`` cubes high each."""
    heightmap = torch.zeros(1, 128, 128)
    for row, col, level in cubes:
        heightmap[:, row:row + 13, col:col + 13] = 0.04 * level
    return heightmap


def played(frames: list[torch.Tensor], holding: list[int]) -> TensorDict:
    """The ``[T]`` rollout through the scenes ``frames`` (T + 1 of them), the hand at each step's start in
    ``holding`` (T + 1 values: the last one after the last step)."""
    steps = len(frames) - 1
    hand = torch.tensor(holding, dtype=torch.bool).reshape(-1, 1)
    maps = torch.stack(frames)
    return TensorDict({"heightmap": maps[:-1], "holding": hand[:-1],
                       "next": {"heightmap": maps[1:], "holding": hand[1:]}}, batch_size=[steps])


def test_undone_places_counts_a_block_put_back_where_its_pick_took_it():
    start, lifted = scene((20, 20, 1), (60, 60, 1)), scene((60, 60, 1))
    back, nudged, off = scene((20, 20, 1), (60, 60, 1)), scene((22, 21, 1), (60, 60, 1)), scene((26, 20, 1), (60, 60, 1))
    stacked, elsewhere = scene((60, 60, 2)), scene((90, 30, 1), (60, 60, 1))
    assert undone_places(played([start, lifted, back], [0, 1, 0])) == 1
    assert undone_places(played([start, lifted, nudged], [0, 1, 0])) == 1  # 2 px and 1 px off: still put back
    assert undone_places(played([start, lifted, off], [0, 1, 0])) == 0  # 6 px off: a move
    assert undone_places(played([start, lifted, stacked], [0, 1, 0])) == 0  # onto the other cube
    assert undone_places(played([start, lifted, elsewhere], [0, 1, 0])) == 0
    # a 2-cycle twice: pick, put back, pick, put back
    assert undone_places(played([start, lifted, back, lifted, back], [0, 1, 0, 1, 0])) == 2
    # an empty pick (nothing changed, the hand stays empty) is no pair; nor is a place without the pick before it
    assert undone_places(played([start, start, lifted, back], [0, 0, 1, 0])) == 1
    assert undone_places(played([lifted, back], [1, 0])) == 0
    with pytest.raises(ValueError, match=r"missing \['heightmap'"):
        undone_places(rollout([0, 1], [1, 0]))
