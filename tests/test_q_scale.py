"""QScale and the losses that fit Q on it: a log scale changes what Q regresses, never the targets."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from ldm_rl.objectives import LookaheadLoss, SpatialDQNLoss
from ldm_rl.objectives.q_scale import QScale
from policy_helpers import tiny_networks, transitions

pytestmark = pytest.mark.filterwarnings("ignore:No target network updater has been associated:UserWarning")


def test_log_scale_is_increasing_invertible_above_the_floor_and_flat_below():
    scale = QScale(0.01)
    returns = torch.tensor([0.0, 0.005, 0.01, 0.02, 0.3, 1.0])
    q = scale.encode(returns)
    assert torch.equal(q[:3], torch.full((3,), math.log(0.01)))
    assert bool((q[2:].diff() > 0).all())
    torch.testing.assert_close(scale.decode(q[2:]), returns[2:])
    # the gap of an empty pick (a factor γ) is log(1/γ) whatever the return's size
    gamma = 0.87
    for r in (0.03, 0.3):
        assert scale.encode(torch.tensor(r)) - scale.encode(torch.tensor(gamma * r)) == pytest.approx(-math.log(gamma))
    linear = QScale(None)
    assert torch.equal(linear.encode(returns), returns) and torch.equal(linear.decode(returns), returns)


@pytest.mark.parametrize("floor", [0, 1, 1.5, -0.1, True, "0.1"])
def test_bad_floor_is_refused_in_one_line(floor):
    with pytest.raises(ValueError, match=r"q_log_floor must be null .* got") as info:
        QScale(floor)
    assert "\n" not in str(info.value)


def test_lookahead_loss_fits_q_on_the_log_of_unchanged_targets():
    q, dynamics, value = tiny_networks(0)
    linear = LookaheadLoss(q, dynamics, value, gamma=0.9, num_target_candidates=3, chunk_size=5)
    q, dynamics, value = tiny_networks(0)
    logged = LookaheadLoss(q, dynamics, value, gamma=0.9, num_target_candidates=3, chunk_size=5,
                           q_target="lookahead", q_log_floor=0.05)
    batch = transitions(6, terminated=torch.tensor([[True], [False], [False], [True], [False], [False]]))
    y_q, y_v = logged.targets(batch.clone())
    assert torch.equal(y_q, y_v)  # the lookahead target is V's, on the return scale
    torch.testing.assert_close(y_v, linear.targets(batch.clone())[1])
    out = logged(batch.clone())
    with torch.no_grad():
        q_pred = logged.q_network.action_values(batch["heightmap"], batch["in_hand"], batch["holding"],
                                                batch["action"]).reshape(-1, 1)
    torch.testing.assert_close(out["loss_q"], F.smooth_l1_loss(q_pred, y_q.clamp_min(0.05).log()))
    torch.testing.assert_close(out["q_target"], y_q.mean())


def test_dqn_loss_reads_the_target_map_back_from_the_log_scale():
    q = tiny_networks(0)[0]
    loss = SpatialDQNLoss(q, gamma=0.9, q_log_floor=0.01)
    batch = transitions(4, terminated=torch.tensor([[True], [False], [False], [False]]))
    with torch.no_grad(), loss.target_q_network_params.to_module(loss.q_network):
        q_map = loss.q_network.eval()(batch["next", "heightmap"], batch["next", "in_hand"], batch["next", "holding"])
    y = loss.targets(batch)
    reward = batch["next", "reward"].reshape(-1, 1)
    assert torch.equal(y[:1], reward[:1])
    torch.testing.assert_close(y[1:], reward[1:] + 0.9 * q_map[1:].flatten(1).amax(1, keepdim=True).exp())
    out = loss(batch)
    assert torch.isfinite(out["loss_q"]) and batch["td_error"].shape == (4,)
    with pytest.raises(ValueError, match="q_log_floor"):
        SpatialDQNLoss(q, q_log_floor=0.0)


@pytest.mark.parametrize("name", ["ldm", "fcdqn", "dynaq"])
def test_agent_q_log_floor_reaches_the_agents_q_loss(name):
    from test_baselines import make_agent

    assert make_agent(name).loss.q_scale.log_floor is None  # the paper's linear Q by default
    assert make_agent(name, "agent.q_log_floor=0.01").loss.q_scale.log_floor == 0.01
