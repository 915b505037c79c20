"""The agent's prioritized replay buffer, on TorchRL, storing each observation frame once as uint8 classes.

Two pieces:

* :class:`TorchPrioritizedSampler` — TorchRL's :class:`~torchrl.data.PrioritizedSampler` with its C++
  sum/min segment trees replaced by tensor-backed ones (torchrl 0.14.1's extension does not load
  against the CPU torch we use, so the stock sampler fails with "SumSegmentTreeFp32 is not
  available"). :func:`make_prioritized_sampler` returns the stock sampler whenever the C++ trees
  exist and the fallback only when they are missing.
* :class:`FrameReplay` — prioritized transitions over shared frames. A trajectory of ``T`` steps is
  written as ``T + 1`` frames; frame ``t`` holds the state before step ``t`` (heights as uint8 depth
  classes) together with the transition taken from it (action, reward, terminated, truncated,
  is_expert), and the final frame (``is_last``) holds the last next-state and no transition. A
  transition's next state is simply the following frame (index ``+1`` modulo the capacity); TorchRL's
  round-robin writer keeps that true after any number of wrap-arounds, because every episode is
  written contiguously and the newest frame is always an ``is_last`` frame.

Stored frame (≈ 16.98 KB; 9 frames per 8-step episode ≈ 19.1 KB per transition):

====================  ======================  ==============================================
key                   shape / dtype           meaning
====================  ======================  ==============================================
``heightmap``         ``[1, 128, 128]`` uint8  depth classes of the state
``in_hand``           ``[1, 24, 24]`` uint8    depth classes of the in-hand image
``holding``           ``[1]`` bool             hand state
``action``            ``[3]`` int16            (row, col, rot) taken from this frame
``reward``            ``[1]`` float32          reward received on that step
``terminated``        ``[1]`` bool             the step ended the episode (MDP terminal)
``truncated``         ``[1]`` bool             the step ended the episode by a time limit
``is_expert``         ``[1]`` bool             the action came from the expert
``is_last``           ``[1]`` bool             final frame of its episode: no transition
====================  ======================  ==============================================

Priorities follow Hester et al. (DQfD): ``p = |δ| + priority_eps + expert_bonus · is_expert``, new
transitions get the largest priority seen so far (1.0 at first), the sampler stores
``(p + 1e-8) ** alpha`` and ``is_last`` frames get priority 0 (and are redrawn if still drawn).
"""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyMemmapStorage, LazyTensorStorage, PrioritizedSampler, ReplayBuffer, RoundRobinWriter
from torchrl.data.replay_buffers.samplers import prioritized as _torchrl_prioritized

from ldm_rl.geometry import HAND_SIZE, HEIGHTMAP_SIZE, classes_to_heights, heights_to_classes
from ldm_rl.keys import (
    ACTION,
    DONE,
    HEIGHTMAP,
    HOLDING,
    IN_HAND,
    NEXT,
    REWARD,
    TERMINATED,
    TRUNCATED,
)
from ldm_rl.run.outputs import atomic_path

__all__ = [
    "TensorSumTree",
    "TensorMinTree",
    "TorchPrioritizedSampler",
    "cpp_segment_trees_available",
    "make_prioritized_sampler",
    "FrameReplay",
    "IS_EXPERT",
    "IS_LAST",
]

IS_EXPERT, IS_LAST = "is_expert", "is_last"
_INDEX, _WEIGHT = "index", "priority_weight"
_CPP_TREES = ("SumSegmentTreeFp32", "MinSegmentTreeFp32", "SumSegmentTreeFp64", "MinSegmentTreeFp64")
_META_FILE = "frame_replay.json"
_EMPTY_RNG_FILE = "generator_state.pt"
_FORMAT = 2
RETURN_TO_GO = "return_to_go"
_FRAMES_DIR = "frames"


# --------------------------------------------------------------------------------------------
# Tensor-backed segment "trees" (same Python API as torchrl._torchrl.{Sum,Min}SegmentTreeFp32/64)
# --------------------------------------------------------------------------------------------
def _is_python_index(index) -> bool:
    return not torch.is_tensor(index) and hasattr(index, "__index__")


