"""Predictions (foresight, imagination, the TensorDict module) run in eval mode and leave the model as found.

A dynamics model in train mode must come out of every prediction with bit-identical BatchNorm running
statistics and with each submodule's train/eval flag unchanged, including one deliberately in eval.
"""

import pytest
import torch
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import TransformedEnv

from dyn_helpers import tiny_model, transitions
from dyn_helpers import one_torch_thread  # noqa: F401  (fixture)
from ldm_rl.world_model import ForesightTransform, LDMImaginedEnv, make_dynamics_module

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _training_model():
    """The tiny model in train mode, except one BatchNorm put in eval on purpose; returns (model, that name)."""
    model = tiny_model().train()
    name, frozen = next((n, m) for n, m in model.named_modules() if isinstance(m, nn.BatchNorm2d))
    frozen.eval()
    return model, name


def _snapshot(model):
    """Every BatchNorm buffer (running_mean, running_var, num_batches_tracked) cloned, and every module's flag."""
    stats = {
        f"{name}.{buf}": getattr(m, buf).clone()
        for name, m in model.named_modules()
        if isinstance(m, nn.modules.batchnorm._BatchNorm)
        for buf in ("running_mean", "running_var", "num_batches_tracked")
    }
    flags = {name: m.training for name, m in model.named_modules()}
    return stats, flags


def _assert_untouched(model, before, frozen_name):
    stats, flags = before
    assert stats, "the model has no BatchNorm: the test would prove nothing"
    now_stats, now_flags = _snapshot(model)
    for key, value in stats.items():
        assert torch.equal(now_stats[key], value), f"{key} changed"
    assert now_flags == flags
    assert model.training and not dict(model.named_modules())[frozen_name].training


def _eval_prediction(model, td):
    """The same model's prediction in eval mode, computed on a copy (the reference)."""
    import copy

    reference = copy.deepcopy(model).eval()
    with torch.no_grad():
        return reference.predict(td["heightmap"], td["in_hand"], td["holding"], td["action"])


def _start(n):
    return transitions(n).select("heightmap", "in_hand", "holding")


def test_a_training_step_moves_the_statistics_so_the_check_has_teeth():
    model, frozen = _training_model()
    before = _snapshot(model)
    td = transitions(4)
    model(td["heightmap"], td["in_hand"], td["holding"], td["action"])  # a train-mode forward pass
    changed = [k for k, v in before[0].items() if not torch.equal(_snapshot(model)[0][k], v)]
    assert changed and not any(k.startswith(f"{frozen}.") for k in changed)


def test_foresight_on_a_replay_batch_runs_in_eval_mode():
    model, frozen = _training_model()
    before = _snapshot(model)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(16), batch_size=4)
    rb.extend(transitions(6))
    rb.append_transform(ForesightTransform(model))  # TorchRL calls transform.eval() here
    _assert_untouched(model, before, frozen)
    sample = rb.sample()
    _assert_untouched(model, before, frozen)
    expected = _eval_prediction(model, sample)
    assert torch.equal(sample["next", "pred_heightmap"], expected.heightmap)
    assert torch.equal(sample["next", "pred_holding"], expected.holding)
    assert not sample["next", "pred_heightmap"].requires_grad


def test_foresight_on_a_transformed_env_step_runs_in_eval_mode():
    model, frozen = _training_model()
    before = _snapshot(model)
    # the base env imagines with a separate (eval) model, so only the transform touches `model`
    env = TransformedEnv(LDMImaginedEnv(tiny_model()), ForesightTransform(model))  # calls transform.eval()
    _assert_untouched(model, before, frozen)
    td = env.reset(_start(2))
    td["action"] = env.action_spec.rand((2,))
    out = env.step(td)
    _assert_untouched(model, before, frozen)
    expected = _eval_prediction(model, td)
    assert torch.equal(out["next", "pred_heightmap"], expected.heightmap)
    assert torch.equal(out["next", "pred_in_hand"], expected.in_hand)


def test_imagined_env_rollout_runs_in_eval_mode():
    model, frozen = _training_model()
    before = _snapshot(model)
    env = LDMImaginedEnv(model)
    start = _start(3)
    rollout = env.rollout(3, tensordict=env.reset(start), auto_reset=False)
    _assert_untouched(model, before, frozen)
    first = _eval_prediction(model, start.set("action", rollout["action"][:, 0]))
    assert torch.equal(rollout["next", "heightmap"][:, 0], first.heightmap)
    assert not rollout["next", "heightmap"].requires_grad


def test_dynamics_module_predicts_in_eval_mode():
    model, frozen = _training_model()
    before = _snapshot(model)
    module = make_dynamics_module(model)
    td = transitions(4).exclude("next")
    out = module(td)
    _assert_untouched(model, before, frozen)
    expected = _eval_prediction(model, td)
    assert torch.equal(out["next", "pred_heightmap"], expected.heightmap)
    assert torch.equal(out["next_logits"], expected.logits) and not out["next_logits"].requires_grad


def test_foresight_transform_train_and_eval_leave_the_model_alone():
    model, frozen = _training_model()
    before = _snapshot(model)
    transform = ForesightTransform(model)
    transform.eval()
    assert not transform.training
    _assert_untouched(model, before, frozen)
    transform.train()
    assert transform.training
    _assert_untouched(model, before, frozen)
