"""End to end: recipes/train_policy.py experiment=smoke (seconds), then recipes/evaluate.py on its checkpoint."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
SMOKE = ("experiment=smoke", "agent.return_lower_bound=true", "agent.greedy_ema_decay=0.9",
         "agent.termination_head=true", "agent.value_raise_levels=2", "agent.value_raise_height=0.04",
         "agent.value_raise_region=top")


def run(script: str, *overrides: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "recipes" / script), *overrides], capture_output=True, text=True,
                          env=ENV, cwd=cwd, timeout=900)


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("train_policy")
    # with the return bound on (the stacking_lite choice), so the replay's return column runs end to end, and the
    # greedy policy's averaged weights, V's termination head and its raised towers, so the checkpoints, the resume
    # and evaluate.py carry them
    proc = run("train_policy.py", *SMOKE, f"hydra.run.dir={out}", cwd=out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, proc


@pytest.mark.slow
def test_smoke_run_writes_curve_checkpoint_and_metrics(smoke_run):
    out, proc = smoke_run
    final = json.loads((out / "final_metrics.json").read_text())
    assert final["agent"] == "ldm" and final["episodes_final_eval"] == 2
    assert 0.0 <= final["success_rate"] <= 1.0 and final["episodes"] >= 2
    assert 0 < final["replay_bytes_per_transition"] <= 20_000
    curve = (out / "curve.csv").read_text().splitlines()
    assert curve[0].startswith("updates,episodes,env_steps,wall_s,success_rate") and len(curve) >= 3
    assert (out / "learning_curve.png").stat().st_size > 10_000
    assert "done: greedy success" in proc.stdout
    assert "Initialized LazyTensorStorage" not in proc.stdout + proc.stderr  # torchrl's INFO lines are quieted
    # checkpoint selection: the earliest best in-training evaluation, re-scored on held-out scenes
    rows = [dict(zip(curve[0].split(","), line.split(","))) for line in curve[1:-1]]  # the last row is the final one
    rates = [float(row["success_rate"]) for row in rows]
    first_best = rows[rates.index(max(rates))]
    assert final["best"]["selected_at"]["updates"] == int(first_best["updates"])
    assert final["best"]["eval_episodes"] == 2 and (out / "best_policy.pt").exists()
    from ldm_rl.run.checkpoint import load_checkpoint

    state = load_checkpoint(out / "best_policy.pt").state["agent"]
    assert "averaged_planner.n_averaged" in state
    assert any("value_network.termination_head" in key for key in state)  # V's third head travels with the weights


@pytest.mark.slow
def test_evaluate_runs_a_saved_checkpoint_on_more_objects(smoke_run, tmp_path):
    out, _ = smoke_run
    proc = run("evaluate.py", f"checkpoint={out / 'best_policy.pt'}", "episodes=2", "num_objects=4", "progress=false",
               f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((tmp_path / "evaluation.json").read_text())
    assert result["num_objects"] == 4 and result["trained_on"] == 3 and result["episodes"] == 2
    assert result["ci_low"] <= result["success_rate"] <= result["ci_high"]
    assert "online_weights" not in result  # the averaged weights, what the run's own evaluations played
    assert result["finger_spinning_friction"] == 0.1  # the physics the run was trained on (conf/env)
    assert result["scene_seed"] == 0  # evaluate.py's seed: which held-out scenes were played
    per_episode = result["per_episode"]  # each scene's outcome in order, for paired comparisons of two evaluations
    assert len(per_episode["success"]) == len(per_episode["length"]) == 2
    assert sum(per_episode["success"]) == result["successes"]
    assert sum(per_episode["length"]) / 2 == pytest.approx(result["mean_length"])
    # every step is a pick (empty hand) or a place, and each place follows a pick that held (the last may not be placed)
    for length, picks, held in zip(per_episode["length"], per_episode["picks"], per_episode["picks_held"]):
        assert 1 <= picks <= length and length - picks <= held <= min(picks, length - picks + 1)
    assert result["picks"]["picks"] == sum(per_episode["picks"]) and result["picks"]["held"] == sum(per_episode["picks_held"])
    # a place that put back what its pick took is one of the places: at most one per place
    assert all(0 <= undone <= length - picks for undone, length, picks in
               zip(per_episode["undone"], per_episode["length"], per_episode["picks"]))
    assert result["undone"] == {"places": sum(per_episode["undone"]), "episodes": sum(n > 0 for n in per_episode["undone"])}

    # the same training played with its online weights (the run has agent.greedy_ema_decay), and with the places
    # predicted to recreate a scene of the episode ranked last (the env remembering 4 scenes)
    online = tmp_path / "online"
    proc = run("evaluate.py", f"checkpoint={out / 'checkpoint.pt'}", "episodes=1", "online_weights=true", "progress=false",
               "finger_spinning_friction=0", "planner.revisits_last=true", "scene_memory=4", "height_anchor=0.08",
               f"hydra.run.dir={online}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((online / "evaluation.json").read_text())
    assert result["online_weights"] is True and result["finger_spinning_friction"] == 0.0  # played on other physics
    assert result["played_with"]["planner"]["revisits_last"] is True and result["scene_memory"] == 4
    assert result["played_with"]["height_anchor"] == result["height_anchor"] == 0.08  # the LDM's frame anchored at 8 cm


@pytest.mark.slow
def test_evaluate_rejects_a_checkpoint_of_another_preset(smoke_run, tmp_path):
    out, _ = smoke_run
    proc = run("evaluate.py", f"checkpoint={out / 'checkpoint.pt'}", "episodes=1", "preset=paper", f"hydra.run.dir={tmp_path}",
               cwd=tmp_path)
    assert proc.returncode != 0
    assert "preset" in proc.stderr and "paper" in proc.stderr and "lite" in proc.stderr
    # the revisit rule without the scenes it reads: one line, before anything is played
    proc = run("evaluate.py", f"checkpoint={out / 'checkpoint.pt'}", "episodes=1", "planner.revisits_last=true",
               f"hydra.run.dir={tmp_path / 'revisits'}", cwd=tmp_path)
    assert proc.returncode == 2 and "planner.revisits_last=true reads the scenes the env remembers, but scene_memory is 0" \
        in proc.stderr, proc.stderr[-2000:]
    proc = run("evaluate.py", f"checkpoint={out / 'checkpoint.pt'}", "episodes=1", "height_anchor=0.3",
               f"hydra.run.dir={tmp_path / 'anchor'}", cwd=tmp_path)
    assert proc.returncode == 2 and "height_anchor must be in [0, max_height = 0.25) metres (0 = none)" in proc.stderr, \
        proc.stderr[-2000:]


def test_unknown_agent_is_one_clear_error():
    from ldm_rl.agents import build_agent

    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose(config_name="train_policy", overrides=["experiment=smoke"])
    cfg.agent.name = "alphazero"
    with pytest.raises(ValueError, match=r"agent.name must be one of \['dynaq', 'fcdqn', 'ldm', 'rs'\], got 'alphazero'"):
        build_agent(cfg, 0.25)


def test_train_policy_config_composes_every_group():
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose(config_name="train_policy", overrides=["experiment=stacking_lite"])
    assert cfg.agent.name == "ldm" and cfg.planner.num_candidates == 10 and cfg.replay.alpha == 0.6
    assert cfg.schedule.max_wall_clock_s == 2160 and cfg.threads == 1 and cfg.env.num_objects == 3
    assert cfg.agent.num_target_candidates == 3 and cfg.schedule.pretrain_updates == 200
    assert cfg.schedule.updates_per_step == 0.5 and cfg.agent.bootstrap_cache == 4096
    assert cfg.agent.q_frame_margin == 8 and cfg.agent.lr.q == 1e-3 and cfg.agent.lr.value == 1e-4
    from ldm_rl.agents import build_agent

    assert build_agent(cfg, float(cfg.env.max_height)).planner.q_network.frame_margin == 8


def test_the_planner_is_chosen_by_name_and_configs_without_the_name_get_the_papers():
    from omegaconf import OmegaConf

    from ldm_rl.agents import build_agent
    from ldm_rl.planning.planner import LookaheadPlanner

    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        composed = compose(config_name="train_policy", overrides=["experiment=smoke"])
    composed.logger.exp_name = "run"  # an interpolation of Hydra's runtime
    cfg = OmegaConf.to_container(composed, resolve=True)
    assert cfg["planner"]["name"] == "diverse"
    old = {**cfg, "planner": {k: v for k, v in cfg["planner"].items() if k != "name"}}  # a checkpoint's config before the key
    assert type(build_agent(old, 0.25).planner) is LookaheadPlanner
    with pytest.raises(ValueError, match=r"planner.name must be one of \['diverse', 'tree'\], got 'beam'"):
        build_agent({**cfg, "planner": {**cfg["planner"], "name": "beam"}}, 0.25)


@pytest.mark.slow
def test_a_killed_run_resumes_to_the_same_weights_and_curve(smoke_run, tmp_path):
    """SIGKILL after the first checkpoint, then resume=true: the same final weights and curve as the
    uninterrupted run (same seed and threads)."""
    import signal
    import time

    import torch

    from ldm_rl.run.checkpoint import load_checkpoint

    out, _ = smoke_run
    run_dir = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, str(ROOT / "recipes" / "train_policy.py"), *SMOKE,
                             f"hydra.run.dir={run_dir}"], env=ENV, cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.time() + 600
    while not (run_dir / "checkpoint.pt").exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.2)
    assert proc.poll() is None, "the run ended before its first checkpoint"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed = load_checkpoint(run_dir / "checkpoint.pt").state["counters"]["episodes"]
    resumed = run("train_policy.py", "resume=true", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    a = load_checkpoint(out / "checkpoint.pt").state
    b = load_checkpoint(run_dir / "checkpoint.pt").state
    assert killed < a["counters"]["episodes"] == b["counters"]["episodes"]
    assert a["agent"].keys() == b["agent"].keys()
    assert all(torch.equal(a["agent"][k], b["agent"][k]) for k in a["agent"])
    drop = ("wall_s",)
    assert [{k: v for k, v in r.items() if k not in drop} for r in a["curve"]] == \
        [{k: v for k, v in r.items() if k not in drop} for r in b["curve"]]


@pytest.mark.slow
def test_a_run_stopped_in_its_final_evaluation_resumes_to_that_evaluation_only(smoke_run, tmp_path):
    """The last checkpoint is written when the budget is spent, before the final evaluation; a run killed during that
    evaluation resumes to it without collecting or updating any further (it once ran one more episode)."""
    import shutil

    import torch

    from ldm_rl.run.checkpoint import load_checkpoint

    out, _ = smoke_run
    run_dir = tmp_path / "run"
    shutil.copytree(out, run_dir)
    (run_dir / "final_metrics.json").unlink()
    resumed = run("train_policy.py", "resume=true", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    a = load_checkpoint(out / "checkpoint.pt").state
    b = load_checkpoint(run_dir / "checkpoint.pt").state
    assert a["counters"] == b["counters"]
    assert all(torch.equal(a["agent"][k], b["agent"][k]) for k in a["agent"])
    first = json.loads((out / "final_metrics.json").read_text())
    again = json.loads((run_dir / "final_metrics.json").read_text())
    assert (again["episodes"], again["updates"]) == (first["episodes"], first["updates"])
    assert "final evaluation only" in (run_dir / "train_policy.log").read_text()


@pytest.mark.slow
def test_a_finished_run_given_a_larger_budget_ends_as_a_run_with_that_budget_from_the_start(smoke_run, tmp_path):
    """``schedule.total_episodes`` only says when the loop stops: resuming a finished run with a larger one is
    allowed (any other change is refused), goes on from its checkpoint, keeps the earlier final metrics under their
    episode count, and ends with the weights and curve of the run that had the larger budget from the start."""
    import shutil

    import torch

    from ldm_rl.run.checkpoint import load_checkpoint

    out, _ = smoke_run
    finished = json.loads((out / "final_metrics.json").read_text())
    larger = f"schedule.total_episodes={finished['episodes'] + 1}"
    extended = tmp_path / "extended"
    shutil.copytree(out, extended)
    resumed = run("train_policy.py", "resume=true", f"hydra.run.dir={extended}", larger, cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert json.loads((extended / f"final_metrics_at_{finished['episodes']}_episodes.json").read_text()) == finished
    assert json.loads((extended / "final_metrics.json").read_text())["episodes"] == finished["episodes"] + 1
    direct = tmp_path / "direct"
    proc = run("train_policy.py", *SMOKE, larger, f"hydra.run.dir={direct}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    a = load_checkpoint(direct / "checkpoint.pt").state
    b = load_checkpoint(extended / "checkpoint.pt").state
    assert a["counters"] == b["counters"]
    assert all(torch.equal(a["agent"][k], b["agent"][k]) for k in a["agent"])
    drop = ("wall_s",)
    assert [{k: v for k, v in r.items() if k not in drop} for r in a["curve"]] == \
        [{k: v for k, v in r.items() if k not in drop} for r in b["curve"]]


@pytest.mark.slow
def test_sigterm_saves_and_exits_with_one_line(tmp_path):
    """A wall-clock-bound run: progress in minutes of its budget, the first signal says what the run waits
    for, the stop line names the budget, and the folder then refuses a fresh start naming the episode, and a
    resume with another config naming the override that gives the run's back."""
    import signal
    import time

    run_dir = tmp_path / "run"
    command = [sys.executable, str(ROOT / "recipes" / "train_policy.py"), "experiment=smoke", "schedule.total_episodes=50",
               "schedule.max_wall_clock_s=3600", "schedule.progress=true", f"hydra.run.dir={run_dir}"]
    proc = subprocess.Popen(command, env={**ENV, "LDM_RL_PROGRESS": "lines"}, cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 600
    while not (run_dir / "curve.csv").exists() and time.time() < deadline:  # set-up is done
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=600)
    assert proc.returncode == 143
    lines = stderr.strip().splitlines()
    assert any(line.startswith("SIGTERM: stopping after the current episode") for line in lines), stderr[-3000:]
    progress = (run_dir / "train_policy.log").read_text()  # the progress lines of a non-terminal run
    import re

    assert re.search(r"train \(wall-clock budget\): [0-9.]+/60.0 min \(0%\) \[elapsed [0-9:]+, ETA (59|60):", progress), \
        progress[-3000:]
    assert "/50 episode" not in progress  # the episode cap does not bound this run
    last = lines[-1]
    assert last.startswith("stopped by SIGTERM at episode ") and " of 60.0 min of the wall-clock budget" in last, last
    assert "resume=true" in last
    assert (run_dir / "checkpoint.pt").exists() and len(list(run_dir.glob("replay-*"))) == 1
    again = subprocess.run(command, env=ENV, cwd=tmp_path, capture_output=True, text=True)
    assert again.returncode == 2 and len(again.stderr.strip().splitlines()) == 1, again.stderr
    assert "already holds a run's checkpoint (episode " in again.stderr and " updates): continue it with resume=true" in again.stderr
    # resuming with another config is refused in one line naming the override that gives the run's back
    changed = subprocess.run([*command[:2], "resume=true", f"hydra.run.dir={run_dir}", "agent.greedy_ema_decay=0.5"],
                             env=ENV, cwd=tmp_path, capture_output=True, text=True)
    assert changed.returncode == 2 and len(changed.stderr.strip().splitlines()) == 1, changed.stderr
    assert "agent.greedy_ema_decay: the run has null, the command gives 0.5" in changed.stderr
    assert changed.stderr.strip().endswith("to resume it as it ran, add: agent.greedy_ema_decay=null"), changed.stderr