class _TensorTree:
    """A flat ``[capacity]`` tensor of leaf values with the segment-tree interface TorchRL calls.

    Every operation is O(capacity) tensor work instead of O(log capacity) tree walks, which is
    fast at replay sizes up to a few 10⁵ frames and keeps the code obviously correct.
    """

    identity: float = 0.0

    def __init__(self, capacity: int, dtype: torch.dtype = torch.float32, device=None):
        if not isinstance(capacity, int) or isinstance(capacity, bool) or capacity < 1:
            raise ValueError(f"capacity must be a positive int, got {capacity!r}")
        if dtype not in (torch.float32, torch.float64):
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self.capacity = capacity
        self.values = torch.full((capacity,), self.identity, dtype=dtype, device=device)

    @property
    def device(self) -> torch.device:
        return self.values.device

    @property
    def size(self) -> int:
        return self.capacity

    def __len__(self) -> int:
        return self.capacity

    def _flat_index(self, index) -> torch.Tensor:
        idx = torch.as_tensor(index, device=self.device)
        if idx.is_floating_point() or idx.dtype == torch.bool:
            raise IndexError(f"segment tree indices must be integers, got dtype {idx.dtype}")
        idx = idx.long().reshape(-1)
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= self.capacity):
            raise IndexError(f"segment tree index out of range [0, {self.capacity})")
        return idx

    def _python_index(self, index) -> int:
        i = index.__index__()
        if not 0 <= i < self.capacity:
            raise IndexError(f"segment tree index {i} out of range [0, {self.capacity})")
        return i

    def __getitem__(self, index):
        if _is_python_index(index):  # fast path: TorchRL's dumps/loads walk the leaves one by one
            return self.values[self._python_index(index)].item()
        shape = torch.as_tensor(index).shape
        return self.values[self._flat_index(index)].reshape(shape)

    def __setitem__(self, index, value) -> None:
        if _is_python_index(index) and isinstance(value, (int, float)):
            self.values[self._python_index(index)] = value
            self._changed()
            return
        idx = self._flat_index(index)
        val = torch.as_tensor(value, dtype=self.values.dtype, device=self.device)
        val = val.reshape(-1)
        if val.numel() == 1:
            val = val.expand(idx.numel())
        elif val.numel() != idx.numel():
            raise ValueError(f"cannot set {val.numel()} values at {idx.numel()} indices")
        if idx.numel() > 1:
            # Sequential semantics (the C++ tree assigns one index after the other): last write wins.
            uniq, inverse = torch.unique(idx, return_inverse=True)
            if uniq.numel() < idx.numel():
                order = torch.arange(idx.numel(), device=self.device)
                last = torch.full((uniq.numel(),), -1, dtype=torch.long, device=self.device)
                last.scatter_reduce_(0, inverse, order, reduce="amax")
                idx, val = uniq, val[last]
        self.values[idx] = val
        self._changed()

    def _changed(self) -> None:
        pass

    @staticmethod
    def _bounds(start, end) -> tuple[int, int, bool]:
        as_tensor = torch.is_tensor(start) or torch.is_tensor(end)
        return int(start), int(end), as_tensor

    def __deepcopy__(self, memo):
        other = type(self).__new__(type(self))
        other.capacity = self.capacity
        other.values = self.values.clone()
        return other

    def __repr__(self) -> str:
        return f"{type(self).__name__}(capacity={self.capacity}, dtype={self.values.dtype})"


class TensorSumTree(_TensorTree):
    """Sum "tree": ``query(l, r)`` = Σ values[l:r]; ``scan_lower_bound(m)`` = first i with Σ values[:i+1] ≥ m.

    Prefix sums are accumulated in float64 and cached until the next write, so ``query(0, n)`` and
    ``scan_lower_bound`` agree exactly: a mass drawn in ``[0, query(0, n))`` always lands below ``n``.
    A mass above the total returns ``capacity`` (as the C++ tree returns its size).
    """

    identity = 0.0

    def __init__(self, capacity: int, dtype: torch.dtype = torch.float32, device=None):
        super().__init__(capacity, dtype, device)
        self._prefix = None

    def _changed(self) -> None:
        self._prefix = None

    def prefix_sums(self) -> torch.Tensor:
        """``[capacity]`` float64 inclusive prefix sums (cached)."""
        if self._prefix is None:
            self._prefix = torch.cumsum(self.values, 0, dtype=torch.float64)
        return self._prefix

    def query(self, start, end):
        lo, hi, as_tensor = self._bounds(start, end)
        lo, hi = max(lo, 0), min(hi, self.capacity)
        if hi <= lo:
            total = torch.zeros((), dtype=torch.float64, device=self.device)
        elif lo == 0:
            total = self.prefix_sums()[hi - 1]
        else:
            total = self.values[lo:hi].sum(dtype=torch.float64)
        return total.to(self.values.dtype) if as_tensor else float(total)

    def scan_lower_bound(self, mass):
        scalar = _is_python_index(mass) or isinstance(mass, float)
        m = torch.as_tensor(mass, device=self.device).to(torch.float64)
        out = torch.searchsorted(self.prefix_sums(), m.reshape(-1), right=False).reshape(m.shape)
        return int(out) if scalar else out

    def __deepcopy__(self, memo):
        other = super().__deepcopy__(memo)
        other._prefix = None
        return other


