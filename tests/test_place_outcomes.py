"""benchmarks/place_outcomes.py: the tilt of a resting block, the rank correlation, the place rows, bad arguments."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchmark_loader import load_benchmark


def rotation(axis: str, degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def test_tilt_is_the_angle_to_the_nearest_face_down_pose():
    bench = load_benchmark("place_outcomes")
    assert bench.tilt_degrees(np.eye(3)) == pytest.approx(0.0, abs=1e-6)
    assert bench.tilt_degrees(rotation("z", 70.0)) == pytest.approx(0.0, abs=1e-6)  # yaw is not tilt
    assert bench.tilt_degrees(rotation("x", 90.0)) == pytest.approx(0.0, abs=1e-6)  # on another face: not tilted
    assert bench.tilt_degrees(rotation("x", 30.0) @ rotation("z", 50.0)) == pytest.approx(30.0, abs=1e-4)
    assert bench.tilt_degrees(rotation("y", 60.0)) == pytest.approx(30.0, abs=1e-4)  # 60 off z, 30 off x
    stacked = np.stack([np.eye(3), rotation("y", 20.0)])
    assert bench.tilt_degrees(stacked) == pytest.approx([0.0, 20.0], abs=1e-4)


def test_yaw_off_axes_folds_a_resting_blocks_heading_onto_the_frames_walls():
    bench = load_benchmark("place_outcomes")
    assert bench.yaw_off_axes(rotation("z", 30.0), 0.0) == pytest.approx(30.0)
    assert bench.yaw_off_axes(rotation("z", 30.0), math.radians(30.0)) == pytest.approx(0.0, abs=1e-6)
    assert bench.yaw_off_axes(rotation("z", 100.0), 0.0) == pytest.approx(10.0)  # a quarter turn is the same walls
    assert bench.yaw_off_axes(rotation("z", -50.0), 0.0) == pytest.approx(40.0)
    on_its_side = rotation("z", 20.0) @ rotation("x", 90.0)  # body z now horizontal: still the heading that counts
    assert bench.yaw_off_axes(on_its_side, 0.0) == pytest.approx(20.0)


def test_rank_correlation_is_spearmans_with_ties_and_nan_for_constants():
    bench = load_benchmark("place_outcomes")
    x = np.array([0.05, 0.02, 0.09, 0.04])
    assert bench.rank_correlation(x, x ** 3) == pytest.approx(1.0)
    assert bench.rank_correlation(x, -x) == pytest.approx(-1.0)
    assert math.isnan(bench.rank_correlation(x, np.ones(4)))
    assert math.isnan(bench.rank_correlation(x[:1], x[:1]))
    # ties get their average rank: ranks (0.5, 0.5, 2) against (0, 1, 2)
    expect = np.corrcoef([0.5, 0.5, 2.0], [0.0, 1.0, 2.0])[0, 1]
    assert bench.rank_correlation(np.array([1.0, 1.0, 3.0]), np.array([1.0, 2.0, 3.0])) == pytest.approx(expect)


def block(in_bin=True, tilt=0.0, height=0.04, lying=0.04, yaw_off=0.0, volume=6.4e-5):
    return {"in_bin": in_bin, "tilt": tilt, "height": height, "lying": lying, "yaw_off": yaw_off, "volume": volume}


def test_place_rows_keep_only_places_into_the_bin_and_read_the_rest_pose():
    bench = load_benchmark("place_outcomes")
    snapshots = [
        {"held": None, "step": 0, "blocks": {1: block(in_bin=False), 2: block(in_bin=False)}},  # a pick
        {"held": 1, "step": 1, "blocks": {1: block(in_bin=False, tilt=15.0), 2: block(in_bin=False)}},  # place 1
        {"held": None, "step": 2, "blocks": {1: block(tilt=25.0, height=0.09), 2: block(in_bin=False)}},
        {"held": 2, "step": 3, "blocks": {1: block(tilt=25.0, height=0.09), 2: block(in_bin=False)}},  # place 2: misses
        {"held": None, "step": 4, "blocks": {1: block(tilt=25.0, height=0.09), 2: block(in_bin=False, height=0.043)}},
    ]
    rows = bench.place_rows(snapshots, tilt=10.0)
    assert rows == [{"tilted": True, "raised": True, "tilted_in_hand": True, "step": 1, "turned": False, "largest": True}]
    snapshots[2]["blocks"][1] = block(tilt=5.0, height=0.045, yaw_off=8.0)  # level, within the 6 mm slack
    snapshots[1]["blocks"][1] = block(in_bin=False, tilt=5.0)
    assert bench.place_rows(snapshots, tilt=10.0) == [
        {"tilted": False, "raised": False, "tilted_in_hand": False, "step": 1, "turned": False, "largest": True}]
    snapshots[2]["blocks"][1]["yaw_off"] = 30.0  # level but turned against the walls
    assert bench.place_rows(snapshots, tilt=10.0)[0]["turned"]
    snapshots[1]["blocks"][2]["volume"] = 1e-4  # a larger block was still outside: not the largest first
    assert not bench.place_rows(snapshots, tilt=10.0)[0]["largest"]
    snapshots[1]["blocks"][2]["in_bin"] = True  # ... unless it was already in the bin
    assert bench.place_rows(snapshots, tilt=10.0)[0]["largest"]


@pytest.mark.parametrize("argv, message", [
    (["--episodes", "0"], "--episodes must be >= 1, got 0"),
    (["--tilt", "90"], "--tilt must be in (0, 90) degrees, got 90.0"),
    (["--planner", "name"], "--planner takes KEY=VALUE items, got 'name'"),
    (["--place-weights", "fit.pt", "--expert-does", "picks"], "--place-weights fit.pt makes the places: leave out"),
    (["--place-planner", "q_blend"], "--place-planner takes KEY=VALUE items, got 'q_blend'"),
    (["--place-planner", "q_blend=0", "--expert-does", "picks"], "--place-planner {'q_blend': 0} sets the places' planner"),
    (["--top-quantile", "0.9"], "--top-quantile must be in (0, 1) and go with --choose lowest-top, got 0.9 with --choose value"),
    (["--choose", "lowest-top", "--top-quantile", "1"], "--top-quantile must be in (0, 1)"),
])
def test_place_outcomes_refuses_bad_arguments_in_one_line(argv, message, capsys):
    bench = load_benchmark("place_outcomes")
    with pytest.raises(SystemExit):
        bench.parse_args(["run/checkpoint.pt", *argv])
    assert message in capsys.readouterr().err


def test_planner_settings_are_read_as_numbers_and_flags():
    bench = load_benchmark("place_outcomes")
    args = bench.parse_args(["c.pt", "--planner", "uncertainty_penalty=0.25", "name=tree", "depth=2",
                             "empty_picks_last=true"])
    assert args.planner == {"uncertainty_penalty": 0.25, "name": "tree", "depth": 2, "empty_picks_last": True}
    args = bench.parse_args(["c.pt", "--planner", "q_blend=1.0", "--place-planner", "q_blend=0"])
    assert args.planner == {"q_blend": 1.0} and args.place_planner == {"q_blend": 0}


def test_place_outcomes_refuses_a_missing_checkpoint_in_one_line(tmp_path, capsys):
    bench = load_benchmark("place_outcomes")
    with pytest.raises(SystemExit) as exit_info:
        bench.main([str(tmp_path / "nowhere" / "checkpoint.pt"), "--episodes", "1"])
    message = str(exit_info.value)
    assert message.startswith("error: ") and "nowhere" in message and "\n" not in message
    assert not any(tmp_path.iterdir())  # nothing written


def test_lowest_top_choice_takes_the_lowest_entering_candidate_and_leaves_picks_to_the_planner():
    import gymnasium as gym
    import torch
    from types import SimpleNamespace

    import ldm_rl.envs  # noqa: F401  (registers the ids)

    bench = load_benchmark("place_outcomes")
    task = gym.make("ldm_rl/BinPacking-v0").unwrapped
    try:
        task.reset(seed=3)
        inside = torch.as_tensor(bench.bin_interior(task))
        before = torch.zeros(2, 1, *inside.shape)  # two states: the first holds a block, the second does not
        after = before[:, None].repeat(1, 4, 1, 1, 1)  # [B, N=4, 1, H, W]
        rows, cols = inside.nonzero().T
        centre = (rows[len(rows) // 2], cols[len(cols) // 2])
        after[:, 0, 0][:, centre[0], centre[1]] = 0.12          # enters the bin, the tallest pile
        after[:, 1, 0][:, rows[:40], cols[:40]] = 0.05          # enters, the lowest pile
        after[:, 2, 0][:, centre[0], centre[1]] = 0.08          # a single pixel: too little added to count as entering
        after[:, 3, 0][:, ~inside] = 0.05                        # lands outside the bin
        planner_scores = torch.tensor([[0.0, 0.1, 0.9, 0.5], [0.0, 0.1, 0.9, 0.5]])
        planner = SimpleNamespace(score=lambda *a, **o: (planner_scores, SimpleNamespace(next_heightmap=after)))
        bench.choose_lowest_top(planner, task, min_volume=1.5e-5)
        after[:, 0, 0][:, rows[-40:], cols[-40:]] = 0.12
        holding = torch.tensor([1.0, 0.0])
        scores, _ = planner.score(before, None, holding, None, 0.0)
        assert scores[0].argmax() == 1 and scores[0, :2].tolist() == pytest.approx([-0.12, -0.05])
        assert scores[0, 2:].isinf().all()
        assert torch.equal(scores[1], planner_scores[1])  # a pick: the planner's own scores
        after[:, :2] = 0.0  # nothing enters the bin: the planner's own scores again
        scores, _ = planner.score(before, None, holding, None, 0.0)
        assert torch.equal(scores, planner_scores)
    finally:
        task.close()


@pytest.mark.parametrize("expert_does", ["places", "picks"])
def test_split_policy_gives_the_expert_its_primitives_and_writes_only_the_action(expert_does):
    import torch
    from tensordict import TensorDict

    bench = load_benchmark("place_outcomes")

    def agent(td):
        return td.set("action", torch.tensor([1, 1, 1])).set("candidate_actions", torch.zeros(10, 3))

    def expert(td):
        return td.set("action", torch.tensor([2, 2, 2]))

    policy = bench.split_policy(agent, expert, expert_does)
    for holding in (False, True):
        td = policy(TensorDict({"holding": torch.tensor([holding])}, []))
        by_expert = holding == (expert_does == "places")
        assert td["action"].tolist() == ([2, 2, 2] if by_expert else [1, 1, 1])
        assert set(td.keys()) == {"holding", "action"}


def test_expert_does_leaves_no_place_to_choose_in_one_line(capsys):
    bench = load_benchmark("place_outcomes")
    with pytest.raises(SystemExit):
        bench.parse_args(["c.pt", "--expert-does", "places", "--choose", "q-first"])
    assert "--expert-does places leaves no place decision to --choose q-first" in capsys.readouterr().err


def test_nearest_expert_choice_takes_the_candidate_nearest_the_experts_action_rotations_counted():
    import gymnasium as gym
    import torch
    from types import SimpleNamespace

    import ldm_rl.envs  # noqa: F401  (registers the ids)
    from ldm_rl.envs.base import ExpertNoise

    bench = load_benchmark("place_outcomes")
    task = gym.make("ldm_rl/BinPacking-v0").unwrapped
    try:
        task.reset(seed=5)
        row, col, rot = (int(v) for v in task.expert_action(ExpertNoise()))
        other = (rot + task.num_rotations // 2) % task.num_rotations
        candidates = torch.tensor([[[row + 12, col, rot], [row, col + 1, other], [row + 3, col - 4, rot], [row, col, other]]])
        planner_scores = torch.tensor([[0.9, 0.5, 0.1, 0.7]])
        q_map = torch.zeros(1, task.num_rotations, 128, 128)
        q_map[0, rot, row, col] = 1.0
        q_map[0, other, :2, :2] = 2.0  # four entries above the expert's place
        planner = SimpleNamespace(score=lambda *a, **o: (planner_scores, None), q_network=lambda *a: q_map)
        nearest = bench.choose_nearest_expert(planner, task)
        scores, _ = planner.score(None, None, torch.tensor([1.0]), candidates, 0.0)
        assert scores[0].argmax() == 2 and scores[0].isinf().sum() == 3  # 5 px at its rotation beats 1 px turned
        assert nearest == [(5.0, 0, pytest.approx(4 / q_map.numel()))]
        scores, _ = planner.score(None, None, torch.tensor([0.0]), candidates, 0.0)  # a pick: the planner's scores
        assert torch.equal(scores, planner_scores) and len(nearest) == 1
        with pytest.raises(ValueError, match="plays one env: a batch of 1 state, got 2"):
            planner.score(None, None, torch.tensor([1.0, 1.0]), candidates.repeat(2, 1, 1), 0.0)
    finally:
        task.close()


def test_route_places_hands_the_held_blocks_to_the_placer_and_keeps_each_output_whole():
    """--place-weights: a decision with a block in the hand is the placer's, every other the picker's, with all the
    keys each writes (the candidates the decision readings need), not the action alone."""
    from tensordict import TensorDict

    bench = load_benchmark("place_outcomes")

    def planner(tag):
        def act(td):
            return td.set("action", torch.full((1, 3), tag)).set("candidate_actions", torch.full((1, 2, 3), tag))
        return act

    policy = bench.route_places(planner(1), planner(2))
    for holding, tag in ((False, 1), (True, 2)):
        out = policy(TensorDict({"holding": torch.tensor([[holding]])}, batch_size=[1]))
        assert (out["action"] == tag).all() and (out["candidate_actions"] == tag).all()


def test_place_weights_of_another_task_or_a_missing_file_stop_in_one_line_before_any_episode(tmp_path, capsys):
    """--place-weights must name an LDM checkpoint of the same task: another task's, or no file, is one error line."""
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from ldm_rl.agents import build_agent
    from ldm_rl.run.checkpoint import save_checkpoint

    bench = load_benchmark("place_outcomes")
    root = Path(__file__).resolve().parents[1]
    paths = {}
    for env in ("bin_packing", "block_stacking"):
        with initialize_config_dir(version_base="1.3", config_dir=str(root / "conf")):
            cfg = compose(config_name="train_policy", overrides=["experiment=smoke", f"env={env}"])
        stored = {key: value for key, value in OmegaConf.to_container(cfg).items() if key != "logger"}
        meta = {"kind": "agent", "agent": "ldm", "preset": "lite", "task": cfg.env.id,
                "config": OmegaConf.to_container(OmegaConf.create(stored), resolve=True)}
        agent = build_agent(cfg, float(cfg.env.max_height))
        paths[env] = save_checkpoint(tmp_path / f"{env}.pt", {"agent": agent.policy_state_dict()}, meta=meta)
    for placer, expected in ((paths["block_stacking"], "need LDM checkpoints of one task"),
                             (tmp_path / "nowhere.pt", "nowhere.pt")):
        with pytest.raises(SystemExit) as stop:
            bench.main([str(paths["bin_packing"]), "--episodes", "1", "--place-weights", str(placer)])
        message = str(stop.value)
        assert message.startswith("error: ") and expected in message and "\n" not in message


