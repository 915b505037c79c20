"""Batched one-step lookahead: ``V(f(s, a))`` for N candidate actions of every state, in one pass.

The dynamics model ``f`` (one LDM head per sample, chosen by the hand state) predicts each candidate's
next state; the value network scores it. Both run in eval mode under ``no_grad`` (BatchNorm statistics
untouched, the callers' train/eval flags restored). The B·N state-candidate pairs are processed in
chunks of ``chunk_size`` so large batches (the training targets: 32 states × N) stay in cache; the
states are gathered per chunk, never copied N times as a whole.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from ldm_rl.torch_utils import eval_mode

__all__ = ["LookaheadResult", "lookahead", "shooting_scores", "PICK_OUTCOMES"]

# how a pick is scored: by the mode of the LDM's prediction (the paper), or by its expected value over its two
# outcomes (held, with the model's probability; empty, the scene unchanged)
PICK_OUTCOMES = ("mode", "expected")


class LookaheadResult(NamedTuple):
    """Scores of ``[B, N]`` candidates."""

    values: torch.Tensor  # [B, N] float32: V(f(s, a)) ([B, N, K] for a value network with K outputs)
    rewards: torch.Tensor | None  # [B, N] float32: R(f(s, a)) (reward head), when asked for
    next_holding: torch.Tensor  # [B, N] bool: predicted hand state after the action
    next_heightmap: torch.Tensor | None = None  # [B, N, 1, H, W] float32 m: predicted next scenes, when asked for
    next_in_hand: torch.Tensor | None = None  # [B, N, 1, h, h] float32 m: predicted in-hand images, when asked for
    entropy: torch.Tensor | None = None  # [B, N] float32 nats: the LDM's mean pixel entropy in B_a, when asked for
    hold_probability: torch.Tensor | None = None  # [B, N] float32: P(a pick holds) (0 at places), pick_outcome="expected"


def lookahead(
    dynamics: nn.Module,
    value_network: nn.Module,
    heightmap: torch.Tensor,
    in_hand: torch.Tensor,
    holding: torch.Tensor,
    candidates: torch.Tensor,
    *,
    chunk_size: int = 64,
    with_reward: bool = False,
    dynamics_autocast: bool = False,
    with_states: bool = False,
    with_entropy: bool = False,
    pick_outcome: str = "mode",
) -> LookaheadResult:
    """Score ``candidates`` ``[B, N, 3]`` int64 (row, col, rot) of the states ``heightmap``
    ``[B, 1, 128, 128]`` f32 m, ``in_hand`` ``[B, 1, 24, 24]`` f32 m, ``holding`` ``[B, 1]`` bool.

    ``dynamics`` is a :class:`~ldm_rl.world_model.DynamicsModel`; ``value_network`` maps
    (heightmap, in_hand) to ``[M, 1]`` values (or ``[M, K]``: K scores per state, e.g. under two sets of
    weights, giving ``values`` ``[B, N, K]``; a plain callable runs in the mode its caller set) and offers ``value_and_reward`` when ``with_reward``.
    ``dynamics_autocast``: the LDM predicts under bf16 autocast (the paper preset's heavy convolutions;
    measured slower for the lite preset), V still scores in float32. ``with_states``: also return the
    predicted next states (``next_heightmap``, ``next_in_hand``). ``with_entropy``: also return each
    prediction's uncertainty (:func:`~ldm_rl.world_model.core.pixel_entropy` of the logits already computed).
    ``pick_outcome="expected"`` (not in the paper): a pick from an empty hand scores
    ``p·V(s_held) + (1 − p)·V(s)``, its held branch and probability ``p`` from
    :meth:`~ldm_rl.world_model.DynamicsModel.held_outcome` and ``s`` the state itself (an empty pick changes
    nothing), where ``"mode"`` scores ``V`` of the predicted mode alone, which calls a pick that holds one time in
    three "no change"; places keep ``V(f(s, a))``. ``next_holding`` stays the mode's; the states returned with
    ``with_states`` are the ones V scored (a pick's held branch); not with ``with_reward``.
    """
    if not torch.is_tensor(candidates) or candidates.dim() != 3 or candidates.shape[-1] != 3:
        shape = tuple(candidates.shape) if torch.is_tensor(candidates) else type(candidates).__name__
        raise ValueError(f"candidates must be [B, N, 3] int64 (row, col, rot), got {shape}")
    if heightmap.dim() != 4 or heightmap.shape[0] != candidates.shape[0]:
        raise ValueError(f"heightmap must be [B, 1, H, W] with B = {candidates.shape[0]} (candidates' batch), got {tuple(heightmap.shape)}")
    if not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
    if pick_outcome not in PICK_OUTCOMES:
        raise ValueError(f"pick_outcome must be one of {PICK_OUTCOMES}, got {pick_outcome!r}")
    expected = pick_outcome == "expected"
    if expected and with_reward:
        raise ValueError("pick_outcome='expected' scores V alone: with_reward (R + γV, the tree's backups, Random "
                         "Shooting) has no expected-value form here; use pick_outcome='mode'")
    b, n = candidates.shape[:2]
    flat_actions = candidates.reshape(b * n, 3).long()
    owner = torch.arange(b, device=candidates.device).repeat_interleave(n)  # state row of each pair
    holding = holding.reshape(b, 1).bool()
    values, rewards, next_holding, states, entropies, holds = [], [], [], [], [], []
    with eval_mode(*(m for m in (dynamics, value_network) if isinstance(m, nn.Module))):
        if expected:  # V(s): an empty pick's outcome, once per state
            here = value_network(heightmap, in_hand)
            here = here.reshape(here.shape[0], -1)
        for start in range(0, b * n, chunk_size):
            rows = owner[start : start + chunk_size]
            with torch.autocast(heightmap.device.type, dtype=torch.bfloat16, enabled=dynamics_autocast):
                pred = dynamics.predict(
                    heightmap.index_select(0, rows),
                    in_hand.index_select(0, rows),
                    holding.index_select(0, rows),
                    flat_actions[start : start + chunk_size],
                )
            next_heightmap, next_in_hand = pred.heightmap.float(), pred.in_hand.float()
            if expected:
                picking = ~holding.index_select(0, rows).view(-1)
                held = dynamics.held_outcome(heightmap.index_select(0, rows), flat_actions[start : start + chunk_size],
                                             pred.logits)
                hold = torch.where(picking, held.probability, 0.0)
                next_heightmap = torch.where(picking.view(-1, 1, 1, 1), held.heightmap.float(), next_heightmap)
                next_in_hand = torch.where(picking.view(-1, 1, 1, 1), held.in_hand.float(), next_in_hand)
                holds.append(hold)
            if with_reward:
                value, reward = value_network.value_and_reward(next_heightmap, next_in_hand)
                rewards.append(reward.reshape(-1))
            else:
                value = value_network(next_heightmap, next_in_hand)
            value = value.reshape(value.shape[0], -1)
            if expected:
                p = hold.view(-1, 1)
                value = torch.where(picking.view(-1, 1), p * value + (1 - p) * here.index_select(0, rows), value)
            values.append(value)
            next_holding.append(pred.holding.reshape(-1))
            if with_states:
                states.append((next_heightmap, next_in_hand))
            if with_entropy:
                entropies.append(pred.entropy())
    values = torch.cat(values)
    next_states = [torch.cat(part).reshape(b, n, *part[0].shape[1:]) for part in zip(*states)] if with_states else [None, None]
    return LookaheadResult(
        values.reshape(b, n) if values.shape[1] == 1 else values.reshape(b, n, -1),
        torch.cat(rewards).reshape(b, n) if with_reward else None,
        torch.cat(next_holding).reshape(b, n),
        *next_states,
        torch.cat(entropies).reshape(b, n) if with_entropy else None,
        torch.cat(holds).reshape(b, n) if expected else None,
    )


def shooting_scores(dynamics, value_network, heightmap, in_hand, holding, candidates, *, gamma: float,
                    chunk_size: int = 64) -> torch.Tensor:
    """``R(f(s, a)) + γ·V(f(s, a))`` ``[B, N]`` of ``candidates`` ``[B, N, 3]`` (eval mode, no gradients): the
    Random Shooting score, with ``value_network``'s reward head."""
    out = lookahead(dynamics, value_network, heightmap, in_hand, holding, candidates, chunk_size=chunk_size,
                    with_reward=True)
    return out.rewards + gamma * out.values
