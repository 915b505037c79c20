"""Tests for ldm_rl.data.replay: the pure-torch PER fallback and the frame-sharing prioritized replay."""

from __future__ import annotations

import functools
import math
import time

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, PrioritizedSampler, TensorDictReplayBuffer
from torchrl.data.replay_buffers.samplers import prioritized as torchrl_prioritized

from ldm_rl.data import replay
from ldm_rl.data.replay import (
    FrameReplay,
    TensorMinTree,
    TensorSumTree,
    TorchPrioritizedSampler,
    cpp_segment_trees_available,
    make_prioritized_sampler,
)
from ldm_rl.geometry import classes_to_heights, heights_to_classes

MAX_H, K = 0.25, 21
SAMPLER_EPS = 1e-8


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------
def make_episode(ep_id: int, steps: int, *, seed: int = 0, expert: bool | None = None, end: str = "terminated"):
    """A trajectory whose frame f (0..steps) encodes (ep_id, f) in its pixels, action and reward.

    heightmap classes: [0,0,0] = ep_id % K, [0,0,1] = ep_id // K % K, [0,0,2] = f % K; in_hand [0,0,0] = f % K;
    holding = f odd; action of step t = (ep_id % 128, t, ep_id % 8); reward of step t = 100·ep_id + t.
    """
    gen = torch.Generator().manual_seed(1000 * seed + ep_id)
    frames = steps + 1
    f = torch.arange(frames)
    hm = torch.randint(0, K, (frames, 1, 128, 128), generator=gen, dtype=torch.uint8)
    hm[:, 0, 0, 0], hm[:, 0, 0, 1], hm[:, 0, 0, 2] = ep_id % K, ep_id // K % K, f % K
    hand = torch.randint(0, K, (frames, 1, 24, 24), generator=gen, dtype=torch.uint8)
    hand[:, 0, 0, 0] = f % K
    hm_m, hand_m = classes_to_heights(hm, MAX_H, K), classes_to_heights(hand, MAX_H, K)
    # a little sub-class noise: storage must round it back to the same classes
    hm_m = hm_m + (torch.rand(hm_m.shape, generator=gen) - 0.5) * (MAX_H / (K - 1)) * 0.5
    holding = (f % 2 == 1).unsqueeze(-1)
    t = torch.arange(steps)
    action = torch.stack([torch.full((steps,), ep_id % 128), t, torch.full((steps,), ep_id % 8)], -1)
    done = torch.zeros(steps, 1, dtype=torch.bool)
    done[-1] = True
    no = torch.zeros(steps, 1, dtype=torch.bool)
    td = TensorDict(
        {
            "heightmap": hm_m[:-1],
            "in_hand": hand_m[:-1],
            "holding": holding[:-1],
            "action": action,
            "next": {
                "heightmap": hm_m[1:],
                "in_hand": hand_m[1:],
                "holding": holding[1:],
                "reward": (100.0 * ep_id + t.float()).unsqueeze(-1),
                "terminated": done if end == "terminated" else no,
                "truncated": done if end == "truncated" else no,
                "done": done if end in ("terminated", "truncated") else no,
            },
        },
        batch_size=[steps],
    )
    if expert is not None:
        td["is_expert"] = torch.full((steps, 1), expert)
    return td


