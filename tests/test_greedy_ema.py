"""agent.greedy_ema_decay: the greedy policy plays an exponential moving average of the online weights and
BatchNorm statistics; training itself is unchanged."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from test_baselines import batch, make_agent, states

AGENT_NAMES = ("ldm", "fcdqn", "rs", "dynaq")


def _planner_state(module) -> dict[str, torch.Tensor]:
    """Float parameters and buffers of a planner, by name."""
    return {k: v.detach().clone() for k, v in module.state_dict().items() if v.is_floating_point()}


@pytest.mark.parametrize("name", AGENT_NAMES)
def test_the_average_leaves_training_unchanged_and_follows_the_ema_recursion(name):
    decay = 0.8
    plain, averaged = make_agent(name, seed=3), make_agent(name, f"agent.greedy_ema_decay={decay}", seed=3)
    assert averaged.greedy_policy is averaged.policy  # nothing averaged yet: the online planner plays
    expected = None
    for seed in range(2):  # a copy, then one lerp
        for agent in (plain, averaged):  # the same draws for both (RS's target candidates are random)
            torch.manual_seed(seed)
            agent.update(batch(4, seed))
        online = _planner_state(averaged.policy)
        # the first update copies, later ones lerp by 1 - decay (weights and BatchNorm statistics alike)
        expected = online if expected is None else {k: decay * expected[k] + (1 - decay) * online[k] for k in online}
        assert averaged.greedy_policy is not averaged.policy
        got = _planner_state(averaged.greedy_policy)
        assert got.keys() == expected.keys()
        for key in expected:
            torch.testing.assert_close(got[key], expected[key], rtol=1e-5, atol=1e-7, msg=key)
    running = [k for k in expected if k.endswith("running_mean")]
    assert running or name in ("fcdqn", "dynaq")  # the LDM / V BatchNorm statistics too (a Q-map policy has none)
    # the online networks trained exactly as without the average
    plain_state, averaged_state = plain.state_dict(), averaged.state_dict()
    for key, value in plain_state.items():
        assert torch.equal(value, averaged_state[key]), key
    # and the two greedy policies now decide differently from each other only through the weights
    assert any(not torch.equal(expected[k], _planner_state(averaged.policy)[k]) for k in expected)


def test_the_averaged_greedy_policy_survives_a_policy_state_round_trip():
    agent = make_agent("ldm", "agent.greedy_ema_decay=0.5", seed=1)
    for seed in range(2):
        agent.update(batch(4, seed))
    state = agent.policy_state_dict()
    assert any(key.startswith("averaged_planner.module.") for key in state) and "averaged_planner.n_averaged" in state
    copy = make_agent("ldm", "agent.greedy_ema_decay=0.5", seed=9)
    copy.load_policy_state_dict(state)
    probe = states(2, seed=4)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        a = agent.greedy_policy(probe.clone())
        b = copy.greedy_policy(probe.clone())
    assert torch.equal(a["action"], b["action"]) and torch.equal(a["candidate_values"], b["candidate_values"])


@pytest.mark.parametrize("decay", ["0", "1", "1.5"])
def test_a_decay_outside_the_open_unit_interval_is_refused(decay):
    with pytest.raises(ValueError, match=r"greedy_ema_decay"):
        make_agent("ldm", f"agent.greedy_ema_decay={decay}")


@pytest.mark.parametrize("name", AGENT_NAMES)
def test_evaluation_policy_plays_the_average_or_on_request_the_online_weights(name):
    averaged = make_agent(name, "agent.greedy_ema_decay=0.5", seed=2)
    averaged.update(batch(4, 0))
    assert averaged.evaluation_policy() is averaged.greedy_policy is not averaged.policy
    assert averaged.evaluation_policy(online_weights=True) is averaged.policy
    plain = make_agent(name, seed=2)
    assert plain.evaluation_policy() is plain.policy
    with pytest.raises(ValueError, match=r"needs a run trained with agent.greedy_ema_decay"):
        plain.evaluation_policy(online_weights=True)


def test_a_tail_shortens_the_average_to_that_fraction_of_the_updates_so_far():
    decay, tail = 0.9, 0.5
    agent = make_agent("fcdqn", f"agent.greedy_ema_decay={decay}", f"agent.greedy_ema_tail={tail}", seed=5)
    expected = None
    for n in range(6):  # n earlier averages: decays min(0.9, 1 - 1/max(1, n/2)) = copy, 0, 0, 1/3, 1/2, 0.6
        agent.update(batch(4, n))
        online = _planner_state(agent.policy)
        d = min(decay, 1 - 1 / max(1.0, tail * n))
        expected = online if expected is None else {k: d * expected[k] + (1 - d) * online[k] for k in online}
    got = _planner_state(agent.greedy_policy)
    for key in expected:
        torch.testing.assert_close(got[key], expected[key], rtol=1e-5, atol=1e-7, msg=key)
    # two updates at decay 0 would have left the current weights: the tail is what made it an average
    assert any(not torch.equal(got[k], online[k]) for k in got)


@pytest.mark.parametrize("overrides, message", [
    (["agent.greedy_ema_tail=0.5"], r"greedy_ema_tail=0.5 needs greedy_ema_decay"),
    (["agent.greedy_ema_decay=0.99", "agent.greedy_ema_tail=1.5"], r"greedy_ema_tail must be a number in \(0, 1\]"),
])
def test_a_tail_without_a_decay_or_out_of_range_is_refused(overrides, message):
    with pytest.raises(ValueError, match=message):
        make_agent("ldm", *overrides)


@pytest.mark.parametrize("name", ["ldm", "rs"])
def test_without_the_model_the_greedy_policy_plans_with_the_online_model_and_averaged_values(name):
    agent = make_agent(name, "agent.greedy_ema_decay=0.5", "agent.greedy_ema_model=false", seed=4)
    for seed in range(3):
        agent.update(batch(4, seed))
    online, averaged = agent.policy, agent.greedy_policy
    assert averaged is not online
    model_online, model_averaged = online.dynamics.state_dict(), averaged.dynamics.state_dict()
    assert all(torch.equal(model_online[k], model_averaged[k]) for k in model_online)
    value_online, value_averaged = _planner_state(online.value_network), _planner_state(averaged.value_network)
    assert any(not torch.equal(value_online[k], value_averaged[k]) for k in value_online)  # V is still averaged


@pytest.mark.parametrize("overrides, message", [
    (["agent.greedy_ema_model=false"], r"greedy_ema_model=False needs greedy_ema_decay"),
])
def test_leaving_the_model_out_needs_an_average(overrides, message):
    with pytest.raises(ValueError, match=message):
        make_agent("ldm", *overrides)


def test_leaving_the_model_out_of_a_policy_without_one_is_refused():
    with pytest.raises(ValueError, match=r"plans with no model"):
        make_agent("fcdqn", "agent.greedy_ema_decay=0.5", "agent.greedy_ema_model=false")