@pytest.mark.parametrize("rate, pattern", [(1, [1, 1, 1, 1]), (2, [2, 2, 2, 2]), (0.5, [0, 1, 0, 1]),
                                           (0.25, [0, 0, 0, 1]), (1.5, [1, 2, 1, 2])])
def test_updates_due_spreads_a_fractional_update_rate_evenly(rate, pattern):
    sys.path.insert(0, str(ROOT / "recipes"))
    try:
        from train_policy import updates_due
    finally:
        sys.path.remove(str(ROOT / "recipes"))
    assert [updates_due(n, rate) for n in range(1, 5)] == pattern
    assert sum(updates_due(n, 0.35) for n in range(1, 1001)) == 350  # exact rational arithmetic: no drift


def test_the_short_try_runs_the_shipped_cpu_networks_without_pretraining():
    """experiment=try: stacking_lite's networks and batch, no model-only pretraining, evaluation sized for a try;
    an explicit env or agent on the command line still wins."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        cfg = compose("train_policy", overrides=["experiment=try", "env=house_building", "agent=fcdqn"])
    assert cfg.agent.name == "fcdqn" and cfg.env.id == "ldm_rl/HouseBuilding-v0"
    assert cfg.agent.q_width == 0.25 and cfg.replay.batch_size == 16 and cfg.threads == 1
    s = cfg.schedule
    assert (s.pretrain_updates, s.total_episodes, s.max_wall_clock_s, s.keep_best) == (0, 3, None, False)
    assert (s.eval_episodes, s.final_eval_episodes) == (5, 10)


def test_a_curve_resumed_across_the_packing_columns_keeps_its_older_rows_with_empty_cells(tmp_path):
    import csv

    sys.path.insert(0, str(ROOT / "recipes"))
    try:
        from train_policy import CURVE_FIELDS, PACKING_FIELDS, write_curve
    finally:
        sys.path.remove(str(ROOT / "recipes"))
    plain = {"updates": 0, "episodes": 0, "env_steps": 0, "wall_s": 1.0, "success_rate": 0.0, "ci_low": 0.0,
             "ci_high": 0.5, "mean_length": 20.0}
    write_curve([plain], tmp_path, "a task without packs")
    assert (tmp_path / "curve.csv").read_text().splitlines()[0] == ",".join(CURVE_FIELDS)
    # a bin-packing run written before the packing columns, resumed: its old row, an evaluation that packed nothing
    # (no pile), one that packed
    nothing = {**plain, "updates": 250, "mean_pile_top": None, "mean_return": 0.0, "mean_return_authors": 0.0,
               "mean_blocks_in_bin": 3.5}
    packed = {**plain, "updates": 500, "success_rate": 0.5, "mean_pile_top": 0.12, "mean_return": 0.125,
              "mean_return_authors": -1.0, "mean_blocks_in_bin": 7.5}
    write_curve([plain, nothing, packed], tmp_path, "bin packing")
    with open(tmp_path / "curve.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == [*CURVE_FIELDS, *PACKING_FIELDS]
    assert [row["mean_pile_top"] for row in rows] == ["", "", "0.12"]
    assert [row["mean_blocks_in_bin"] for row in rows] == ["", "3.5", "7.5"]
    assert rows[2]["mean_return_authors"] == "-1.0" and rows[0]["success_rate"] == "0.0"