def decode_ids(heightmap_m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    c = heights_to_classes(heightmap_m, MAX_H, K).long()
    return c[:, 0, 0, 0] + K * c[:, 0, 0, 1], c[:, 0, 0, 2]


def make_buffer(capacity=64, seed=0, **kw) -> FrameReplay:
    return FrameReplay(capacity, max_height=MAX_H, num_classes=K, generator=torch.Generator().manual_seed(seed), **kw)


def stored(rb: FrameReplay) -> TensorDict:
    return rb.buffer.storage._storage[: rb.num_frames].clone()


def tree_values(rb: FrameReplay) -> torch.Tensor:
    return torch.as_tensor(rb.sampler._sum_tree[torch.arange(rb.capacity)]).clone()


@pytest.fixture
def fake_cpp_trees(monkeypatch):
    """Pretend torchrl's C++ trees loaded, using the tensor trees as their stand-ins (same API)."""
    monkeypatch.setattr(torchrl_prioritized, "SumSegmentTreeFp32", TensorSumTree)
    monkeypatch.setattr(torchrl_prioritized, "MinSegmentTreeFp32", TensorMinTree)
    monkeypatch.setattr(torchrl_prioritized, "SumSegmentTreeFp64", functools.partial(TensorSumTree, dtype=torch.float64))
    monkeypatch.setattr(torchrl_prioritized, "MinSegmentTreeFp64", functools.partial(TensorMinTree, dtype=torch.float64))


# --------------------------------------------------------------------------------------------
# 1. pure-torch segment trees and sampler
# --------------------------------------------------------------------------------------------
def test_sum_tree_matches_bruteforce_lower_bound():
    gen = torch.Generator().manual_seed(0)
    tree = TensorSumTree(50)
    values = torch.rand(50, generator=gen)
    values[[3, 4, 17, 40]] = 0.0
    tree[torch.arange(50)] = values
    prefix = torch.cumsum(values.double(), 0)
    masses = torch.cat([torch.rand(500, generator=gen).double() * float(prefix[-1]), prefix[:10], torch.zeros(1)])
    got = tree.scan_lower_bound(masses)
    want = torch.tensor([int((prefix >= m).nonzero()[0]) for m in masses.tolist()])
    assert torch.equal(got, want)
    assert tree.scan_lower_bound(float(prefix[-1]) * 1.01) == 50  # above the total: the tree's size
    assert isinstance(tree.scan_lower_bound(0.3), int)
    assert tree.query(0, 50) == pytest.approx(float(prefix[-1]), rel=1e-12)
    assert tree.query(10, 20) == pytest.approx(float(values[10:20].double().sum()), rel=1e-6)
    assert tree.query(5, 5) == 0.0


def test_trees_getitem_setitem_semantics():
    s, m = TensorSumTree(6), TensorMinTree(6)
    assert s[2] == 0.0 and m[2] == math.inf and m.query(0, 6) == math.inf  # identities
    idx = torch.tensor([1, 4, 1])  # duplicate: the last write wins, as with sequential C++ writes
    s[idx] = torch.tensor([5.0, 2.0, 3.0])
    m[idx] = torch.tensor([5.0, 2.0, 3.0])
    assert s[1] == 3.0 and isinstance(s[1], float)
    assert torch.equal(s[torch.tensor([[1, 4]])], torch.tensor([[3.0, 2.0]]))
    assert s.query(0, 6) == 5.0 and m.query(0, 6) == 2.0 and m.query(0, 2) == 3.0
    s[torch.arange(6)] = 1.5  # scalar broadcast
    assert s.query(0, 6) == 9.0
    with pytest.raises(ValueError):
        s[torch.arange(3)] = torch.ones(2)
    with pytest.raises(IndexError):
        s[6] = 1.0


def test_factory_prefers_cpp_trees_and_falls_back(monkeypatch, fake_cpp_trees):
    assert cpp_segment_trees_available()
    sampler = make_prioritized_sampler(16, alpha=0.6, beta=0.4)
    assert type(sampler) is PrioritizedSampler  # TorchRL's own class, running on the "C++" trees
    assert (sampler.alpha, sampler.beta) == (0.6, 0.4)
    monkeypatch.setattr(torchrl_prioritized, "MinSegmentTreeFp64", None)
    assert not cpp_segment_trees_available()
    fallback = make_prioritized_sampler(16, alpha=0.6, beta=0.4)
    assert type(fallback) is TorchPrioritizedSampler and isinstance(fallback, PrioritizedSampler)
    with pytest.raises(ValueError):
        make_prioritized_sampler(16, alpha=-1.0, beta=0.0)


def test_factory_on_this_install():
    # torchrl 0.14.1's extension does not load against torch 2.13 CPU: the stock class cannot even be built.
    if not cpp_segment_trees_available():
        with pytest.raises(RuntimeError, match="SumSegmentTreeFp32"):
            PrioritizedSampler(8, alpha=0.6, beta=0.4)
        assert type(make_prioritized_sampler(8, alpha=0.6, beta=0.4)) is TorchPrioritizedSampler
    else:
        assert type(make_prioritized_sampler(8, alpha=0.6, beta=0.4)) is PrioritizedSampler


def _td_buffer(sampler, seed=0):
    return TensorDictReplayBuffer(
        storage=LazyTensorStorage(8), sampler=sampler, priority_key="td_error",
        generator=torch.Generator().manual_seed(seed),
    )


def test_fallback_sampler_per_semantics_in_torchrl_buffer(tmp_path):
    alpha, beta = 0.7, 0.5
    prio = torch.tensor([0.1, 0.5, 1.0, 2.0, 3.0, 0.2, 4.0, 0.05])
    rb = _td_buffer(TorchPrioritizedSampler(8, alpha=alpha, beta=beta))
    rb.extend(TensorDict({"x": torch.arange(8), "td_error": prio}, [8]))
    p = (prio.double() + SAMPLER_EPS) ** alpha
    s = rb.sample(40_000)
    freq = torch.bincount(s["x"], minlength=8).double() / 40_000
    assert torch.allclose(freq, p / p.sum(), atol=0.01)
    want_w = (p[s["index"]] / p.min()) ** -beta
    torch.testing.assert_close(s["priority_weight"].double(), want_w, rtol=1e-5, atol=0)
    # update_tensordict_priority through TorchRL's buffer
    batch = rb.sample(4)
    batch["td_error"] = torch.full((4,), 7.0)
    rb.update_tensordict_priority(batch)
    assert torch.allclose(rb.sampler._sum_tree[batch["index"]].double(), torch.full((4,), (7.0 + SAMPLER_EPS) ** alpha, dtype=torch.float64))
    # alpha setter re-transforms the stored values
    before = torch.as_tensor(rb.sampler._sum_tree[torch.arange(8)]).double()
    rb.sampler.alpha = 0.3
    after = torch.as_tensor(rb.sampler._sum_tree[torch.arange(8)]).double()
    torch.testing.assert_close(after, before ** (0.3 / alpha), rtol=1e-5, atol=0)
    # dumps / loads: same trees, same next sample
    rb.dumps(tmp_path / "rb")
    other = _td_buffer(TorchPrioritizedSampler(8, alpha=0.9, beta=0.0), seed=123)
    other.loads(tmp_path / "rb")
    assert (other.sampler.alpha, other.sampler.beta) == (0.3, beta)
    assert torch.equal(other.sampler._sum_tree.values, rb.sampler._sum_tree.values)
    assert torch.equal(other.sampler._min_tree.values, rb.sampler._min_tree.values)
    a, b = rb.sample(16), other.sample(16)
    assert torch.equal(a["index"], b["index"]) and torch.equal(a["priority_weight"], b["priority_weight"])


# --------------------------------------------------------------------------------------------
# 2. FrameReplay
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs",
    [
        {"capacity_frames": 1},
        {"capacity_frames": 8.0},
        {"max_height": 0.0},
        {"max_height": float("nan")},
        {"num_classes": 1},
        {"num_classes": 300},
        {"batch_size": 0},
        {"alpha": -0.1},
        {"beta": -1.0},
        {"priority_eps": -1e-6},
        {"expert_bonus": float("inf")},
        {"generator": 3},
        {"scratch_dir": 5},
    ],
)
def test_constructor_validation(kwargs):
    args = {"capacity_frames": 16, "max_height": MAX_H, **kwargs}
    with pytest.raises(ValueError):
        FrameReplay(args.pop("capacity_frames"), **args)


