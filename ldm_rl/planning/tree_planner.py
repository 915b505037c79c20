"""``TreePlanner``: the paper's planner looking ``depth`` primitives ahead through the LDM (not in the paper).

The one-step planner rates an action by ``V(f(s, a))`` alone; a mistake V cannot see from the next state
(a placement that leaves no good place for the following block, paper §5) is only seen one step later.
This planner expands a tree over imagined states, one batched LDM pass per depth:

1. depth 1: N proposals from Q(s), each predicted and scored as the one-step planner does
   (``V − λ·H`` with an ``uncertainty_penalty`` λ);
2. the best ``branching`` K of them are expanded: Q proposes N actions on each *predicted* state
   (argmax with inhibition, deterministic), the LDM predicts them, V scores them; recursively to ``depth``;
3. each expanded node is backed up as V's own target is formed (``ldm_rl.objectives.LookaheadLoss``: V
   includes the reward received on arriving)::

       score(s, a) = R(ŝ') − λ·H(s, a) + γ · (1 − T(ŝ')) · max_{a'} score(ŝ', a'),   ŝ' = f(s, a)

   with ``R`` V's reward head and ``T(ŝ') = [R(ŝ') > terminal_reward]``: every task here rewards only its
   terminal success, so a predicted success ends its branch; the leaves score ``V − λ·H``. With ``penalty_depth``
   d, ``λ·H`` is charged at the first d steps only (1: the first action's prediction, whose entropy is read off the
   real scene);
4. the action is chosen among the K expanded first actions by their backed-up score (greedy: the best,
   first on ties; exploring: a draw from ``softmax(score/τ_v)``).

Cost per decision (depth 2): 1 + K Q maps and N·(1 + K) LDM predictions (N = 10, K = 3: measured 4.4× the
one-step planner's time, docs/planning.md). ``depth=1`` is the one-step planner; ``branching=1`` with a constant V picks the
one-step planner's first proposal.
"""

from __future__ import annotations

import torch
from torch import nn

from ldm_rl import keys
from ldm_rl.planning.planner import LookaheadPlanner
from ldm_rl.planning.sampling import sample_candidates

__all__ = ["TreePlanner", "TREE_KEYS"]

# the constructor arguments only this planner reads (beside LookaheadPlanner's)
TREE_KEYS = ("depth", "branching", "gamma", "terminal_reward", "penalty_depth")


