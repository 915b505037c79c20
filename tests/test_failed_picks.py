"""FailedPickMemory (an env transform) and the Q-map policies that never repeat a pick that came up empty."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from ldm_rl import keys
from ldm_rl.envs.memory import FailedPickMemory
from ldm_rl.planning.planner import LookaheadPlanner
from ldm_rl.planning.q_map import QMapPolicy
from ldm_rl.planning.sampling import mask_actions
from benchmark_loader import load_benchmark
from policy_helpers import scenes, tiny_networks

EMPTY_CORNER = (12, 12, 0)  # a pick far from every cube of the seeded scenes below: the hand stays empty


def test_mask_actions_matches_a_loop_oracle_and_ignores_padding():
    g = torch.Generator().manual_seed(0)
    q = torch.randn(2, 6, 9, 9, generator=g)
    avoid = torch.tensor([[[4, 4, 0], [-1, -1, -1]], [[0, 8, 5], [8, 1, 2]]])
    masked = mask_actions(q, avoid, radius=2.0, rot_radius=1)
    expect = q.clone()
    for b in range(2):
        for row, col, rot in avoid[b].tolist():
            if row < 0:
                continue
            for k in range(6):
                if min((k - rot) % 6, (rot - k) % 6) > 1:
                    continue
                for i in range(9):
                    for j in range(9):
                        if (i - row) ** 2 + (j - col) ** 2 <= 4:
                            expect[b, k, i, j] = -math.inf
    assert torch.equal(masked, expect) and torch.isfinite(q).all()  # bin 5 wraps to bin 0; q untouched
    assert torch.equal(mask_actions(q, torch.full((2, 3, 3), -1)), q)
    with pytest.raises(ValueError, match="actions"):
        mask_actions(q, avoid[0])
    with pytest.raises(ValueError, match="integer"):
        mask_actions(q, avoid.float())
    with pytest.raises(ValueError, match="radius"):
        mask_actions(q, avoid, radius=-1.0)


def _memory_env():
    from ldm_rl.envs import make_env

    env = make_env("ldm_rl/BlockStacking-v0", num_objects=2, max_steps=6, transforms=[FailedPickMemory(2)])
    env.set_seed(3)
    return env


@pytest.mark.slow
def test_memory_records_empty_picks_and_clears_when_the_hand_changes():
    from ldm_rl.envs import expert_policy

    env = _memory_env()
    try:
        check_env_specs(env, seed=3)
        td = env.reset()
        assert td[keys.FAILED_PICKS].tolist() == [[-1, -1, -1]] * 2
        memories = []
        for action in (EMPTY_CORNER, (20, 12, 3), (12, 20, 1)):
            td = env.step(td.set(keys.ACTION, torch.tensor(action)))["next"]
            memories.append(td[keys.FAILED_PICKS].tolist())
        assert memories == [[list(EMPTY_CORNER), [-1, -1, -1]], [[20, 12, 3], list(EMPTY_CORNER)],
                            [[12, 20, 1], [20, 12, 3]]]  # most recent first, the oldest dropped
        td = env.step(expert_policy(env)(td))["next"]  # the expert's pick holds a cube
        assert bool(td[keys.HOLDING]) and td[keys.FAILED_PICKS].tolist() == [[-1, -1, -1]] * 2
        td = env.step(td.set(keys.ACTION, torch.tensor(EMPTY_CORNER)))["next"]  # a place: the hand changes again
        assert td[keys.FAILED_PICKS].tolist() == [[-1, -1, -1]] * 2
    finally:
        env.close()
    with pytest.raises(ValueError, match="size"):
        FailedPickMemory(0)


class FixedQ(nn.Module):
    """A Q 'network' whose map peaks at one action (what an untrained or wrong Q may do)."""

    num_rotations = 8

    def forward(self, heightmap, in_hand, holding):
        q = torch.zeros(heightmap.shape[0], 8, 128, 128)
        q[:, EMPTY_CORNER[2], EMPTY_CORNER[0], EMPTY_CORNER[1]] = 1.0
        return q


@pytest.mark.slow
def test_a_greedy_q_policy_repeats_an_empty_pick_without_the_memory_and_not_with_it():
    from ldm_rl.envs import make_env

    policy = QMapPolicy(FixedQ(), write_action_value=False)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        plain = make_env("ldm_rl/BlockStacking-v0", num_objects=2, max_steps=3)
        plain.set_seed(3)
        repeated = plain.rollout(3, policy)[keys.ACTION]
        plain.close()
        env = _memory_env()
        varied = env.rollout(3, policy)[keys.ACTION]
        env.close()
    assert repeated.tolist() == [list(EMPTY_CORNER)] * 3
    assert varied[0].tolist() == list(EMPTY_CORNER)
    for t in (1, 2):  # each later pick keeps clear of every earlier empty one
        for earlier in varied[:t]:
            assert (varied[t, :2] - earlier[:2]).pow(2).sum() > 16 or \
                min((varied[t, 2] - earlier[2]) % 8, (earlier[2] - varied[t, 2]) % 8) > 1


def test_the_lookahead_planner_proposes_nothing_near_an_avoided_action():
    q, dynamics, value = tiny_networks(0)
    planner = LookaheadPlanner(q, dynamics, value, num_candidates=6, write_action_value=False)
    td = TensorDict(scenes(3, 1), batch_size=[3])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        first = planner(td.clone())
        avoid = torch.full((3, 2, 3), -1)
        avoid[:, 0] = first[keys.ACTION]
        second = planner(td.clone().set(keys.FAILED_PICKS, avoid))
    cands, taken = second[keys.CANDIDATE_ACTIONS], first[keys.ACTION][:, None]
    near_px = (cands[..., :2] - taken[..., :2]).pow(2).sum(-1) <= 16
    d_rot = (cands[..., 2] - taken[..., 2]).remainder(8)
    near_rot = torch.minimum(d_rot, 8 - d_rot) <= 1
    assert not (near_px & near_rot).any() and not torch.equal(second[keys.ACTION], first[keys.ACTION])


def test_pick_outcomes_benchmark_measures_distance_to_the_object_and_ranks_scores():
    """benchmarks/pick_outcomes.py: the pick's distance to the centroid of the object under it (nan on bare
    floor or on a region too large to be an object), the object's span along the fingers' closing direction,
    the AUROC of a score against an outcome, the rotation a sweep of K bins chooses, and whether a pick is a
    fitting, centred grasp."""
    import numpy as np

    bench = load_benchmark("pick_outcomes")
    heightmap = np.zeros((32, 32), np.float32)
    heightmap[10:15, 10:15] = 0.03  # a 5×5 px block, centroid (12, 12)
    assert bench.centroid_distance(heightmap, np.array([12, 14]), 0.012, 1500) == 2.0
    assert np.isnan(bench.centroid_distance(heightmap, np.array([0, 0]), 0.012, 1500))  # bare floor
    assert np.isnan(bench.centroid_distance(heightmap, np.array([12, 12]), 0.012, 20))  # a container, not an object
    brick = np.zeros((32, 32), np.float32)
    brick[10:15, 4:17] = 0.03  # 5 rows × 13 columns
    region = bench.object_region(brick, np.array([12, 10]), 0.012, 1500)
    assert bench.closing_span(region, 0.0) == 5.0  # fingers closing along the rows: across the short side
    assert bench.closing_span(region, np.pi / 2) == pytest.approx(13.0)  # along the columns: its length
    assert bench.closing_span(region, np.pi / 4) == pytest.approx(16 / np.sqrt(2) + 1)
    assert bench.object_region(brick, np.array([0, 0]), 0.012, 1500) is None
    # --proposals' grasp quality (2 rotation bins: 0 closes along the rows, 1 along the columns; 1 m per px, 6 m open)
    picks = {"heightmap": brick[None], "num_rotations": 2}
    assert bench.grasp_quality(picks, 0, (12, 10, 0), 0.012, 1500, 6.0, 1.0) == (True, True)  # across, at the centroid
    assert bench.grasp_quality(picks, 0, (12, 10, 1), 0.012, 1500, 6.0, 1.0) == (False, False)  # along its length
    assert bench.grasp_quality(picks, 0, (12, 15, 0), 0.012, 1500, 6.0, 1.0) == (True, False)  # 5 px off the centroid
    assert bench.grasp_quality(picks, 0, (0, 0, 0), 0.012, 1500, 6.0, 1.0) == (False, False)  # bare floor
    # --frame-pad: the same Q weights in padded frames agree with the plain maps wherever those are finite
    from ldm_rl.models.q_fcn import QFCN

    torch.manual_seed(0)
    plain = QFCN(0.15, width=0.125, frame_margin=8)
    padded = bench.padded_q(plain, 32)
    assert padded.frame_size == 192 and padded.frame_margin == 8
    scene = torch.zeros(1, 1, 128, 128)
    scene[..., 60:70, 60:72] = 0.04
    with torch.no_grad():
        a, b = (q(scene, torch.zeros(1, 1, 24, 24), torch.zeros(1, 1, dtype=torch.bool)) for q in (plain, padded))
    torch.testing.assert_close(a[..., 40:88, 40:88], b[..., 40:88, 40:88])  # far from every frame's edge
    assert torch.isfinite(b[..., 4:-4, 4:-4]).all() and not torch.isfinite(a).all()
    # --proposals' rank of the expert's action in Q's map: entries strictly above it and the gap to the best, masked out
    maps = torch.tensor([[[[0.0, 0.5], [0.2, 0.1]]], [[[0.3, float("-inf")], [0.3, 0.1]]], [[[1.0, float("-inf")], [0.0, 0.0]]]])
    above, gap = bench.expert_ranks(maps, torch.tensor([[1, 0, 0], [0, 0, 0], [0, 1, 0]]))
    assert above.tolist() == [1, 0] and gap.tolist() == pytest.approx([0.3, 0.0])  # a tie is not above; the third: masked
    # planner.pick_rotations=K as the benchmark reads it: the best p_drop among the taken bin's K evenly spaced bins
    p_drop = np.array([[0.1, 0.9, 0.2, 0.3, 0.8, 0.0, 0.7, 0.0], [0.5, 0.1, 0.1, 0.1, 0.5, 0.1, 0.1, 0.1]])
    assert bench.swept_choice(p_drop, np.array([2, 0]), 1).tolist() == [2, 0]
    assert bench.swept_choice(p_drop, np.array([2, 0]), 2).tolist() == [6, 0]  # bins {2, 6}; {0, 4} tied: the first
    assert bench.swept_choice(p_drop, np.array([2, 0]), 4).tolist() == [4, 0]  # bins {2, 4, 6, 0}
    assert bench.swept_choice(p_drop, np.array([2, 0]), 8).tolist() == [1, 0]  # every bin
    label = np.array([True, True, False, False])
    assert bench.auroc(np.array([0.9, 0.8, 0.1, 0.2]), label) == 1.0
    assert bench.auroc(np.array([0.1, 0.2, 0.9, 0.8]), label) == 0.0
    assert bench.auroc(np.array([0.5, 0.5, 0.5, 0.5]), label) == 0.5  # ties count half
    # the agent's picks over training: equal consecutive parts, the last one taking the remainder
    held = np.array([0, 0, 1, 0, 1, 1, 1], bool)
    fits = np.array([0, 1, 1, 1, 1, 1, 0], bool)
    assert bench.over_training(held, fits, 3) == [(0, 2, 0.0, 0.5), (2, 4, 0.5, 1.0), (4, 7, 1.0, 2 / 3)]
    assert bench.over_training(held, fits, 8) == []  # fewer picks than parts
    with pytest.raises(ValueError, match="parts must be an int >= 1, got 0"):
        bench.over_training(held, fits, 0)
    assert np.isnan(bench.auroc(np.array([0.5, 0.5]), np.array([True, True])))


@pytest.mark.parametrize("argv, message", [
    (["--proposals", "--weights", "policy.pt"], "--weights must be checkpoint.pt or best_policy.pt"),
    (["--weights", "best_policy.pt"], "pass --proposals too"),
    (["--margin-steps", "5"], "goes with --proposals or --places, got 5"),
    (["--places", "--proposals"], "--places reads the expert's places alone"),
    (["--places", "--save-weights", "fit.pt"], "--save-weights fit.pt writes the Q (or V) that --margin-steps"),
    (["--margin-steps", "5", "--proposals", "--save-weights", "fit.pt"], "pass --places, one of them and one run"),
    (["--value-margin-steps", "5"], "--value-margin-steps must be >= 0 and goes with --places, got 5"),
    (["--places", "--value-margin", "0"], "--value-margin must be > 0 (V's units), got 0.0"),
])
def test_pick_outcomes_refuses_weights_it_cannot_read(argv, message, monkeypatch, capsys, tmp_path):
    """--weights names a file of the run folder (the final or the selected weights), and only --proposals reads it:
    anything else stops at the parser with one line naming the value."""
    import sys

    bench = load_benchmark("pick_outcomes")
    monkeypatch.setattr(sys, "argv", ["pick_outcomes.py", str(tmp_path), *argv])
    with pytest.raises(SystemExit) as stop:
        bench.main()
    assert stop.value.code == 2 and message in capsys.readouterr().err


def test_pick_outcomes_feeds_q_the_hand_of_a_place_and_an_empty_hand_to_a_pick():
    """--places reads Q with each place's in-hand image and the holding flag; the pick readings with an empty hand."""
    bench = load_benchmark("pick_outcomes")
    rows = np.array([2, 0])
    in_hand = np.random.default_rng(0).random((3, 24, 24)).astype(np.float32)
    hand, holding = bench._hand({"in_hand": in_hand, "holding": True}, rows)
    assert hand.shape == (2, 1, 24, 24) and torch.equal(hand[:, 0], torch.from_numpy(in_hand[rows]))
    assert holding.dtype == torch.bool and holding.all() and holding.shape == (2, 1)
    hand, holding = bench._hand({"hand_size": 24}, rows)
    assert hand.shape == (2, 1, 24, 24) and not hand.any() and not holding.any()