def test_storage_layout_and_sampled_contract():
    rb = make_buffer(32)
    episode = make_episode(5, 3, expert=True)
    index = rb.extend_episode(episode)
    assert index.tolist() == [0, 1, 2, 3] and rb.num_frames == 4 and len(rb) == 3
    frames = stored(rb)
    dtypes = {k: frames[k].dtype for k in frames.keys()}
    assert dtypes == {
        "heightmap": torch.uint8, "in_hand": torch.uint8, "holding": torch.bool, "action": torch.int16,
        "reward": torch.float32, "terminated": torch.bool, "truncated": torch.bool, "is_expert": torch.bool,
        "is_last": torch.bool,
    }
    assert frames["is_last"].reshape(-1).tolist() == [False, False, False, True]
    s = rb.sample(64)
    assert s.batch_size == torch.Size([64])
    assert set(s.keys(True, True)) == {
        "heightmap", "in_hand", "holding", "action", "is_expert", "index", "priority_weight",
        ("next", "heightmap"), ("next", "in_hand"), ("next", "holding"), ("next", "reward"),
        ("next", "done"), ("next", "terminated"), ("next", "truncated"),
    }
    assert s["heightmap"].dtype == torch.float32 and s["heightmap"].shape == (64, 1, 128, 128)
    assert s["in_hand"].shape == (64, 1, 24, 24) and s["action"].dtype == torch.int64 and s["action"].shape == (64, 3)
    assert s["holding"].shape == (64, 1) and s["is_expert"].all() and s["priority_weight"].shape == (64,)
    t = s["index"]
    assert set(t.tolist()) == {0, 1, 2}  # all three transitions, never the last frame
    # decoded heights are exactly classes_to_heights(heights_to_classes(original))
    want = classes_to_heights(heights_to_classes(episode["heightmap"], MAX_H, K), MAX_H, K)
    want_next = classes_to_heights(heights_to_classes(episode["next", "heightmap"], MAX_H, K), MAX_H, K)
    assert torch.equal(s["heightmap"], want[t]) and torch.equal(s["next", "heightmap"], want_next[t])
    want_hand = classes_to_heights(heights_to_classes(episode["next", "in_hand"], MAX_H, K), MAX_H, K)
    assert torch.equal(s["next", "in_hand"], want_hand[t])
    assert torch.equal(s["action"], episode["action"][t]) and torch.equal(s["next", "reward"], episode["next", "reward"][t])
    assert torch.equal(s["next", "terminated"].reshape(-1), t == 2) and not s["next", "truncated"].any()
    assert torch.equal(s["next", "done"], s["next", "terminated"])
    assert torch.equal(s["holding"], episode["holding"][t]) and torch.equal(s["next", "holding"], episode["next", "holding"][t])


