"""What every transition loss of the agents shares: its input keys (TorchRL ``_AcceptedKeys``), ``in_keys``, the
return lower bound and the expert large-margin term of the Q losses."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from ldm_rl import keys

__all__ = ["TransitionKeys", "TransitionLoss"]


@dataclass
class TransitionKeys:
    """State, action, reward, termination, and the replay's priority keys; change them with
    ``loss.set_keys(...)``. A loss that reads more subclasses it (``class _AcceptedKeys(TransitionKeys)``)."""

    heightmap: NestedKey = keys.HEIGHTMAP
    in_hand: NestedKey = keys.IN_HAND
    holding: NestedKey = keys.HOLDING
    action: NestedKey = keys.ACTION
    reward: NestedKey = (keys.NEXT, keys.REWARD)
    terminated: NestedKey = (keys.NEXT, keys.TERMINATED)
    priority: NestedKey = "td_error"
    priority_weight: NestedKey = "priority_weight"
    return_to_go: NestedKey = "return_to_go"
    index: NestedKey = "index"  # the replay's row index (a TorchRL replay sample's "index"): cache key
    is_expert: NestedKey = "is_expert"  # the action came from the expert (the replay's flag): the margin term's rows


class TransitionLoss(LossModule):
    """Base of the agents' losses over flat batches of transitions: declares the keys and the inputs.

    ``in_keys`` = the state, the action, the next state, the reward and the termination flag.
    """

    _AcceptedKeys = TransitionKeys
    default_keys = TransitionKeys
    tensor_keys: TransitionKeys

    #: raise a target to the return the episode actually collected from the transition on (set by subclasses)
    return_lower_bound: bool = False
    #: λ, l, the row cap and the temperature of the expert large-margin term (:meth:`expert_margin_loss`; λ = 0: off)
    expert_margin_weight: float = 0.0
    expert_margin: float = 0.1
    expert_margin_rows: int = 4
    expert_margin_temperature: float = 0.0

    def set_expert_margin(self, weight: float = 0.0, margin: float = 0.1, rows: int = 4,
                          temperature: float = 0.0) -> None:
        """Switch the expert large-margin term on (``weight`` λ > 0) or off (0); checks the four numbers."""
        for name, value, ok, want in (
                ("expert_margin_weight", weight, lambda v: v >= 0, "a number >= 0 (0 = off)"),
                ("expert_margin", margin, lambda v: v > 0, "a number > 0 (Q's fitted units)"),
                ("expert_margin_temperature", temperature, lambda v: v >= 0,
                 "a number >= 0 (Q's fitted units; 0 = the hard max)")):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not ok(value):
                raise ValueError(f"{name} must be {want}, got {value!r}")
        if isinstance(rows, bool) or not isinstance(rows, int) or rows < 1:
            raise ValueError(f"expert_margin_rows must be an int >= 1, got {rows!r}")
        self.expert_margin_weight, self.expert_margin, self.expert_margin_rows = float(weight), float(margin), rows
        self.expert_margin_temperature = float(temperature)

    def expert_margin_loss(self, q_network, tensordict: TensorDictBase) -> torch.Tensor | None:
        """DQfD's large-margin term (Hester et al. 2018) on the batch's expert rows; None when off.

        For each of the first ``expert_margin_rows`` rows whose ``is_expert`` is set, with ``a_E`` its action and
        ``Q`` its whole map ``[R, H, W]`` (on Q's fitted scale, log with ``q_log_floor``; ``-inf`` entries never
        proposed stay out): ``max_a [Q(s, a) + l·1(a ≠ a_E)] − Q(s, a_E) ≥ 0``, zero once the expert's action
        leads every other by ``l``. Returns the mean over those rows, ``[]`` float32 (0 without expert rows, or where
        ``a_E`` is masked). The TD loss fits Q's values; this term orders them, so Q's argmax and proposals learn
        the expert's pose (pixel and rotation) from the demonstrations, not only from their returns. Costs one
        forward and backward pass of the whole map (all R rotations) per row: hence the cap.

        With ``expert_margin_temperature`` τ > 0 the max becomes the soft max ``τ·logsumexp(·/τ)`` (≥ the hard
        one, equal as τ → 0): its gradient lowers every action near the top in proportion to its softmax weight,
        not the single argmax, so a flat map whose top holds thousands of near-ties is pushed below the expert's
        action as a whole. At l = 0 it is τ times the expert's negative log-likelihood under softmax(Q/τ), the
        planner's own proposal distribution at that temperature.
        """
        if not self.expert_margin_weight:
            return None
        k = self.tensor_keys
        rows = self.expert_rows(tensordict, "expert_margin_weight")
        if rows.numel() == 0:
            return tensordict.get(k.heightmap).new_zeros(())
        state = [tensordict.get(key).index_select(0, rows) for key in (k.heightmap, k.in_hand)]
        holding = tensordict.get(k.holding).reshape(-1, 1).bool().index_select(0, rows)
        q_map = q_network(*state, holding).float().flatten(1)  # [n, R·H·W]
        action = tensordict.get(k.action).reshape(-1, 3).long().index_select(0, rows)
        height, width = state[0].shape[-2:]
        flat = ((action[:, 2] * height + action[:, 0]) * width + action[:, 1]).unsqueeze(1)  # [n, 1]
        q_expert = q_map.gather(1, flat)  # [n, 1]
        live = torch.isfinite(q_expert).squeeze(1)  # a masked expert action has no margin to keep
        if not bool(live.any()):
            return q_map.new_zeros(())
        q_map, flat, q_expert = q_map[live], flat[live], q_expert[live]
        with_margin = (q_map + self.expert_margin).scatter(1, flat, q_expert)
        tau = self.expert_margin_temperature
        top = tau * torch.logsumexp(with_margin / tau, 1, keepdim=True) if tau else with_margin.amax(1, keepdim=True)
        return ((top - q_expert).sum() / rows.numel()).reshape(())

    def expert_rows(self, tensordict: TensorDictBase, option: str) -> torch.Tensor:
        """``[n]`` int64: the first ``expert_margin_rows`` rows of the batch whose ``is_expert`` is set (a margin
        term's rows); a ``KeyError`` naming ``option`` (the term's switch) when the batch has no such flag."""
        flags = tensordict.get(self.tensor_keys.is_expert, None)
        if flags is None:
            raise KeyError(f"{type(self).__name__} with {option} > 0 needs {self.tensor_keys.is_expert!r} in the batch "
                           "(FrameReplay samples carry it)")
        return flags.reshape(-1).bool().nonzero().squeeze(1)[: self.expert_margin_rows]

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def lower_bounded(self, target: torch.Tensor, tensordict: TensorDictBase, key=None) -> torch.Tensor:
        """``max(target, return_to_go)`` ``[B, 1]`` when ``return_lower_bound`` is on, else ``target``.

        ``return_to_go`` ``[B, 1]`` is ``Σ_k γ^k r_{t+k}`` of the transition's own episode (``-inf`` where the
        episode was truncated): written by :class:`~ldm_rl.data.FrameReplay` built with ``return_gamma = γ``.
        A return some policy collected is a lower bound of the optimal value, so the bootstrapped target
        cannot sink below what the agent (or the expert) actually reached (He et al. 2017, "optimality
        tightening"); it can still rise above it. ``key``: read the bound elsewhere, e.g. ``("next",
        "return_to_go")`` (the return from the *next* step on, for a value that excludes the arrival reward).
        """
        if not self.return_lower_bound:
            return target
        key = self.tensor_keys.return_to_go if key is None else key
        bound = tensordict.get(key, None)
        if bound is None:
            raise KeyError(f"{type(self).__name__}(return_lower_bound=True) needs {key!r} "
                           "in the batch: sample from FrameReplay(return_gamma=gamma)")
        return torch.maximum(target, bound.reshape(-1, 1).to(target))

    def check_batch(self, tensordict: TensorDictBase) -> None:
        """The input is a flat, non-empty batch of transitions with every in-key (one ``ValueError`` otherwise)."""
        keys.require_keys(tensordict, self.in_keys, type(self).__name__)
        if tensordict.batch_dims != 1 or tensordict.batch_size[0] == 0:
            raise ValueError(f"{type(self).__name__} needs a flat, non-empty batch of transitions, got batch_size "
                             f"{tuple(tensordict.batch_size)}")

    def importance_weights(self, tensordict: TensorDictBase, like: torch.Tensor) -> torch.Tensor:
        """``[B, 1]`` prioritized-replay importance weights (``priority_weight``), ones without them; as ``like``."""
        weight = tensordict.get(self.tensor_keys.priority_weight, None)
        return torch.ones_like(like) if weight is None else weight.reshape(-1, 1).to(like)

    @property
    def in_keys(self) -> list[NestedKey]:
        k = self.tensor_keys
        state = [k.heightmap, k.in_hand, k.holding]
        return [*state, k.action, *[(keys.NEXT, key) for key in state], k.reward, k.terminated]
