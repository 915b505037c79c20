"""Expert episodes: the direct scripted planner, and the paper's deconstruct-and-replay procedure.

Both return a list of ``Transition`` (gymnasium observations, the action taken, what followed), so
``ldm_rl.data.demos`` can turn either into demo TensorDicts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ldm_rl.envs.base import ExpertNoise, PickPlaceEnv, PrimitiveTarget

__all__ = ["Transition", "run_expert_episode", "run_deconstruct_episode"]


@dataclass
class Transition:
    obs: dict
    action: np.ndarray  # [3] int64 (row, col, rot)
    reward: float
    next_obs: dict
    terminated: bool
    truncated: bool
    primitive_success: bool
    is_expert: bool  # False when the (noisy) expert took a uniformly random action


def _step(env: PickPlaceEnv, obs: dict, target: PrimitiveTarget, noise: ExpertNoise) -> Transition:
    """Take ``target`` (with ``noise``) and record the transition."""
    action, random = env.noisy_action(target, noise)
    next_obs, reward, terminated, truncated, info = env.step(action)
    return Transition(obs, action, reward, next_obs, terminated, truncated, info["primitive_success"], not random)


def run_expert_episode(env: PickPlaceEnv, seed: int, noise: ExpertNoise | None = None) -> list[Transition]:
    """One episode of the direct scripted expert from ``env.reset(seed=seed)``."""
    noise = noise or env.expert_noise
    obs, _ = env.reset(seed=seed)
    episode = []
    for _ in range(env.max_steps):
        t = _step(env, obs, env.expert_target(), noise)
        episode.append(t)
        obs = t.next_obs
        if t.terminated or t.truncated:
            break
    return episode


def run_deconstruct_episode(env: PickPlaceEnv, seed: int, noise: ExpertNoise | None = None) -> list[Transition] | None:
    """The paper's demo procedure (block stacking, house building).

    1. reset to the finished structure; 2. deconstruct it with the planner (pick the highest object,
    put it down at a free spot) until every object stands apart on the table; 3. replay the recorded
    actions in reverse order in the same simulation (each place becomes a pick and vice versa),
    recording the real observations. With noise, replayed actions are jittered / randomised; after a
    failed replayed primitive the direct expert finishes the episode. Returns None when the
    deconstruction itself failed (a primitive failed or the scene became invalid) - discard it.
    """
    noise = noise or env.expert_noise
    env.reset_to_goal(seed=seed)
    actions = []
    for _ in range(4 * env.num_objects):
        if env.is_scattered():
            break
        target = env.deconstruct_target()
        action = env.pose_to_action(target.x, target.y, target.yaw)
        _, _, _, _, info = env.step(action)
        if info["invalid"] or not info["primitive_success"]:
            return None
        actions.append(action)
    else:
        return None
    if not actions:
        return None
    obs = env.restart_clock()
    episode: list[Transition] = []
    on_script = True
    for replayed in reversed(actions):
        target = env.action_to_target(replayed) if on_script else env.expert_target()
        t = _step(env, obs, target, noise)
        episode.append(t)
        obs = t.next_obs
        on_script = on_script and t.primitive_success
        if t.terminated or t.truncated:
            return episode
    while not (episode[-1].terminated or episode[-1].truncated):
        t = _step(env, obs, env.expert_target(), noise)
        episode.append(t)
        obs = t.next_obs
    return episode