def test_truncated_and_unfinished_episodes_and_expert_flags():
    rb = make_buffer(32)
    rb.extend_episode(make_episode(1, 2, end="truncated"), expert=True)
    rb.extend_episode(make_episode(2, 2, end="none"))  # not finished (e.g. a rollout chunk)
    mixed = make_episode(3, 3)
    mixed["is_expert"] = torch.tensor([True, False, True])  # [T] accepted, per-step
    mixed["episode"] = torch.full((3,), 3)  # extra demo keys are ignored
    mixed["next", "primitive_success"] = torch.ones(3, 1, dtype=torch.bool)
    mixed.set_non_tensor("metadata", {"env_id": "x"})
    rb.extend_episode(mixed)
    assert len(rb) == 7 and rb.num_frames == 10
    s = rb.sample(256)
    ep, step = decode_ids(s["heightmap"])
    assert torch.equal(s["next", "truncated"].reshape(-1), (ep == 1) & (step == 1))
    assert not s["next", "done"][ep == 2].any()
    want_expert = (ep == 1) | ((ep == 3) & (step != 1))
    assert torch.equal(s["is_expert"].reshape(-1), want_expert)


def _bad_episodes():
    good = make_episode(0, 3)

    def edit(fn):
        td = good.clone()
        fn(td)
        return td

    def mid_done(td):
        td["next", "terminated"][1] = True
        td["next", "done"][1] = True

    def broken_chain(td):
        td["heightmap"][2, 0, 5, 5] = td["heightmap"][2, 0, 5, 5] + MAX_H / 2

    def nan(td):
        td["in_hand"][0, 0, 0, 0] = float("nan")

    return {
        "not a tensordict": {"heightmap": 1},
        "missing key": good.exclude(("next", "reward")),
        "wrong shape": edit(lambda td: td.set("heightmap", td["heightmap"][:, :, :64, :64].clone())),
        "float action": edit(lambda td: td.set("action", td["action"].float())),
        "int holding": edit(lambda td: td.set("holding", td["holding"].long())),
        "action out of range": edit(lambda td: td["action"].__setitem__((0, 0), 128)),
        "done mid-episode": edit(mid_done),
        "done != terminated|truncated": edit(lambda td: td["next", "done"].zero_()),
        "non-contiguous": edit(broken_chain),
        "nan heights": edit(nan),
        "inf reward": edit(lambda td: td["next", "reward"].__setitem__(0, float("inf"))),
        "bad is_expert": edit(lambda td: td.set("is_expert", torch.ones(3, 1))),
        "2-d batch": good.unsqueeze(0),
        "too long": make_episode(1, 40),
    }


