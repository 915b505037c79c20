"""The TensorDict policy base every planner stands on: batching over any ``[*B]``, schedules, greedy or not.

A planner implements :meth:`StatePolicy.decide` on a flat batch of states (and, where the env writes
``failed_picks`` (:class:`~ldm_rl.envs.memory.FailedPickMemory`), the actions to leave out); :meth:`StatePolicy.forward`
takes a TensorDict of any batch shape (unbatched, ``[B]``, ``[B1, B2]``, ...) — an ``env.rollout`` step or
a collector's batch — and writes the decision back in that shape. Whether to act greedily is read from
TorchRL's exploration type (:func:`is_greedy`); hyperparameters are floats or schedules ``step -> float``
(:mod:`ldm_rl.schedules`) evaluated at :attr:`StatePolicy.step`, which the training loop advances.
"""

from __future__ import annotations

from typing import Callable, Union

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, exploration_type

from ldm_rl import keys
from ldm_rl.schedules import Constant

__all__ = ["StatePolicy", "ScheduleLike", "as_schedule", "is_greedy"]

ScheduleLike = Union[float, Callable[[int], float]]
_GREEDY = (ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN)


def is_greedy() -> bool:
    """True under ``set_exploration_type(DETERMINISTIC | MODE | MEAN)``; False when exploring or unset."""
    return exploration_type() in _GREEDY


def as_schedule(value: ScheduleLike, name: str) -> Callable[[int], float]:
    """A float becomes a constant schedule; a callable is kept."""
    if callable(value):
        return value
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return Constant(float(value))
    raise ValueError(f"{name} must be a number or a schedule step -> float, got {value!r}")


class StatePolicy(TensorDictModuleBase):
    """A TensorDict policy over states (``heightmap``, ``in_hand``, ``holding``) of any batch shape:
    subclasses implement :meth:`decide` on a flat batch ``[B]``.

    ``schedules``: name -> float or ``step -> float``, evaluated at ``self.step`` (:meth:`set_step`)."""

    in_keys = [keys.HEIGHTMAP, keys.IN_HAND, keys.HOLDING]

    def __init__(self, **schedules: ScheduleLike) -> None:
        super().__init__()
        self.schedules = {name: as_schedule(value, name) for name, value in schedules.items()}
        self.step = 0

    def set_step(self, step: int) -> None:
        """Advance the schedules to training step ``step``."""
        if not isinstance(step, int) or step < 0:
            raise ValueError(f"step must be a non-negative int, got {step!r}")
        self.step = step

    def hyperparameters(self) -> dict[str, float]:
        """The schedules' current values."""
        return {name: float(schedule(self.step)) for name, schedule in self.schedules.items()}

    def decide(self, heightmap, in_hand, holding, *, greedy: bool, avoid=None, visited=None) -> dict[str, torch.Tensor]:
        """Flat states (``[B, 1, H, W]`` m, ``[B, 1, h, h]`` m, ``[B, 1]`` bool) -> name -> ``[B, ...]`` tensor.
        ``avoid``: ``[B, M, 3]`` int64 actions not to take (``-1`` rows: none) or None; ``visited``: ``[B, M, 1, H, W]``
        scenes seen with an empty hand this episode (``-1``: none; :class:`~ldm_rl.envs.memory.SceneMemory`) or None,
        read by the planners that rank predicted revisits last and ignored by the others."""
        raise NotImplementedError

    def check_input(self, tensordict: TensorDictBase) -> None:
        """Called before :meth:`decide` on the caller's TensorDict (default: the in-keys are present)."""
        keys.require_keys(tensordict, self.in_keys, type(self).__name__)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        self.check_input(tensordict)
        unbatched = tensordict.batch_dims == 0
        td = tensordict.unsqueeze(0) if unbatched else tensordict
        batch = td.batch_size
        flat = td.reshape(-1)
        holding = flat.get(keys.HOLDING).reshape(-1, 1).bool()
        avoid, visited = flat.get(keys.FAILED_PICKS, None), flat.get(keys.VISITED_SCENES, None)
        decision = self.decide(flat.get(keys.HEIGHTMAP), flat.get(keys.IN_HAND), holding, greedy=is_greedy(), avoid=avoid,
                               visited=visited)
        for name, value in decision.items():
            value = value.reshape(*batch, *value.shape[1:])
            tensordict.set(name, value.squeeze(0) if unbatched else value)
        return tensordict
