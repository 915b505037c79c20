"""Success rate of any policy on any env, with a 95 % interval.

An episode succeeds when it ends *terminated* with a positive reward (every task rewards success
positively; invalid scenes terminate with 0 and timeouts truncate). Episodes run under
``ExplorationType.DETERMINISTIC`` (greedy agents) and without gradients.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

__all__ = ["EvaluationResult", "wilson_interval", "evaluate_policy"]


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


def evaluate_policy(env, policy, episodes: int, *, seed: int | None = None, max_steps: int = 1000,
                    progress: bool = False) -> EvaluationResult:
    """Run ``episodes`` greedy episodes of ``policy`` (a TensorDict module) on ``env`` (a TorchRL env).

    ``seed`` reseeds ``env`` first, so the same seed gives the same evaluation scenes.
    """
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type
    from tqdm.auto import tqdm

    if not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be a positive int, got {episodes!r}")
    if seed is not None:
        env.set_seed(int(seed))
    successes, returns, lengths = 0, [], []
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        for _ in tqdm(range(episodes), desc="evaluate", unit="episode", disable=not progress):
            rollout = env.rollout(max_steps, policy, break_when_any_done=True)
            last = rollout[-1]
            reward = float(last["next", "reward"].sum())
            successes += int(bool(last["next", "terminated"].any()) and reward > 0)
            returns.append(float(rollout["next", "reward"].sum()))
            lengths.append(rollout.shape[0])
    low, high = wilson_interval(successes, episodes)
    return EvaluationResult(episodes, successes, successes / episodes, low, high,
                            sum(returns) / episodes, sum(lengths) / episodes)
