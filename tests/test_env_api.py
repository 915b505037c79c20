"""The gymnasium / TorchRL interface of the tasks: spaces, checkers, determinism, bad input."""

import hashlib
import subprocess
import sys
import textwrap

import gymnasium as gym
import numpy as np
import pytest
import torch

import ldm_rl.envs
from ldm_rl.envs import ENV_IDS, make_env

TASKS = sorted(ENV_IDS)


@pytest.mark.parametrize("env_id", TASKS)
def test_gymnasium_check_env(env_id):
    from gymnasium.utils.env_checker import check_env

    env = gym.make(env_id, render_mode="rgb_array")
    try:
        check_env(env.unwrapped, skip_render_check=False)
        obs, _ = env.reset(seed=0)
        assert obs["heightmap"].shape == (1, 128, 128) and obs["heightmap"].dtype == np.float32
        assert obs["in_hand"].shape == (1, 24, 24) and obs["holding"].shape == (1,)
        assert env.action_space.nvec.tolist() == [128, 128, 8]
        frame = env.render()
        assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    finally:
        env.close()


@pytest.mark.parametrize("env_id", TASKS)
def test_torchrl_check_env_specs(env_id):
    from torchrl.envs.utils import check_env_specs

    env = make_env(env_id)
    try:
        check_env_specs(env, seed=0)
        # random actions may end an episode at its first step (a bottle knocked over): reset and go on, so the
        # rollout always has two steps whatever the global RNG holds after other tests
        td = env.rollout(2, break_when_any_done=False)
        assert td["holding"].shape == (2, 1) and td["holding"].dtype == torch.bool
        assert td["action"].shape == (2, 3) and td["action"].dtype == torch.int64
        assert td["next", "heightmap"].shape == (2, 1, 128, 128)
        assert td["next", "in_hand"].shape == (2, 1, 24, 24)
        assert td["next", "reward"].shape == (2, 1)
    finally:
        env.close()


def test_make_env_from_config_and_bad_id():
    from omegaconf import OmegaConf

    from ldm_rl.envs.torchrl_env import unwrap

    cfg = OmegaConf.create({"env": {"id": "ldm_rl/BlockStacking-v0", "num_objects": 4, "max_steps": 7,
                                    "num_rotations": 8, "max_height": 0.25, "demo_procedure": "direct"}})
    env = ldm_rl.envs.make_env_from_config(cfg.env)
    try:
        task = unwrap(env)
        assert task.num_objects == 4 and task.max_steps == 7
    finally:
        env.close()
    with pytest.raises(ValueError, match="env_id"):
        make_env("ldm_rl/Nope-v0")


def test_train_object_counts_vary_the_training_scenes_only():
    """The training env (and the demos) draw each scene's object count from train_object_counts, seeded;
    the evaluation env keeps num_objects; the step limit fits the largest count."""
    from ldm_rl.data.demos import collect_demos
    from ldm_rl.envs.torchrl_env import unwrap

    cfg = {"id": "ldm_rl/BlockStacking-v0", "num_objects": 3, "train_object_counts": [2, 3]}

    def counts(env, n=12):
        task = unwrap(env)
        seen = []
        for _ in range(n):
            env.reset()
            seen.append((task.num_objects, len(task.sim.objects)))
        env.close()
        return seen, task.max_steps

    drawn, max_steps = counts(ldm_rl.envs.make_env_from_config(cfg, training=True, reset_seed=4))
    assert all(n == m for n, m in drawn) and {n for n, _ in drawn} == {2, 3} and max_steps == 10
    assert drawn == counts(ldm_rl.envs.make_env_from_config(cfg, training=True, reset_seed=4))[0]
    assert counts(ldm_rl.envs.make_env_from_config(cfg, reset_seed=4))[0] == [(3, 3)] * 12
    demos = collect_demos(cfg, num_episodes=8, seed=0, progress=False)
    lengths = torch.unique_consecutive(demos["episode"], return_counts=True)[1].tolist()
    assert {2, 4} <= set(lengths) and bool(demos["next", "reward"].sum() == 8)  # 2 cubes: one pick, one place
    with pytest.raises(ValueError, match="object_counts"):
        gym.make("ldm_rl/BlockStacking-v0", object_counts=[])
    with pytest.raises(ValueError, match="tray slots"):
        gym.make("ldm_rl/BottleArrangement-v0", num_objects=4, object_counts=[4, 7])


