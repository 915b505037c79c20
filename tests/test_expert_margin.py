"""agent.expert_margin_weight: DQfD's large-margin term on the expert rows of a batch, for every Q loss.

``max_a [Q(s, a) + l·1(a ≠ a_E)] − Q(s, a_E)`` on each of the first ``expert_margin_rows`` expert rows, added to
``loss_q`` times λ; zero once the expert's action leads every other by l."""

from __future__ import annotations

import pytest
import torch

from ldm_rl.objectives import LookaheadLoss, SpatialDQNLoss
from policy_helpers import tiny_networks, transitions

pytestmark = pytest.mark.filterwarnings("ignore:No target network updater has been associated:UserWarning")

EXPERT = torch.tensor([[True], [False], [True], [True], [False], [True]])


def expert_batch(seed: int = 0):
    batch = transitions(6, seed=seed, terminated=torch.zeros(6, 1, dtype=torch.bool))
    batch["is_expert"] = EXPERT.clone()
    return batch


def by_hand(q, batch, rows, margin):
    """The term computed from Q's own whole maps, one row at a time."""
    terms = []
    with torch.no_grad():
        for i in rows:
            maps = q(batch["heightmap"][i : i + 1], batch["in_hand"][i : i + 1], batch["holding"][i : i + 1])[0]
            row, col, rot = batch["action"][i].tolist()
            q_e = maps[rot, row, col]
            others = maps.clone()
            others[rot, row, col] = float("-inf")
            terms.append(torch.clamp(others.max() + margin - q_e, min=0.0))
    return torch.stack(terms).sum() / len(rows)


@pytest.mark.parametrize("loss_cls", [SpatialDQNLoss, LookaheadLoss])
def test_the_term_is_the_margin_violation_of_the_first_expert_rows_and_is_added_to_loss_q(loss_cls):
    q, dynamics, value = tiny_networks(0)
    nets = (q,) if loss_cls is SpatialDQNLoss else (q, dynamics, value)
    options = {} if loss_cls is SpatialDQNLoss else {"num_target_candidates": 2}
    on = loss_cls(*nets, gamma=0.9, expert_margin_weight=0.5, expert_margin=0.2, expert_margin_rows=2, **options)
    off = loss_cls(*nets, gamma=0.9, **options)
    batch = expert_batch()
    out_on, out_off = on(batch.clone()), off(batch.clone())
    expected = by_hand(on.q_network, batch, rows=[0, 2], margin=0.2)  # the first two expert rows; row 1 is the agent's
    assert expected > 0  # untrained, the expert's action is not Q's argmax by 0.2
    torch.testing.assert_close(out_on["expert_margin"], expected, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out_on["loss_q"] - out_off["loss_q"], 0.5 * expected, rtol=1e-4, atol=1e-5)
    assert "expert_margin" in on.out_keys and "expert_margin" not in off.out_keys
    assert "expert_margin" not in out_off.keys()


def test_steps_on_the_term_raise_the_experts_actions_in_q_s_ranking():
    q, _, _ = tiny_networks(1)
    loss = SpatialDQNLoss(q, gamma=0.9, expert_margin_weight=1.0, expert_margin=0.05, expert_margin_rows=2)
    batch = expert_batch(seed=3)
    rows = EXPERT.view(-1).nonzero().view(-1)[:2]
    flat = (batch["action"][rows, 2] * 128 + batch["action"][rows, 0]) * 128 + batch["action"][rows, 1]

    def term_and_ranks():
        with torch.no_grad():
            maps = loss.q_network(batch["heightmap"][rows], batch["in_hand"][rows], batch["holding"][rows]).flatten(1)
            ranks = (maps > maps.gather(1, flat.view(-1, 1))).sum(1)  # entries above the expert's action
            return float(loss.expert_margin_loss(loss.q_network, batch)), ranks

    before, ranks_before = term_and_ranks()
    optimiser = torch.optim.Adam(list(loss.q_network_params.values(True, True)), lr=1e-2)
    for _ in range(25):
        optimiser.zero_grad()
        loss.expert_margin_loss(loss.q_network, batch).backward()
        optimiser.step()
    after, ranks_after = term_and_ranks()
    assert after < 0.5 * before
    assert bool((ranks_after < ranks_before).all()), (ranks_before, ranks_after)


def test_without_expert_rows_the_term_is_zero_and_off_it_is_none():
    q, _, _ = tiny_networks(0)
    batch = expert_batch()
    batch["is_expert"] = torch.zeros(6, 1, dtype=torch.bool)
    on = SpatialDQNLoss(q, expert_margin_weight=1.0)
    assert float(on.expert_margin_loss(on.q_network, batch)) == 0.0
    assert SpatialDQNLoss(q).expert_margin_loss(q, batch) is None


def test_bad_settings_and_a_batch_without_the_flag_are_one_line_errors():
    q, _, _ = tiny_networks(0)
    with pytest.raises(ValueError, match="expert_margin_weight must be a number >= 0 .* got -1"):
        SpatialDQNLoss(q, expert_margin_weight=-1)
    with pytest.raises(ValueError, match="expert_margin must be a number > 0 .* got 0"):
        SpatialDQNLoss(q, expert_margin_weight=1.0, expert_margin=0)
    with pytest.raises(ValueError, match="expert_margin_rows must be an int >= 1, got 0"):
        SpatialDQNLoss(q, expert_margin_weight=1.0, expert_margin_rows=0)
    batch = expert_batch()
    del batch["is_expert"]
    with pytest.raises(KeyError, match="needs 'is_expert' in the batch"):
        SpatialDQNLoss(q, expert_margin_weight=1.0)(batch)


@pytest.mark.parametrize("name", ["ldm", "fcdqn", "dynaq"])
def test_every_q_agent_built_from_the_config_trains_with_the_term(name):
    from test_baselines import batch as replay_batch, make_agent

    agent = make_agent(name, "agent.expert_margin_weight=0.1", "agent.expert_margin=0.2", "agent.expert_margin_rows=2")
    assert (agent.loss.expert_margin_weight, agent.loss.expert_margin, agent.loss.expert_margin_rows) == (0.1, 0.2, 2)
    data = replay_batch(4)
    data["is_expert"] = torch.tensor([[True], [False], [True], [False]])
    metrics = agent.update(data)
    assert metrics["expert_margin"] > 0 and data["td_error"].shape == (4,)
    assert make_agent(name).loss.expert_margin_weight == 0.0  # off by default: the paper


def test_the_config_refuses_the_term_for_random_shooting():
    from ldm_rl.config_schema import ConfigError, TrainPolicyConfig, validate_config
    from test_baselines import config

    with pytest.raises(ConfigError, match="expert_margin_weight=0.1 is set but agent=rs builds no Q network"):
        validate_config(config("rs", "agent.expert_margin_weight=0.1"), TrainPolicyConfig)
