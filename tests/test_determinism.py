"""Determinism, stated and tested in fresh processes, and runs that survive being killed.

* same seed + same threads (the default, 1) => bit-identical weights, optimizer state and metrics;
* a run killed with SIGKILL after its first checkpoint, resumed with `resume=true`, ends bit-identical
  to the uninterrupted run;
* SIGTERM saves a checkpoint and exits with one line (exit code 143).
"""

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from ldm_rl.run.checkpoint import load_checkpoint
from ldm_rl.run.outputs import read_scalars

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "train_dynamics.py"
ITERATIONS = 40
TINY_RUN = ["dynamics.num_demo_steps=24", f"dynamics.iterations={ITERATIONS}", "dynamics.eval_every=10", "dynamics.batch_size=4",
            "dynamics.checkpoint_every=4", "dynamics.grid_samples=1", "model.width=0.0625", "demos.progress=false", "seed=3"]


def command(run_dir, *extra):
    return [sys.executable, str(RECIPE), *TINY_RUN, *extra, f"hydra.run.dir={run_dir}"]


def run(run_dir, *extra, cwd):
    done = subprocess.run(command(run_dir, *extra), capture_output=True, text=True, cwd=cwd, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def start(run_dir, cwd):
    return subprocess.Popen(command(run_dir), cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for_checkpoint(proc, run_dir, timeout=300.0):
    deadline = time.monotonic() + timeout
    while not (run_dir / "checkpoint.pt").exists():
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        assert time.monotonic() < deadline, "no checkpoint appeared"
        time.sleep(0.01)


def same_run(a: Path, b: Path) -> None:
    """Final weights, loss buffers, optimizer, schedule, RNGs and metrics equal bit for bit (elapsed_s aside)."""
    ca, cb = load_checkpoint(a), load_checkpoint(b)
    assert ca.meta["complete"] and cb.meta["complete"]
    for part in ("model", "loss"):
        assert ca.state[part].keys() == cb.state[part].keys()
        for key, value in ca.state[part].items():
            assert torch.equal(value, cb.state[part][key]), f"{part}.{key}"
    for group_a, group_b in zip(ca.state["optimizer"]["state"].values(), cb.state["optimizer"]["state"].values()):
        assert all(torch.equal(group_a[k], group_b[k]) for k in group_a)
    assert ca.state["scheduler"] == cb.state["scheduler"]
    assert torch.equal(ca.state["rng"]["torch"], cb.state["rng"]["torch"])
    rows = [[{k: v for k, v in r.items() if k != "elapsed_s"} for r in c.state["rows"]] for c in (ca, cb)]
    assert rows[0] == rows[1] and len(rows[0]) == ITERATIONS // 10
    clock = ("dynamics/elapsed_s", "dynamics/iterations_per_s")  # wall-clock scalars; a killed run's repeats keep the last
    logged = [{k: v for k, v in read_scalars(d).items() if k not in clock} for d in (a, b)]
    assert logged[0] == logged[1] and len(logged[0]["dynamics/sr"]) == ITERATIONS // 10


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run (fresh process, default threads)."""
    folder = tmp_path_factory.mktemp("reference")
    run(folder / "run", cwd=folder)
    return folder / "run"


def test_default_threads_is_a_fixed_number(reference):
    from hydra import compose, initialize_config_dir

    from ldm_rl import config_schema  # noqa: F401  (registers the schema)

    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        assert compose(config_name="train_dynamics").threads == 1
    assert load_checkpoint(reference).meta["threads"] == 1  # the recipe applied it


def test_same_seed_and_threads_in_a_fresh_process_is_bit_identical(reference, tmp_path):
    run(tmp_path / "again", cwd=tmp_path)
    same_run(reference, tmp_path / "again")


def test_sigkill_after_the_first_checkpoint_then_resume_ends_identical(reference, tmp_path):
    run_dir = tmp_path / "killed"
    proc = start(run_dir, tmp_path)
    wait_for_checkpoint(proc, run_dir)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    at = load_checkpoint(run_dir).meta["iteration"]
    assert 4 <= at < ITERATIONS, f"the kill came too late (iteration {at})"
    resumed = subprocess.run([sys.executable, str(RECIPE), "resume=true", f"hydra.run.dir={run_dir}"], capture_output=True,
                             text=True, cwd=tmp_path, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"resuming at iteration {at}/{ITERATIONS}" in resumed.stdout
    same_run(reference, run_dir)


def test_sigterm_saves_a_checkpoint_and_exits_with_one_line(tmp_path):
    run_dir = tmp_path / "stopped"
    proc = start(run_dir, tmp_path)
    wait_for_checkpoint(proc, run_dir)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, stderr[-3000:]
    lines = [ln for ln in stderr.splitlines() if ln.strip() and not ln.startswith("pybullet build time")]
    # the signal's acknowledgement (what the run waits for), then the one stop line
    assert len(lines) == 2 and lines[0].startswith("SIGTERM: stopping after the current iteration"), stderr
    lines = lines[1:]
    saved = load_checkpoint(run_dir)
    at = saved.meta["iteration"]
    assert not saved.meta["complete"] and at < ITERATIONS
    assert lines[0].startswith(f"stopped by SIGTERM at iteration {at}/{ITERATIONS}; checkpoint saved to {run_dir / 'checkpoint.pt'}; "
                               "resume with: python ")
    assert lines[0].endswith("train_dynamics.py resume=true hydra.run.dir=stopped")