def test_expert_policy_solves_block_stacking_in_a_torchrl_rollout():
    env = make_env("ldm_rl/BlockStacking-v0")
    try:
        env.set_seed(0)
        td = env.rollout(10, ldm_rl.envs.expert_policy(env))
        assert td.batch_size == (4,)  # 2 picks + 2 places, then terminated
        assert td["next", "reward"][-1].item() == 1.0 and td["next", "terminated"][-1].item()
        assert td["next", "holding"][:, 0].tolist() == [True, False, True, False]
    finally:
        env.close()


@pytest.mark.parametrize(
    "action, component",
    [([128, 0, 0], "row"), ([0, -1, 0], "col"), ([3, 4, 8], "rot"), ([1, 2], "3 integers"), ([0.5, 1, 1], "3 integers")],
)
def test_action_outside_the_space_raises(action, component):
    env = gym.make("ldm_rl/BlockStacking-v0").unwrapped
    try:
        env.reset(seed=0)
        with pytest.raises(ValueError, match=component):
            env.step(np.array(action))
    finally:
        env.close()


def test_constructor_arguments_are_validated():
    with pytest.raises(ValueError, match="num_objects"):
        gym.make("ldm_rl/HouseBuilding-v0", num_objects=4)
    with pytest.raises(ValueError, match="num_objects"):
        gym.make("ldm_rl/BottleArrangement-v0", num_objects=7)
    from ldm_rl.envs.tasks.block_stacking import BlockStackingEnv

    with pytest.raises(ValueError, match="render_mode"):
        BlockStackingEnv(render_mode="human")
    with pytest.raises(ValueError, match="random_action_prob"):
        gym.make("ldm_rl/BlockStacking-v0", expert_noise={"random_action_prob": 2.0})


def test_truncation_at_max_steps():
    env = gym.make("ldm_rl/BlockStacking-v0", max_steps=3).unwrapped
    try:
        env.reset(seed=0)
        flags = [env.step(np.array([0, 0, 0]))[2:4] for _ in range(3)]  # empty corner: picks fail
        assert flags == [(False, False), (False, False), (False, True)]
    finally:
        env.close()


EPISODE_DIGEST = textwrap.dedent(
    """
    import hashlib, gymnasium as gym, numpy as np, ldm_rl.envs
    def digest(env_id, seed, steps=4):
        env = gym.make(env_id).unwrapped
        h = hashlib.sha256()
        obs, _ = env.reset(seed=seed)
        for k in range(steps):
            for key in ("heightmap", "in_hand", "holding"):
                h.update(obs[key].tobytes())
            obs, *_ = env.step(env.expert_action())
        env.close()
        return h.hexdigest()
    """
)


def _digest(env_id, seed):
    namespace = {}
    exec(EPISODE_DIGEST, namespace)
    return namespace["digest"](env_id, seed)


def test_same_seed_same_observations_twice_and_in_a_fresh_process():
    first = _digest("ldm_rl/BlockStacking-v0", 7)
    assert _digest("ldm_rl/BlockStacking-v0", 7) == first
    assert _digest("ldm_rl/BlockStacking-v0", 8) != first
    code = EPISODE_DIGEST + "\nprint(digest('ldm_rl/BlockStacking-v0', 7))\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.strip().splitlines()[-1] == first


def test_same_env_reset_with_same_seed_repeats_the_episode():
    env = gym.make("ldm_rl/BinPacking-v0").unwrapped
    try:
        runs = []
        for _ in range(2):
            obs, _ = env.reset(seed=11)
            frames = [obs["heightmap"]]
            for _ in range(3):
                obs, *_ = env.step(env.expert_action())
                frames.append(obs["heightmap"])
            runs.append(hashlib.sha256(np.stack(frames).tobytes()).hexdigest())
        assert runs[0] == runs[1]
    finally:
        env.close()


@pytest.mark.slow
def test_parallel_env_workers_register_the_ids():
    from functools import partial

    from torchrl.envs import ParallelEnv

    penv = ParallelEnv(2, partial(make_env, "ldm_rl/BlockStacking-v0"), mp_start_method="spawn")
    try:
        td = penv.rollout(2)
        assert td.batch_size == (2, 2)
        assert td["next", "holding"].dtype == torch.bool
    finally:
        penv.close()
