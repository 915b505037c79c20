"""Success rate of any policy on any env, with a 95 % interval.

An episode succeeds when it ends *terminated* with a positive reward (every task rewards success
positively; invalid scenes terminate with 0 and timeouts truncate). Episodes run under
``ExplorationType.DETERMINISTIC`` (greedy agents) and without gradients.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Callable

__all__ = ["EvaluationResult", "wilson_interval", "evaluate_policy", "episode_succeeded", "pick_counts", "undone_places",
           "episode_steps", "is_bin_packing", "episode_record", "packing_report", "packing_line"]


@dataclass(frozen=True)
class EvaluationResult:
    episodes: int
    successes: int
    success_rate: float
    ci_low: float  # 95 % Wilson interval
    ci_high: float
    mean_return: float
    mean_length: float  # primitives per episode

    def as_dict(self) -> dict:
        return asdict(self)

    def __str__(self) -> str:
        return (f"success {100 * self.success_rate:.1f}% ({self.successes}/{self.episodes}, 95% CI "
                f"{100 * self.ci_low:.1f}-{100 * self.ci_high:.1f}%), mean length {self.mean_length:.2f}")


def wilson_interval(successes: int, trials: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % for the default z)."""
    if trials < 1 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials and trials >= 1, got {successes}/{trials}")
    p = successes / trials
    denom = 1 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denom
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def episode_succeeded(rollout) -> bool:
    """An episode (``[T]`` TensorDict of ``env.rollout``) succeeded: it ended terminated with a positive reward."""
    last = rollout[-1]
    return bool(last["next", "terminated"].any()) and float(last["next", "reward"].sum()) > 0


def pick_counts(rollout) -> tuple[int, int]:
    """``(picks, held)`` of an episode (``[T]`` TensorDict of ``env.rollout``): its steps taken with an empty hand
    (``holding`` false: every one a pick) and those after which the hand held an object (``("next", "holding")``)."""
    missing = [key for key in ("holding", ("next", "holding")) if key not in rollout.keys(include_nested=True)]
    if missing or len(rollout.shape) != 1:
        raise ValueError(f"pick_counts needs one episode, a [T] TensorDict with 'holding' and ('next', 'holding'); got "
                         f"batch shape {tuple(rollout.shape)}" + (f", missing {missing}" if missing else ""))
    before = rollout["holding"].reshape(rollout.shape[0], -1).any(-1)
    after = rollout["next", "holding"].reshape(rollout.shape[0], -1).any(-1)
    picks = ~before
    return int(picks.sum()), int((picks & after).sum())


def undone_places(rollout, *, changed: float = 0.015, restored: float = 0.5) -> int:
    """Places of an episode (``[T]`` TensorDict of ``env.rollout`` with ``heightmap``, ``holding`` and their
    ``("next", …)``) that put back what the pick before them took: a 2-cycle's first half (pick a block, put it
    back, pick it again). A pick that held changed ``m`` pixels by more than ``changed`` m; the place after it undid
    it when the scene then differs from the one before the pick in at most ``restored``·``m`` pixels (a 4 cm cube of
    13 × 13 px put back 3 px off differs in 0.46 of its pixels; one put elsewhere, on the table or on another object,
    in twice as many as it covers)."""
    needed = ("heightmap", "holding", ("next", "heightmap"), ("next", "holding"))
    missing = [key for key in needed if key not in rollout.keys(include_nested=True)]
    if missing or len(rollout.shape) != 1:
        raise ValueError(f"undone_places needs one episode, a [T] TensorDict with {needed}; got batch shape "
                         f"{tuple(rollout.shape)}" + (f", missing {missing}" if missing else ""))
    if rollout.shape[0] < 2:
        return 0
    steps = rollout.shape[0]
    holding = rollout["holding"].reshape(steps, -1).any(-1)
    held_after = rollout["next", "holding"].reshape(steps, -1).any(-1)
    before_pick, after_pick = rollout["heightmap"][:-1], rollout["next", "heightmap"][:-1]
    after_place = rollout["next", "heightmap"][1:]
    moved = ((after_pick - before_pick).abs() > changed).flatten(1).sum(1)
    differs = ((after_place - before_pick).abs() > changed).flatten(1).sum(1)
    pairs = ~holding[:-1] & held_after[:-1] & holding[1:]  # a pick that held, then the place of what it held
    return int((pairs & (moved > 0) & (differs <= restored * moved)).sum())