def test_extend_episode_validates_everything_before_writing():
    rb = make_buffer(32)
    rb.extend_episode(make_episode(9, 2))
    before, priorities, cursor = stored(rb), tree_values(rb), rb.buffer.writer._cursor
    for name, bad in _bad_episodes().items():
        with pytest.raises(ValueError) as info:
            rb.extend_episode(bad)
        assert "\n" not in str(info.value), name
        assert rb.num_frames == 3 and rb.buffer.writer._cursor == cursor, name
    with pytest.raises(ValueError, match="contradicts"):
        rb.extend_episode(make_episode(2, 2, expert=True), expert=False)
    assert (stored(rb) == before).all() and torch.equal(tree_values(rb), priorities)


def test_round_robin_wraparound_keeps_true_next_states():
    rb = make_buffer(23, seed=1)
    gen = torch.Generator().manual_seed(7)
    live = {}
    for ep_id in range(150):
        steps = int(torch.randint(1, 7, (), generator=gen))
        rb.extend_episode(make_episode(ep_id, steps, seed=1))
        live[ep_id] = steps
        if ep_id % 5:
            continue
        s = rb.sample(48)
        ep, step = decode_ids(s["heightmap"])
        nep, nstep = decode_ids(s["next", "heightmap"])
        hand_step = heights_to_classes(s["next", "in_hand"], MAX_H, K)[:, 0, 0, 0].long()
        assert torch.equal(nep, ep) and torch.equal(nstep, step + 1) and torch.equal(hand_step, step + 1)
        assert torch.equal(s["action"][:, 0], ep % 128) and torch.equal(s["action"][:, 1], step)
        assert torch.equal(s["next", "reward"].reshape(-1), 100.0 * ep + step)
        assert torch.equal(s["next", "holding"].reshape(-1), (step + 1) % 2 == 1)
        steps_of = torch.tensor([live[int(e)] for e in ep])
        assert torch.equal(s["next", "terminated"].reshape(-1), step == steps_of - 1)
        assert int(ep.min()) >= ep_id - 23  # only recent episodes survive in 23 frames
    assert rb.num_frames == 23 and rb.buffer.writer._cursor != 0


def test_last_frames_are_redrawn_and_never_returned():
    # alpha = 0 makes every frame (last frames included) equally likely: many rows need a re-draw.
    rb = make_buffer(64, alpha=0.0)
    for ep_id in range(20):
        rb.extend_episode(make_episode(ep_id, 1))  # half of the frames are last frames
    s = rb.sample(1000)
    is_last = rb.buffer.storage._storage["is_last"].reshape(-1)
    assert not is_last[s["index"]].any()
    assert set(s["index"].tolist()) == set((~is_last[: rb.num_frames]).nonzero().reshape(-1).tolist())
    rb.max_redraws = 1
    with pytest.raises(RuntimeError, match="re-draws"):
        for _ in range(20):
            rb.sample(64)


