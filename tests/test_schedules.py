"""Tests of the scalar schedules (ldm_rl.schedules)."""

import math
import pickle
import subprocess
import sys

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from ldm_rl.schedules import Constant, Exponential, Linear, StepDecay, StepLinear


def test_constant():
    s = Constant(3)
    assert [s(0), s(1), s(10**9)] == [3.0, 3.0, 3.0]
    assert isinstance(s(0), float)


def test_linear_boundaries():
    s = Linear(start=1.0, end=0.1, steps=100)
    assert s(0) == 1.0
    assert s(50) == pytest.approx(0.55)
    assert s(99) == pytest.approx(0.109)
    assert s(100) == 0.1 and s(101) == 0.1 and s(10**9) == 0.1
    values = [s(i) for i in range(102)]
    assert all(a >= b for a, b in zip(values, values[1:]))  # monotone
    rising = Linear(0, 4, 1)
    assert (rising(0), rising(1), rising(2)) == (0.0, 4.0, 4.0)


def test_step_decay_boundaries():
    s = StepDecay(start=1e-3, factor=0.95, every=2000)
    assert s(0) == s(1999) == 1e-3
    assert s(2000) == pytest.approx(0.95e-3) and s(3999) == s(2000)
    assert s(4000) == pytest.approx(1e-3 * 0.95**2)
    floored = StepDecay(start=1.0, factor=0.5, every=10, minimum=0.2)
    assert [floored(i) for i in (0, 9, 10, 20, 30, 1000)] == [1.0, 1.0, 0.5, 0.25, 0.2, 0.2]
    assert StepDecay(1.0, 0.5, 1)(10**6) == 0.0  # underflows quietly, no OverflowError
    assert StepDecay(2.0, 1.0, 3)(10**6) == 2.0


def test_step_linear_reproduces_the_reference_pen_decay():
    pos = StepLinear(start=10, delta=-2, every=500, limit=2)
    rot = StepLinear(start=4, delta=-1, every=500, limit=0)
    steps = (0, 499, 500, 1000, 1500, 2000, 2500, 10**6)
    assert [pos(i) for i in steps] == [10, 10, 8, 6, 4, 2, 2, 2]
    assert [rot(i) for i in steps] == [4, 4, 3, 2, 1, 0, 0, 0]
    up = StepLinear(0.0, 0.5, 2, limit=1.0)
    assert [up(i) for i in range(7)] == [0.0, 0.0, 0.5, 0.5, 1.0, 1.0, 1.0]
    assert StepLinear(1.0, 0.0, 5, limit=0.5)(100) == 1.0
    assert StepLinear(1.0, -1.0, 1)(3) == -2.0


def test_exponential_boundaries():
    s = Exponential(start=1.0, end=0.1, half_life=100)
    assert s(0) == 1.0
    assert s(100) == pytest.approx(0.55) and s(200) == pytest.approx(0.325)
    assert s(10**9) == pytest.approx(0.1)


@pytest.mark.parametrize("step", [np.int64(7), torch.tensor(7), 7])
def test_integer_like_steps(step):
    assert Linear(0.0, 14.0, 14)(step) == 7.0


@pytest.mark.parametrize("step", [-1, 1.5, 2.0, "3", None, True, torch.tensor(1.0)])
def test_bad_steps_raise(step):
    for s in (Constant(1.0), Linear(0, 1, 5), StepDecay(1, 0.5, 2), StepLinear(1, -1, 2), Exponential(1, 0, 3)):
        with pytest.raises(ValueError, match="step must be a non-negative int"):
            s(step)


@pytest.mark.parametrize(
    "factory, match",
    [
        (lambda: Constant(math.nan), "Constant.value must be a finite number"),
        (lambda: Constant("1"), "Constant.value"),
        (lambda: Linear(1.0, math.inf, 10), "Linear.end must be a finite number"),
        (lambda: Linear(1.0, 0.0, 0), "Linear.steps must be a positive integer"),
        (lambda: Linear(1.0, 0.0, 2.5), "Linear.steps"),
        (lambda: Linear(1.0, 0.0, True), "Linear.steps"),
        (lambda: StepDecay(1.0, 0.0, 10), "StepDecay.factor must lie in \\(0, 1\\]"),
        (lambda: StepDecay(1.0, 1.5, 10), "StepDecay.factor"),
        (lambda: StepDecay(1.0, 0.5, -1), "StepDecay.every must be a positive integer"),
        (lambda: StepDecay(1.0, 0.5, 10, minimum=2.0), "StepDecay.minimum must be <= start"),
        (lambda: StepLinear(10, -2, 500, limit=12), "StepLinear.limit=12.0 lies behind start"),
        (lambda: StepLinear(10, -2, 0), "StepLinear.every"),
        (lambda: StepLinear(10, None, 1), "StepLinear.delta"),
        (lambda: Exponential(1.0, 0.0, 0), "Exponential.half_life must be a positive"),
        (lambda: Exponential(1.0, 0.0, -5), "Exponential.half_life"),
    ],
)
def test_bad_arguments_raise_one_line_value_errors(factory, match):
    with pytest.raises(ValueError, match=match) as info:
        factory()
    assert "\n" not in str(info.value)


def test_integral_float_counts_from_yaml():
    assert Linear(0, 1, 2e3).steps == 2000 and isinstance(Linear(0, 1, 2e3).steps, int)


def test_hydra_instantiate_pickle_and_repr():
    cfg = OmegaConf.create(
        """
        temperature: {_target_: ldm_rl.schedules.Linear, start: 1.0, end: 0.1, steps: 1000}
        lr: {_target_: ldm_rl.schedules.StepDecay, start: 1.0e-3, factor: 0.95, every: 2000, minimum: null}
        pen: {_target_: ldm_rl.schedules.StepLinear, start: 10, delta: -2, every: 500, limit: 2}
        beta: {_target_: ldm_rl.schedules.Exponential, start: 1, end: 0, half_life: 500}
        fixed: {_target_: ldm_rl.schedules.Constant, value: 0.5}
        """
    )
    built = {name: instantiate(node) for name, node in cfg.items()}
    assert built["temperature"] == Linear(1.0, 0.1, 1000)
    assert built["temperature"](1000) == 0.1
    assert built["lr"](2000) == pytest.approx(0.95e-3)
    assert built["pen"](2000) == 2.0
    assert built["fixed"](3) == 0.5
    assert instantiate({"_target_": "ldm_rl.schedules.Linear", "start": 2, "end": 0, "steps": 4})(1) == 1.5
    for s in built.values():
        clone = pickle.loads(pickle.dumps(s))
        assert clone == s and clone(1234) == s(1234)
    assert repr(built["temperature"]) == "Linear(start=1.0, end=0.1, steps=1000)"
    assert repr(built["lr"]) == "StepDecay(start=0.001, factor=0.95, every=2000, minimum=None)"
    with pytest.raises(Exception, match="steps must be a positive integer"):
        instantiate({"_target_": "ldm_rl.schedules.Linear", "start": 1, "end": 0, "steps": -3})


def test_schedules_are_frozen():
    s = Linear(0, 1, 10)
    with pytest.raises(AttributeError):
        s.steps = 3


def test_module_imports_neither_torch_nor_the_rest_of_the_package():
    code = "import sys, ldm_rl.schedules; print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'ldm_rl')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['ldm_rl', 'ldm_rl.keys', 'ldm_rl.schedules']"  # keys: plain strings, no imports
