"""``RandomShootingPlanner``: random actions near objects, each scored through the LDM by ``R + γ·V``.

N candidates drawn uniformly near the scene's objects (:class:`~ldm_rl.planning.sampling.NearObjectSampler`),
one batched LDM → (V, R) pass (:func:`~ldm_rl.planning.lookahead.shooting_scores`); a draw from
``softmax(score/τ_v)`` while exploring, the best score when greedy (the candidates stay random: RS's greedy
policy is stochastic by construction). No Q network.
"""

from __future__ import annotations

import torch
from torch import nn

from ldm_rl import keys
from ldm_rl.planning.lookahead import shooting_scores
from ldm_rl.planning.policy import ScheduleLike, StatePolicy
from ldm_rl.planning.sampling import NearObjectSampler

__all__ = ["RandomShootingPlanner"]


class RandomShootingPlanner(StatePolicy):
    """RS policy: random near-object candidates → LDM → ``R + γ·V`` → action.

    Args:
        dynamics: the :class:`~ldm_rl.world_model.DynamicsModel`.
        value_network: ``(heightmap, in_hand) -> [B, 1]`` with ``value_and_reward``.
        num_candidates: N candidates per decision.
        gamma: discount of the score.
        height_threshold, dilation: the candidate rule (metres, pixels).
        tau_value: temperature of the choice among the N scores while exploring (float or schedule).
        chunk_size: state-candidate pairs per LDM/V pass.

    Writes ``action`` ``[*B, 3]``, ``candidate_actions`` ``[*B, N, 3]`` and ``candidate_values``
    ``[*B, N]`` (the scores).
    """

    out_keys = [keys.ACTION, keys.CANDIDATE_ACTIONS, keys.CANDIDATE_VALUES]

    def __init__(
        self,
        dynamics: nn.Module,
        value_network: nn.Module,
        *,
        num_candidates: int = 10,
        gamma: float = 0.95,
        height_threshold: float = 0.01,
        dilation: int = 8,
        tau_value: ScheduleLike = 0.1,
        chunk_size: int = 64,
    ) -> None:
        super().__init__(tau_value=tau_value)
        if not isinstance(num_candidates, int) or isinstance(num_candidates, bool) or num_candidates < 1:
            raise ValueError(f"num_candidates must be a positive int, got {num_candidates!r}")
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma!r}")
        self.dynamics, self.value_network = dynamics, value_network
        self.num_candidates, self.gamma, self.chunk_size = num_candidates, float(gamma), int(chunk_size)
        self.rule = NearObjectSampler(dynamics.num_rotations, height_threshold, dilation)

    def decide(self, heightmap, in_hand, holding, *, greedy: bool, avoid=None, visited=None) -> dict[str, torch.Tensor]:
        # avoid (failed picks) is not used: fresh uniform candidates each step rarely repeat an action
        candidates = self.rule(heightmap, self.num_candidates)
        scores = shooting_scores(self.dynamics, self.value_network, heightmap, in_hand, holding, candidates,
                                 gamma=self.gamma, chunk_size=self.chunk_size)
        if greedy:
            choice = scores.argmax(-1)
        else:
            choice = torch.multinomial(torch.softmax(scores / self.hyperparameters()["tau_value"], -1), 1).squeeze(-1)
        action = candidates.gather(1, choice.view(-1, 1, 1).expand(-1, 1, 3)).squeeze(1)
        return {keys.ACTION: action, keys.CANDIDATE_ACTIONS: candidates, keys.CANDIDATE_VALUES: scores}