def test_priorities_max_insert_expert_bonus_and_weights():
    alpha, beta = 0.6, 0.4
    rb = make_buffer(64, alpha=alpha, beta=beta)
    with pytest.raises(RuntimeError, match="no transitions"):
        rb.sample()
    rb.extend_episode(make_episode(0, 3), expert=True)  # frames 0..3
    rb.extend_episode(make_episode(1, 3), expert=False)  # frames 4..7
    assert rb.max_priority == 1.0
    want = torch.tensor([1.0, 1, 1, 0, 1, 1, 1, 0]).double()
    torch.testing.assert_close(tree_values(rb)[:8].double(), (want + SAMPLER_EPS) ** alpha)
    rb.update_priority(torch.tensor([0, 4, 5, 3]), torch.tensor([0.5, -2.5, 0.1, 9.0]))
    raw = torch.tensor([0.5 + 1e-6 + 1.0, 1.0, 1.0, 0.0, 2.5 + 1e-6, 0.1 + 1e-6, 1.0, 0.0]).double()
    torch.testing.assert_close(tree_values(rb)[:8].double(), (raw + SAMPLER_EPS) ** alpha, rtol=1e-6, atol=0)
    assert rb.max_priority == pytest.approx(2.5 + 1e-6)  # the last frame (index 3) stayed at 0
    rb.extend_episode(make_episode(2, 2))  # frames 8..10 enter at the max priority seen
    torch.testing.assert_close(tree_values(rb)[8:11].double(), (torch.tensor([2.5 + 1e-6, 2.5 + 1e-6, 0.0]).double() + SAMPLER_EPS) ** alpha)
    # importance weights: (p_i / p_min_batch) ** -beta, max 1 in the batch
    s = rb.sample(256)
    p = tree_values(rb).double()[s["index"]]
    torch.testing.assert_close(s["priority_weight"].double(), (p / p.min()) ** -beta, rtol=1e-5, atol=0)
    assert s["priority_weight"].max() == 1.0
    batch = rb.sample(4)
    batch["td_error"] = torch.zeros(4, 1)
    rb.update_tensordict_priority(batch)
    rb.beta = 1.0
    rb.alpha = 0.5
    assert (rb.beta, rb.alpha, rb.sampler.beta) == (1.0, 0.5, 1.0)
    for bad in (dict(index=torch.tensor([99]), td_error=torch.ones(1)), dict(index=torch.tensor([0, 1]), td_error=torch.ones(3)),
                dict(index=torch.tensor([0]), td_error=torch.tensor([float("nan")])), dict(index=torch.tensor([0.0]), td_error=torch.ones(1))):
        with pytest.raises(ValueError):
            rb.update_priority(**bad)
    with pytest.raises(ValueError):
        rb.beta = -0.5


def _assert_same_state(a: FrameReplay, b: FrameReplay):
    assert (len(a), a.num_frames, a.max_priority, a.alpha, a.beta) == (len(b), b.num_frames, b.max_priority, b.alpha, b.beta)
    assert (stored(a) == stored(b)).all()
    assert torch.equal(tree_values(a), tree_values(b))
    assert a.buffer.writer._cursor == b.buffer.writer._cursor


def test_dumps_loads_restores_identical_buffer(tmp_path):
    rb = make_buffer(30, seed=3, beta=0.3)
    for ep_id in range(12):
        rb.extend_episode(make_episode(ep_id, 1 + ep_id % 4), expert=ep_id % 3 == 0)
        s = rb.sample(8)
        rb.update_priority(s["index"], torch.randn(8, generator=torch.Generator().manual_seed(ep_id)))
    rb.sample(5)  # advance the generator past its initial state
    rb.dumps(tmp_path / "ckpt")
    rb.dumps(tmp_path / "ckpt")  # overwriting a checkpoint is fine (atomic replace)

    fresh = make_buffer(30, seed=99)
    fresh.loads(tmp_path / "ckpt")
    used = make_buffer(30, seed=5, alpha=0.2)  # loading over a buffer that already holds data
    for ep_id in range(4):
        used.extend_episode(make_episode(50 + ep_id, 3))
    used.update_priority(torch.tensor([0, 1]), torch.tensor([30.0, 40.0]))
    used.loads(tmp_path / "ckpt")
    memmap = make_buffer(30, seed=7, scratch_dir=tmp_path / "scratch")
    memmap.loads(tmp_path / "ckpt")
    for other in (fresh, used, memmap):
        _assert_same_state(rb, other)
    want = rb.sample(16)
    for other in (fresh, used, memmap):  # each draws the same next sample as rb did
        assert (other.sample(16) == want).all()
    # and the future stays in lock-step: same writes, same priorities, same samples
    for buf in (rb, fresh, memmap):
        buf.extend_episode(make_episode(77, 3))
        buf.update_priority(torch.tensor([2, 3]), torch.tensor([0.5, 5.0]))
    _assert_same_state(rb, fresh)
    _assert_same_state(rb, memmap)
    a, b, c = rb.sample(), fresh.sample(), memmap.sample()
    assert (a == b).all() and (a == c).all()
    with pytest.raises(ValueError, match="capacity_frames"):
        make_buffer(31).loads(tmp_path / "ckpt")
    with pytest.raises(ValueError, match="not a FrameReplay checkpoint"):
        make_buffer(30).loads(tmp_path)