class TreePlanner(LookaheadPlanner):
    """Q proposals → LDM → V, expanded ``depth`` primitives deep over the best ``branching`` candidates.

    Args (beside :class:`~ldm_rl.planning.planner.LookaheadPlanner`'s):
        depth: primitives looked ahead (1 = the one-step planner; 2 or 3 in practice).
        branching: K, candidates expanded per node (1 ≤ K ≤ ``num_candidates``).
        gamma: the agent's discount γ of the backed-up scores (the V targets' γ).
        terminal_reward: a predicted state whose predicted reward exceeds this ends its branch (> 0).
        penalty_depth: with an ``uncertainty_penalty`` λ, the steps of the tree where ``λ·H`` is charged: the first
            ``penalty_depth`` (1 = the first action's prediction alone, whose entropy is read off the real scene; the
            deeper ones are read off predicted scenes); None = every depth.

    ``value_network`` needs ``value_and_reward`` (the LDM agent's V has its reward head). Writes what the
    one-step planner writes and ``candidate_scores`` ``[*B, N]``: the backed-up score of each expanded first
    candidate, ``-inf`` for the others.
    """

    def __init__(self, q_network: nn.Module, dynamics: nn.Module, value_network: nn.Module, *, depth: int = 2,
                 branching: int = 3, gamma: float, terminal_reward: float = 0.1, penalty_depth: int | None = None,
                 **kwargs) -> None:
        super().__init__(q_network, dynamics, value_network, **kwargs)
        if isinstance(depth, bool) or not isinstance(depth, int) or depth < 1:
            raise ValueError(f"depth must be an int >= 1 (primitives looked ahead), got {depth!r}")
        if isinstance(branching, bool) or not isinstance(branching, int) or not 1 <= branching <= self.num_candidates:
            raise ValueError(f"branching must be an int in [1, num_candidates={self.num_candidates}], got {branching!r}")
        if not isinstance(gamma, (int, float)) or isinstance(gamma, bool) or not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be a number in [0, 1], got {gamma!r}")
        if not isinstance(terminal_reward, (int, float)) or isinstance(terminal_reward, bool) or not terminal_reward > 0:
            raise ValueError(f"terminal_reward must be a number > 0, got {terminal_reward!r}")
        if depth > 1 and not hasattr(value_network, "value_and_reward"):
            raise ValueError(f"depth={depth} backs scores up through V's reward head: value_network "
                             f"{type(value_network).__name__} has no value_and_reward")
        if depth > 1 and self.pick_outcome != "mode":
            raise ValueError(f"pick_outcome={self.pick_outcome!r} is the one-step planner's (depth=1): the tree backs "
                             f"up R + γV through one predicted state per candidate; got depth={depth}")
        if penalty_depth is not None and (isinstance(penalty_depth, bool) or not isinstance(penalty_depth, int)
                                          or not 1 <= penalty_depth <= depth):
            raise ValueError(f"penalty_depth must be None (every depth) or an int in [1, depth={depth}], got {penalty_depth!r}")
        self.depth, self.branching = depth, branching
        self.penalty_depth = depth if penalty_depth is None else penalty_depth
        self.lookahead_options = {"with_states": depth > 1, "with_reward": depth > 1}
        self.gamma, self.terminal_reward = float(gamma), float(terminal_reward)
        self.out_keys = [*self.out_keys, keys.CANDIDATE_SCORES]

    def backup(self, result, scores: torch.Tensor, hp: dict[str, float], holding: torch.Tensor) -> torch.Tensor:
        """The depth-``depth`` scores of the first candidates (``-inf`` where not expanded)."""
        return scores if self.depth == 1 else self._expand(result, scores, self.depth - 1, hp, holding)

    def _expand(self, result, scores: torch.Tensor, remaining: int, hp: dict[str, float],
                holding: torch.Tensor) -> torch.Tensor:
        """Back up the best K of ``scores`` ``[M, N]`` (their predicted states, rewards and entropies in the
        lookahead ``result``; ``holding`` ``[M, 1]``, the hand of the states they were taken from) over ``remaining``
        more primitives: ``[M, N]``, ``-inf`` where not expanded."""
        m, n = scores.shape
        k = self.branching
        best = scores.sort(dim=1, descending=True, stable=True).indices[:, :k]  # [M, K], first index on ties

        def pick(x):  # [M, N, ...] -> [M·K, ...], the expanded candidates' rows
            index = best.view(m, k, *([1] * (x.dim() - 2))).expand(m, k, *x.shape[2:])
            return x.gather(1, index).flatten(0, 1)

        continuation = self._continuation(pick(result.next_heightmap), pick(result.next_in_hand),
                                          pick(result.next_holding).view(-1, 1), remaining, hp)
        reward = pick(result.rewards)
        live = (reward <= self.terminal_reward).float()
        node = reward + self.gamma * live * continuation
        penalty = self._penalty(hp, self.depth - remaining)  # these nodes are actions at that depth
        if penalty:
            node = node - penalty * pick(self.charged_entropy(result.entropy, holding))
        return torch.full_like(scores, float("-inf")).scatter(1, best, node.view(m, k))

    def _penalty(self, hp: dict[str, float], depth: int) -> float:
        """λ charged on the predictions of actions at ``depth`` (1 = the first action): 0 beyond ``penalty_depth``."""
        return hp["uncertainty_penalty"] if depth <= self.penalty_depth else 0.0

    def _continuation(self, heightmap, in_hand, holding, remaining: int, hp: dict[str, float]) -> torch.Tensor:
        """``[M]``: the best score reachable from the predicted states ``[M]`` within ``remaining`` primitives."""
        q_map = self.q_network(heightmap, in_hand, holding).float()
        candidates = sample_candidates(q_map, self.num_candidates, beta=hp["beta"], sigma=hp["sigma"],
                                       sigma_rot=hp["sigma_rot"], mode="argmax")
        deeper = remaining > 1
        scores, result = self.score(heightmap, in_hand, holding, candidates,
                                    self._penalty(hp, self.depth - remaining + 1), with_states=deeper, with_reward=deeper)
        if deeper:
            scores = self._expand(result, scores, remaining - 1, hp, holding)
        return scores.amax(1)