class TensorMinTree(_TensorTree):
    """Min "tree": ``query(l, r)`` = min values[l:r] (``inf`` for an empty range; unwritten leaves are ``inf``)."""

    identity = math.inf

    def query(self, start, end):
        lo, hi, as_tensor = self._bounds(start, end)
        lo, hi = max(lo, 0), min(hi, self.capacity)
        if hi <= lo:
            low = torch.full((), math.inf, dtype=self.values.dtype, device=self.device)
        else:
            low = self.values[lo:hi].min()
        return low if as_tensor else float(low)


def _drop_extension_warning(record: logging.LogRecord) -> bool:
    return not str(record.msg).startswith("Failed to import torchrl C++ binaries")


class TorchPrioritizedSampler(PrioritizedSampler):
    """TorchRL's :class:`~torchrl.data.PrioritizedSampler` on pure-torch sum/min trees.

    Only ``_init`` (the tree construction) differs, so sampling, importance weights,
    ``update_priority``, ``update_tensordict_priority`` (it is a ``PrioritizedSampler``), the ``alpha``
    / ``beta`` setters, ``state_dict`` and ``dumps``/``loads`` (same on-disk format) behave as with the
    C++ trees. Prefer :func:`make_prioritized_sampler`, which uses the C++ trees when they load.
    """

    def __init__(self, *args, **kwargs) -> None:
        # The stock constructor logs TorchRL's "Failed to import torchrl C++ binaries ... prioritized
        # replay buffers may not work" warning on every construction; with these trees they do work.
        log = logging.getLogger("torchrl")
        log.addFilter(_drop_extension_warning)
        try:
            super().__init__(*args, **kwargs)
        finally:
            log.removeFilter(_drop_extension_warning)

    def _init(self) -> None:
        if self.dtype in (torch.float32, torch.float):
            dtype = torch.float32
        elif self.dtype in (torch.float64, torch.double):
            dtype = torch.float64
        else:
            raise NotImplementedError(f"dtype {self.dtype} not supported by {type(self).__name__}")
        self._sum_tree = TensorSumTree(self._max_capacity, dtype, self._device)
        self._min_tree = TensorMinTree(self._max_capacity, dtype, self._device)
        self._max_priority = None


def cpp_segment_trees_available() -> bool:
    """True when torchrl's C++ segment trees imported (the stock ``PrioritizedSampler`` works)."""
    return all(getattr(_torchrl_prioritized, name, None) is not None for name in _CPP_TREES)


