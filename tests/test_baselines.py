"""The baselines (agent=fcdqn|rs|dynaq): their defining behaviour, exact resume, config errors, smoke runs."""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from ldm_rl.agents import build_agent
from ldm_rl.planning.q_map import QMapPolicy
from ldm_rl.config_schema import ConfigError, TrainPolicyConfig, validate_config
from ldm_rl.models.q_fcn import QFCN
from ldm_rl.planning.sampling import object_mask, sample_near_objects
from policy_helpers import MAX_HEIGHT, scenes, transitions

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "train_policy.py"
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg", "RL_WARNINGS": "0"}
BASELINES = ("fcdqn", "rs", "dynaq")


def config(name: str, *overrides: str):
    """The smoke preset (tiny networks) with ``agent=name``."""
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        return compose(config_name="train_policy", overrides=["experiment=smoke", f"agent={name}", *overrides])


def make_agent(name: str, *overrides: str, seed: int = 0):
    torch.manual_seed(seed)
    return build_agent(config(name, *overrides), MAX_HEIGHT)


def batch(n: int = 4, seed: int = 0) -> TensorDict:
    data = transitions(n, seed)
    data["priority_weight"] = torch.linspace(0.5, 1.0, n, dtype=torch.float64)
    return data


def states(n: int = 3, seed: int = 0) -> TensorDict:
    return TensorDict(scenes(n, seed), batch_size=[n])


class FixedQ(torch.nn.Module):
    """A 'Q network' returning a given map for every state."""

    def __init__(self, q_map: torch.Tensor) -> None:
        super().__init__()
        self.q_map = q_map

    def forward(self, heightmap, in_hand, holding):
        return self.q_map.expand(heightmap.shape[0], *self.q_map.shape)


# ----------------------------------------------------------------------------------------- FC-DQN


