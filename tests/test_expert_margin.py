"""agent.expert_margin_weight: DQfD's large-margin term on the expert rows of a batch, for every Q loss.

``max_a [Q(s, a) + l·1(a ≠ a_E)] − Q(s, a_E)`` on each of the first ``expert_margin_rows`` expert rows, added to
``loss_q`` times λ; zero once the expert's action leads every other by l. With ``expert_margin_temperature`` τ > 0
the max is the soft max ``τ·logsumexp(·/τ)``."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

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
    with pytest.raises(ValueError, match="expert_margin_temperature must be a number >= 0 .* got -0.1"):
        SpatialDQNLoss(q, expert_margin_weight=1.0, expert_margin_temperature=-0.1)
    batch = expert_batch()
    del batch["is_expert"]
    with pytest.raises(KeyError, match="needs 'is_expert' in the batch"):
        SpatialDQNLoss(q, expert_margin_weight=1.0)(batch)


class MapQ(torch.nn.Module):
    """A Q 'network' whose map is one learnable tensor ``[R, H, W]``, the same for every state; the entry ``pinned``
    keeps its value (as the TD loss holds the expert's action at its return)."""

    def __init__(self, table: torch.Tensor, pinned: tuple[int, int, int] = (1, 3, 4)) -> None:
        super().__init__()
        self.table = torch.nn.Parameter(table.clone())
        keep = torch.zeros_like(table)
        keep[pinned] = 1.0
        self.register_buffer("keep", keep)
        self.register_buffer("pinned_value", table * keep)

    def forward(self, heightmap, in_hand, holding):
        table = self.table * (1 - self.keep) + self.pinned_value
        return table.expand(heightmap.shape[0], *table.shape)


def flat_top_map(ties: int = 50, rotations: int = 2, size: int = 16, seed: int = 0):
    """A map whose top is ``ties`` near-equal entries 0.01 above the expert's action at (3, 4, rotation 1)."""
    torch.manual_seed(seed)
    table = -1.0 + 0.1 * torch.rand(rotations, size, size)
    top = torch.randperm(rotations * size * size)[: ties + 1]
    table.view(-1)[top] = 0.02 + 0.001 * torch.rand(ties + 1)
    table[1, 3, 4] = 0.0
    return table


def map_batch(n: int = 1, size: int = 16):
    return TensorDict({"heightmap": torch.zeros(n, 1, size, size), "in_hand": torch.zeros(n, 1, 4, 4),
                       "holding": torch.zeros(n, 1, dtype=torch.bool), "action": torch.tensor([[3, 4, 1]] * n),
                       "is_expert": torch.ones(n, 1, dtype=torch.bool)}, batch_size=[n])


@torch.no_grad()  # values only: the gradients are the other tests'
def test_the_soft_max_is_tau_logsumexp_above_the_hard_max_and_tends_to_it():
    table = flat_top_map()
    loss = SpatialDQNLoss(MapQ(table), expert_margin_weight=1.0, expert_margin=0.1)
    batch = map_batch()
    hard = float(loss.expert_margin_loss(loss.q_network, batch))
    others = table.clone() + 0.1
    others[1, 3, 4] = table[1, 3, 4]
    assert hard == pytest.approx(float(others.max() - table[1, 3, 4]), abs=1e-6)
    for tau in (0.5, 0.05):
        loss.set_expert_margin(1.0, 0.1, 4, tau)
        soft = float(loss.expert_margin_loss(loss.q_network, batch))
        assert soft == pytest.approx(float(tau * torch.logsumexp(others.flatten() / tau, 0) - table[1, 3, 4]), rel=1e-5)
        assert soft > hard
    loss.set_expert_margin(1.0, 0.1, 4, 1e-4)
    assert float(loss.expert_margin_loss(loss.q_network, batch)) == pytest.approx(hard, abs=1e-3)


def test_the_soft_margin_lowers_every_near_tie_where_the_hard_one_lowers_only_the_argmax():
    """On a map whose top is 50 near-ties above the expert's action (held where it is, as TD holds it), 20 plain
    gradient steps of the hard term lower one entry each and leave the expert's action ranked behind most of them;
    the soft term (τ = 0.01) lowers all of them together and puts the expert's action first."""
    ranks = {}
    for tau in (0.0, 0.01):
        loss = SpatialDQNLoss(MapQ(flat_top_map()), expert_margin_weight=1.0, expert_margin=0.1,
                              expert_margin_temperature=tau)
        optimiser = torch.optim.SGD(list(loss.q_network_params.values(True, True)), lr=0.5)
        first = None
        for _ in range(20):
            optimiser.zero_grad()
            loss.expert_margin_loss(loss.q_network, map_batch()).backward()
            grad = next(iter(loss.q_network_params.values(True, True))).grad
            first = int((grad > 0).sum()) if first is None else first
            optimiser.step()
        with torch.no_grad():
            table = loss.q_network(torch.zeros(1, 1, 16, 16), None, None)[0]
        ranks[tau] = int((table > table[1, 3, 4]).sum())
        if tau == 0.0:
            assert first == 1  # the hard max: one entry lowered per step
        else:
            assert first > 50  # every near-tie (and, a little, the rest)
    assert ranks[0.0] >= 25, ranks
    assert ranks[0.01] == 0, ranks


@pytest.mark.parametrize("name", ["ldm", "fcdqn", "dynaq"])
def test_every_q_agent_built_from_the_config_trains_with_the_term(name):
    from test_baselines import batch as replay_batch, make_agent

    agent = make_agent(name, "agent.expert_margin_weight=0.1", "agent.expert_margin=0.2", "agent.expert_margin_rows=2",
                       "agent.expert_margin_temperature=0.05")
    assert (agent.loss.expert_margin_weight, agent.loss.expert_margin, agent.loss.expert_margin_rows,
            agent.loss.expert_margin_temperature) == (0.1, 0.2, 2, 0.05)
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