def _smoke_agent(overrides=()):
    """The LDM agent of experiment=smoke (random weights) and the meta a training run writes for it."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from ldm_rl.agents import build_agent

    root = Path(__file__).resolve().parents[1]
    with initialize_config_dir(version_base="1.3", config_dir=str(root / "conf")):
        cfg = compose(config_name="train_policy", overrides=["experiment=smoke", *overrides])
    stored = {key: value for key, value in OmegaConf.to_container(cfg).items() if key != "logger"}
    meta = {"kind": "agent", "agent": "ldm", "preset": "lite", "task": cfg.env.id,
            "config": OmegaConf.to_container(OmegaConf.create(stored), resolve=True)}
    return build_agent(cfg, float(cfg.env.max_height)), meta


def test_save_weights_writes_the_fitted_q_as_a_checkpoint_that_plays(tmp_path, capsys):
    """--save-weights: the fitted weights under the run's meta plus a note; load_agent rebuilds them exactly."""
    from ldm_rl.agents import load_agent
    from ldm_rl.run.checkpoint import read_checkpoint_meta, save_checkpoint

    bench = load_benchmark("pick_outcomes")
    trained, meta = _smoke_agent()
    save_checkpoint(tmp_path / "checkpoint.pt", {"agent": trained.policy_state_dict()}, meta=meta)
    agent, _ = load_agent(tmp_path / "checkpoint.pt")
    weight = next(agent.planner.q_network.parameters())
    with torch.no_grad():
        weight.add_(1.0)  # what --margin-steps does, in one step
    bench.save_fitted(agent, tmp_path, "checkpoint.pt", tmp_path / "fit" / "fitted.pt", "Q fitted")
    assert "saved the fitted weights to" in capsys.readouterr().out
    fitted, fitted_cfg = load_agent(tmp_path / "fit" / "fitted.pt")
    assert torch.equal(next(fitted.planner.q_network.parameters()), weight.detach())
    assert fitted_cfg == meta["config"] and read_checkpoint_meta(tmp_path / "fit" / "fitted.pt")["note"] == "Q fitted"


