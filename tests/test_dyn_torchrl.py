"""TorchRL wrappers: TensorDictModule keys, foresight transform (replay buffer, env), imagined env."""

from pathlib import Path

import pytest
import torch
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import TransformedEnv

from dyn_helpers import tiny_model, transitions
from dyn_helpers import one_torch_thread  # noqa: F401  (fixture)
from ldm_rl.world_model import ForesightTransform, LDMImaginedEnv, make_dynamics_module

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_dynamics_module_writes_the_predicted_keys_beside_the_real_next_state():
    model = tiny_model()
    td = transitions(4)
    real_next = td["next"].clone()
    module = make_dynamics_module(model)
    out = module(td)  # a real transition (a replay sample): its ("next", ...) data must survive
    pred = model.predict(td["heightmap"], td["in_hand"], td["holding"], td["action"])
    assert torch.equal(out["next", "pred_heightmap"], pred.heightmap)
    assert torch.equal(out["next", "pred_in_hand"], pred.in_hand)
    assert out["next", "pred_holding"].shape == (4, 1) and out["next", "pred_holding"].dtype == torch.bool
    assert out["next_logits"].shape == (4, 21, 64, 64)
    for key in ("heightmap", "in_hand", "holding"):
        assert torch.equal(out["next", key], real_next[key]), key
    assert not torch.equal(out["next", "pred_heightmap"], out["next", "heightmap"])
    with pytest.raises(KeyError, match="action"):
        module(td.exclude("action"))
    with pytest.raises(ValueError, match="empty batch"):
        module(td[:0])


def test_dynamics_module_can_write_the_next_state_for_imagined_data():
    from ldm_rl.world_model.modules import NEXT_KEYS

    model = tiny_model()
    td = transitions(2).exclude("next")
    out = make_dynamics_module(model, out_keys=NEXT_KEYS)(td)
    assert torch.equal(out["next", "heightmap"], model.predict(td["heightmap"], td["in_hand"], td["holding"], td["action"]).heightmap)


def test_foresight_transform_on_a_replay_buffer():
    model = tiny_model()
    data = transitions(6)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(16), batch_size=4)
    rb.extend(data)
    rb.append_transform(ForesightTransform(model))
    sample = rb.sample()
    assert {"pred_heightmap", "pred_in_hand", "pred_holding", "heightmap"} <= set(sample["next"].keys())
    pred = model.predict(sample["heightmap"], sample["in_hand"], sample["holding"], sample["action"])
    assert torch.equal(sample["next", "pred_heightmap"], pred.heightmap)
    assert not sample["next", "pred_heightmap"].requires_grad
    with pytest.raises(ValueError, match="missing"):
        ForesightTransform(model)(data.exclude("action"))


def _start(n):
    return transitions(n).select("heightmap", "in_hand", "holding")


def test_imagined_env_rollout_steps_with_the_model():
    model = tiny_model()
    env = LDMImaginedEnv(model)
    start = _start(3)
    rollout = env.rollout(4, tensordict=env.reset(start), auto_reset=False)
    assert rollout.batch_size == (3, 4)
    assert (rollout["next", "reward"] == 0).all() and not rollout["next", "done"].any()
    first = model.predict(start["heightmap"], start["in_hand"], start["holding"], rollout["action"][:, 0])
    assert torch.equal(rollout["next", "heightmap"][:, 0], first.heightmap)
    assert torch.equal(rollout["heightmap"][:, 1], first.heightmap)  # the imagined state is carried on
    with pytest.raises(ValueError, match="start state"):
        env.reset()


def test_imagined_env_uses_a_reward_module():
    from tensordict.nn import TensorDictModule

    reward = TensorDictModule(lambda h: h.flatten(-3).amax(-1, keepdim=True), in_keys=["heightmap"], out_keys=["reward"])
    env = LDMImaginedEnv(tiny_model(), reward_module=reward)
    rollout = env.rollout(2, tensordict=env.reset(_start(2)), auto_reset=False)
    torch.testing.assert_close(rollout["next", "reward"], rollout["next", "heightmap"].flatten(-3).amax(-1, keepdim=True))


def test_foresight_transform_on_a_transformed_env():
    model = tiny_model()
    env = TransformedEnv(LDMImaginedEnv(model), ForesightTransform(model))
    assert "pred_heightmap" in env.observation_spec.keys()
    rollout = env.rollout(3, tensordict=env.reset(_start(2)), auto_reset=False)
    # the base env steps with the same model, so the foresight equals the transition exactly
    assert torch.equal(rollout["next", "pred_heightmap"], rollout["next", "heightmap"])
    assert torch.equal(rollout["next", "pred_holding"], rollout["next", "holding"])
    assert (rollout["pred_heightmap"][:, 0] == 0).all()  # reset: no prediction yet
    assert rollout.batch_size == (2, 3)


def test_imagined_and_transformed_envs_pass_check_env_specs():
    from torchrl.envs.utils import check_env_specs

    model = tiny_model()
    start = _start(1)[0]
    imagined = LDMImaginedEnv(model)
    check_env_specs(imagined, tensordict=imagined.reset(start.clone()))
    foresight = TransformedEnv(LDMImaginedEnv(model), ForesightTransform(model))
    check_env_specs(foresight, tensordict=foresight.reset(start.clone()))


def test_foresight_transform_on_the_real_env():
    from omegaconf import OmegaConf

    from ldm_rl.envs.torchrl_env import expert_policy, make_env_from_config

    cfg = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "env" / "block_stacking.yaml")
    env = make_env_from_config(OmegaConf.to_container(cfg))
    model = tiny_model(num_rotations=int(cfg.num_rotations))
    env.append_transform(ForesightTransform(model))
    env.set_seed(0)
    rollout = env.rollout(2, expert_policy(env))
    assert rollout["next", "pred_heightmap"].shape == rollout["next", "heightmap"].shape
    expected = model.predict(rollout["heightmap"], rollout["in_hand"], rollout["holding"], rollout["action"])
    assert torch.equal(rollout["next", "pred_heightmap"], expected.heightmap)
    assert torch.equal(rollout["next", "pred_holding"], expected.holding)
    env.close()
