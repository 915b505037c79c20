"""Where a run's scenes come from: streams of env reset seeds derived from the run's ``seed``, written once.

A run with ``seed = s`` draws its expert demonstrations, training episodes, in-training evaluations and
held-out re-scoring from separate streams. Training episode ``k`` resets with seed ``training_scenes(s) + k``;
an evaluation resets once with its stream's seed and draws its scenes on from there. Known overlap, kept so
that runs in progress resume on the same scenes: seed 1's first evaluation scene (``10⁶ + 1``) is its
training episode 1, and seed 2's first held-out scene (``2·10⁶ + 2``) its training episode 2 — one scene of
20–100 each; no other seed ≤ 1000 meets one. A new stream layout would fix it at the cost of every kept run's scenes.
"""

from __future__ import annotations

__all__ = ["SEED_BLOCK", "training_scenes", "evaluation_scenes", "held_out_scenes", "expert_scenes"]

SEED_BLOCK = 1_000_000  # reset seeds per stream (collector workers split the training block among themselves)


def training_scenes(seed: int) -> int:
    """The first reset seed of the training episodes (worker w of N starts ``w · SEED_BLOCK // N`` later)."""
    return int(seed) * SEED_BLOCK


def evaluation_scenes(seed: int) -> int:
    """The in-training evaluations and the final one (``curve.csv``, ``final_metrics.json``)."""
    return int(seed) + SEED_BLOCK


def held_out_scenes(seed: int) -> int:
    """``recipes/evaluate.py`` and the re-scoring of the selected weights (``best_policy.pt``)."""
    return int(seed) + 2 * SEED_BLOCK


def expert_scenes(seed: int) -> int:
    """The scripted expert's demonstrations that seed the replay."""
    return int(seed) + 10_000
