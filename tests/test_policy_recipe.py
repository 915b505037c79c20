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


def run(script: str, *overrides: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "recipes" / script), *overrides], capture_output=True, text=True,
                          env=ENV, cwd=cwd, timeout=900)


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("train_policy")
    proc = run("train_policy.py", "experiment=smoke", f"hydra.run.dir={out}", cwd=out)
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


@pytest.mark.slow
def test_evaluate_runs_a_saved_checkpoint_on_more_objects(smoke_run, tmp_path):
    out, _ = smoke_run
    proc = run("evaluate.py", f"checkpoint={out / 'checkpoint.pt'}", "episodes=2", "num_objects=4", "progress=false",
               f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((tmp_path / "evaluation.json").read_text())
    assert result["num_objects"] == 4 and result["trained_on"] == 3 and result["episodes"] == 2
    assert result["ci_low"] <= result["success_rate"] <= result["ci_high"]


@pytest.mark.slow
def test_evaluate_rejects_a_checkpoint_of_another_preset(smoke_run, tmp_path):
    out, _ = smoke_run
    proc = run("evaluate.py", f"checkpoint={out / 'checkpoint.pt'}", "episodes=1", "preset=paper", f"hydra.run.dir={tmp_path}",
               cwd=tmp_path)
    assert proc.returncode != 0
    assert "preset" in proc.stderr and "paper" in proc.stderr and "lite" in proc.stderr


def test_unknown_agent_is_one_clear_error():
    from ldm_rl.agents import build_agent

    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose(config_name="train_policy", overrides=["experiment=smoke"])
    cfg.agent.name = "alphazero"
    with pytest.raises(ValueError, match=r"agent.name must be one of \['ldm'\], got 'alphazero'"):
        build_agent(cfg, 0.25)


def test_train_policy_config_composes_every_group():
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose(config_name="train_policy", overrides=["experiment=stacking_lite"])
    assert cfg.agent.name == "ldm" and cfg.planner.num_candidates == 10 and cfg.replay.alpha == 0.6
    assert cfg.schedule.max_wall_clock_s == 6600 and cfg.threads == 1 and cfg.env.num_objects == 3
    assert cfg.agent.num_target_candidates == 3 and cfg.schedule.pretrain_updates == 200
