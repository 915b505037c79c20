"""The lookahead planner: greedy = best-scored candidate, exploration over candidates, eval mode, rollouts."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from ldm_rl.planning.lookahead import lookahead
from ldm_rl.planning.planner import LookaheadPlanner
from ldm_rl.schedules import Linear
from policy_helpers import scenes, tiny_networks


@pytest.fixture(scope="module")
def nets():
    return tiny_networks(0)


def make_planner(nets, **kwargs):
    q, dynamics, value = nets
    return LookaheadPlanner(q, dynamics, value, **{"num_candidates": 5, "tau": 0.05, "tau_value": 0.1, **kwargs})


def batch(n=4, seed=0):
    return TensorDict(scenes(n, seed), batch_size=[n])


def test_deterministic_picks_the_best_scored_candidate_and_repeats(nets):
    planner = make_planner(nets)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        first = planner(batch())
        second = planner(batch())
    best = first["candidate_values"].argmax(-1)
    expected = first["candidate_actions"][torch.arange(4), best]
    assert torch.equal(first["action"], expected)
    assert torch.equal(first["action"], second["action"])
    assert first["candidate_actions"].shape == (4, 5, 3) and first["candidate_values"].shape == (4, 5)
    assert first["action_value"].shape == (4, 8, 128, 128) and first["state_value"].shape == (4, 1)


def test_one_candidate_greedy_is_the_argmax_of_the_q_map(nets):
    """num_candidates=1 (evaluate.py's planner.num_candidates=1): Q alone decides, V only scores its choice."""
    from ldm_rl.geometry import flat_to_action

    planner = make_planner(nets, num_candidates=1)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = planner(batch())
    q_map = out["action_value"]  # [4, R, H, W]
    expected = flat_to_action(q_map.reshape(4, -1).argmax(-1), 128, 128)
    assert torch.equal(out["action"], expected) and out["candidate_actions"].shape == (4, 1, 3)


def test_candidate_values_are_v_of_the_predicted_next_states(nets):
    q, dynamics, value = nets
    planner = make_planner(nets)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = planner(batch(3))
    s = scenes(3)
    with torch.no_grad():
        pred = dynamics.eval().predict(s["heightmap"][:, None].expand(3, 5, 1, 128, 128), s["in_hand"][:, None].expand(3, 5, 1, 24, 24),
                                       s["holding"][:, None].expand(3, 5, 1), out["candidate_actions"])
        v = value.eval()(pred.heightmap.reshape(15, 1, 128, 128), pred.in_hand.reshape(15, 1, 24, 24)).reshape(3, 5)
    torch.testing.assert_close(out["candidate_values"], v)


def test_exploring_draws_among_candidates_following_softmax_of_scores(nets):
    torch.manual_seed(0)
    planner = make_planner(nets, tau_value=1e6, proposal="argmax")  # flat softmax over the 5 scores
    same = batch(1).expand(12).clone()  # one scene 12 times: the same 5 candidates in every row
    with set_exploration_type(ExplorationType.RANDOM):
        out = planner(same)
    match = (out["candidate_actions"] == out["action"][:, None]).all(-1)  # [12, 5]: the action is one candidate
    assert match.sum(-1).tolist() == [1] * 12 and (out["candidate_actions"] == out["candidate_actions"][:1]).all()
    assert len(set(match.float().argmax(-1).tolist())) >= 3  # near-uniform draws, not the best score each time
    # the draw itself (what the planner calls while exploring): frequencies follow softmax(score / tau_v)
    scores = torch.tensor([[0.30, 0.25, 0.20, 0.10, 0.0]]).expand(20_000, 5)
    drawn = LookaheadPlanner.choose(scores, {"tau_value": 0.05}, greedy=False)
    frequency = torch.bincount(drawn, minlength=5).float() / len(drawn)
    torch.testing.assert_close(frequency, torch.softmax(scores[0] / 0.05, -1), atol=0.01, rtol=0)
    assert torch.equal(LookaheadPlanner.choose(scores[:1], {"tau_value": 0.05}, greedy=True), torch.tensor([0]))
    greedy = make_planner(nets, tau_value=1e-6, proposal="argmax")
    with set_exploration_type(ExplorationType.RANDOM):
        out = greedy(batch(1))
    assert torch.equal(out["action"][0], out["candidate_actions"][0, out["candidate_values"][0].argmax()])


def test_networks_keep_their_mode_and_batchnorm_statistics(nets):
    q, dynamics, value = nets
    for module in nets:
        module.train()
    before = {k: v.clone() for k, v in dynamics.state_dict().items() if "running" in k or "num_batches" in k}
    make_planner(nets)(batch(2))
    after = dynamics.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert q.training and dynamics.training and value.training


def test_unbatched_and_multi_dim_batches(nets):
    planner = make_planner(nets)
    single = planner(batch(1)[0])
    assert single["action"].shape == (3,) and single["candidate_values"].shape == (5,)
    grid = planner(TensorDict(scenes(6), batch_size=[6]).reshape(2, 3))
    assert grid["action"].shape == (2, 3, 3)


def test_schedules_follow_the_step(nets):
    planner = make_planner(nets, tau=Linear(1.0, 0.1, 10))
    assert planner.hyperparameters()["tau"] == 1.0
    planner.set_step(10)
    assert planner.hyperparameters()["tau"] == pytest.approx(0.1)


def test_greedy_proposals_use_the_start_inhibition_unless_asked_for_the_current(nets):
    # late in training the 1-px inhibition packs the argmax proposals together; the greedy policy keeps them apart
    def closest_pair_px(greedy_schedules):
        planner = make_planner(nets, proposal="argmax", sigma=Linear(8.0, 1.0, 100), sigma_rot=Linear(2.0, 0.5, 100),
                               greedy_schedules=greedy_schedules)
        planner.set_step(100)
        assert planner.hyperparameters()["sigma"] == 1.0
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            position = planner(batch(2))["candidate_actions"][..., :2].float()  # [B, N, 2]
        distance = torch.cdist(position, position) + 1e9 * torch.eye(position.shape[1])
        return planner.hyperparameters(greedy=True)["sigma"], distance.amin((-1, -2))

    sigma_start, closest_start = closest_pair_px("start")
    sigma_current, closest_current = closest_pair_px("current")
    assert (sigma_start, sigma_current) == (8.0, 1.0)
    assert (closest_start > closest_current).all(), (closest_start, closest_current)


def test_lookahead_is_chunk_invariant(nets):
    q, dynamics, value = nets
    s = scenes(3)
    cands = torch.stack([torch.randint(16, 112, (3, 4)), torch.randint(16, 112, (3, 4)), torch.randint(0, 8, (3, 4))], -1)
    a = lookahead(dynamics, value, s["heightmap"], s["in_hand"], s["holding"], cands, chunk_size=1).values
    b = lookahead(dynamics, value, s["heightmap"], s["in_hand"], s["holding"], cands, chunk_size=64).values
    torch.testing.assert_close(a, b)


def test_bad_input_is_one_clear_error(nets):
    planner = make_planner(nets)
    with pytest.raises(ValueError, match="missing keys"):
        planner(TensorDict({"heightmap": torch.zeros(1, 1, 128, 128)}, batch_size=[1]))
    bad = batch(1)
    bad["heightmap"] = torch.zeros(1, 1, 64, 64)
    with pytest.raises(ValueError, match="heightmap"):
        planner(bad)
    with pytest.raises(ValueError, match="num_candidates"):
        make_planner(nets, num_candidates=0)
    with pytest.raises(ValueError, match="proposal"):
        make_planner(nets, proposal="best")
    # too many candidates for the Q map: refused at construction, naming the argument and the limit
    with pytest.raises(ValueError, match=r"num_candidates must be an int in \[1, 131072\] .* got 131073"):
        make_planner(nets, num_candidates=131073)
    # an unbatched state: the error quotes the shape the caller passed, not one with a batch dim added
    single = batch(1)[0]
    single["heightmap"] = torch.zeros(1, 64, 64)
    with pytest.raises(ValueError, match=r"heightmap must have shape \(1, 128, 128\) .* got \(1, 64, 64\)$"):
        planner(single)


@pytest.mark.slow
def test_env_rollout_with_the_planner(nets):
    from ldm_rl.envs import make_env

    env = make_env("ldm_rl/BlockStacking-v0", num_objects=2, max_steps=2)
    env.set_seed(0)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = env.rollout(2, make_planner(nets))
    env.close()
    assert rollout["action"].shape == (2, 3) and rollout["candidate_actions"].shape == (2, 5, 3)


def test_bf16_autocast_scores_the_same_candidates_in_float32(nets):
    q, dynamics, value = nets
    plain, fast = make_planner(nets, proposal="argmax"), make_planner(nets, proposal="argmax", autocast="bf16")
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        ref, out = plain(batch(2)), fast(batch(2))
    assert out["candidate_values"].dtype == torch.float32 and out["action_value"].dtype == torch.float32
    # V in float32 on the bf16 LDM's predictions: the same scores as a float32 pass on those candidates
    s = scenes(2)
    expected = lookahead(dynamics, value, s["heightmap"], s["in_hand"], s["holding"].reshape(2, 1),
                         out["candidate_actions"], dynamics_autocast=True).values
    torch.testing.assert_close(out["candidate_values"], expected)
    torch.testing.assert_close(out["action_value"], ref["action_value"], atol=0.05, rtol=0.05)
    with pytest.raises(ValueError, match="autocast must be None or 'bf16'"):
        make_planner(nets, autocast="fp16")