def evaluate_policy(env, policy, episodes: int, *, seed: int | None = None, max_steps: int = 1000,
                    progress: bool = False, on_episode: Callable[[int, Any], None] | None = None) -> EvaluationResult:
    """Run ``episodes`` greedy episodes of ``policy`` (a TensorDict module) on ``env`` (a TorchRL env).

    ``seed`` reseeds ``env`` first, so the same seed gives the same evaluation scenes. ``on_episode(i,
    rollout)`` (optional) receives each finished episode ``i`` (from 0) as the ``[T]`` TensorDict of
    ``env.rollout`` (state, the policy's outputs, ``("next", …)``), e.g. to keep some for pictures
    (:func:`episode_steps`).
    """
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from ldm_rl.run.progress import progress_bar

    if not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be a positive int, got {episodes!r}")
    if seed is not None:
        env.set_seed(int(seed))
    successes, returns, lengths = 0, [], []
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        for index in progress_bar(range(episodes), desc="evaluate", unit="episode", enabled=progress):
            rollout = env.rollout(max_steps, policy, break_when_any_done=True)
            successes += int(episode_succeeded(rollout))
            returns.append(float(rollout["next", "reward"].sum()))
            lengths.append(rollout.shape[0])
            if on_episode is not None:
                on_episode(index, rollout)
    low, high = wilson_interval(successes, episodes)
    return EvaluationResult(episodes, successes, successes / episodes, low, high,
                            sum(returns) / episodes, sum(lengths) / episodes)


def is_bin_packing(env) -> bool:
    """Whether ``env`` (a TorchRL env from :func:`~ldm_rl.envs.make_env`) plays bin packing, whose report adds
    the packed fraction, the pile top and the blocks left in the bin (:func:`packing_report`)."""
    from ldm_rl.envs.tasks.bin_packing import BinPackingEnv
    from ldm_rl.envs.torchrl_env import unwrap

    return isinstance(unwrap(env), BinPackingEnv)


def episode_record(env, returns: list[float], blocks_in_bin: list[int] | None = None) -> Callable[[int, Any], None]:
    """An ``on_episode`` callback for :func:`evaluate_policy` that appends each episode's return to ``returns``
    and, given ``blocks_in_bin`` (bin packing), the blocks in the bin when the episode ended; bin packing's
    ``returns`` then get the pack's reward alone (its last step's ``pack_reward``, without the optional
    progress term), which :func:`~ldm_rl.envs.tasks.bin_packing.packing_scores` reads. Read from ``env``
    before its next reset."""
    from ldm_rl.envs.torchrl_env import unwrap

    def record(index: int, rollout) -> None:
        if blocks_in_bin is None:
            returns.append(float(rollout["next", "reward"].sum()))
            return
        task = unwrap(env)
        returns.append(float(task.pack_reward))
        blocks_in_bin.append(int(task.blocks_in_bin()))
    return record


def packing_report(env, returns: list[float], blocks_in_bin: list[int], *, seed: int | None, progress: bool = False) -> dict:
    """Bin packing's report for the ``returns`` and ``blocks_in_bin`` (one per episode, :func:`episode_record`) of
    an evaluation with ``seed``, and under ``"expert"`` the scripted expert's on the same scenes (the same seed,
    as many episodes): packed fraction, mean pile top (m), mean return under ours and the authors' reward, mean
    blocks in the bin at the end (:func:`~ldm_rl.envs.tasks.bin_packing.packing_scores`)."""
    from ldm_rl.envs import expert_policy
    from ldm_rl.envs.tasks.bin_packing import packing_scores

    expert_returns: list[float] = []
    expert_blocks: list[int] = []
    evaluate_policy(env, expert_policy(env), len(returns), seed=seed, progress=progress,
                    on_episode=episode_record(env, expert_returns, expert_blocks))
    return {**packing_scores(returns, blocks_in_bin), "expert": packing_scores(expert_returns, expert_blocks)}