def test_fcdqn_greedy_action_is_the_argmax_of_its_q_map():
    agent = make_agent("fcdqn")
    assert not any(type(m).__name__ in ("DynamicsModel", "VCNN") for m in agent.modules())  # Q alone
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = agent.policy(states(3))
        again = agent.policy(states(3))
    q_map = out["action_value"]
    with torch.no_grad():
        torch.testing.assert_close(q_map, agent.policy.q_network.eval()(*scenes(3).values()))
    flat = q_map.flatten(1).argmax(1)
    r, h, w = q_map.shape[1:]
    expected = torch.stack((flat % (h * w) // w, flat % w, flat // (h * w)), -1)
    assert torch.equal(out["action"], expected) and torch.equal(out["action"], again["action"])
    torch.testing.assert_close(out["chosen_action_value"], q_map.flatten(1).amax(1, keepdim=True))
    # a known map: the action is (row, col, rot) of its maximum, for any batch shape
    q = torch.randn(8, 128, 128)
    q[3, 5, 77] = 10.0
    policy = QMapPolicy(FixedQ(q))
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert policy(states(1)[0])["action"].tolist() == [5, 77, 3]
        grid = policy(TensorDict(scenes(6), batch_size=[6]).reshape(2, 3))
    assert grid["action"].shape == (2, 3, 3) and (grid["action"] == torch.tensor([5, 77, 3])).all()


def test_fcdqn_explores_by_softmax_of_q_over_the_whole_map():
    q = torch.zeros(8, 128, 128)
    q[6, 100, 20] = 1.0
    cold, hot = QMapPolicy(FixedQ(q), tau=1e-3), QMapPolicy(FixedQ(q), tau=1e3)
    torch.manual_seed(0)
    with set_exploration_type(ExplorationType.RANDOM):
        assert (cold(states(4))["action"] == torch.tensor([100, 20, 6])).all()
        drawn = hot(TensorDict(scenes(64), batch_size=[64]))["action"]
    assert len({tuple(a) for a in drawn.tolist()}) > 60  # near-uniform over 131072 actions
    assert set(drawn[:, 2].tolist()) > {0, 7} and hot.hyperparameters() == {"tau": 1e3}


def test_dqn_targets_terminal_rows_priorities_and_the_hard_update():
    agent = make_agent("fcdqn", "agent.gamma=0.9")
    loss = agent.loss
    data = batch(4)
    data["next", "terminated"] = torch.tensor([[True], [False], [True], [False]])
    y = loss.targets(data)
    reward = data["next", "reward"]
    assert torch.equal(y[[0, 2]], reward[[0, 2]])
    with torch.no_grad():
        q_next = loss.q_network.eval()(data["next", "heightmap"], data["next", "in_hand"], data["next", "holding"])
    torch.testing.assert_close(y[[1, 3]], reward[[1, 3]] + 0.9 * q_next[[1, 3]].flatten(1).amax(1, keepdim=True))
    out = loss(data)
    with torch.no_grad():
        q_sa = loss.q_network.action_values(data["heightmap"], data["in_hand"], data["holding"], data["action"])
    torch.testing.assert_close(data["td_error"], (q_sa - y.squeeze(1)).abs())
    plain = loss(data.exclude("priority_weight"))["loss_q"]
    assert not torch.allclose(out["loss_q"], plain)  # importance weights are applied
    # the target network lags until TorchRL's HardUpdate copies it (every target_update_interval updates)
    agent = make_agent("fcdqn", "agent.target_update_interval=2")
    live = batch(4)
    live["next", "terminated"] = torch.zeros(4, 1, dtype=torch.bool)
    before = agent.loss.targets(live)
    agent.update(batch(4, seed=1))
    assert torch.equal(agent.loss.targets(live), before)
    agent.update(batch(4, seed=1))
    assert not torch.equal(agent.loss.targets(live), before)
    assert agent.updates == 2 and agent.policy.step == 2


@pytest.mark.parametrize("name", ["fcdqn", "dynaq"])
def test_dqn_return_lower_bound_raises_the_target_and_imagined_rows_get_none(name):
    plain = make_agent(name, "agent.gamma=0.9")
    bounded = make_agent(name, "agent.gamma=0.9", "agent.return_lower_bound=true")
    data = batch(4)
    data["return_to_go"] = torch.tensor([[5.0], [-5.0], [float("-inf")], [0.5]])
    torch.testing.assert_close(bounded.loss.targets(data), torch.maximum(plain.loss.targets(data), data["return_to_go"]))
    if name == "dynaq":  # the update runs with the bound (imagined rows carry -inf) and writes the real rows' priorities
        bounded.update(data)
        assert data["td_error"].shape == (4,) and torch.isfinite(data["td_error"]).all()


def test_fcdqn_pretraining_trains_nothing_and_update_writes_priorities():
    agent = make_agent("fcdqn")
    weights = {k: v.clone() for k, v in agent.state_dict().items()}
    assert agent.pretrain_update(batch()) == {} and agent.updates == 0
    assert all(torch.equal(weights[k], v) for k, v in agent.state_dict().items())
    data = batch()
    metrics = agent.update(data)
    assert data["td_error"].shape == (4,) and (data["td_error"] >= 0).all()
    assert {"loss_q", "q_target", "chosen_action_value"} <= set(metrics) and agent.updates == 1
    assert set(agent.learning_rates()) == {"lr_q"}


# ------------------------------------------------------------------------------- Random Shooting


def test_rs_candidates_are_near_objects_distinct_and_fall_back_to_uniform():
    heightmap = torch.zeros(2, 1, 128, 128)
    heightmap[0, 0, 40:50, 60:70] = 0.03
    heightmap[0, 0, 100:102, 10:12] = 0.005  # below the threshold: not an object
    mask = object_mask(heightmap, height_threshold=0.01, dilation=4)
    assert mask[0].sum() == 18 * 18 and mask[0, 36:54, 56:74].all() and not mask[1].any()
    assert object_mask(heightmap, height_threshold=0.01, dilation=0)[0].sum() == 100
    torch.manual_seed(0)
    cands = sample_near_objects(heightmap, 200, num_rotations=8, height_threshold=0.01, dilation=4)
    assert cands.shape == (2, 200, 3) and cands.dtype == torch.int64
    near = cands[0]
    assert ((near[:, 0] >= 36) & (near[:, 0] < 54) & (near[:, 1] >= 56) & (near[:, 1] < 74)).all()
    assert len({tuple(a) for a in near.tolist()}) == 200 and set(near[:, 2].tolist()) == set(range(8))
    empty = cands[1]  # nothing on the table: uniform over the whole map
    assert empty[:, :2].float().std(0).min() > 25 and len({tuple(a) for a in empty.tolist()}) == 200
    # fewer near-object actions than N: the whole map
    few = sample_near_objects(heightmap[:1], 18 * 18 * 8 + 1, num_rotations=8, height_threshold=0.01, dilation=4)
    assert not ((few[0, :, 0] >= 36) & (few[0, :, 0] < 54) & (few[0, :, 1] >= 56) & (few[0, :, 1] < 74)).all()
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    assert torch.equal(sample_near_objects(heightmap, 5, num_rotations=8, generator=g1),
                       sample_near_objects(heightmap, 5, num_rotations=8, generator=g2))
    with pytest.raises(ValueError, match="num must be"):
        sample_near_objects(heightmap, 0, num_rotations=8)
    with pytest.raises(ValueError, match="dilation"):
        object_mask(heightmap, dilation=-1)


def test_rs_never_calls_a_q_network(monkeypatch):
    agent = make_agent("rs")
    assert not any(isinstance(m, QFCN) for m in agent.modules())

    def no_q(*args, **kwargs):
        raise AssertionError("Random Shooting called a Q network")

    monkeypatch.setattr(QFCN, "forward", no_q)
    monkeypatch.setattr(QFCN, "action_values", no_q)
    for mode in (ExplorationType.DETERMINISTIC, ExplorationType.RANDOM):
        with set_exploration_type(mode):
            out = agent.policy(states(2))
        assert out["action"].shape == (2, 3) and out["candidate_actions"].shape == (2, 3, 3)
    assert set(agent.pretrain_update(batch())) == {"loss_dynamics", "loss_reward", "pixel_accuracy"}
    data = batch()
    metrics = agent.update(data)
    assert data["td_error"].shape == (4,) and {"loss_value", "loss_reward", "loss_dynamics"} <= set(metrics)
    assert set(agent.learning_rates()) == {"lr_value", "lr_dynamics"}


def test_rs_scores_are_reward_plus_gamma_value_of_the_prediction_and_greedy_takes_the_best():
    agent = make_agent("rs", "agent.gamma=0.8")
    planner = agent.policy
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = planner(states(2))
    s, cands = scenes(2), out["candidate_actions"]
    n = cands.shape[1]
    with torch.no_grad():
        pred = planner.dynamics.eval().predict(s["heightmap"][:, None].expand(2, n, 1, 128, 128),
                                               s["in_hand"][:, None].expand(2, n, 1, 24, 24),
                                               s["holding"][:, None].expand(2, n, 1), cands)
        v, r = planner.value_network.eval().value_and_reward(pred.heightmap.flatten(0, 1), pred.in_hand.flatten(0, 1))
    torch.testing.assert_close(out["candidate_values"], (r + 0.8 * v).reshape(2, n))
    best = out["candidate_values"].argmax(-1)
    assert torch.equal(out["action"], cands[torch.arange(2), best])
    assert (object_mask(s["heightmap"], height_threshold=0.01, dilation=8)[
        torch.arange(2)[:, None], cands[..., 0], cands[..., 1]]).all()


def test_rs_value_targets_are_the_best_target_score_of_fresh_candidates():
    agent = make_agent("rs", "agent.gamma=0.9", "agent.num_target_candidates=4")
    loss = agent.loss
    data = batch(3)
    data["next", "terminated"] = torch.tensor([[False], [True], [False]])
    torch.manual_seed(5)
    y = loss.targets(data)
    assert y[1].item() == 0.0  # nothing follows a terminal step
    live = data[[0, 2]]
    torch.manual_seed(5)
    cands = loss.rule(live["next", "heightmap"], 4)
    with torch.no_grad():
        pred = loss.dynamics.eval().predict(live["next", "heightmap"][:, None].expand(2, 4, 1, 128, 128),
                                            live["next", "in_hand"][:, None].expand(2, 4, 1, 24, 24),
                                            live["next", "holding"][:, None].expand(2, 4, 1), cands)
        v, r = loss.value_network.eval().value_and_reward(pred.heightmap.flatten(0, 1), pred.in_hand.flatten(0, 1))
    torch.testing.assert_close(y[[0, 2]], (r + 0.9 * v).reshape(2, 4).amax(1, keepdim=True))  # target = online at start
    # return_lower_bound: the bound is the return from the NEXT step on (RS's V excludes the arrival reward)
    bounded = make_agent("rs", "agent.gamma=0.9", "agent.num_target_candidates=4", "agent.return_lower_bound=true")
    data["return_to_go"] = torch.full((3, 1), 7.0)  # the transition's own return: must not be used
    data["next", "return_to_go"] = torch.tensor([[5.0], [float("-inf")], [-5.0]])
    torch.manual_seed(5)
    y_bounded = bounded.loss.targets(data)
    torch.testing.assert_close(y_bounded, torch.maximum(y, data["next", "return_to_go"]))


# ----------------------------------------------------------------------------------------- Dyna-Q


def test_dynaq_update_consumes_imagined_transitions_started_from_the_replay_batch(monkeypatch):
    agent = make_agent("dynaq", "agent.imagined_ratio=2.0", "agent.imagined_terminal_reward=0.3")
    seen = []
    forward = agent.loss.forward

    def spy(tensordict):
        seen.append(tensordict.clone())
        return forward(tensordict)

    monkeypatch.setattr(agent.loss, "forward", spy)
    data = batch(3)
    metrics = agent.update(data)
    (consumed,) = seen
    assert consumed.batch_size == (3 + 6,) and metrics["imagined"] == 6.0
    real, imagined = consumed[:3], consumed[3:]
    for key in ("heightmap", "in_hand", "holding", "action", ("next", "heightmap"), ("next", "reward")):
        assert torch.equal(real[key], data[key])
    rows = torch.arange(6) % 3  # the imagined start states are the batch's own states
    for key in ("heightmap", "in_hand", "holding"):
        assert torch.equal(imagined[key], data[key][rows])
    assert (imagined["priority_weight"] == 1).all()
    assert torch.equal(real["priority_weight"], data["priority_weight"].float())
    # the next states are the LDM's predictions, the rewards the reward head's (weights as they were then:
    # recompute with a fresh agent of the same seed)
    fresh = make_agent("dynaq", "agent.imagined_ratio=2.0", "agent.imagined_terminal_reward=0.3")
    with torch.no_grad():
        pred = fresh.dynamics.eval().predict(*(imagined[key] for key in ("heightmap", "in_hand", "holding", "action")))
        _, reward = fresh.value_network.eval().value_and_reward(pred.heightmap, pred.in_hand)
    assert torch.equal(imagined["next", "heightmap"], pred.heightmap)
    assert torch.equal(imagined["next", "holding"], pred.holding)
    torch.testing.assert_close(imagined["next", "reward"], reward)
    assert torch.equal(imagined["next", "terminated"], reward > 0.3)
    assert data["td_error"].shape == (3,) and agent.updates == 1
    # imagined_ratio = 0: the real batch alone
    plain = make_agent("dynaq", "agent.imagined_ratio=0")
    monkeypatch.setattr(plain.loss, "forward", spy)
    seen.clear()
    assert plain.update(batch(3))["imagined"] == 0.0 and seen[0].batch_size == (3,)


def test_dynaq_trains_q_the_ldm_and_the_reward_head():
    agent = make_agent("dynaq")
    before = {name: [p.clone() for p in module.parameters()] for name, module in agent.trained.items()}
    assert set(agent.pretrain_update(batch())) == {"loss_dynamics", "loss_reward", "pixel_accuracy"}
    assert agent.updates == 0 and all(torch.equal(a, b) for a, b in zip(before["q"], agent.trained["q"].parameters()))
    agent.update(batch())
    for name, module in agent.trained.items():
        assert any(not torch.equal(a, b) for a, b in zip(before[name], module.parameters())), name
    value_head = agent.value_network.value_head
    assert all(p.grad is None for p in value_head.parameters())  # only the reward head is used
    assert set(agent.learning_rates()) == {"lr_q", "lr_value", "lr_dynamics"}
    assert not any(k.startswith("reward_model") for k in agent.state_dict())


# ---------------------------------------------------------------------------------- all baselines


@pytest.mark.parametrize("name", BASELINES)
def test_checkpoint_round_trip_continues_identically(name):
    """state_dict + training_state through torch.save into an agent built from another seed: the next
    updates (LR decay every update, target copies every 2nd) give bit-identical weights and metrics."""
    overrides = ("agent.target_update_interval=2", "agent.lr_decay_every=1", "agent.lr_decay=0.5")
    first = make_agent(name, *overrides, seed=0)
    first.update(batch(4, seed=1))
    buffer = io.BytesIO()
    torch.save({"agent": first.state_dict(), "training": first.training_state()}, buffer)
    buffer.seek(0)
    saved = torch.load(buffer, weights_only=False)
    second = make_agent(name, *overrides, seed=1)
    assert any(not torch.equal(v, second.state_dict()[k]) for k, v in first.state_dict().items())
    second.load_state_dict(saved["agent"])
    second.load_training_state(saved["training"])
    assert second.updates == 1 and second.learning_rates() == first.learning_rates()
    assert second.policy.hyperparameters() == first.policy.hyperparameters()
    results = []
    for agent in (first, second):
        torch.manual_seed(7)
        metrics = [agent.update(batch(4, seed=2)), agent.update(batch(4, seed=3))]
        with set_exploration_type(ExplorationType.RANDOM):
            action = agent.policy(states(2))["action"]
        results.append((metrics, action, agent.state_dict(), agent.training_state()["target_updater_counter"]))
    (m1, a1, s1, c1), (m2, a2, s2, c2) = results
    assert m1 == m2 and torch.equal(a1, a2) and c1 == c2
    assert s1.keys() == s2.keys() and all(torch.equal(s1[k], s2[k]) for k in s1)


@pytest.mark.parametrize("name", BASELINES)
def test_every_baseline_config_validates_and_names_its_agent(name):
    cfg = config(name)
    validate_config(cfg, TrainPolicyConfig)
    agent = build_agent(cfg, MAX_HEIGHT)
    assert agent.name == name == cfg.agent.name and cfg.agent.preset is None
    assert set(agent.policy.hyperparameters()) == ({"tau_value"} if name == "rs" else {"tau"})


@pytest.mark.parametrize(
    "agent, override, message",
    [
        ("dynaq", "agent.imagined_ratio=-1", r"agent.imagined_ratio=-1(\.0)? is out of range: must be in \[0, 16\]"),
        ("rs", "agent.object_dilation=null", r"agent.object_dilation is null: agent=rs needs it"),
        ("fcdqn", "agent.imagined_ratio=1", r"agent.imagined_ratio=1(\.0)? is set but only agent=dynaq uses it"),
        ("rs", "agent.object_height_threshold=0", r"agent.object_height_threshold=0(\.0)? is out of range"),
    ],
)
def test_bad_baseline_config_is_one_clear_error(agent, override, message):
    with pytest.raises(ConfigError, match=message):
        validate_config(config(agent, override), TrainPolicyConfig)


def test_bad_config_errors_from_the_builder_and_the_command_line():
    cfg = config("rs")
    cfg.agent.object_height_threshold = None
    with pytest.raises(ValueError, match=r"agent=rs needs agent.object_height_threshold"):
        build_agent(cfg, MAX_HEIGHT)
    cfg = config("dynaq")
    cfg.agent.name = "alphazero"
    with pytest.raises(ValueError, match=r"agent.name must be one of \['dynaq', 'fcdqn', 'ldm', 'rs'\]"):
        build_agent(cfg, MAX_HEIGHT)
    proc = subprocess.run([sys.executable, str(RECIPE), "agent=dynaq", "agent.imagined_ratio=-1"],
                          capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=120)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert proc.stderr.startswith("error:") and "agent.imagined_ratio=-1" in proc.stderr


@pytest.mark.slow
@pytest.mark.parametrize("name", BASELINES)
def test_smoke_run_end_to_end(name, tmp_path):
    """recipes/train_policy.py experiment=smoke agent=<name>: curve, checkpoint, final metrics; the
    checkpoint loads back into the same agent."""
    from ldm_rl.agents import load_agent

    command = [sys.executable, str(RECIPE), "experiment=smoke", f"agent={name}", f"hydra.run.dir={tmp_path}"]
    proc = subprocess.run(command, capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    final = json.loads((tmp_path / "final_metrics.json").read_text())
    assert final["agent"] == name and final["episodes"] >= 2 and final["episodes_final_eval"] == 2
    assert 0.0 <= final["success_rate"] <= 1.0 and final["updates"] > 0
    assert len((tmp_path / "curve.csv").read_text().splitlines()) >= 3
    agent, cfg = load_agent(tmp_path / "checkpoint.pt")
    assert agent.name == name and agent.updates == 0  # load_agent restores weights (training state: resume)


def recipe_expert_episodes(cfg):
    """recipes/train_policy.py's ``expert_episodes(cfg)``: the demonstrations that seed a training run's replay."""
    sys.path.insert(0, str(ROOT / "recipes"))
    try:
        from train_policy import expert_episodes
    finally:
        sys.path.remove(str(ROOT / "recipes"))
    return expert_episodes(cfg)


def test_the_seeded_replay_keeps_the_demos_flags_where_noise_replaced_the_experts_action():
    """recipes/train_policy.py's expert episodes carry each step's is_expert (False at a turned rotation), and the
    replay seeded with them keeps it: no expert bonus, no expert margin on the noise."""
    from ldm_rl.data.replay import FrameReplay

    cfg = config("fcdqn", "schedule.expert_episodes=2", "schedule.expert_noise.rotation_prob=0.5")
    episodes = recipe_expert_episodes(cfg)
    flags = torch.cat([episode["is_expert"].reshape(-1) for episode in episodes])
    assert flags.any() and not flags.all()  # seeded: both kinds at p = 0.5
    replay = FrameReplay(64, max_height=MAX_HEIGHT, generator=torch.Generator().manual_seed(0))
    for episode in episodes:
        replay.extend_episode(episode)
    sample = replay.sample(256)
    assert not sample["is_expert"].all() and sample["is_expert"].any()


@pytest.mark.slow
def test_bin_packing_smoke_run_counts_positive_pile_rewards_as_successes(tmp_path):
    """experiment=smoke env=bin_packing: the expert episodes that seed the replay end terminated with a
    reward in (0, 1] (the pile reward), the recipe counts exactly those as successes, and a run ends (Q on the
    log scale)."""
    from ldm_rl.evaluation import episode_succeeded, pick_counts

    cfg = config("fcdqn", "env=bin_packing", "schedule.expert_episodes=2")
    episodes = recipe_expert_episodes(cfg)
    assert len(episodes) == 2
    for episode in episodes:
        last = episode[-1]
        reward = float(last["next", "reward"])
        assert bool(last["next", "terminated"]) and 0.0 < reward <= 1.0
        assert episode_succeeded(episode)
        assert (episode[:-1]["next", "reward"] == 0).all()  # the pile reward comes only with success
        picks, held = pick_counts(episode)  # a successful episode ends with a place: one per pick that held
        assert held == episode.shape[0] - picks >= 8 and picks >= 8
    failed = episodes[0].clone()
    failed[-1]["next", "reward"].zero_()
    assert not episode_succeeded(failed)  # terminated at 0 reward (an invalid scene) is no success

    # Q on the log scale (agent.q_log_floor), the option meant for this task's small action gaps; with the
    # progress term (env.progress_reward), whose rewards the packing report must leave out
    command = [sys.executable, str(RECIPE), "experiment=smoke", "env=bin_packing", "agent=fcdqn", "agent.q_log_floor=0.01",
               "env.progress_reward=0.03", "schedule.total_episodes=1", "schedule.final_eval_episodes=1",
               "env.max_steps=3", f"hydra.run.dir={tmp_path}"]
    proc = subprocess.run(command, capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    final = json.loads((tmp_path / "final_metrics.json").read_text())
    assert final["task"] == "ldm_rl/BinPacking-v0" and final["num_objects"] == 8
    assert 0.0 <= final["success_rate"] <= 1.0 and final["episodes_final_eval"] == 1 and final["updates"] > 0
    packing = final["packing"]  # the agent's and the scripted expert's packing report on the same scene
    assert packing["episodes"] == packing["expert"]["episodes"] == 1
    assert packing["packed"] == final["success_rate"] and 0.0 <= packing["expert"]["packed"] <= 1.0
    # every evaluation's row of curve.csv scores the packs too; the final one is the report's
    with open(tmp_path / "curve.csv", newline="") as f:
        last = list(csv.DictReader(f))[-1]
    assert float(last["mean_return"]) == packing["mean_return"] and last["mean_pile_top"] == ("" if packing["mean_pile_top"] is None else str(packing["mean_pile_top"]))
    assert float(last["mean_blocks_in_bin"]) == packing["mean_blocks_in_bin"]
    assert 0 <= packing["mean_blocks_in_bin"] <= 8 and 0 <= packing["expert"]["mean_blocks_in_bin"] <= 8
    # 3 primitives cannot pack 8 blocks; the expert's first place puts its first block in the bin
    assert packing["expert"]["mean_blocks_in_bin"] == 1 and packing["expert"]["packed"] == 0
    # its episode earned the progress term's 0.03 for that block; the report's returns are the pack's alone
    assert packing["expert"]["mean_return"] == 0.0 and packing["expert"]["mean_return_authors"] == 0.0
    assert "the scripted expert on the same scenes" in proc.stdout + proc.stderr

    # recipes/evaluate.py gives the same report for a bin-packing checkpoint (agent and expert, same scenes)
    evaluate = [sys.executable, str(ROOT / "recipes" / "evaluate.py"), f"checkpoint={tmp_path / 'checkpoint.pt'}",
                "episodes=2", "max_steps=3", f"hydra.run.dir={tmp_path / 'evaluation'}"]
    proc = subprocess.run(evaluate, capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    evaluation = json.loads((tmp_path / "evaluation" / "evaluation.json").read_text())
    assert evaluation["played_with"] == {"q_pick_min_height": 0.0}  # FC-DQN: Q's mask (off), no LDM planner
    packing = evaluation["packing"]
    assert packing["episodes"] == packing["expert"]["episodes"] == 2
    assert packing["expert"]["mean_blocks_in_bin"] == 1 and packing["expert"]["packed"] == 0  # one place in 3 steps
    assert 0 <= packing["mean_blocks_in_bin"] <= 8 and packing["packed"] == 0
    blocks = evaluation["per_episode"]["blocks_in_bin"]  # per scene, in order, for paired comparisons
    assert len(blocks) == 2 and sum(blocks) / 2 == pytest.approx(packing["mean_blocks_in_bin"])
    assert evaluation["per_episode"]["pile_top"] == [None, None]  # per scene too; no pile where it did not pack
    # online_weights needs a run trained with averaged greedy weights: one line, before any episode
    proc = subprocess.run([*evaluate[:-1], "online_weights=true", f"hydra.run.dir={tmp_path / 'online'}"],
                          capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=600)
    assert proc.returncode == 2 and not (tmp_path / "online" / "evaluation.json").exists()
    assert proc.stderr.strip().splitlines()[-1].startswith("error: online_weights=true needs a run trained with agent.greedy_ema_decay")