def test_dumps_loads_empty_buffer(tmp_path):
    rb = make_buffer(16, seed=4, beta=0.7)
    rb.dumps(tmp_path / "empty")
    other = make_buffer(16, seed=8)
    other.extend_episode(make_episode(1, 2))
    other.loads(tmp_path / "empty")
    assert len(other) == 0 and other.num_frames == 0 and other.beta == 0.7
    for buf in (rb, other):
        buf.extend_episode(make_episode(2, 5))
    _assert_same_state(rb, other)
    assert (rb.sample() == other.sample()).all()


def test_memmap_storage_writes_files(tmp_path):
    rb = make_buffer(20, scratch_dir=tmp_path / "scratch")
    for ep_id in range(6):
        rb.extend_episode(make_episode(ep_id, 4))
    assert any((tmp_path / "scratch").rglob("*.memmap"))
    s = rb.sample(32)
    ep, step = decode_ids(s["heightmap"])
    nep, nstep = decode_ids(s["next", "heightmap"])
    assert torch.equal(ep, nep) and torch.equal(nstep, step + 1)
    # dumps from memmap frames; later writes must not leak into the checkpoint
    rb.dumps(tmp_path / "ckpt")
    ram = make_buffer(20, seed=5)
    ram.loads(tmp_path / "ckpt")
    _assert_same_state(rb, ram)
    for ep_id in range(6, 9):
        rb.extend_episode(make_episode(ep_id, 4))
    again = make_buffer(20, seed=6)
    again.loads(tmp_path / "ckpt")
    _assert_same_state(ram, again)
    assert (ram.sample() == again.sample()).all()


def test_cpp_sampler_path_runs_the_same_buffer(fake_cpp_trees):
    rb = make_buffer(32, seed=2)
    assert type(rb.sampler) is PrioritizedSampler
    for ep_id in range(6):
        rb.extend_episode(make_episode(ep_id, 3))
    s = rb.sample(16)
    rb.update_priority(s["index"], torch.rand(16))
    assert not rb.buffer.storage._storage["is_last"].reshape(-1)[rb.sample(64)["index"]].any()


def test_seeded_global_rng_fixes_the_sample_stream():
    def run():
        torch.manual_seed(11)
        rb = FrameReplay(32, max_height=MAX_H)
        for ep_id in range(4):
            rb.extend_episode(make_episode(ep_id, 3))
        return rb.sample(16)["index"]

    assert torch.equal(run(), run())