def packing_line(scores: dict) -> str:
    """One line of a :func:`packing_report` (the agent's part, or its ``"expert"``), for a log."""
    top = "-" if scores["mean_pile_top"] is None else f"{100 * scores['mean_pile_top']:.1f} cm"
    return (f"packed {100 * scores['packed']:.0f}%, mean pile top {top}, mean return {scores['mean_return']:.3f} "
            f"(the authors' reward: {scores['mean_return_authors']:.2f}), "
            f"{scores['mean_blocks_in_bin']:.2f} blocks in the bin at the end")


def episode_steps(rollout, *, episode: int = 0, dynamics=None, q_network=None) -> list[dict]:
    """One plain row per step of an evaluation episode, for :mod:`ldm_rl.plots` (``plot_decision``,
    ``plot_episodes_gif``).

    Args:
        rollout: the ``[T]`` TensorDict of ``env.rollout`` (as :func:`evaluate_policy` passes it).
        episode: the episode's index, copied into the rows.
        dynamics: a :class:`~ldm_rl.world_model.DynamicsModel`; gives ``predicted_heightmap``, its
            prediction for the action taken (one batched pass in eval mode, no gradients).
        q_network: ``(heightmap, in_hand, holding) -> [T, R, H, W]``, used for ``q_map`` when the
            policy did not write ``action_value``.

    Each row: ``episode``, ``step``, ``num_steps``, ``heightmap`` / ``next_heightmap`` ``[H, W]`` m,
    ``action`` ``[3]``, ``is_pick`` (hand empty before the step), ``reward``, ``outcome`` (last step
    only: ``success`` / ``failure``), and where available ``q_map`` ``[R, H, W]``, ``candidates``
    ``[N, 3]``, ``values`` ``[N]``, ``predicted_heightmap`` ``[H, W]``.
    """
    import torch

    from ldm_rl import keys
    from ldm_rl.torch_utils import eval_mode

    keys.require_keys(rollout, [keys.HEIGHTMAP, keys.IN_HAND, keys.HOLDING, keys.ACTION,
                                (keys.NEXT, keys.HEIGHTMAP), (keys.NEXT, keys.REWARD)], "episode_steps")
    state = [rollout.get(k) for k in (keys.HEIGHTMAP, keys.IN_HAND, keys.HOLDING)]
    present = set(rollout.keys())
    q_maps = rollout.get(keys.ACTION_VALUE) if keys.ACTION_VALUE in present else None
    predicted = None
    with torch.no_grad():
        if q_maps is None and q_network is not None:
            with eval_mode(q_network):
                q_maps = q_network(*state)
        if dynamics is not None:
            with eval_mode(dynamics):
                predicted = dynamics.predict(*state, rollout.get(keys.ACTION)).heightmap
    candidates = rollout.get(keys.CANDIDATE_ACTIONS) if keys.CANDIDATE_ACTIONS in present else None
    values = rollout.get(keys.CANDIDATE_VALUES) if keys.CANDIDATE_VALUES in present else None
    n = rollout.shape[0]
    outcome = "success" if episode_succeeded(rollout) else "failure"
    rows = []
    for t in range(n):
        row = {
            "episode": episode, "step": t, "num_steps": n,
            "heightmap": state[0][t, 0], "next_heightmap": rollout.get((keys.NEXT, keys.HEIGHTMAP))[t, 0],
            "action": rollout.get(keys.ACTION)[t], "is_pick": not bool(state[2][t].any()),
            "reward": float(rollout.get((keys.NEXT, keys.REWARD))[t].sum()),
        }
        if t == n - 1:
            row["outcome"] = outcome
        if q_maps is not None:
            row["q_map"] = q_maps[t]
        if candidates is not None and values is not None:
            row["candidates"], row["values"] = candidates[t], values[t]
        if predicted is not None:
            row["predicted_heightmap"] = predicted[t, 0]
        rows.append(row)
    return rows
