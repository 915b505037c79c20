"""benchmarks/fit_world_model.py: more LDM-only steps on a run's own replay, written as a checkpoint to play."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
SCRIPT = ROOT / "benchmarks" / "fit_world_model.py"


def fit(*argv: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *argv], capture_output=True, text=True, env=ENV, cwd=cwd,
                          timeout=900)


@pytest.mark.parametrize("argv, message", [(["--steps", "-1"], "--steps must be >= 0"),
                                           (["--report-every", "0"], "--report-every >= 1")])
def test_bad_arguments_stop_in_one_line(tmp_path, argv, message):
    proc = fit(str(tmp_path), *argv)
    assert proc.returncode == 2 and message in proc.stderr.strip().splitlines()[-1], proc.stderr


def test_a_folder_without_a_checkpoint_stops_in_one_line(tmp_path):
    proc = fit(str(tmp_path))
    assert proc.returncode == 2 and "no checkpoint.pt (pass a training run's folder)" in proc.stderr, proc.stderr


def test_another_agents_run_stops_in_one_line_naming_the_agent(tmp_path):
    from ldm_rl.run.checkpoint import save_checkpoint

    save_checkpoint(tmp_path / "checkpoint.pt", {"agent": {}}, meta={"kind": "agent", "agent": "fcdqn"})
    proc = fit(str(tmp_path))
    last = proc.stderr.strip().splitlines()[-1]  # argparse's usage, then one error line
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert last.startswith("fit_world_model.py: error: ") and last.endswith("agent is 'fcdqn', expected 'ldm'"), last


@pytest.mark.slow
def test_the_fitted_world_model_is_the_one_the_greedy_planner_plans_with_and_nothing_else_moves(tmp_path):
    import torch

    from ldm_rl.run.checkpoint import load_checkpoint

    run = tmp_path / "run"
    proc = subprocess.run([sys.executable, str(ROOT / "recipes" / "train_policy.py"), "experiment=smoke",
                           "agent.greedy_ema_decay=0.9", f"hydra.run.dir={run}"], capture_output=True, text=True,
                          env=ENV, cwd=tmp_path, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    saved = tmp_path / "fitted.pt"
    out = fit(str(run), "--steps", "3", "--report-every", "2", "--save", str(saved), cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    assert [line.split("|")[1].strip() for line in out.stdout.splitlines() if line.startswith("| ") and
            line.split("|")[1].strip().isdigit()] == ["2", "3"]
    before = load_checkpoint(run / "checkpoint.pt").state["agent"]
    after = load_checkpoint(saved).state["agent"]
    online, greedy = "planner.dynamics.", "averaged_planner.module.dynamics."
    moved = [k for k in after if k.startswith(online) and after[k].is_floating_point()
             and not torch.equal(after[k], before[k])]
    assert moved, "three LDM steps changed no weight"
    assert all(torch.equal(after[greedy + k[len(online):]], after[k]) for k in after if k.startswith(online))
    others = [k for k in after if "dynamics" not in k]  # Q, V, their averages; the LDM's also sit under the loss
    assert others and all(torch.equal(after[k], before[k]) for k in others)
