"""Recipes: config composition, Table-1 aggregation, a smoke run of recipes/train_dynamics.py and its exact
resume after a stop."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from ldm_rl import config_schema  # registers the schema, as the recipes do

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("model, name, crop", [("ldm64", "ldm", 64), ("ldm128", "ldm", 128), ("naive", "naive", 64)])
def test_model_configs_compose_and_build(model, name, crop):
    from ldm_rl.world_model import build_dynamics_model

    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose(config_name="train_dynamics", overrides=[f"model={model}", "model.width=0.125"])
    assert cfg.model.name == name and cfg.model.crop_size == crop and cfg.model.preset == "lite"
    built = build_dynamics_model(cfg.model, max_height=0.15)
    assert built.frame == ("global" if name == "naive" else "local")
    assert built.frame_size == (128 if name == "naive" else crop)


def test_paper_preset_builds_the_reference_widths():
    from ldm_rl.world_model import build_dynamics_model, count_parameters

    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose(config_name="train_dynamics", overrides=["model.preset=paper", "model.num_depth_classes=11"])
    assert count_parameters(build_dynamics_model(cfg.model, 0.15).net.pick) == 24_893_963


def test_aggregate_table1_writes_mean_and_std(tmp_path):
    for seed, sr in enumerate((0.8, 0.9)):
        run = tmp_path / str(seed)
        run.mkdir()
        (run / "final_metrics.json").write_text(
            json.dumps({"task": "block_stacking", "model": "LDM(64)", "seed": seed, "sr": sr, "l1_mm": 2.0, "preset": "lite"})
        )
    out = tmp_path / "table.md"
    subprocess.run([sys.executable, "-m", "ldm_rl.reports.aggregate_table1", str(tmp_path), "--out", str(out)], check=True,
                   capture_output=True)
    text = out.read_text()
    assert "| LDM(64) | 85.0 ± 7.1 (n=2) [83.4] |" in text
    assert "| Naive | – [38.0] |" in text


def test_documented_table1_is_rebuilt_from_the_kept_runs(tmp_path):
    """docs/results/table1/table1.md and the table in docs/dynamics.md come from the kept final_metrics.json files."""
    results = ROOT / "docs" / "results" / "table1"
    out = tmp_path / "table1.md"
    subprocess.run([sys.executable, "-m", "ldm_rl.reports.aggregate_table1", str(results), "--out", str(out)], check=True,
                   capture_output=True)
    rebuilt = out.read_text()
    assert rebuilt == (results / "table1.md").read_text()
    docs = (ROOT / "docs" / "dynamics.md").read_text()
    rows = [line for line in rebuilt.splitlines()[:9] if line.startswith(("| LDM", "| Naive", "| *floor"))]
    assert len(rows) == 4 and all(row in docs for row in rows)


def test_balanced_sampler_draws_half_picks_half_places():
    import torch

    from ldm_rl.world_model.training import PrimitiveBalancedSampler

    holding = torch.tensor([False] * 9 + [True])
    idx = PrimitiveBalancedSampler(holding, 8, seed=0).sample()
    assert holding[idx].sum() == 4 and len(idx) == 8
    only_picks = PrimitiveBalancedSampler(torch.zeros(5, dtype=torch.bool), 6, seed=0).sample()
    assert len(only_picks) == 6 and (only_picks < 5).all()


def test_train_dynamics_recipe_smoke(tmp_path):
    run_dir = tmp_path / "run"
    cmd = [
        sys.executable, str(ROOT / "recipes" / "train_dynamics.py"),
        "dynamics.num_demo_steps=24", "dynamics.iterations=4", "dynamics.eval_every=2", "dynamics.batch_size=4",
        "dynamics.grid_samples=2", "model.width=0.125", "demos.progress=false", "threads=1", f"hydra.run.dir={run_dir}",
    ]
    result = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    for name in ("checkpoint.pt", "predictions.png", "final_metrics.json", "sr_vs_iteration.png", "config_resolved.yaml"):
        assert (run_dir / name).is_file(), name
    from ldm_rl.run.outputs import read_scalars

    scalars = read_scalars(run_dir)  # the CSV logger (logger=csv, the default) is the one record of each scalar
    assert [step for step, _ in scalars["dynamics/sr"]] == [2, 4] and len(scalars["dynamics/iterations_per_s"]) == 2
    curve = (run_dir / "curve.csv").read_text().splitlines()  # one line per evaluation, same values as the logger's
    assert curve[0].startswith("iteration,loss,sr,sr_pick,sr_place") and [line.split(",")[0] for line in curve[1:]] == ["2", "4"]
    assert [float(line.split(",")[2]) for line in curve[1:]] == pytest.approx([v for _, v in scalars["dynamics/sr"]])
    assert not (run_dir / "metrics.csv").exists()
    assert "${" in (run_dir / ".hydra" / "config.yaml").read_text()  # Hydra's copy keeps interpolations...
    assert "${" not in (run_dir / "config_resolved.yaml").read_text()  # ...the run's own copy has the values it used
    logged = (run_dir / "train_dynamics.log").read_text()  # Python logging: the run's log holds the console's lines
    shown = [line for line in result.stdout.splitlines() if line.strip()]
    assert shown and all(line in logged for line in shown)
    assert "train dynamics: 4/4 it (100%)" in logged and "done: SR" in logged
    summary = json.loads((run_dir / "final_metrics.json").read_text())
    assert summary["model"] == "LDM(64)" and summary["task"] == "block_stacking" and 0 <= summary["sr"] <= 1
    near_floor = summary["sr"] - summary["floor_sr"] < 0.05  # the last line says what an SR near the floor means
    assert ("SR is within 5 points of its floor after 4 iterations: expected for a short run" in logged) == near_floor
    from ldm_rl.world_model.factory import load_dynamics_checkpoint

    model, checkpoint = load_dynamics_checkpoint(run_dir, expect={"preset": "lite", "task": "ldm_rl/BlockStacking-v0"})
    assert checkpoint.meta["iteration"] == 4 and checkpoint.meta["complete"] and checkpoint.meta["threads"] == 1
    assert checkpoint.meta["config"]["model"]["width"] == 0.125 and model.frame_size == 64
    assert {"model", "loss", "optimizer", "scheduler", "rng", "rows", "running", "iteration"} <= checkpoint.state.keys()
    assert checkpoint.state["rows"][-1]["sr"] == summary["sr"]
    groups = checkpoint.state["optimizer"]["param_groups"]  # Adam with its fused kernel (ldm_rl.torch_utils.make_adam)
    assert groups and all(group["fused"] is True for group in groups)


TABLE1 = {"block_stacking": 5000, "house_building": 5000, "bottle_arrangement": 10000, "bin_packing": 10000}


@pytest.mark.parametrize("task, iterations", sorted(TABLE1.items()))
def test_table1_presets_follow_the_protocol(task, iterations):
    """Each Table 1 preset: its task, 5k noisy expert steps, the paper's iterations, a 20 % held-out split,
    and no model of its own (so `model=ldm64,ldm128,naive` sweeps the three rows)."""
    env = OmegaConf.load(ROOT / "conf" / "env" / f"{task}.yaml")
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        default = compose(config_name="train_dynamics", overrides=[f"experiment=table1_{task}"])
        for model in ("ldm64", "ldm128", "naive"):
            cfg = compose(config_name="train_dynamics", overrides=[f"experiment=table1_{task}", f"model={model}"])
            plain = compose(config_name="train_dynamics", overrides=[f"env={task}", f"model={model}"])
            assert OmegaConf.to_container(cfg.model) == OmegaConf.to_container(plain.model), model
    assert default.env.id == env.id and default.env.max_height == env.max_height and default.env.num_objects == env.num_objects
    assert default.dynamics.num_demo_steps == 5000 and default.dynamics.iterations == iterations
    assert default.dynamics.val_fraction == 0.2 and default.demos.noise.position > 0
    assert default.model.name == "ldm" and default.model.crop_size == 64
    config_schema.validate_config(default, config_schema.TrainDynamicsConfig)


def _dynamics_command(run_dir, *extra) -> list[str]:
    return [sys.executable, str(ROOT / "recipes" / "train_dynamics.py"), "dynamics.num_demo_steps=24",
            "dynamics.iterations=60", "dynamics.eval_every=30", "dynamics.checkpoint_every=10", "dynamics.batch_size=4",
            "dynamics.grid_samples=1", "model.width=0.125", "demos.progress=false", "threads=1", f"hydra.run.dir={run_dir}",
            *extra]


def _same(a, b) -> bool:
    import torch

    if isinstance(a, torch.Tensor):
        return torch.equal(a, b)
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a if k != "elapsed_s")
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


@pytest.mark.slow
def test_a_stopped_dynamics_run_resumes_to_the_uninterrupted_weights(tmp_path):
    """SIGTERM after the first checkpoint: the run saves, exits 143 with a resume line; resume=true then ends
    with the weights, loss buffers, optimiser, schedule and curve of the uninterrupted run (same seed, one thread)."""
    import signal
    import time

    from ldm_rl.run.checkpoint import CheckpointError, load_checkpoint
    from ldm_rl.world_model.factory import load_dynamics_checkpoint

    # the uninterrupted run beside the one to stop (one thread each)
    full = subprocess.Popen(_dynamics_command(tmp_path / "full"), cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    run_dir = tmp_path / "stopped"
    proc = subprocess.Popen(_dynamics_command(run_dir), cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    deadline = time.time() + 600
    while not (run_dir / "checkpoint.pt").exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before its first checkpoint"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 128 + signal.SIGTERM and "resume with:" in err, err[-2000:]
    stopped_at = load_checkpoint(run_dir).state["iteration"]
    assert 10 <= stopped_at < 60 and not load_checkpoint(run_dir).meta["complete"]
    _, full_err = full.communicate(timeout=600)
    assert full.returncode == 0, full_err[-3000:]
    resumed = subprocess.run(_dynamics_command(run_dir, "resume=true"), capture_output=True, text=True, cwd=tmp_path,
                             timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    a, b = load_checkpoint(tmp_path / "full").state, load_checkpoint(run_dir).state
    for key in ("model", "loss", "optimizer", "scheduler", "rows", "running", "iteration"):
        assert _same(a[key], b[key]), key
    model, checkpoint = load_dynamics_checkpoint(run_dir, expect={"preset": "lite"})
    assert not model.training and checkpoint.meta["iteration"] == 60 and checkpoint.meta["complete"]
    with pytest.raises(CheckpointError, match="task is 'ldm_rl/BlockStacking-v0', expected 'ldm_rl/HouseBuilding-v0'"):
        load_dynamics_checkpoint(run_dir, expect={"task": "ldm_rl/HouseBuilding-v0"})