def _averaged_agent_and_places(n: int = 6):
    """The smoke LDM agent trained with agent.greedy_ema_decay after one averaged update (its greedy policy is the
    averaged copy), and ``n`` place rows as ``load_places`` gives them: a 3 cm-high square, a random in-hand image,
    the expert's place at (60, 62), bin 0."""
    agent, _ = _smoke_agent(["agent.greedy_ema_decay=0.99"])
    agent.averaged_planner.update_parameters(agent.planner)
    heightmap = np.zeros((n, 128, 128), np.float32)
    heightmap[:, 50:70, 50:70] = 0.03
    in_hand = np.random.default_rng(0).random((n, 24, 24)).astype(np.float32) * 0.03
    return agent, {"heightmap": heightmap, "in_hand": in_hand, "holding": True,
                   "action": np.stack([np.full(n, 60), np.full(n, 62), np.zeros(n)], 1).astype(np.int64)}


def test_margin_fit_and_q_readings_act_on_the_weights_the_greedy_policy_plays():
    """A run trained with agent.greedy_ema_decay plays its averaged weights: --margin-steps fits that Q (the online
    one is left as it is) and the rank reading reads it, so a saved fit plays what was measured."""
    bench = load_benchmark("pick_outcomes")
    agent, p = _averaged_agent_and_places()
    assert agent.greedy_policy is not agent.planner
    online = {k: v.clone() for k, v in agent.planner.q_network.state_dict().items()}
    averaged = {k: v.clone() for k, v in agent.greedy_policy.q_network.state_dict().items()}
    n = len(p["action"])
    trace = bench.fit_margin(agent, p, np.arange(n), steps=3, lr=1e-2)
    assert len(trace) == 2 and all(np.isfinite(trace))  # steps 0 and 2
    for key, value in agent.planner.q_network.state_dict().items():
        assert torch.equal(value, online[key]), key  # the online Q untouched
    assert any(not torch.equal(v, averaged[k]) for k, v in agent.greedy_policy.q_network.state_dict().items())
    reading = bench.rank_reading(agent, p, np.arange(n))
    with torch.no_grad():  # spoil the online Q (a constant map): the reading of the greedy one does not move
        for param in agent.planner.q_network.parameters():
            param.zero_()
    assert bench.rank_reading(agent, p, np.arange(n)) == reading
    agent.averaged_planner.module.q_network.load_state_dict(agent.planner.q_network.state_dict())
    assert bench.rank_reading(agent, p, np.arange(n)) != reading  # and it does read the greedy copy's weights