def _check_number(name: str, value, *, low: float = 0.0, strict: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < low or (strict and value == low):
        bound = f"> {low}" if strict else f">= {low}"
        raise ValueError(f"{name} must be a finite number {bound}, got {value!r}")
    return float(value)


def _check_positive_int(name: str, value, minimum: int = 1) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")
    return value


def make_prioritized_sampler(capacity: int, *, alpha: float, beta: float, eps: float = 1e-8) -> PrioritizedSampler:
    """TorchRL's ``PrioritizedSampler`` when its C++ trees are available, else :class:`TorchPrioritizedSampler`."""
    _check_positive_int("capacity", capacity)
    alpha = _check_number("alpha", alpha)
    beta = _check_number("beta", beta)
    eps = _check_number("eps", eps, strict=True)
    cls = PrioritizedSampler if cpp_segment_trees_available() else TorchPrioritizedSampler
    return cls(capacity, alpha=alpha, beta=beta, eps=eps)


# --------------------------------------------------------------------------------------------
# FrameReplay
# --------------------------------------------------------------------------------------------
_ROOT_KEYS = (HEIGHTMAP, IN_HAND, HOLDING, ACTION)
_NEXT_KEYS = tuple((NEXT, key) for key in (HEIGHTMAP, IN_HAND, HOLDING, REWARD, TERMINATED, TRUNCATED))


class FrameReplay:
    """Prioritized replay of transitions stored as shared uint8 frames (TorchRL storage/writer/sampler).

    Args:
        capacity_frames: frames the storage holds (each episode of ``T`` steps takes ``T + 1``).
        max_height: metres mapped to the top depth class (``geometry.heights_to_classes``).
        num_classes: depth classes K (2..256).
        batch_size: default ``sample()`` size.
        alpha, beta: PER exponents (settable properties; anneal ``beta`` 0 → 1).
        priority_eps: added to ``|δ|`` in :meth:`update_priority`.
        expert_bonus: ε_d added to the priority of expert transitions (Hester et al.).
        scratch_dir: ``None`` keeps frames in RAM (``LazyTensorStorage``); a directory uses
            ``LazyMemmapStorage(scratch_dir=…)`` (files created on the first write; the directory
            must not already hold a buffer's files).
        generator: the ``torch.Generator`` that drives sampling; by default a fresh one seeded from
            the global torch RNG, so seeding torch before construction fixes the sample stream. Its
            state is checkpointed by :meth:`dumps`.
        max_redraws: rounds of re-drawing rows that hit an ``is_last`` frame before giving up.

    ``sample()`` returns a ``[B]`` TensorDict in the data contract of ``ldm_rl.keys`` / demos:
    ``heightmap``/``in_hand`` float32 metres, ``holding`` ``[B,1]`` bool, ``action`` ``[B,3]`` int64,
    ``is_expert`` ``[B,1]`` bool, ``("next", heightmap|in_hand|holding|reward|done|terminated|truncated)``,
    ``index`` ``[B]`` (frame index, for :meth:`update_priority`) and ``priority_weight`` ``[B]``
    (importance weights ``(p_i / p_min)^-β`` normalised by the batch max).
    """

    def __init__(
        self,
        capacity_frames: int,
        *,
        max_height: float,
        num_classes: int = 21,
        batch_size: int = 32,
        alpha: float = 0.6,
        beta: float = 0.0,
        priority_eps: float = 1e-6,
        expert_bonus: float = 1.0,
        scratch_dir: str | os.PathLike | None = None,
        generator: torch.Generator | None = None,
        max_redraws: int = 64,
        return_gamma: float | None = None,
    ):
        self.capacity = _check_positive_int("capacity_frames", capacity_frames, minimum=2)
        if not isinstance(num_classes, int) or isinstance(num_classes, bool) or not 2 <= num_classes <= 256:
            raise ValueError(f"num_classes must be an int in [2, 256] (stored as uint8), got {num_classes!r}")
        self.max_height = _check_number("max_height", max_height, strict=True)
        self.num_classes = num_classes
        self.batch_size = _check_positive_int("batch_size", batch_size)
        alpha = _check_number("alpha", alpha)
        beta = _check_number("beta", beta)
        self.priority_eps = _check_number("priority_eps", priority_eps)
        self.expert_bonus = _check_number("expert_bonus", expert_bonus)
        self.max_redraws = _check_positive_int("max_redraws", max_redraws)
        if return_gamma is not None and not (isinstance(return_gamma, (int, float)) and 0.0 <= return_gamma <= 1.0):
            raise ValueError(f"return_gamma must be None or a discount in [0, 1], got {return_gamma!r}")
        self.return_gamma = None if return_gamma is None else float(return_gamma)
        if generator is not None and not isinstance(generator, torch.Generator):
            raise ValueError(f"generator must be a torch.Generator or None, got {type(generator).__name__}")
        if scratch_dir is not None and not isinstance(scratch_dir, (str, os.PathLike)):
            raise ValueError(f"scratch_dir must be a directory path or None, got {scratch_dir!r}")
        if generator is None:
            generator = torch.Generator().manual_seed(int(torch.randint(0, 2**62, ())))
        self.scratch_dir = None if scratch_dir is None else str(scratch_dir)
        if self.scratch_dir is None:
            storage = LazyTensorStorage(self.capacity)
        else:
            storage = LazyMemmapStorage(self.capacity, scratch_dir=self.scratch_dir)
        self._rb = ReplayBuffer(
            storage=storage,
            sampler=make_prioritized_sampler(self.capacity, alpha=alpha, beta=beta),
            writer=RoundRobinWriter(),
            batch_size=self.batch_size,
            generator=generator,
        )
        # class -> metres lookup table: bit-identical to classes_to_heights, ~5x faster to apply.
        self._heights = classes_to_heights(torch.arange(num_classes, dtype=torch.uint8), self.max_height, num_classes)
        self._max_priority = 1.0

    @classmethod
    def from_config(cls, cfg, *, in_ram: bool = False) -> "FrameReplay":
        """The replay a ``train_policy`` run uses, from its whole config (the composed ``DictConfig`` or the
        plain dict a checkpoint holds): sizes and PER settings from ``replay``, ``max_height`` from ``env``, the
        depth classes from ``model``, ``return_gamma`` = ``agent.gamma`` where ``agent.return_lower_bound`` is on.
        Frames live in ``replay.scratch_dir`` where set, unless ``in_ram`` (a copy read beside the run's own)."""
        replay, agent = cfg["replay"], cfg["agent"]
        return cls(int(replay["capacity"]), max_height=float(cfg["env"]["max_height"]),
                   num_classes=int(cfg["model"]["num_depth_classes"]),
                   return_gamma=float(agent["gamma"]) if agent.get("return_lower_bound") else None,
                   batch_size=int(replay["batch_size"]), alpha=float(replay["alpha"]),
                   priority_eps=float(replay["priority_eps"]), expert_bonus=float(replay["expert_bonus"]),
                   scratch_dir=None if in_ram else replay.get("scratch_dir"))

    # ---------------------------------------------------------------- properties
    @property
    def buffer(self) -> ReplayBuffer:
        """The underlying TorchRL ``ReplayBuffer`` (frames, round-robin writer, prioritized sampler)."""
        return self._rb

    @property
    def sampler(self) -> PrioritizedSampler:
        return self._rb.sampler

    @property
    def generator(self) -> torch.Generator:
        """The generator that drives sampling (replaced by :meth:`loads`)."""
        return self._rb._rng

    @property
    def alpha(self) -> float:
        return self.sampler.alpha

    @alpha.setter
    def alpha(self, value: float) -> None:
        self.sampler.alpha = _check_number("alpha", value)

    @property
    def beta(self) -> float:
        return self.sampler.beta

    @beta.setter
    def beta(self, value: float) -> None:
        self.sampler.beta = _check_number("beta", value)

    @property
    def max_priority(self) -> float:
        """Largest raw priority seen so far (1.0 before any update): new transitions get it."""
        return self._max_priority

    @property
    def num_frames(self) -> int:
        """Frames currently stored (``≤ capacity``)."""
        return len(self._rb.storage)

    def __len__(self) -> int:
        """Sampleable transitions: stored frames that are not an episode's last frame."""
        n = self.num_frames
        if n == 0:
            return 0
        return n - int(self._column(IS_LAST)[:n].sum())

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(transitions={len(self)}, frames={self.num_frames}/{self.capacity}, "
            f"alpha={self.alpha}, beta={self.beta}, storage={type(self._rb.storage).__name__})"
        )

    def _column(self, key: str) -> torch.Tensor:
        """The whole stored column ``key`` (``[capacity, …]``, the storage's own tensor, no copy)."""
        return self._rb.storage._storage.get(key)

    def bytes_per_transition(self) -> float:
        """Bytes of stored frame tensors per sampleable transition (``inf`` when there is none).

        Counts every tensor in the storage; the sampler's trees add 8 bytes per frame (two float32
        leaves, plus an 8-byte float64 prefix-sum cache with the pure-torch fallback).
        """
        n = len(self)
        if n == 0:
            return math.inf
        per_frame = sum(
            leaf[0].numel() * leaf.element_size()
            for leaf in self._rb.storage._storage.values(include_nested=True, leaves_only=True)
        )
        return per_frame * self.num_frames / n

    # ---------------------------------------------------------------- writing
    def extend_episode(self, episode: TensorDictBase, *, expert: bool | None = None) -> torch.Tensor:
        """Write one trajectory ``[T]`` as ``T + 1`` frames; return their frame indices ``[T + 1]``.

        ``episode`` has the demo/rollout keys: ``heightmap`` ``[T,1,128,128]``, ``in_hand``
        ``[T,1,24,24]`` (float metres), ``holding`` ``[T,1]`` bool, ``action`` ``[T,3]`` int, and
        ``("next", heightmap|in_hand|holding|reward|terminated|truncated)`` (``("next","done")``
        optional, checked if present); ``("next", …)`` of step t must equal the root of step t+1 and
        only the last step may be done. ``is_expert`` ``[T]``/``[T,1]`` bool is optional; ``expert``
        sets it for the whole episode. Everything is validated before anything is written.
        """
        frames = self._episode_to_frames(episode, expert)
        index = self._rb.extend(frames)
        priority = torch.full((frames.batch_size[0],), self._max_priority, dtype=torch.float64)
        priority[-1] = 0.0
        self._rb.update_priority(index, priority)
        return index

    def _episode_to_frames(self, episode, expert) -> TensorDict:
        if not isinstance(episode, TensorDictBase):
            raise ValueError(f"episode must be a TensorDict, got {type(episode).__name__}")
        if episode.batch_dims != 1 or episode.batch_size[0] < 1:
            raise ValueError(f"episode must have batch size [T] with T >= 1, got {list(episode.batch_size)}")
        steps = episode.batch_size[0]
        if steps + 1 > self.capacity:
            raise ValueError(
                f"an episode of {steps} steps needs {steps + 1} frames, more than capacity_frames={self.capacity}"
            )
        present = set(episode.keys(include_nested=True, leaves_only=True))
        missing = [key for key in (*_ROOT_KEYS, *_NEXT_KEYS) if key not in present]
        if missing:
            raise ValueError(f"episode is missing keys {missing}")

        def get(key, shape, kind):
            value = episode.get(key)
            if not torch.is_tensor(value) or tuple(value.shape) != (steps, *shape):
                got = tuple(value.shape) if torch.is_tensor(value) else type(value).__name__
                raise ValueError(f"episode[{key!r}] must have shape {(steps, *shape)}, got {got}")
            bad = {
                "float": not value.is_floating_point(),
                "bool": value.dtype != torch.bool,
                "int": value.is_floating_point() or value.is_complex() or value.dtype == torch.bool,
            }[kind]
            if bad:
                raise ValueError(f"episode[{key!r}] must have a {kind} dtype, got {value.dtype}")
            return value.detach().cpu()

        hm_shape, hand_shape = (1, HEIGHTMAP_SIZE, HEIGHTMAP_SIZE), (1, HAND_SIZE, HAND_SIZE)
        heightmap = get(HEIGHTMAP, hm_shape, "float")
        in_hand = get(IN_HAND, hand_shape, "float")
        holding = get(HOLDING, (1,), "bool")
        action = get(ACTION, (3,), "int")
        next_heightmap = get((NEXT, HEIGHTMAP), hm_shape, "float")
        next_in_hand = get((NEXT, IN_HAND), hand_shape, "float")
        next_holding = get((NEXT, HOLDING), (1,), "bool")
        reward = get((NEXT, REWARD), (1,), "float")
        terminated = get((NEXT, TERMINATED), (1,), "bool")
        truncated = get((NEXT, TRUNCATED), (1,), "bool")
        done = terminated | truncated
        if (NEXT, DONE) in present and not torch.equal(get((NEXT, DONE), (1,), "bool"), done):
            raise ValueError("episode[('next', 'done')] must equal terminated | truncated")
        if done[:-1].any():
            step = int(done[:-1].reshape(-1).nonzero()[0])
            raise ValueError(f"only the last step of an episode may be done, but step {step} of {steps} is")
        if not torch.isfinite(reward).all():
            raise ValueError("episode[('next', 'reward')] must be finite")
        if action.numel():
            pix, rot = action[:, :2], action[:, 2]
            if int(pix.min()) < 0 or int(pix.max()) >= HEIGHTMAP_SIZE or int(rot.min()) < 0 or int(rot.max()) > 32767:
                raise ValueError(
                    f"episode['action'] must hold (row, col) in [0, {HEIGHTMAP_SIZE}) and rot in [0, 32767], "
                    f"got values in [{int(action.min())}, {int(action.max())}]"
                )
        is_expert = self._expert_flags(episode, expert, steps)

        def classes(heights, key):
            try:
                return heights_to_classes(heights, self.max_height, self.num_classes)
            except ValueError as err:
                raise ValueError(f"episode[{key!r}]: {err}") from None

        hm_c, next_hm_c = classes(heightmap, HEIGHTMAP), classes(next_heightmap, (NEXT, HEIGHTMAP))
        hand_c, next_hand_c = classes(in_hand, IN_HAND), classes(next_in_hand, (NEXT, IN_HAND))
        for name, nxt, cur in (
            (HEIGHTMAP, next_hm_c, hm_c), (IN_HAND, next_hand_c, hand_c), (HOLDING, next_holding, holding)
        ):
            same = (nxt[:-1] == cur[1:]).flatten(1).all(-1)
            if not same.all():
                step = int((~same).nonzero()[0])
                raise ValueError(
                    f"episode is not one contiguous trajectory: ('next', {name!r})[{step}] != {name!r}[{step + 1}]"
                )

        def with_last(values, last):
            return torch.cat([values, last.unsqueeze(0).to(values.dtype)])

        n = steps + 1
        frames = TensorDict(
            {
                HEIGHTMAP: with_last(hm_c, next_hm_c[-1]),
                IN_HAND: with_last(hand_c, next_hand_c[-1]),
                HOLDING: with_last(holding, next_holding[-1]),
                ACTION: torch.cat([action.to(torch.int16), torch.zeros(1, 3, dtype=torch.int16)]),
                REWARD: torch.cat([reward.to(torch.float32), torch.zeros(1, 1)]),
                TERMINATED: torch.cat([terminated, torch.zeros(1, 1, dtype=torch.bool)]),
                TRUNCATED: torch.cat([truncated, torch.zeros(1, 1, dtype=torch.bool)]),
                IS_EXPERT: torch.cat([is_expert, torch.zeros(1, 1, dtype=torch.bool)]),
                IS_LAST: (torch.arange(n) == steps).unsqueeze(-1),
            },
            batch_size=[n],
        )
        if self.return_gamma is not None:
            frames.set(RETURN_TO_GO, torch.cat([self._returns_to_go(reward, bool(terminated[-1])), torch.full((1, 1), -math.inf)]))
        return frames

    def _returns_to_go(self, reward: torch.Tensor, terminated: bool) -> torch.Tensor:
        """``[T, 1]`` float32: ``Σ_k γ^k r_{t+k}`` per step of a terminated episode, ``-inf`` for a truncated one."""
        if not terminated:
            return torch.full_like(reward, -math.inf, dtype=torch.float32)
        steps = reward.shape[0]
        exponent = torch.arange(steps, dtype=torch.float64)
        # returns[t] = Σ_{j ≥ t} γ^(j − t) r_j, as one triangular matrix product (episodes are short)
        powers = (exponent.unsqueeze(0) - exponent.unsqueeze(1)).clamp(min=0)
        discount = torch.where(exponent.unsqueeze(0) >= exponent.unsqueeze(1), self.return_gamma ** powers, 0.0)
        return (discount @ reward.double().reshape(steps, 1)).float()

    @staticmethod
    def _expert_flags(episode, expert, steps) -> torch.Tensor:
        flags = None
        if IS_EXPERT in episode.keys():
            flags = episode.get(IS_EXPERT)
            shape_ok = torch.is_tensor(flags) and flags.numel() == steps and flags.shape[0] == steps
            if not shape_ok or flags.dtype != torch.bool:
                raise ValueError(f"episode['is_expert'] must be a bool tensor of shape [T] or [T, 1] with T={steps}")
            flags = flags.detach().cpu().reshape(steps, 1)
        if expert is not None:
            if not isinstance(expert, bool):
                raise ValueError(f"expert must be a bool or None, got {expert!r}")
            if flags is not None and not bool((flags == expert).all()):
                raise ValueError(f"expert={expert} contradicts episode['is_expert']")
            flags = torch.full((steps, 1), expert)
        return flags if flags is not None else torch.zeros(steps, 1, dtype=torch.bool)

    # ---------------------------------------------------------------- sampling
    def sample(self, batch_size: int | None = None) -> TensorDict:
        """Draw ``B`` transitions by priority (never an ``is_last`` frame); see the class docstring."""
        size = self.batch_size if batch_size is None else _check_positive_int("batch_size", batch_size)
        if len(self) == 0:
            raise RuntimeError("cannot sample: the replay buffer holds no transitions yet")
        storage, sampler = self._rb.storage, self.sampler
        index, info = sampler.sample(storage, size)
        index = torch.as_tensor(index, dtype=torch.long).reshape(-1).clone()
        weight = torch.as_tensor(info[_WEIGHT], dtype=torch.float64).reshape(-1).clone()
        is_last = self._column(IS_LAST).reshape(-1)
        bad = is_last[index].nonzero().reshape(-1)
        for _ in range(self.max_redraws):
            if bad.numel() == 0:
                break
            redrawn, info = sampler.sample(storage, bad.numel())
            index[bad] = torch.as_tensor(redrawn, dtype=torch.long).reshape(-1)
            weight[bad] = torch.as_tensor(info[_WEIGHT], dtype=torch.float64).reshape(-1)
            bad = bad[is_last[index[bad]]]
        if bad.numel():
            raise RuntimeError(
                f"{bad.numel()} of {size} rows still drew an episode's last frame after {self.max_redraws} "
                "re-draws; transition priorities are too small next to the last frames' (alpha=0?)"
            )
        frames = storage.get(torch.cat([index, (index + 1) % self.capacity]))
        current, following = frames[:size], frames[size:]
        heightmap = self._decode(frames.get(HEIGHTMAP))
        in_hand = self._decode(frames.get(IN_HAND))
        terminated, truncated = current.get(TERMINATED), current.get(TRUNCATED)
        return TensorDict(
            {
                HEIGHTMAP: heightmap[:size],
                IN_HAND: in_hand[:size],
                HOLDING: current.get(HOLDING),
                ACTION: current.get(ACTION).long(),
                IS_EXPERT: current.get(IS_EXPERT),
                NEXT: {
                    HEIGHTMAP: heightmap[size:],
                    IN_HAND: in_hand[size:],
                    HOLDING: following.get(HOLDING),
                    REWARD: current.get(REWARD),
                    DONE: terminated | truncated,
                    TERMINATED: terminated,
                    TRUNCATED: truncated,
                    **({RETURN_TO_GO: following.get(RETURN_TO_GO)} if self.return_gamma is not None else {}),
                },
                _INDEX: index,
                _WEIGHT: (weight / weight.max()).to(torch.float32),
                **({RETURN_TO_GO: current.get(RETURN_TO_GO)} if self.return_gamma is not None else {}),
            },
            batch_size=[size],
        )

    def _decode(self, classes: torch.Tensor) -> torch.Tensor:
        return torch.take(self._heights, classes.long())

    # ---------------------------------------------------------------- priorities
    def update_priority(self, index: torch.Tensor, td_error: torch.Tensor) -> None:
        """Set ``p = |td_error| + priority_eps + expert_bonus · is_expert`` at frame ``index`` ``[B]``.

        ``td_error`` is ``[B]`` or ``[B, 1]``. Indices of ``is_last`` frames (e.g. a slot overwritten
        since it was sampled) keep priority 0.
        """
        index = torch.as_tensor(index)
        if index.is_floating_point() or index.dtype == torch.bool:
            raise ValueError(f"index must be an integer tensor of frame indices, got dtype {index.dtype}")
        index = index.detach().cpu().long().reshape(-1)
        td_error = torch.as_tensor(td_error).detach().cpu().to(torch.float64).reshape(-1)
        if td_error.numel() != index.numel():
            raise ValueError(f"td_error has {td_error.numel()} values for {index.numel()} indices")
        if index.numel() == 0:
            return
        if int(index.min()) < 0 or int(index.max()) >= self.num_frames:
            raise ValueError(
                f"index must lie in [0, {self.num_frames}), got values in [{int(index.min())}, {int(index.max())}]"
            )
        if not torch.isfinite(td_error).all():
            raise ValueError("td_error must be finite")
        is_expert = self._column(IS_EXPERT).reshape(-1)[index]
        is_last = self._column(IS_LAST).reshape(-1)[index]
        priority = td_error.abs() + self.priority_eps + self.expert_bonus * is_expert.to(torch.float64)
        priority = torch.where(is_last, torch.zeros_like(priority), priority)
        if not bool(is_last.all()):
            self._max_priority = max(self._max_priority, float(priority[~is_last].max()))
        self._rb.update_priority(index, priority)

    def update_tensordict_priority(self, batch: TensorDictBase, key: str = "td_error") -> None:
        """:meth:`update_priority` with ``batch["index"]`` and ``batch[key]``."""
        self.update_priority(batch.get(_INDEX), batch.get(key))

    # ---------------------------------------------------------------- checkpoints
    def _metadata(self) -> dict:
        return {
            "format": _FORMAT,
            "capacity_frames": self.capacity,
            "max_height": self.max_height,
            "num_classes": self.num_classes,
            "return_gamma": self.return_gamma,
            "max_priority": self._max_priority,
            "num_frames": self.num_frames,
            "num_transitions": len(self),
        }

    def dumps(self, path: str | os.PathLike) -> Path:
        """Write the buffer (frames, priorities, writer cursor, generator, max priority) to directory ``path``.

        Only the stored frames are written (TorchRL's own ``dumps`` writes the whole preallocated
        storage: 1.6 GB for 1 000 transitions in a 100 000-frame buffer). Atomic: ``path`` is replaced
        only once everything is written.
        """
        path = Path(path)
        with atomic_path(path) as tmp:
            tmp.mkdir()
            if self.num_frames:
                self._rb.storage._storage[: self.num_frames].memmap(tmp / _FRAMES_DIR, copy_existing=True)
                self._rb.sampler.dumps(tmp / "sampler")
                self._rb.writer.dumps(tmp / "writer")
            state = {"rng_state": self.generator.get_state(), "alpha": self.alpha, "beta": self.beta}
            torch.save(state, tmp / _EMPTY_RNG_FILE)
            (tmp / _META_FILE).write_text(json.dumps(self._metadata(), indent=2))
        return path

    def loads(self, path: str | os.PathLike) -> None:
        """Restore a buffer written by :meth:`dumps` (same capacity, max_height and num_classes)."""
        path = Path(path)
        meta_file = path / _META_FILE
        if not meta_file.is_file():
            raise ValueError(f"{str(path)!r} is not a FrameReplay checkpoint (no {_META_FILE})")
        meta = json.loads(meta_file.read_text())
        if meta.get("format") != _FORMAT:
            raise ValueError(f"unsupported FrameReplay checkpoint format {meta.get('format')!r} (expected {_FORMAT})")
        ours = self._metadata()
        for key in ("capacity_frames", "max_height", "num_classes", "return_gamma"):
            if meta[key] != ours[key]:
                raise ValueError(f"checkpoint has {key}={meta[key]!r} but this buffer has {key}={ours[key]!r}")
        # Start from a clean sampler/writer state (TorchRL's sampler.loads cannot overwrite a live max priority).
        self._rb.empty()
        if meta["num_frames"]:
            frames = TensorDict.load_memmap(path / _FRAMES_DIR).to_tensordict()
            self._rb.storage.set(torch.arange(meta["num_frames"]), frames)
            self._rb.sampler.loads(path / "sampler")
            self._rb.writer.loads(path / "writer")
        state = torch.load(path / _EMPTY_RNG_FILE)
        generator = torch.Generator()
        generator.set_state(state["rng_state"])
        self._rb.set_rng(generator)
        self.alpha, self.beta = state["alpha"], state["beta"]
        self._max_priority = float(meta["max_priority"])
