"""The README's two set-up commands stay true: CI runs the test command verbatim."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def setup_commands():
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Set-up: two commands", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```bash\n(.+?)\n```", section)


def test_readme_has_exactly_two_setup_commands_installing_torch_first():
    commands = setup_commands()
    assert len(commands) == 2, commands
    for command in commands:
        assert "\n" not in command and command.startswith("pip install torch==2.13.0 && pip install -e ")


def test_ci_runs_the_readme_test_command_verbatim():
    test_command = setup_commands()[1]
    assert "pytest" in test_command
    ci_lines = (ROOT / ".ci" / "run").read_text().splitlines()
    assert test_command in ci_lines


def test_main_command_runs_and_writes_what_the_readme_promises(tmp_path):
    """The README's main job: a few hundred noisy expert steps of 3-block stacking, the lite LDM(64), and
    metrics, a checkpoint and prediction images under outputs/. Run here with the same recipe and defaults,
    only a smaller budget (the full job takes minutes)."""
    import json
    import subprocess
    import sys

    from ldm_rl.run.checkpoint import load_checkpoint

    main_command = setup_commands()[0]
    job = main_command.rsplit("&& ", 1)[1].split()
    assert job[0] == "python" and job[1].startswith("recipes/") and len(job) == 2, job
    recipe = ROOT / job[1]
    shown = subprocess.run([sys.executable, str(recipe), "--cfg", "job", "--resolve"], capture_output=True, text=True,
                           cwd=tmp_path, timeout=120)
    assert shown.returncode == 0, shown.stderr
    from omegaconf import OmegaConf

    cfg = OmegaConf.create(shown.stdout)
    assert cfg.env.id == "ldm_rl/BlockStacking-v0" and cfg.env.num_objects == 3
    assert 100 <= cfg.dynamics.num_demo_steps <= 1000 and cfg.demos.noise.position > 0 and cfg.dynamics.data is None
    assert cfg.model.name == "ldm" and cfg.model.crop_size == 64 and cfg.model.preset == "lite"
    small = ["dynamics.num_demo_steps=24", "dynamics.iterations=2", "dynamics.eval_every=2", "dynamics.batch_size=4",
             "dynamics.grid_samples=1", "model.width=0.125", "demos.progress=false"]
    done = subprocess.run([sys.executable, str(recipe), *small], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    (run_dir,) = (tmp_path / "outputs").glob("*/*")  # outputs/<date>/<time>/
    for name in ("train_dynamics/scalars/dynamics/sr.csv", "checkpoint.pt", "predictions.png", "final_metrics.json"):
        assert (run_dir / name).is_file(), name
    summary = json.loads((run_dir / "final_metrics.json").read_text())
    assert (summary["model"], summary["preset"], summary["task"]) == ("LDM(64)", "lite", "block_stacking")
    assert load_checkpoint(run_dir / "checkpoint.pt", expect={"kind": "dynamics", "preset": "lite"}).meta["complete"]
