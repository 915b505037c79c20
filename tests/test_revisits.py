"""planner.revisits_last and env.scene_memory: the scenes an episode showed with an empty hand, remembered as an
observation, and the places the LDM predicts to recreate one of them ranked last (a 2-cycle's put-back)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from ldm_rl import keys
from ldm_rl.envs.memory import SceneMemory
from ldm_rl.planning.lookahead import lookahead
from ldm_rl.planning.planner import LookaheadPlanner, rank_revisits_last
from policy_helpers import scenes, tiny_networks
from test_evaluation import scene

EMPTY_CORNER = (12, 12, 0)  # no cube of the seeded scene below lies here: a pick there comes up empty


def test_rank_revisits_last_ranks_a_place_that_puts_back_what_was_picked_last():
    start, lifted = scene((20, 20, 1), (60, 60, 1)), scene((60, 60, 1))
    back, nudged = scene((20, 20, 1), (60, 60, 1)), scene((22, 21, 1), (60, 60, 1))
    stacked, elsewhere = scene((60, 60, 2)), scene((90, 30, 1), (60, 60, 1))
    predicted = torch.stack([back, nudged, stacked, elsewhere]).unsqueeze(0)  # [1, 4, 1, H, W]
    scores = torch.tensor([[0.875, 0.75, 0.5, 0.25]])  # exact in float32
    none = torch.full((1, 1, 128, 128), -1.0)
    visited = torch.cat([start.unsqueeze(0), none], 0).unsqueeze(0)  # [1, 2, 1, H, W]: the start, one empty row
    holding = torch.tensor([[True]])
    ranked = rank_revisits_last(scores, lifted.unsqueeze(0), holding, predicted, visited)
    assert ranked.tolist() == [[float("-inf"), float("-inf"), 0.5, 0.25]]  # put back, and put back 2 px off
    # a pick decision is left alone; so is a state whose every candidate is a revisit; empty rows never match
    assert torch.equal(rank_revisits_last(scores, lifted.unsqueeze(0), ~holding, predicted, visited), scores)
    assert torch.equal(rank_revisits_last(scores[:, :2], lifted.unsqueeze(0), holding, predicted[:, :2], visited),
                       scores[:, :2])
    assert torch.equal(rank_revisits_last(scores, lifted.unsqueeze(0), holding, predicted, none.unsqueeze(0)), scores)
    with pytest.raises(ValueError, match="must agree"):
        rank_revisits_last(scores, lifted.unsqueeze(0), holding, predicted[:, :3], visited)


def test_the_planner_does_not_choose_a_place_predicted_to_recreate_a_visited_scene():
    q, dynamics, value = tiny_networks(0)
    kwargs = {"num_candidates": 5, "tau": 0.05, "tau_value": 0.1}
    plain = LookaheadPlanner(q, dynamics, value, **kwargs)
    avoiding = LookaheadPlanner(q, dynamics, value, revisits_last=True, **kwargs)
    state = scenes(1, 2)
    state["holding"] = torch.ones(1, 1, dtype=torch.bool)  # a place decision
    td = TensorDict(state, batch_size=[1])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        first = plain(td.clone())
        best = int(first["candidate_values"][0].argmax())
        with torch.no_grad():
            predicted = lookahead(dynamics, value, td["heightmap"], td["in_hand"], td["holding"],
                                  first["candidate_actions"], with_states=True).next_heightmap  # [1, N, 1, H, W]
        assert ((predicted[0, best] - td["heightmap"][0]).abs() > 0.015).any()  # the chosen place changes the scene
        # the episode already showed the scene the best-scored place is predicted to make
        td[keys.VISITED_SCENES] = torch.stack([predicted[0, best], torch.full_like(predicted[0, best], -1.0)]).unsqueeze(0)
        again = avoiding(td.clone())
        ignored = plain(td.clone())  # without the option the key changes nothing
    assert torch.equal(again["candidate_actions"], first["candidate_actions"])
    assert not torch.equal(again["action"], first["action"]) and torch.equal(ignored["action"], first["action"])
    with pytest.raises(ValueError, match="revisits_last must be True or False"):
        LookaheadPlanner(q, dynamics, value, revisits_last=1)


def test_scene_memory_keeps_the_scenes_seen_with_an_empty_hand_most_recent_first():
    from ldm_rl.envs import expert_policy, make_env

    env = make_env("ldm_rl/BlockStacking-v0", num_objects=3, max_steps=8, transforms=[SceneMemory(2)])
    try:
        check_env_specs(env, seed=3)
        env.set_seed(3)
        td = env.reset()
        start = td[keys.HEIGHTMAP]
        assert torch.equal(td[keys.VISITED_SCENES][0], start) and (td[keys.VISITED_SCENES][1] == -1).all()
        td = env.step(td.set(keys.ACTION, torch.tensor(EMPTY_CORNER)))["next"]  # an empty pick: no second copy
        assert not bool(td[keys.HOLDING]) and (td[keys.VISITED_SCENES][1] == -1).all()
        td = env.step(expert_policy(env)(td))["next"]  # a pick that holds: a scene with the hand full, not kept
        assert bool(td[keys.HOLDING]) and (td[keys.VISITED_SCENES][1] == -1).all()
        td = env.step(expert_policy(env)(td))["next"]  # the place: kept in front
        placed = td[keys.HEIGHTMAP]
        assert not bool(td[keys.HOLDING]) and torch.equal(td[keys.VISITED_SCENES][0], placed)
        assert torch.equal(td[keys.VISITED_SCENES][1], start)
        td = env.step(expert_policy(env)(td))["next"]
        td = env.step(expert_policy(env)(td))["next"]  # the second pick and place: the start drops out
        assert torch.equal(td[keys.VISITED_SCENES][0], td[keys.HEIGHTMAP])
        assert torch.equal(td[keys.VISITED_SCENES][1], placed)
    finally:
        env.close()
    with pytest.raises(ValueError, match="size"):
        SceneMemory(0)


def test_revisits_last_without_the_scene_memory_is_one_config_error():
    from test_config import make_cfg

    from ldm_rl import config_schema

    cfg = make_cfg("planner.revisits_last=true", config_name="train_policy")
    with pytest.raises(config_schema.ConfigError, match=r"planner.revisits_last=true reads the scenes of env.scene_memory"):
        config_schema.validate_config(cfg, config_schema.TrainPolicyConfig)
    config_schema.validate_config(make_cfg("planner.revisits_last=true", "env.scene_memory=8", config_name="train_policy"),
                                  config_schema.TrainPolicyConfig)
    with pytest.raises(config_schema.ConfigError, match="only agent=ldm uses it"):
        config_schema.validate_config(make_cfg("agent=fcdqn", "planner.revisits_last=true", "env.scene_memory=8",
                                               config_name="train_policy"), config_schema.TrainPolicyConfig)
