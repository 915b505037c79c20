"""Scalar schedules ``schedule(step: int) -> float`` for temperatures, inhibition sizes, learning rates...

Plain frozen dataclasses: picklable, comparable, readable ``repr``, and Hydra-instantiable, e.g.::

    temperature:
      _target_: ldm_rl.schedules.Linear
      start: 1.0
      end: 0.1
      steps: 10000

``step`` is any non-negative integer (python/numpy int or 0-d integer tensor); a negative or
non-integer step raises ValueError. Every schedule returns a python float. Nothing here imports torch.

The reference code's inhibition-pen decay (``[max(rot − 1, 0), max(pos − 2, 2)]`` every 500 trainer
steps, notes §5) is :class:`StepLinear`; the paper's "× 0.95 every 2000 steps" is :class:`StepDecay`.
"""

from __future__ import annotations

import math
import numbers
import operator
from dataclasses import dataclass

__all__ = ["Constant", "Linear", "StepDecay", "StepLinear", "Exponential"]


def _number(cls: str, name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ValueError(f"{cls}.{name} must be a finite number, got {value!r}")
    return float(value)


def _count(cls: str, name: str, value) -> int:
    """A positive int; integral floats (``2e3`` from a YAML file) are accepted."""
    if isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value):
        if float(value).is_integer() and value >= 1:
            return int(value)
    raise ValueError(f"{cls}.{name} must be a positive integer number of steps, got {value!r}")


def _step(step) -> int:
    try:
        if isinstance(step, bool):
            raise TypeError
        step = operator.index(step)
    except TypeError:
        raise ValueError(f"step must be a non-negative int, got {step!r}") from None
    if step < 0:
        raise ValueError(f"step must be a non-negative int, got {step}")
    return step


def _set(obj, **values) -> None:
    for name, value in values.items():
        object.__setattr__(obj, name, value)


@dataclass(frozen=True)
class Constant:
    """``value`` at every step."""

    value: float

    def __post_init__(self):
        _set(self, value=_number("Constant", "value", self.value))

    def __call__(self, step) -> float:
        _step(step)
        return self.value


@dataclass(frozen=True)
class Linear:
    """``start`` at step 0, linear to ``end`` at step ``steps`` (≥ 1), then ``end``."""

    start: float
    end: float
    steps: int

    def __post_init__(self):
        _set(
            self,
            start=_number("Linear", "start", self.start),
            end=_number("Linear", "end", self.end),
            steps=_count("Linear", "steps", self.steps),
        )

    def __call__(self, step) -> float:
        step = _step(step)
        if step >= self.steps:
            return self.end
        t = step / self.steps
        return (1.0 - t) * self.start + t * self.end


@dataclass(frozen=True)
class StepDecay:
    """``start · factor^(step // every)``, floored at ``minimum`` (None: no floor); ``0 < factor ≤ 1``."""

    start: float
    factor: float
    every: int
    minimum: float | None = None

    def __post_init__(self):
        start = _number("StepDecay", "start", self.start)
        factor = _number("StepDecay", "factor", self.factor)
        if not 0 < factor <= 1:
            raise ValueError(f"StepDecay.factor must lie in (0, 1], got {self.factor!r}")
        minimum = None if self.minimum is None else _number("StepDecay", "minimum", self.minimum)
        if minimum is not None and minimum > start:
            raise ValueError(f"StepDecay.minimum must be <= start={start}, got {minimum}")
        _set(self, start=start, factor=factor, every=_count("StepDecay", "every", self.every), minimum=minimum)

    def __call__(self, step) -> float:
        value = self.start * self.factor ** (_step(step) // self.every)
        return value if self.minimum is None else max(value, self.minimum)


@dataclass(frozen=True)
class StepLinear:
    """``start + delta · (step // every)``, clamped at ``limit`` (a floor if delta < 0, a ceiling if > 0).

    The reference's inhibition-pen decay: ``StepLinear(start=10, delta=-2, every=500, limit=2)``.
    """

    start: float
    delta: float
    every: int
    limit: float | None = None

    def __post_init__(self):
        start = _number("StepLinear", "start", self.start)
        delta = _number("StepLinear", "delta", self.delta)
        limit = None if self.limit is None else _number("StepLinear", "limit", self.limit)
        if limit is not None and (limit - start) * delta < 0:
            raise ValueError(f"StepLinear.limit={limit} lies behind start={start} for delta={delta}")
        _set(self, start=start, delta=delta, every=_count("StepLinear", "every", self.every), limit=limit)

    def __call__(self, step) -> float:
        value = self.start + self.delta * (_step(step) // self.every)
        if self.limit is None or self.delta == 0:
            return value
        return max(value, self.limit) if self.delta < 0 else min(value, self.limit)


@dataclass(frozen=True)
class Exponential:
    """``end + (start − end) · 2^(−step / half_life)``: the distance to ``end`` halves every ``half_life`` steps."""

    start: float
    end: float
    half_life: float

    def __post_init__(self):
        half_life = _number("Exponential", "half_life", self.half_life)
        if half_life <= 0:
            raise ValueError(f"Exponential.half_life must be a positive number of steps, got {self.half_life!r}")
        start, end = _number("Exponential", "start", self.start), _number("Exponential", "end", self.end)
        _set(self, start=start, end=end, half_life=half_life)

    def __call__(self, step) -> float:
        return self.end + (self.start - self.end) * 2.0 ** (-_step(step) / self.half_life)
