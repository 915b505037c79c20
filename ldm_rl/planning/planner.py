"""``LookaheadPlanner``: the paper's policy as a TensorDict module (``env.rollout``, any TorchRL collector).

One decision, batched over ``[*B]`` states (paper §3.3–3.4):

1. ``Q`` map of the current primitive over R rotations (``action_value`` ``[*B, R, 128, 128]``);
2. N diverse candidates from ``softmax(Q/τ)`` with Gaussian inhibition (β, σ, σ_rot) around every draw
   (:func:`~ldm_rl.planning.sampling.sample_candidates`), or the reference's argmax-with-inhibition;
3. every candidate scored by ``V(f(s, a))`` in one batched pass (:func:`~ldm_rl.planning.lookahead.lookahead`);
4. the action: a draw from ``softmax(score/τ_v)`` while exploring, the best-scored candidate under
   ``ExplorationType.DETERMINISTIC`` (or MODE/MEAN); outside any exploration context TorchRL reports
   no type and the planner explores.

Option (not in the paper, off by default): ``uncertainty_penalty`` λ > 0 scores each candidate by
``V(f(s, a)) − λ·H(s, a)``, ``H`` the LDM's mean pixel entropy inside B_a
(:func:`~ldm_rl.world_model.core.pixel_entropy`, from the logits the lookahead computes anyway): among
outcomes V rates alike, the planner prefers those its model is sure of (paper §5); ``greedy_uncertainty_penalty``
sets another λ for the greedy decisions alone (explore where the model is unsure, act where it is sure);
``uncertainty_penalty_on="places"`` charges it on places alone (a pick is scored by V).
``empty_picks_last``: a pick the LDM predicts to leave the hand empty is ranked below every candidate of the same
state predicted to hold (:func:`rank_empty_picks_last`). ``revisits_last``: a place whose predicted scene is one the
episode already showed with an empty hand (``visited_scenes``, :class:`~ldm_rl.envs.memory.SceneMemory`) is ranked
below the other candidates (:func:`rank_revisits_last`): the loop of two primitives, as an empty pick is the loop of one. ``pick_outcome="expected"``: a pick scores its expected
value over its two outcomes, ``p·V(s_held) + (1 − p)·V(s)`` (:func:`~ldm_rl.planning.lookahead.lookahead`), where
the paper's mode calls a pick that holds one time in three "no change". ``pick_rotations`` K > 1: each pick
proposal is also scored at K − 1 more rotations of its pixel, evenly spaced over π
(:func:`~ldm_rl.planning.sampling.sweep_rotations`), so the LDM — not Q alone — chooses how the fingers close on
what Q points at (N·K candidates; a place decision's N proposals are scored once and repeated K times).
``q_blend`` w > 0: the choice is made on ``(1 − w)·score + w·Q(s, a)``, the model-based estimate of each candidate's
return averaged with Q's model-free estimate of the same return (:meth:`LookaheadPlanner.blend_q`); ``greedy_q_blend``
sets another w for the greedy decisions alone.

All networks run in eval mode without gradients; their train/eval flags are restored. τ, β, σ, σ_rot and
τ_v are floats or schedules ``step -> float`` (:mod:`ldm_rl.schedules`) evaluated at ``planner.step``,
which the training loop advances with :meth:`LookaheadPlanner.set_step`. The greedy policy reads them at
step 0 by default (``greedy_schedules="start"``): the widest inhibition, as the reference's test policy,
so its N proposals stay on different objects however far training has annealed exploration.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn

from ldm_rl import geometry, keys
from ldm_rl.planning.lookahead import PICK_OUTCOMES, LookaheadResult, lookahead
from ldm_rl.planning.policy import ScheduleLike, StatePolicy
from ldm_rl.planning.sampling import mask_actions, sample_candidates, sweep_rotations
from ldm_rl.torch_utils import eval_mode

__all__ = ["LookaheadPlanner", "rank_empty_picks_last", "rank_revisits_last"]

PROPOSAL_MODES = ("softmax", "argmax")
GREEDY_SCHEDULES = ("start", "current")
PENALTY_PRIMITIVES = ("all", "places")  # uncertainty_penalty_on


def rank_empty_picks_last(scores: torch.Tensor, holding: torch.Tensor, next_holding: torch.Tensor) -> torch.Tensor:
    """``scores`` ``[B, N]`` with ``-inf`` at every pick predicted to come up empty, in the states where another
    candidate is predicted to hold.

    An empty pick leaves the scene as it was, so (the dynamics deterministic) its value is γ·V*(s) — below
    V*(s), the value of the best action, whenever that is positive: never the best choice while anything else
    can be done. V scores such a pick by V(s) itself, so wherever V over-rates the current state the greedy
    planner repeats the pick to the step limit (docs/policy.md, "Empty picks"). ``holding`` ``[B]`` or
    ``[B, 1]`` (bool / 0-1: a place decision is left as it is), ``next_holding`` ``[B, N]`` bool, the LDM's
    predicted hand state. A state whose candidates are all predicted empty keeps its scores.
    """
    if scores.dim() != 2 or next_holding.shape != scores.shape or holding.numel() != scores.shape[0]:
        raise ValueError(f"scores [B, N], next_holding [B, N] and holding [B] must agree, got "
                         f"{tuple(scores.shape)}, {tuple(next_holding.shape)} and {tuple(holding.shape)}")
    empty = ~holding.reshape(-1, 1).bool() & ~next_holding.bool()
    return scores.masked_fill(empty & (~empty).any(dim=1, keepdim=True), float("-inf"))


def rank_revisits_last(scores: torch.Tensor, heightmap: torch.Tensor, holding: torch.Tensor, next_heightmap: torch.Tensor,
                       visited: torch.Tensor, *, changed: float = 0.015, restored: float = 0.5) -> torch.Tensor:
    """``scores`` ``[B, N]`` with ``-inf`` at every place predicted to recreate a scene of ``visited``, in the states
    where another candidate is not.

    A place changes ``m`` pixels of the scene ``heightmap`` ``[B, 1, H, W]`` (m) by more than ``changed`` m in its
    predicted scene (``next_heightmap`` ``[B, N, 1, H, W]``); it recreates a visited scene ``[B, M, 1, H, W]`` (``-1``
    rows: none) when the two differ in at most ``restored``·``m`` pixels: a block put back within ≈ 3 px of where its
    pick took it (the rule of :func:`ldm_rl.evaluation.undone_places`). With deterministic dynamics such a place
    undoes the primitives since that scene, and the state's value is discounted by every step of the loop: never
    the best choice while another action exists. ``holding`` ``[B]`` or ``[B, 1]``: a pick decision is left as it is.
    """
    b, n = scores.shape
    if next_heightmap.shape[:2] != (b, n) or heightmap.shape[0] != b or visited.shape[0] != b or holding.numel() != b:
        raise ValueError(f"scores [B, N], heightmap [B, 1, H, W], next_heightmap [B, N, 1, H, W], visited [B, M, 1, H, W] "
                         f"and holding [B] must agree, got {tuple(scores.shape)}, {tuple(heightmap.shape)}, "
                         f"{tuple(next_heightmap.shape)}, {tuple(visited.shape)} and {tuple(holding.shape)}")
    moved = ((next_heightmap - heightmap.unsqueeze(1)).abs() > changed).flatten(2).sum(2)  # [B, N]
    differs = ((next_heightmap.unsqueeze(2) - visited.unsqueeze(1)).abs() > changed).flatten(3).sum(3)  # [B, N, M]
    revisit = (differs <= restored * moved.unsqueeze(2)).any(2) & (moved > 0) & holding.reshape(b, 1).bool()
    return scores.masked_fill(revisit & (~revisit).any(dim=1, keepdim=True), float("-inf"))


def _repeat_result(result: LookaheadResult, k: int) -> LookaheadResult:
    """Every ``[B, N, ...]`` field of ``result`` with each candidate repeated ``k`` times: ``[B, N·K, ...]``."""
    return LookaheadResult(*(None if x is None else x.repeat_interleave(k, dim=1) for x in result))


def _merge_results(first: LookaheadResult, first_rows: torch.Tensor, second: LookaheadResult,
                   second_rows: torch.Tensor) -> LookaheadResult:
    """One result over the states ``first_rows`` ∪ ``second_rows`` (``[B1]``, ``[B2]`` int64, a partition of
    ``0 … B1 + B2 − 1``) from the results of each part."""
    def merge(a, b):
        if a is None:
            return None
        out = a.new_empty((len(first_rows) + len(second_rows), *a.shape[1:]))
        return out.index_copy_(0, first_rows, a).index_copy_(0, second_rows, b)

    return LookaheadResult(*(merge(a, b) for a, b in zip(first, second)))


class LookaheadPlanner(StatePolicy):
    """Q proposals → LDM lookahead → V scores → action.

    Args:
        q_network: ``(heightmap, in_hand, holding) -> [B, R, H, W]`` Q of the current primitive.
        dynamics: the :class:`~ldm_rl.world_model.DynamicsModel`.
        value_network: ``(heightmap, in_hand) -> [B, 1]``.
        num_candidates: N proposals per decision.
        tau, beta, sigma, sigma_rot: proposal temperature (Q units), inhibition height, its width in
            pixels and in rotation bins (floats or schedules).
        tau_value: temperature of the final choice among the N scores (V units) while exploring.
        proposal: ``"softmax"`` (paper) or ``"argmax"`` (reference code) while exploring.
        greedy_proposal: the proposal mode under DETERMINISTIC (``"argmax"``: a deterministic policy).
        greedy_schedules: ``"start"``: under DETERMINISTIC the schedules are read at step 0 (the reference's
            test policy keeps its initial inhibition window); ``"current"``: at :attr:`step`, as when exploring.
        chunk_size: state-candidate pairs per LDM/V pass.
        autocast: ``None`` (float32) or ``"bf16"``: the Q map and the LDM predictions under bf16 autocast,
            V in float32 (the paper preset's decision ≈ 1.7× faster on an AVX-512-bf16 CPU; the lite
            preset is slower in bf16: measure before enabling).
        write_action_value: also write the ``[*B, R, H, W]`` Q map (``action_value``), 512 KB per state.
        uncertainty_penalty: λ ≥ 0 (V units per nat): candidates are scored ``V − λ·H`` (0 = the paper).
        greedy_uncertainty_penalty: λ of the greedy decisions (under DETERMINISTIC) when it differs from the
            exploring one; ``None``: ``uncertainty_penalty`` for both.
        uncertainty_penalty_on: the primitives λ·H is charged on: ``"all"``, or ``"places"`` (a pick is scored by V
            alone, a place by ``V − λ·H``).
        empty_picks_last: picks the LDM predicts to leave the hand empty are scored ``-inf`` where another
            candidate is predicted to hold (:func:`rank_empty_picks_last`; False = the paper).
        pick_outcome: ``"mode"`` (the paper: V of the LDM's most likely outcome) or ``"expected"`` (a pick from an
            empty hand scores ``p·V(s_held) + (1 − p)·V(s)``, ``p`` the LDM's probability that it holds).
        pick_rotations: K, rotations each pick proposal is scored at (an int dividing Q's R; 1 = the paper).
        revisits_last: places predicted to recreate a scene of ``visited_scenes`` are scored ``-inf`` where another
            candidate is not (:func:`rank_revisits_last`; False = the paper; without the key it does nothing).
        q_blend: w in [0, 1]: the choice is made on ``(1 − w)·score + w·Q(s, a)`` (:meth:`blend_q`), the model-based
            estimate of each candidate's return averaged with Q's model-free one (0 = the paper; 1 = Q's ranking of
            its own proposals, which keep their ``-inf`` marks).
        greedy_q_blend: w of the greedy decisions (under DETERMINISTIC) when it differs from the exploring one;
            ``None``: ``q_blend`` for both.
        q_log_floor: None (Q is fitted on returns) or ε: Q is fitted on ``log(max(y, ε))`` (the agent's
            ``q_log_floor``); ``q_blend`` reads it back as ``exp(Q)``.

    Reads ``heightmap``, ``in_hand``, ``holding`` and, if present, ``failed_picks`` (never proposed again) and
    ``visited_scenes`` (with ``revisits_last``);
    writes ``action`` ``[*B, 3]``, ``candidate_actions``
    ``[*B, N·K, 3]``, ``candidate_values`` ``[*B, N·K]`` (``V(f(s, a))``; K = ``pick_rotations``), ``state_value``
    ``[*B, 1]``, ``action_value`` and, with either λ > 0, ``candidate_entropy`` ``[*B, N·K]`` (nats).
    """

    def __init__(
        self,
        q_network: nn.Module,
        dynamics: nn.Module,
        value_network: nn.Module,
        *,
        num_candidates: int = 10,
        tau: ScheduleLike = 1.0,
        beta: ScheduleLike = 1.0,
        sigma: ScheduleLike = 2.0,
        sigma_rot: ScheduleLike = 1.0,
        tau_value: ScheduleLike = 0.1,
        proposal: str = "softmax",
        greedy_proposal: str = "argmax",
        greedy_schedules: str = "start",
        chunk_size: int = 64,
        autocast: str | None = None,
        write_action_value: bool = True,
        uncertainty_penalty: float = 0.0,
        greedy_uncertainty_penalty: float | None = None,
        uncertainty_penalty_on: str = "all",
        empty_picks_last: bool = False,
        pick_outcome: str = "mode",
        pick_rotations: int = 1,
        revisits_last: bool = False,
        q_blend: float = 0.0,
        greedy_q_blend: float | None = None,
        q_log_floor: float | None = None,
    ) -> None:
        super().__init__(tau=tau, beta=beta, sigma=sigma, sigma_rot=sigma_rot, tau_value=tau_value)
        for name, value, allowed in (("q_blend", q_blend, ""), ("greedy_q_blend", greedy_q_blend, " or None")):
            if allowed and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= 1:
                raise ValueError(f"{name} must be a number in [0, 1] (the weight of Q in the decision score){allowed}, "
                                 f"got {value!r}")
        if q_log_floor is not None and (isinstance(q_log_floor, bool) or not isinstance(q_log_floor, (int, float))
                                        or not 0 < q_log_floor < 1):
            raise ValueError(f"q_log_floor must be None (Q on the return scale) or a number in (0, 1) (Q fitted as "
                             f"log(max(y, q_log_floor))), got {q_log_floor!r}")
        self.q_blend, self.q_log_floor = float(q_blend), q_log_floor
        self.greedy_q_blend = None if greedy_q_blend is None else float(greedy_q_blend)
        for name, value, allowed in (("uncertainty_penalty", uncertainty_penalty, ""),
                                     ("greedy_uncertainty_penalty", greedy_uncertainty_penalty, " or None")):
            if allowed and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
                raise ValueError(f"{name} must be a number >= 0 (V units per nat){allowed}, got {value!r}")
        self.uncertainty_penalty = float(uncertainty_penalty)
        self.greedy_uncertainty_penalty = (None if greedy_uncertainty_penalty is None
                                           else float(greedy_uncertainty_penalty))
        self.with_entropy = bool(self.uncertainty_penalty or self.greedy_uncertainty_penalty)  # H computed, written
        if uncertainty_penalty_on not in PENALTY_PRIMITIVES:
            raise ValueError(f"uncertainty_penalty_on must be one of {PENALTY_PRIMITIVES} (the primitives λ·H is charged "
                             f"on), got {uncertainty_penalty_on!r}")
        self.uncertainty_penalty_on = uncertainty_penalty_on
        if not isinstance(empty_picks_last, bool):
            raise ValueError(f"empty_picks_last must be True or False, got {empty_picks_last!r}")
        self.empty_picks_last = empty_picks_last
        if not isinstance(revisits_last, bool):
            raise ValueError(f"revisits_last must be True or False, got {revisits_last!r}")
        self.revisits_last = revisits_last
        if pick_outcome not in PICK_OUTCOMES:
            raise ValueError(f"pick_outcome must be one of {PICK_OUTCOMES}, got {pick_outcome!r}")
        self.pick_outcome = pick_outcome
        self.lookahead_options: dict[str, bool] = {}  # extra lookahead outputs :meth:`backup` reads
        self.num_rotations = getattr(q_network, "num_rotations", 1)
        if isinstance(pick_rotations, bool) or not isinstance(pick_rotations, int) or pick_rotations < 1 \
                or self.num_rotations % pick_rotations:
            raise ValueError(f"pick_rotations must be an int >= 1 dividing Q's num_rotations={self.num_rotations}, "
                             f"got {pick_rotations!r}")
        self.pick_rotations = pick_rotations
        actions = self.num_rotations * geometry.HEIGHTMAP_SIZE**2  # entries of one Q map
        if not isinstance(num_candidates, int) or isinstance(num_candidates, bool) or not 1 <= num_candidates <= actions:
            raise ValueError(f"num_candidates must be an int in [1, {actions}] (the Q map's rotations x pixels), "
                             f"got {num_candidates!r}")
        for name, mode in (("proposal", proposal), ("greedy_proposal", greedy_proposal)):
            if mode not in PROPOSAL_MODES:
                raise ValueError(f"{name} must be one of {PROPOSAL_MODES}, got {mode!r}")
        if greedy_schedules not in GREEDY_SCHEDULES:
            raise ValueError(f"greedy_schedules must be one of {GREEDY_SCHEDULES}, got {greedy_schedules!r}")
        self.greedy_schedules = greedy_schedules
        if autocast not in (None, "bf16"):
            raise ValueError(f"autocast must be None or 'bf16', got {autocast!r}")
        self.autocast = autocast
        self.q_network, self.dynamics, self.value_network = q_network, dynamics, value_network
        self.num_candidates, self.proposal, self.greedy_proposal = num_candidates, proposal, greedy_proposal
        self.chunk_size, self.write_action_value = int(chunk_size), bool(write_action_value)
        self.out_keys = [keys.ACTION, keys.CANDIDATE_ACTIONS, keys.CANDIDATE_VALUES, keys.STATE_VALUE] + (
            [keys.ACTION_VALUE] if write_action_value else []
        ) + ([keys.CANDIDATE_ENTROPY] if self.with_entropy else [])

    def penalty(self, *, greedy: bool) -> float:
        """λ of the exploring (``greedy=False``) or the greedy decisions."""
        if greedy and self.greedy_uncertainty_penalty is not None:
            return self.greedy_uncertainty_penalty
        return self.uncertainty_penalty

    def blend_weight(self, *, greedy: bool) -> float:
        """w of Q in the exploring (``greedy=False``) or the greedy decisions."""
        if greedy and self.greedy_q_blend is not None:
            return self.greedy_q_blend
        return self.q_blend

    def charged_entropy(self, entropy: torch.Tensor, holding: torch.Tensor) -> torch.Tensor:
        """The ``[B, N]`` entropies (nats) of candidates taken from states holding ``[B]`` or ``[B, 1]`` that λ is
        charged on: all of them, or with ``uncertainty_penalty_on="places"`` those of the holding rows (0 elsewhere)."""
        if self.uncertainty_penalty_on == "places":
            return entropy * holding.reshape(-1, 1).to(entropy.dtype)
        return entropy

    def hyperparameters(self, *, greedy: bool = False) -> dict[str, float]:
        """The schedules' values (τ, β, σ, σ_rot, τ_v) used when exploring (``greedy=False``, at :attr:`step`)
        or by the greedy policy."""
        step = 0 if greedy and self.greedy_schedules == "start" else self.step
        return {name: float(schedule(step)) for name, schedule in self.schedules.items()}

    def check_input(self, tensordict: TensorDictBase) -> None:
        super().check_input(tensordict)
        for key, size in ((keys.HEIGHTMAP, geometry.HEIGHTMAP_SIZE), (keys.IN_HAND, geometry.HAND_SIZE)):
            shape, want = tuple(tensordict.get(key).shape), (*tensordict.batch_size, 1, size, size)
            if shape != want:  # checked here, on the caller's shapes (decide sees them with a batch dim added)
                raise ValueError(f"{key} must have shape {want} (batch size {tuple(tensordict.batch_size)} + "
                                 f"[1, {size}, {size}] metres), got {shape}")

    def propose(self, heightmap, in_hand, holding, hp: dict[str, float], *, greedy: bool, avoid=None):
        """``(Q map [B, R, H, W], candidates [B, N·K, 3])`` of flat states (networks already in eval mode; K =
        ``pick_rotations``, :func:`~ldm_rl.planning.sampling.sweep_rotations` at the picks); no candidate lies near
        one of ``avoid`` ``[B, M, 3]`` (:func:`~ldm_rl.planning.sampling.mask_actions`)."""
        with torch.autocast(heightmap.device.type, dtype=torch.bfloat16, enabled=self.autocast == "bf16"):
            q_map = self.q_network(heightmap, in_hand, holding).float()
        candidates = sample_candidates(
            q_map if avoid is None else mask_actions(q_map, avoid), self.num_candidates, tau=hp["tau"], beta=hp["beta"], sigma=hp["sigma"],
            sigma_rot=hp["sigma_rot"], mode=self.greedy_proposal if greedy else self.proposal,
        )
        if self.pick_rotations > 1:
            candidates = sweep_rotations(candidates, self.num_rotations, self.pick_rotations,
                                         active=~holding.reshape(-1).bool(), avoid=avoid)
        return q_map, candidates

    def score(self, heightmap, in_hand, holding, candidates, penalty: float, *, swept: bool = False, visited=None,
              **options):
        """``(scores [B, N], lookahead result)``: ``V(f(s, a)) − λ·H(s, a)`` of ``candidates`` ``[B, N, 3]``,
        λ = ``penalty`` (``-inf`` at predicted empty picks with ``empty_picks_last``, at places predicted to recreate
        one of the ``visited`` ``[B, M, 1, H, W]`` scenes with ``revisits_last``); ``options`` go to
        :func:`~ldm_rl.planning.lookahead.lookahead` (``with_states``, ``with_reward``). ``swept``: the candidates
        come from :meth:`propose` with ``pick_rotations`` K > 1, so a place state's K copies of each proposal are
        predicted once."""
        def predict(rows, actions):
            return lookahead(self.dynamics, self.value_network, heightmap[rows], in_hand[rows], holding[rows], actions,
                             chunk_size=self.chunk_size, dynamics_autocast=self.autocast == "bf16",
                             with_entropy=self.with_entropy, pick_outcome=self.pick_outcome, **options)

        revisits = self.revisits_last and visited is not None
        if revisits:
            options = {**options, "with_states": True}
        k = self.pick_rotations if swept else 1
        placing = holding.reshape(-1).bool()
        if k == 1 or not placing.any():
            result = predict(slice(None), candidates)
        else:
            places = placing.nonzero().squeeze(1)
            result = _repeat_result(predict(places, candidates[places, ::k]), k)
            if not placing.all():
                picks = (~placing).nonzero().squeeze(1)
                result = _merge_results(predict(picks, candidates[picks]), picks, result, places)
        scores = result.values
        if penalty:
            scores = scores - penalty * self.charged_entropy(result.entropy, holding)
        if self.empty_picks_last:
            scores = rank_empty_picks_last(scores, holding, result.next_holding)
        if revisits:
            scores = rank_revisits_last(scores, heightmap, holding, result.next_heightmap, visited)
        return scores, result

    def blend_q(self, scores: torch.Tensor, q_map: torch.Tensor, candidates: torch.Tensor,
                weight: float | None = None) -> torch.Tensor:
        """``(1 − w)·scores + w·Q(s, a)`` ``[B, N]``, w = ``weight`` (``None``: ``q_blend``): each candidate's score (``V(f(s, a))`` less
        any penalty, ``[B, N]``) averaged with Q's own estimate of the same return, read off ``q_map``
        ``[B, R, H, W]`` at ``candidates`` ``[B, N, 3]`` (row, col, rotation) and brought to the return scale
        (``exp`` for a Q fitted on ``log(max(y, q_log_floor))``). A ``-inf`` score (a ranked-last candidate) stays
        ``-inf``; a candidate where Q's map is ``-inf`` (outside its frame) becomes ``-inf``."""
        flat = geometry.action_to_flat(candidates.long(), *q_map.shape[-2:])  # [B, N]
        q = q_map.flatten(1).gather(1, flat).to(scores.dtype)
        if self.q_log_floor is not None:
            q = q.exp()
        w = self.q_blend if weight is None else float(weight)
        return torch.where(torch.isneginf(scores), scores, (1 - w) * scores + w * q)

    @staticmethod
    def choose(scores: torch.Tensor, hp: dict[str, float], *, greedy: bool) -> torch.Tensor:
        """``[B]`` index of the chosen candidate: the best score (first on ties) or a draw from softmax(score/τ_v)."""
        if greedy:
            return scores.argmax(-1)
        return torch.multinomial(torch.softmax(scores / hp["tau_value"], -1), 1).squeeze(-1)

    def backup(self, result, scores: torch.Tensor, hp: dict[str, float], holding: torch.Tensor) -> torch.Tensor:
        """The ``[B, N]`` scores the choice is made on, from the one-step ``scores`` and the lookahead ``result`` of
        the states' candidates (``holding`` ``[B, 1]``: the states' hand; here: the one-step scores; planners that
        look further ahead override it)."""
        return scores

    def decide(self, heightmap, in_hand, holding, *, greedy: bool, avoid=None, visited=None) -> dict[str, torch.Tensor]:
        """Flat ``[B]`` states -> ``{action, candidate_actions, candidate_values, state_value[, action_value]
        [, candidate_entropy][, candidate_scores]}`` (``avoid``, ``visited``: :meth:`StatePolicy.decide`)."""
        hp = {**self.hyperparameters(greedy=greedy), "uncertainty_penalty": self.penalty(greedy=greedy)}
        with eval_mode(self.q_network, self.dynamics, self.value_network):
            q_map, candidates = self.propose(heightmap, in_hand, holding, hp, greedy=greedy, avoid=avoid)
            scores, result = self.score(heightmap, in_hand, holding, candidates, hp["uncertainty_penalty"],
                                        swept=self.pick_rotations > 1, visited=visited, **self.lookahead_options)
            scores = self.backup(result, scores, hp, holding)
            weight = self.blend_weight(greedy=greedy)
            if weight:
                scores = self.blend_q(scores, q_map, candidates, weight)
            choice = self.choose(scores, hp, greedy=greedy)
            action = candidates.gather(1, choice.view(-1, 1, 1).expand(-1, 1, 3)).squeeze(1)
            state_value = self.value_network(heightmap, in_hand)
        out = {
            keys.ACTION: action,
            keys.CANDIDATE_ACTIONS: candidates,
            keys.CANDIDATE_VALUES: result.values,
            keys.STATE_VALUE: state_value,
        }
        if self.write_action_value:
            out[keys.ACTION_VALUE] = q_map
        if self.with_entropy:
            out[keys.CANDIDATE_ENTROPY] = result.entropy
        if keys.CANDIDATE_SCORES in self.out_keys:
            out[keys.CANDIDATE_SCORES] = scores
        return out
