"""BootstrapCache: rows found by replay index only while their next state is the same, capacity, duplicates."""

from __future__ import annotations

import pytest
import torch

from ldm_rl.geometry import classes_to_heights
from ldm_rl.objectives import BootstrapCache

MAX_HEIGHT, CLASSES = 0.25, 21


def states(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    heightmap = classes_to_heights(torch.randint(0, CLASSES, (n, 1, 16, 16), generator=g), MAX_HEIGHT, CLASSES)
    in_hand = classes_to_heights(torch.randint(0, CLASSES, (n, 1, 4, 4), generator=g), MAX_HEIGHT, CLASSES)
    return heightmap, in_hand, torch.rand(n, generator=g) < 0.5


def test_found_only_under_the_same_index_and_next_state():
    cache = BootstrapCache(16, max_height=MAX_HEIGHT, num_classes=CLASSES)
    hm, hand, holding = states(4, 0)
    index = torch.tensor([3, 7, 9, 11])
    values = torch.arange(8.0).view(4, 2)
    cache.put(index, hm, hand, holding, {"v": values})
    slot, found = cache.lookup(torch.tensor([9, 3, 5]), hm[[2, 0, 1]], hand[[2, 0, 1]], holding[[2, 0, 1]])
    assert found.tolist() == [True, True, False] and slot[2] == -1
    assert not cache.lookup(torch.tensor([5, 6]), hm[:2], hand[:2], holding[:2])[1].any()  # no index known
    assert torch.equal(cache.get(slot[:2], "v"), values[[2, 0]])
    other_hm, other_hand, _ = states(1, 1)  # index 7 rewritten in the replay: another next state
    for probe in ((other_hm, hand[1:2], holding[1:2]), (hm[1:2], other_hand, holding[1:2]),
                  (hm[1:2], hand[1:2], ~holding[1:2])):
        assert not cache.lookup(torch.tensor([7]), *probe)[1].any()
    cache.put(torch.tensor([7]), other_hm, hand[1:2], holding[1:2], {"v": torch.tensor([[-1.0, -2.0]])})
    slot, found = cache.lookup(torch.tensor([7]), other_hm, hand[1:2], holding[1:2])
    assert found.all() and cache.get(slot, "v").tolist() == [[-1.0, -2.0]] and len(cache) == 4  # replaced in place
    cache.clear()
    assert len(cache) == 0 and not cache.lookup(index, hm, hand, holding)[1].any()


def test_capacity_duplicates_and_hit_rate():
    cache = BootstrapCache(3, max_height=MAX_HEIGHT, num_classes=CLASSES)
    hm, hand, holding = states(5, 2)
    index = torch.tensor([0, 1, 1, 2, 3])  # index 1 twice (same transition drawn twice): kept once
    cache.put(index, hm[[0, 1, 1, 2, 3]], hand[[0, 1, 1, 2, 3]], holding[[0, 1, 1, 2, 3]], {"v": torch.arange(5.0)})
    assert len(cache) == 3  # rows beyond the capacity are dropped
    slot, found = cache.lookup(index, hm[[0, 1, 1, 2, 3]], hand[[0, 1, 1, 2, 3]], holding[[0, 1, 1, 2, 3]])
    assert found.tolist() == [True, True, True, True, False]
    assert cache.get(slot[:4], "v").tolist() == [0.0, 1.0, 1.0, 3.0]
    assert cache.hit_rate == pytest.approx(4 / 5)


def test_heights_are_kept_as_exact_depth_classes():
    cache = BootstrapCache(8, max_height=MAX_HEIGHT, num_classes=CLASSES)
    hm, hand, holding = states(2, 3)
    classes = cache.classes(hm)
    assert classes.dtype == torch.uint8 and torch.equal(cache.heights(classes), hm)


def test_rows_must_agree():
    cache = BootstrapCache(8, max_height=MAX_HEIGHT, num_classes=CLASSES)
    hm, hand, holding = states(3, 4)
    with pytest.raises(ValueError, match="index must be an integer tensor"):
        cache.lookup(torch.arange(2), hm, hand, holding)
    with pytest.raises(ValueError, match="index must be an integer tensor"):
        cache.put(torch.arange(3.0), hm, hand, holding, {"v": torch.zeros(3)})
    assert len(cache) == 0


@pytest.mark.parametrize("kwargs, match", [({"capacity": 0}, "capacity must be a positive int"),
                                          ({"capacity": 4, "num_classes": 300}, "num_classes must be in")])
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        BootstrapCache(**{"max_height": MAX_HEIGHT, "num_classes": CLASSES, **kwargs})
