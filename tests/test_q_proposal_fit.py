"""agent.q_proposal_fit: Q is also fitted on the target's own proposals at each next state, toward the
lookahead score V⁻(f⁻(s', a')) the target computed for them; the targets themselves do not change."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from ldm_rl.objectives import LookaheadLoss
from ldm_rl.planning.lookahead import lookahead
from ldm_rl.planning.sampling import sample_candidates
from policy_helpers import tiny_networks, transitions

pytestmark = pytest.mark.filterwarnings("ignore:No target network updater has been associated:UserWarning")

TERMINATED = torch.tensor([[False], [True], [False], [False], [True], [False]])


def make_loss(fit: int, **options) -> LookaheadLoss:
    q, dynamics, value = tiny_networks(0)
    return LookaheadLoss(q, dynamics, value, gamma=0.9, num_target_candidates=3, chunk_size=5, target_range=(0.0, 1.0),
                         q_target="lookahead", q_proposal_fit=fit, **options)


def test_q_is_fitted_on_the_first_proposals_toward_their_target_scores_and_the_targets_do_not_change():
    fitted, plain = make_loss(2, q_log_floor=0.05), make_loss(0, q_log_floor=0.05)
    batch = transitions(6, terminated=TERMINATED)
    y_q, y_v, (rows, actions, values) = fitted._targets(batch.clone())
    for a, b in zip((y_q, y_v), plain.targets(batch.clone())):
        torch.testing.assert_close(a, b)
    live = (~TERMINATED.view(-1)).nonzero().view(-1)
    assert torch.equal(rows, live) and actions.shape == (4, 2, 3) and values.shape == (4, 2)
    # what the target networks say at the live next states: their Q map's first proposals and those proposals' V⁻∘f⁻
    nxt = [batch["next", key][live] for key in ("heightmap", "in_hand", "holding")]
    with torch.no_grad(), fitted.target_networks():
        nets = (fitted.q_network.eval(), fitted.dynamics.eval(), fitted.value_network.eval())
        proposals = sample_candidates(nets[0](*nxt), 3, **fitted.target_proposal)
        scores = lookahead(nets[1], nets[2], *nxt, proposals, chunk_size=5).values
    assert torch.equal(actions, proposals[:, :2])
    torch.testing.assert_close(values, scores[:, :2].clamp(0, 1))
    # loss_q: the taken action's term plus the proposals' term, each a mean Huber loss on Q's log scale
    fitted.train(), plain.train()
    extra = fitted(batch.clone())["loss_q"] - plain(batch.clone())["loss_q"]
    with torch.no_grad():
        pairs = [x.repeat_interleave(2, 0) for x in nxt]
        q_pred = fitted.q_network.action_values(pairs[0], pairs[1], pairs[2].view(-1), actions.reshape(-1, 3))
    expected = F.smooth_l1_loss(q_pred, values.reshape(-1).clamp_min(0.05).log())
    torch.testing.assert_close(extra, expected, rtol=1e-5, atol=1e-6)
    assert expected > 0


def test_a_step_on_the_proposal_term_moves_q_of_the_proposals_toward_their_scores():
    loss = make_loss(3)
    batch = transitions(6, terminated=TERMINATED)
    _, _, (rows, actions, values) = loss._targets(batch.clone())
    nxt = [batch["next", key][rows].repeat_interleave(3, 0) for key in ("heightmap", "in_hand", "holding")]

    def error() -> float:
        with torch.no_grad():
            q = loss.q_network.action_values(nxt[0], nxt[1], nxt[2].view(-1), actions.reshape(-1, 3))
        return float((q - values.reshape(-1)).abs().mean())

    before = error()
    params = list(loss.q_network_params.values(True, True))
    optimiser = torch.optim.SGD(params, lr=0.05)
    weight = torch.ones(6, 1)
    for _ in range(5):
        optimiser.zero_grad()
        loss._proposal_fit_loss(batch, weight, rows, actions, values).backward()
        optimiser.step()
    assert error() < 0.9 * before


def test_the_cache_keeps_the_proposals_with_their_scores():
    cached = make_loss(2, bootstrap_cache=16)
    batch = transitions(6, terminated=TERMINATED)
    batch["index"] = torch.arange(6)
    first, second = cached._targets(batch.clone()), cached._targets(batch.clone())
    assert cached.bootstrap_cache.hits == 4  # the second call read every live row from the cache
    for a, b in zip(first[2], second[2]):
        assert torch.equal(a, b)


@pytest.mark.parametrize("value", [-1, 4, True, 1.5])
def test_bad_q_proposal_fit_is_refused_in_one_line(value):
    q, dynamics, value_network = tiny_networks(0)
    with pytest.raises(ValueError, match=r"q_proposal_fit must be an int in \[0, num_target_candidates=3\]") as info:
        LookaheadLoss(q, dynamics, value_network, num_target_candidates=3, q_proposal_fit=value)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("overrides, message", [
    (("agent=fcdqn", "agent.q_proposal_fit=1"), r"agent.q_proposal_fit=1 is set but only agent=ldm uses it"),
    (("agent.num_target_candidates=3", "agent.q_proposal_fit=4"), r"agent.q_proposal_fit=4 exceeds agent.num_target_candidates=3"),
])
def test_misuse_in_the_config_is_one_clear_error(overrides, message):
    from ldm_rl.config_schema import SCHEMAS, ConfigError, validate_config
    from test_planning_options import _composed

    composed, _ = _composed(*overrides)
    with pytest.raises(ConfigError, match=message):
        validate_config(composed, SCHEMAS["train_policy"])


def test_the_agent_option_reaches_the_loss():
    from test_baselines import make_agent

    assert make_agent("ldm").loss.q_proposal_fit == 0  # the paper: Q fitted on the taken action only
    assert make_agent("ldm", "agent.q_proposal_fit=2").loss.q_proposal_fit == 2