def test_quantile_heightmaps_rise_with_the_quantile_and_meet_the_mode_where_the_model_is_sure():
    from dyn_helpers import block_scenes, tiny_model

    bench = load_benchmark("place_outcomes")
    dynamics = tiny_model()
    heightmap = block_scenes(2)
    in_hand, holding = torch.zeros(2, 1, 24, 24), torch.ones(2, 1, dtype=torch.bool)
    candidates = torch.tensor([[[40, 50, 0], [70, 30, 3], [90, 90, 5]]] * 2)
    with torch.no_grad():
        low, mid, high = (bench.quantile_heightmaps(dynamics, heightmap, in_hand, holding, candidates, q)
                          for q in (0.1, 0.5, 0.9))
        assert low.shape == (2, 3, 1, 128, 128)
        assert (low <= mid).all() and (mid <= high).all() and (high > low).any()  # random weights: spread classes
        mode = dynamics.predict(heightmap[[0, 0, 0, 1, 1, 1]], in_hand[[0] * 3 + [1] * 3], holding[[0] * 3 + [1] * 3],
                                candidates.reshape(6, 3)).heightmap.reshape(2, 3, 1, 128, 128)
        outside = (low == mid) & (mid == high)  # pixels the crop does not reach keep the scene
        assert torch.equal(mode[outside], low[outside])
        # a model sure of one class per pixel: every quantile is its mode
        forward = dynamics.forward
        dynamics.forward = lambda *state: 50.0 * torch.nn.functional.one_hot(
            forward(*state).argmax(1), dynamics.num_classes).movedim(-1, 1).float()
        sure = [bench.quantile_heightmaps(dynamics, heightmap, in_hand, holding, candidates, q) for q in (0.1, 0.9)]
        assert torch.equal(sure[0], sure[1]) and torch.equal(sure[0], mode)
