"""Seed sweeps: Hydra multiruns of a real recipe through the basic, joblib and submitit launchers, and
ldm_rl/reports/aggregate_sweep.py on their folders (docs/scaling.md).

The sweeps run recipes/train_dynamics.py, the cheapest recipe, with a tiny world model: 12 expert
transitions, 2 gradient steps, one evaluation. Each launcher starts real processes (the basic one runs
its jobs one after another in the launching process, joblib in worker processes, submitit as local
jobs), so the file takes tens of seconds.
"""

from __future__ import annotations

import csv
import importlib
import json
import math
import statistics
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "train_dynamics.py"
TINY = ["dynamics.num_demo_steps=12", "dynamics.iterations=2", "dynamics.eval_every=2", "dynamics.batch_size=4",
        "dynamics.grid_samples=1", "model.width=0.125", "demos.progress=false", "dynamics.checkpoint_every=0",
        "threads=1", "device=cpu"]
ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "MPLBACKEND": "Agg", "RL_WARNINGS": "0", "HYDRA_FULL_ERROR": "1"}
# final_metrics.json keys that measure wall-clock time, not the run's result
WALL_CLOCK = {"elapsed_s"}


def run_sweep(sweep_dir: Path, seeds: str, *launcher: str) -> Path:
    """``python recipes/train_dynamics.py -m seed=<seeds> <TINY> <launcher> hydra.sweep.dir=<sweep_dir>``."""
    import os

    cmd = [sys.executable, str(RECIPE), "-m", f"seed={seeds}", *TINY, *launcher, f"hydra.sweep.dir={sweep_dir}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=sweep_dir.parent, env={**os.environ, **ENV},
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return sweep_dir


def finals(sweep_dir: Path) -> dict[int, dict]:
    """{seed: final_metrics.json} of every job folder of the sweep."""
    out = {}
    for path in sorted(sweep_dir.glob("*/final_metrics.json")):
        metrics = json.loads(path.read_text())
        out[metrics["seed"]] = metrics
    return out


def results(metrics: dict) -> dict:
    """A run's result: its final metrics without the wall-clock ones."""
    return {k: v for k, v in metrics.items() if k not in WALL_CLOCK}


def aggregate_module():
    """ldm_rl.reports.aggregate_sweep (its ``main(argv)`` is the command line)."""
    return importlib.import_module("ldm_rl.reports.aggregate_sweep")


@pytest.fixture(scope="module")
def basic_sweep(tmp_path_factory) -> Path:
    """Three seeds with Hydra's basic launcher (the jobs run one after another in the launching process)."""
    return run_sweep(tmp_path_factory.mktemp("basic") / "sweep", "0,1,2")


@pytest.mark.slow
def test_three_seed_sweep_aggregates_to_mean_and_std_over_seeds(basic_sweep, tmp_path, capsys):
    runs = finals(basic_sweep)
    assert sorted(runs) == [0, 1, 2] and sorted(p.name for p in basic_sweep.iterdir() if p.is_dir()) == ["0", "1", "2"]
    out = tmp_path / "agg"
    assert aggregate_module().main([str(basic_sweep), "--out", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out

    # sweep_summary.csv: one group (the runs differ only in seed), n=3, sample mean/std of each metric
    with open(out / "sweep_summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len({r["group"] for r in rows}) == 1
    by_metric = {r["metric"]: r for r in rows}
    for name in ("l1_mm", "sr", "floor_l1_mm", "loss"):
        values = [runs[s][name] for s in (0, 1, 2)]
        row = by_metric[name]
        assert row["n"] == "3" and row["seeds"] == "0 1 2"
        assert math.isclose(float(row["mean"]), statistics.fmean(values), rel_tol=1e-12, abs_tol=1e-15)
        assert math.isclose(float(row["std"]), statistics.stdev(values), rel_tol=1e-9, abs_tol=1e-15)
        assert float(row["min"]) == min(values) and float(row["max"]) == max(values)
    assert "seed" not in by_metric
    assert statistics.stdev(runs[s]["l1_mm"] for s in (0, 1, 2)) > 0  # the seeds really differ

    # sweep_summary.md: one table row "| `all runs` | 3 | 0 1 2 | sr % | ... | l1_mm | ..."
    md = (out / "sweep_summary.md").read_text()
    table = [line for line in md.splitlines() if line.startswith("|")]
    header = [c.strip() for c in table[0].strip("|").split("|")]
    assert header[:3] == ["group", "n", "seeds"] and len(table) == 3  # header, separator, one group
    cells = dict(zip(header, (c.strip() for c in table[2].strip("|").split("|"))))
    assert cells["n"] == "3" and cells["seeds"] == "0 1 2"
    l1 = [runs[s]["l1_mm"] for s in (0, 1, 2)]
    assert cells["l1_mm"] == f"{statistics.fmean(l1):.1f} ± {statistics.stdev(l1):.1f}"
    sr = [100 * runs[s]["sr"] for s in (0, 1, 2)]
    assert cells["sr (%)"] == f"{statistics.fmean(sr):.1f} ± {statistics.stdev(sr):.1f}"
    assert "without final_metrics.json" not in md

    # the curve: held-out SR per evaluation (iteration 2), mean over the three runs' logged scalars
    from ldm_rl.run.outputs import read_scalars

    assert (out / "sweep_curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with open(out / "sweep_curve.csv", newline="") as f:
        curve = list(csv.DictReader(f))
    logged = [dict(read_scalars(basic_sweep / str(s))["dynamics/sr"]) for s in (0, 1, 2)]
    assert [float(r["x_value"]) for r in curve] == [2.0]
    assert {(r["x"], r["y"], r["n"]) for r in curve} == {("iteration", "sr", "3")}
    assert math.isclose(float(curve[0]["mean"]), statistics.fmean(run[2] for run in logged), abs_tol=1e-12)


@pytest.mark.slow
def test_joblib_launcher_gives_each_seed_the_basic_launchers_result(basic_sweep, tmp_path):
    """hydra/launcher=joblib runs the jobs in two worker processes at once; seeded, one thread each, every
    seed ends with the same metrics, bit for bit, as in the basic launcher's sweep (docs/reliability.md)."""
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher", reason="pip install 'ldm_rl[sweep]'")
    sweep = run_sweep(tmp_path / "sweep", "0,1", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2")
    launcher = (sweep / "multirun.yaml").read_text()
    assert "JoblibLauncher" in launcher and "n_jobs: 2" in launcher
    joblib_runs, basic_runs = finals(sweep), finals(basic_sweep)
    assert sorted(joblib_runs) == [0, 1]
    for seed in (0, 1):
        assert results(joblib_runs[seed]) == results(basic_runs[seed])


@pytest.mark.slow
def test_submitit_local_launcher_runs_the_sweep_as_jobs(basic_sweep, tmp_path):
    """hydra/launcher=submitit_local: submitit's local executor (the SLURM launcher's code path without
    a cluster) runs each job as a subprocess and keeps its logs under <sweep>/.submitit/."""
    pytest.importorskip("submitit", reason="submitit is not installed: pip install 'ldm_rl[sweep]'")
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="pip install 'ldm_rl[sweep]'")
    sweep = run_sweep(tmp_path / "sweep", "0", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10",
                      "hydra.launcher.cpus_per_task=1")
    assert "LocalLauncher" in (sweep / "multirun.yaml").read_text()
    assert any((sweep / ".submitit").glob("*/*_log.out"))
    runs = finals(sweep)
    assert sorted(runs) == [0] and results(runs[0]) == results(finals(basic_sweep)[0])


# ----------------------------------------------------------------------------------- errors


def _job(folder: Path, overrides: str, metrics: str | None = None) -> None:
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "overrides.yaml").write_text(overrides)
    if metrics is not None:
        (folder / "final_metrics.json").write_text(metrics)


@pytest.mark.parametrize("layout, message", [
    ("missing", "is not a folder: pass a Hydra multirun folder"),
    ("run", "holds no Hydra job folders (<n>/.hydra/overrides.yaml)"),
    ("unfinished", "none of the 2 jobs in"),
    ("bad_json", "final_metrics.json is not valid JSON"),
])
def test_a_folder_that_is_not_a_sweep_is_one_clear_error(tmp_path, capsys, layout, message):
    folder = tmp_path / "x"
    if layout == "run":  # a single run's folder (hydra.run.dir), not a multirun
        _job(folder, "- seed=0\n", '{"seed": 0, "sr": 0.5}')
    elif layout == "unfinished":
        _job(folder / "0", "- seed=0\n")
        _job(folder / "1", "- seed=1\n")
    elif layout == "bad_json":
        _job(folder / "0", "- seed=0\n", '{"seed": 0, "sr": ')
    assert aggregate_module().main([str(folder)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1
    assert not (folder / "sweep_summary.md").exists()


def test_aggregate_cli_exits_nonzero_with_one_line(tmp_path):
    import os

    proc = subprocess.run([sys.executable, "-m", "ldm_rl.reports.aggregate_sweep", str(tmp_path)], capture_output=True, text=True, cwd=tmp_path,
                          env={**os.environ, **ENV}, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.strip().splitlines() == [
        f"error: {tmp_path} holds no Hydra job folders (<n>/.hydra/overrides.yaml): pass the folder of one sweep, "
        "such as multirun/2026-01-01/12-00-00"]