def test_bytes_per_transition_and_sample_time():
    report = {}
    for steps in (4, 8):
        rb = make_buffer(200)
        for ep_id in range(200 // (steps + 1)):
            rb.extend_episode(make_episode(ep_id, steps))
        report[steps] = rb.bytes_per_transition()
        assert report[steps] == pytest.approx(16_975 * (steps + 1) / steps)
    print(f"\nbytes per transition: 4-step {report[4]:.0f} B, 8-step {report[8]:.0f} B")
    assert report[8] <= 20_000
    rb.sample(32)
    start = time.perf_counter()
    for _ in range(20):
        rb.sample(32)
    ms = (time.perf_counter() - start) / 20 * 1e3
    print(f"sample(32): {ms:.2f} ms")
    assert ms < 100  # a few ms on the 2-core CI box; generous bound against load spikes
    assert replay.FrameReplay is FrameReplay


def test_return_to_go_is_the_discounted_return_of_terminated_episodes_only():
    rb = make_buffer(64, return_gamma=0.5)
    rb.extend_episode(make_episode(1, 3))  # rewards 100, 101, 102 at steps 0, 1, 2
    rb.extend_episode(make_episode(2, 2, end="truncated"))
    column = stored(rb)["return_to_go"].reshape(-1)
    expected = torch.tensor([100 + 0.5 * 101 + 0.25 * 102, 101 + 0.5 * 102, 102.0, -math.inf, -math.inf, -math.inf, -math.inf])
    assert torch.allclose(column[:7], expected)
    batch = rb.sample(64)
    ep, step = decode_ids(batch["heightmap"])
    for e, t, value, following in zip(ep.tolist(), step.tolist(), batch["return_to_go"].reshape(-1).tolist(),
                                      batch["next", "return_to_go"].reshape(-1).tolist()):
        assert value == pytest.approx(expected[t].item() if e == 1 else -math.inf)
        assert following == pytest.approx(expected[t + 1].item() if e == 1 else -math.inf)  # -inf after the last step


def test_buffer_without_return_gamma_has_no_return_column():
    rb = make_buffer(64)
    rb.extend_episode(make_episode(1, 3))
    assert "return_to_go" not in stored(rb).keys() and "return_to_go" not in rb.sample(4).keys()
    with pytest.raises(ValueError, match="return_gamma must be None or a discount in"):
        make_buffer(64, return_gamma=1.5)


def test_dumps_writes_only_the_stored_frames_and_checks_return_gamma(tmp_path):
    rb = make_buffer(10_000, return_gamma=0.9)
    for ep_id in range(3):
        rb.extend_episode(make_episode(ep_id, 4))
    rb.dumps(tmp_path / "ckpt")
    size = sum(f.stat().st_size for f in (tmp_path / "ckpt").rglob("*") if f.is_file())
    # 15 frames of ~17 KB plus the sampler's trees (8 bytes per slot): far from 10 000 frames (170 MB)
    assert size < 15 * 17_500 + 10_000 * 16 + 50_000, size
    again = make_buffer(10_000, seed=3, return_gamma=0.9)
    again.loads(tmp_path / "ckpt")
    _assert_same_state(rb, again)
    assert torch.equal(stored(rb)["return_to_go"], stored(again)["return_to_go"])
    with pytest.raises(ValueError, match="return_gamma=0.9 but this buffer has return_gamma=None"):
        make_buffer(10_000).loads(tmp_path / "ckpt")


def test_from_config_reads_the_run_config_composed_or_saved(tmp_path):
    """The replay of a composed train_policy config (the recipe's) and of the plain dict a checkpoint saves (the
    benchmarks') have the config's settings; ``in_ram`` keeps frames in RAM whatever ``replay.scratch_dir`` says."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    root = Path(__file__).resolve().parents[1]
    overrides = ["experiment=curves_bin_packing", "replay.capacity=500", "replay.batch_size=7", "replay.alpha=0.3",
                 "agent.return_lower_bound=true", "agent.gamma=0.8", f"replay.scratch_dir={tmp_path / 'frames'}"]
    with initialize_config_dir(config_dir=str(root / "conf"), version_base="1.3"):
        cfg = compose(config_name="train_policy", overrides=overrides)
    saved = {group: OmegaConf.to_container(cfg[group], resolve=True) for group in ("replay", "agent", "env", "model")}
    for config in (cfg, saved):
        built = FrameReplay.from_config(config)
        assert (built.capacity, built.batch_size, built.alpha, built.return_gamma) == (500, 7, 0.3, 0.8)
        assert built.max_height == float(cfg.env.max_height) and built.num_classes == int(cfg.model.num_depth_classes)
        assert built.expert_bonus == float(cfg.replay.expert_bonus) and built.scratch_dir == str(tmp_path / "frames")
        assert FrameReplay.from_config(config, in_ram=True).scratch_dir is None
    saved["agent"]["return_lower_bound"] = False
    assert FrameReplay.from_config(saved).return_gamma is None