def test_value_margin_reading_is_vs_ranking_of_the_experts_outcome_and_its_fit_moves_the_greedy_v_alone():
    """--value-margin-steps: the reading is V's lead of Q's best proposal over the expert's predicted outcome (the
    hinge of agent.value_margin_weight, read on the greedy policy's networks); the fit trains the greedy copy's V
    and nothing else, and a fit that lowers the term lowers the reading it reports."""
    from ldm_rl.planning.sampling import sample_candidates

    bench = load_benchmark("pick_outcomes")
    agent, p = _averaged_agent_and_places()
    greedy = agent.greedy_policy
    heightmap, n = p["heightmap"], len(p["action"])
    rows = np.arange(n)
    gap = bench.value_margin_reading(agent, p, rows, margin=0.0)
    with torch.no_grad():  # the same by hand: the expert's outcome against Q's proposals, V of each prediction
        x = torch.from_numpy(heightmap).unsqueeze(1)
        hand, holding = bench._hand(p, rows)
        greedy.eval()
        proposals = sample_candidates(greedy.q_network(x, hand, holding).float(), agent.loss.num_target_candidates,
                                      **agent.loss.target_proposal)
        actions = torch.cat((torch.from_numpy(p["action"]).unsqueeze(1), proposals), 1)
        m = actions.shape[1]
        pred = greedy.dynamics.predict(x.repeat_interleave(m, 0), hand.repeat_interleave(m, 0),
                                       holding.repeat_interleave(m, 0), actions.reshape(-1, 3))
        values = greedy.value_network(pred.heightmap, pred.in_hand).reshape(n, m)
    torch.testing.assert_close(gap, values[:, 1:].amax(1) - values[:, 0])
    torch.testing.assert_close(bench.value_margin_reading(agent, p, rows, margin=0.5), gap + 0.5)  # no proposal is a_E
    online = {k: v.clone() for k, v in agent.planner.state_dict().items()}
    untouched = {k: v.clone() for k, v in greedy.state_dict().items() if not k.startswith("value_network.")}
    value_before = {k: v.clone() for k, v in greedy.value_network.state_dict().items()}
    trace = bench.fit_value_margin(agent, p, rows, steps=10, lr=1e-2, margin=0.05)
    assert len(trace) == 2 and all(np.isfinite(trace))  # steps 0 and 9
    for key, value in agent.planner.state_dict().items():
        assert torch.equal(value, online[key]), key  # the online networks untouched
    for key, value in greedy.state_dict().items():
        if key in untouched:
            assert torch.equal(value, untouched[key]), key  # the greedy Q and LDM untouched
    assert any(not torch.equal(v, value_before[k]) for k, v in greedy.value_network.state_dict().items())
    after = bench.value_margin_reading(agent, p, rows, margin=0.05).clamp_min(0).mean()
    assert after < (gap + 0.05).clamp_min(0).mean()  # 10 steps on these six states lower the hinge on them
