"""The paper's comparison: the curves_* / generalization_* presets, ldm_rl/reports/plot_learning_curves.py on a real
multirun (and on written curves with known numbers), ldm_rl/reports/generalization_table.py on a smoke checkpoint."""

from __future__ import annotations

import csv
import importlib
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

from ldm_rl.config_schema import EvaluateConfig, TrainPolicyConfig, validate_config

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg", "RL_WARNINGS": "0"}
AGENTS = ("ldm", "fcdqn", "rs", "dynaq")
TASKS = ("block_stacking", "house_building", "bottle_arrangement", "bin_packing")


def script(name: str):
    """A report tool of ldm_rl/reports/ as a module."""
    return importlib.import_module(f"ldm_rl.reports.{name}")


plot_learning_curves = script("plot_learning_curves")
generalization_table = script("generalization_table")


def make_cfg(config_name: str, *overrides: str, hydra_node: bool = False):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        return compose(config_name=config_name, overrides=list(overrides), return_hydra_config=hydra_node)


# ------------------------------------------------------------------------------------------- presets


@pytest.mark.parametrize("task", TASKS)
def test_curves_preset_gives_every_agent_its_task_and_the_stated_budget(task):
    text = (CONF / "experiment" / f"curves_{task}.yaml").read_text()
    stated = int(re.search(r"budget of (\d+)", text).group(1))
    assert f"python recipes/train_policy.py -m experiment=curves_{task} agent=ldm,fcdqn,rs,dynaq seed=0,1" in text
    env_id = OmegaConf.load(CONF / "env" / f"{task}.yaml").id
    lite = OmegaConf.load(CONF / "experiment" / "stacking_lite.yaml")
    budgets = set()
    for agent in AGENTS:
        cfg = make_cfg("train_policy", f"experiment=curves_{task}", f"agent={agent}")
        validate_config(cfg, TrainPolicyConfig)  # no key of another agent leaks in (AgentConfig.check)
        assert cfg.agent.name == agent and cfg.env.id == env_id and cfg.threads == 1 and cfg.model.preset == "lite"
        assert cfg.agent.q_width == lite.agent.q_width and cfg.replay.batch_size == lite.replay.batch_size
        assert cfg.schedule.max_wall_clock_s is None  # a wall-clock stop would give slower agents fewer episodes
        budgets.add(cfg.schedule.total_episodes)
    assert budgets == {stated}
    if task == "bottle_arrangement":
        assert cfg.env.num_objects == 4  # the paper's training count (5 and 6 are the zero-shot tests)


@pytest.mark.parametrize("task", ["block_stacking", "bottle_arrangement"])
def test_generalization_preset_sweeps_the_papers_object_counts_for_evaluate(task, tmp_path):
    checkpoint = tmp_path / "checkpoint.pt"
    checkpoint.write_bytes(b"")  # the schema only asks that it exists
    cfg = make_cfg("evaluate", f"+experiment=generalization_{task}", f"checkpoint={checkpoint}", hydra_node=True)
    params = cfg.hydra.sweeper.params
    validate_config(cfg, EvaluateConfig)  # (the hydra node is not checked)
    assert cfg.episodes == 100 and cfg.num_objects is None and cfg.max_steps is None  # max_steps: 2·objects + 4
    jobs = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides([f"{k}={v}" for k, v in params.items()]),
                                        None)[0]
    counts = sorted(int(job[0].split("=")[1]) for job in jobs)
    paper = sorted(n for t, n in generalization_table.PAPER["ldm"] if t == task)
    assert counts == paper == list(generalization_table.protocols()[cfg_env_id(task)].counts)
    trained = generalization_table.TRAINED_ON[task]
    assert trained < min(counts) and f"trained on {trained}" in (CONF / "experiment" / f"generalization_{task}.yaml").read_text()


def cfg_env_id(task: str) -> str:
    return str(OmegaConf.load(CONF / "env" / f"{task}.yaml").id)


# ---------------------------------------------------------------------------- learning curves: math


def write_run(folder: Path, *, task: str, objects: int, agent: str, seed: int, points, config=None) -> Path:
    """A run folder as recipes/train_policy.py writes it: .hydra/config.yaml (``config``: more dotted keys) and curve.csv."""
    (folder / ".hydra").mkdir(parents=True)
    cfg = OmegaConf.create({"seed": seed, "env": {"id": task, "num_objects": objects}, "agent": {"name": agent},
                            "schedule": {"total_episodes": 500, "max_wall_clock_s": None}})
    for key, value in (config or {}).items():
        OmegaConf.update(cfg, key, value)
    OmegaConf.save(cfg, folder / ".hydra" / "config.yaml")
    with open(folder / "curve.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["updates", "episodes", "env_steps", "wall_s", "success_rate", "ci_low", "ci_high", "mean_length"])
        for i, (episodes, success) in enumerate(points):
            writer.writerow([10 * i, episodes, 10 * i, float(i), success, 0.0, 1.0, 5.0])
    return folder


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_curves_are_interpolated_averaged_over_seeds_and_split_by_variant(tmp_path, capsys):
    stack, bottles = "ldm_rl/BlockStacking-v0", "ldm_rl/BottleArrangement-v0"
    sweep, base, other_lr = tmp_path / "sweep", {"agent.lr.q": 1e-4}, {"agent.lr.q": 1e-3}
    # two seeds evaluated at different episode counts; seed 0 evaluated twice at 20 episodes (the final eval counts);
    # seed 1 ran under a wall-clock budget instead of an episode budget: the same experiment, so the same line
    write_run(sweep / "0", task=stack, objects=3, agent="ldm", seed=0, points=[(0, 0.0), (10, 0.5), (20, 0.3), (20, 1.0)],
              config=base)
    write_run(sweep / "1", task=stack, objects=3, agent="ldm", seed=1, points=[(0, 0.2), (15, 0.5), (30, 0.8)],
              config={**base, "schedule.total_episodes": 100000, "schedule.max_wall_clock_s": 6600, "logger.backend": "csv"})
    write_run(sweep / "2", task=stack, objects=3, agent="ldm", seed=0, points=[(0, 0.0), (40, 0.1)], config=other_lr)
    write_run(tmp_path / "other" / "run", task=bottles, objects=4, agent="fcdqn", seed=3, points=[(0, 0.0), (50, 0.25)],
              config={"agent.lr.q": 5e-4})
    out = tmp_path / "fig" / "curves.png"
    out.parent.mkdir()
    plot_learning_curves.main([str(sweep), str(tmp_path / "other" / "run"), "--out", str(out)])
    assert out.stat().st_size > 10_000 and "written to" in capsys.readouterr().out
    rows = read_csv(out.with_suffix(".csv"))
    assert {r["label"] for r in rows} == {"LDM (agent.lr.q=0.0001)", "LDM (agent.lr.q=0.001)", "FC-DQN"}
    ldm = [r for r in rows if r["label"] == "LDM (agent.lr.q=0.0001)"]
    # the common range ends at the shorter seed's last evaluation (20); seed 1 interpolated at 10 and 20 (0.4, 0.6)
    assert [float(r["episodes"]) for r in ldm] == [0, 10, 15, 20]
    assert [float(r["mean"]) for r in ldm] == pytest.approx([0.1, 0.45, 0.625, 0.8])
    assert [float(r["se"]) for r in ldm] == pytest.approx([0.1, 0.05, 0.125, 0.2])  # |a - b| / 2 for two seeds
    assert {r["n_seeds"] for r in ldm} == {"2"} and {r["task"] for r in ldm} == {stack}
    variant = [r for r in rows if r["label"] == "LDM (agent.lr.q=0.001)"]  # the agent's other config: its own line
    assert len(variant) == 2 and {r["n_seeds"] for r in variant} == {"1"} and math.isnan(float(variant[0]["se"]))
    single = [r for r in rows if r["task"] == bottles]
    assert [(r["label"], r["num_objects"], float(r["mean"])) for r in single] == [("FC-DQN", "4", 0.0), ("FC-DQN", "4", 0.25)]
    assert plot_learning_curves.panel_title(bottles, 4) == "Bottle arrangement (4 bottles)"


def test_bad_inputs_are_one_clear_error(tmp_path, capsys):
    write_run(tmp_path / "a", task="ldm_rl/BlockStacking-v0", objects=3, agent="rs", seed=0, points=[(0, 0.0)])
    write_run(tmp_path / "b", task="ldm_rl/BlockStacking-v0", objects=3, agent="rs", seed=0, points=[(0, 1.0)])
    with pytest.raises(SystemExit) as stop:
        plot_learning_curves.main([str(tmp_path)])
    assert stop.value.code == 2 and "RS: the same seed twice" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit):
        plot_learning_curves.main([str(tmp_path / "empty")])
    assert capsys.readouterr().err.startswith("error: no curve.csv found under")
    with pytest.raises(SystemExit):
        generalization_table.main([str(tmp_path / "missing")])
    assert "missing: no such file or folder" in capsys.readouterr().err


# ----------------------------------------------------------------------------- a real tiny multirun


@pytest.fixture(scope="module")
def smoke_sweep(tmp_path_factory):
    """recipes/train_policy.py -m experiment=smoke agent=ldm,fcdqn seed=0,1 (4-primitive episodes to stay fast)."""
    sweep = tmp_path_factory.mktemp("sweep")
    command = [sys.executable, str(ROOT / "recipes" / "train_policy.py"), "-m", "experiment=smoke", "agent=ldm,fcdqn",
               "seed=0,1", "env.max_steps=4", f"hydra.sweep.dir={sweep}"]
    done = subprocess.run(command, capture_output=True, text=True, env=ENV, cwd=sweep, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    return sweep


@pytest.mark.slow
def test_plot_learning_curves_aggregates_a_real_multirun(smoke_sweep, tmp_path):
    done = subprocess.run([sys.executable, "-m", "ldm_rl.reports.plot_learning_curves", str(smoke_sweep)],
                          capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=300)
    assert done.returncode == 0, done.stderr
    assert (smoke_sweep / "learning_curves.png").stat().st_size > 10_000
    rows = read_csv(smoke_sweep / "learning_curves.csv")
    assert {r["agent"] for r in rows} == {"ldm", "fcdqn"} and {r["n_seeds"] for r in rows} == {"2"}
    for agent in ("ldm", "fcdqn"):
        runs = [plot_learning_curves.read_run(folder) for folder in sorted(p.parent for p in smoke_sweep.rglob("curve.csv"))]
        seeds = [run for run in runs if run.agent == agent]
        assert sorted(run.seed for run in seeds) == [0, 1]
        first = [r for r in rows if r["agent"] == agent][0]  # before training: both seeds evaluated at 0 episodes
        assert float(first["episodes"]) == 0
        assert float(first["mean"]) == pytest.approx(sum(run.success[0] for run in seeds) / 2)
        assert float(first["se"]) == pytest.approx(abs(seeds[0].success[0] - seeds[1].success[0]) / 2)
    assert "Block stacking (3 blocks), LDM: 2 seed(s)" in done.stdout


@pytest.mark.slow
def test_generalization_table_evaluates_a_smoke_checkpoint_beside_the_paper(smoke_sweep, tmp_path, capfd):
    checkpoint = next(p for p in sorted(smoke_sweep.rglob("checkpoint.pt"))
                      if generalization_table.checkpoint_info(p)["agent"] == "ldm")
    out = tmp_path / "table"
    text = generalization_table.main([str(checkpoint), "--episodes", "2", "--out", str(out)])
    assert "evaluating ldm" in capfd.readouterr().out
    assert (out / "generalization.md").read_text() == text
    header = next(line for line in text.splitlines() if line.startswith("| agent | 4 blocks"))
    assert header == "| agent | 4 blocks | paper | 5 blocks | paper | 5 bottles | paper | 6 bottles | paper |"
    ldm = next(line for line in text.splitlines() if line.startswith("| LDM |")).split(" | ")
    assert ldm[2] == "99" and ldm[4] == "84" and ldm[6] == "86" and ldm[8].rstrip(" |") == "65"
    assert re.fullmatch(r"\d+\.\d \[\d+\.\d–\d+\.\d\] \(k=1, n=2\)", ldm[1]) and ldm[5] == "–"
    fcdqn = next(line for line in text.splitlines() if line.startswith("| FC-DQN |")).split(" | ")
    assert (fcdqn[2], fcdqn[4], fcdqn[6], fcdqn[8].rstrip(" |")) == ("98", "89", "82", "48")
    rs = next(line for line in text.splitlines() if line.startswith("| RS |")).split(" | ")
    assert (rs[2], rs[4], rs[6], rs[8].rstrip(" |")) == ("48", "23", "8", "4")
    written = sorted(out.rglob("evaluation.json"))
    results = [json.loads(p.read_text()) for p in written]
    assert [(r["num_objects"], r["trained_on"], r["episodes"]) for r in results] == [(4, 3, 2), (5, 3, 2)]
    # a second call reads what is written instead of evaluating again
    stamps = [p.stat().st_mtime_ns for p in written]
    assert generalization_table.main([str(checkpoint), "--episodes", "2", "--out", str(out)]) == text
    assert "evaluating" not in capfd.readouterr().out and [p.stat().st_mtime_ns for p in written] == stamps


plot_sample_efficiency = script("plot_sample_efficiency")


def _dynamics_run(folder: Path, task: str, model: str, seed: int, place: list[float], overall: list[float]) -> None:
    folder.mkdir(parents=True)
    (folder / "final_metrics.json").write_text(json.dumps({"task": task, "model": model, "seed": seed}))
    with open(folder / "curve.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["iteration", "sr", "sr_place", "floor_sr", "floor_sr_place"])
        for k, (p, o) in enumerate(zip(place, overall)):
            writer.writerow([250 * (k + 1), o, p, 0.45, 0.0])


def test_sample_efficiency_figure_is_mean_and_standard_error_over_seeds_of_one_task(tmp_path):
    _dynamics_run(tmp_path / "a", "bin_packing", "LDM(64)", 0, [0.1, 0.3], [0.5, 0.6])
    _dynamics_run(tmp_path / "b", "bin_packing", "LDM(64)", 1, [0.3, 0.5, 0.7], [0.6, 0.7, 0.8])  # evaluated once more
    _dynamics_run(tmp_path / "c", "bin_packing", "Naive", 0, [0.0, 0.0], [0.45, 0.46])
    _dynamics_run(tmp_path / "d", "block_stacking", "LDM(64)", 0, [0.9, 0.9], [0.9, 0.9])  # another task: ignored
    out = plot_sample_efficiency.main([str(tmp_path), "--task", "bin_packing", "--out", str(tmp_path / "fig.png")])
    assert out.stat().st_size > 10_000
    rows = list(csv.DictReader(open(tmp_path / "fig.csv")))
    ldm_place = [r for r in rows if r["model"] == "LDM(64)" and r["metric"] == "sr_place"]
    assert [int(r["iteration"]) for r in ldm_place] == [250, 500]  # only where both seeds evaluated
    assert float(ldm_place[1]["mean"]) == pytest.approx(0.4) and float(ldm_place[1]["se"]) == pytest.approx(0.1)
    assert all(r["n_seeds"] == "2" for r in ldm_place)
    naive = [r for r in rows if r["model"] == "Naive" and r["metric"] == "sr"]
    assert float(naive[0]["se"]) == 0.0 and float(naive[1]["mean"]) == pytest.approx(0.46)
    with pytest.raises(SystemExit, match="no run of task 'house_building'"):
        plot_sample_efficiency.main([str(tmp_path), "--task", "house_building"])


def test_the_documented_comparison_is_what_the_script_rebuilds_from_the_kept_runs(tmp_path):
    """docs/results/policy/comparison.md and its table in docs/policy.md come from the kept curve and
    final-metrics files alone (a results folder: no run folders, no configs)."""
    results = ROOT / "docs" / "results" / "policy"
    table = tmp_path / "comparison.md"
    plot_learning_curves.main([str(results), "--out", str(tmp_path / "curves.png"), "--table", str(table)])
    rebuilt = table.read_text()
    assert rebuilt == (results / "comparison.md").read_text()
    rows = [line for line in rebuilt.splitlines() if line.startswith("| ")]
    assert len(rows) > 2 and all(row in (ROOT / "docs" / "policy.md").read_text() for row in rows)


def test_the_documented_comparison_of_today_is_what_its_documented_command_rebuilds(tmp_path):
    """The headline table of docs/policy.md ("The comparison today") is what its documented --only command writes
    from the kept runs, and names one line per agent and task."""
    import shlex

    doc = (ROOT / "docs" / "policy.md").read_text()
    command = re.search(r"python -m ldm_rl.reports.plot_learning_curves docs/results/policy --out "
                        r"docs/img/comparison_today.png.*?\n```", doc, re.S).group(0)[: -len("```")]
    argv = shlex.split(command.replace("\\\n", " "))[3:]
    only = argv[argv.index("--only") + 1:]
    argv = [str(ROOT / a) if a == "docs/results/policy" else a for a in argv]
    argv[argv.index("--out") + 1] = str(tmp_path / "today.png")
    argv[argv.index("--table") + 1] = str(tmp_path / "today.md")
    plot_learning_curves.main(argv)
    rebuilt = (tmp_path / "today.md").read_text()
    assert rebuilt == (ROOT / "docs" / "results" / "policy" / "comparison_today.md").read_text()
    rows = [line.split(" | ") for line in rebuilt.splitlines()[2:]]
    assert all(" | ".join(row) in doc for row in rows) and len(rows) >= len(set(only))
    pairs = [(row[0], row[1].split(" [")[0]) for row in rows]
    assert len(pairs) == len(set(pairs))  # one line per agent and task


def test_only_keeps_the_named_lines_and_refuses_a_name_that_is_no_line(tmp_path, capsys):
    def keep(stem, agent, task, seed):
        with open(tmp_path / f"{stem}_curve.csv", "w", newline="") as f:
            f.write("updates,episodes,success_rate\n0,0,0.0\n10,20,0.5\n")
        (tmp_path / f"{stem}_final_metrics.json").write_text(json.dumps(
            {"task": task, "num_objects": 3, "agent": agent, "seed": seed, "episodes": 20, "success_rate": 0.5}))

    keep("curves_block_stacking_ldm_seed0_new", "ldm", "ldm_rl/BlockStacking-v0", 0)
    keep("curves_block_stacking_ldm_seed0_old", "ldm", "ldm_rl/BlockStacking-v0", 0)
    keep("curves_block_stacking_fcdqn_seed0_old", "fcdqn", "ldm_rl/BlockStacking-v0", 0)
    keep("curves_house_building_ldm_seed0_old", "ldm", "ldm_rl/HouseBuilding-v0", 0)
    table = tmp_path / "t.md"
    rows = plot_learning_curves.main([str(tmp_path), "--out", str(tmp_path / "c.png"), "--table", str(table),
                                      "--only", "LDM [new]", "FC-DQN [old]"])
    assert {(r["task"], r["label"]) for r in rows} == {("ldm_rl/BlockStacking-v0", "LDM [new]"),
                                                       ("ldm_rl/BlockStacking-v0", "FC-DQN [old]")}
    assert [line.split(" | ")[1] for line in table.read_text().splitlines()[2:]] == ["LDM [new]", "FC-DQN [old]"]
    with pytest.raises(SystemExit) as stop:
        plot_learning_curves.main([str(tmp_path), "--out", str(tmp_path / "c.png"), "--only", "LDM [nwe]"])
    assert stop.value.code == 2 and "--only 'LDM [nwe]': no such line" in capsys.readouterr().err
    keep("curves_house_building_ldm_seed0_new", "ldm", "ldm_rl/HouseBuilding-v0", 0)
    rows = plot_learning_curves.main([str(tmp_path), "--out", str(tmp_path / "c.png"),
                                      "--only", "Block stacking: LDM [old]", "House building: LDM [new]"])
    assert {(r["task"], r["label"]) for r in rows} == {("ldm_rl/BlockStacking-v0", "LDM [old]"),
                                                       ("ldm_rl/HouseBuilding-v0", "LDM [new]")}
    with pytest.raises(SystemExit) as stop:  # a line qualified by a task that does not have it
        plot_learning_curves.main([str(tmp_path), "--out", str(tmp_path / "c.png"), "--only", "Bin packing: LDM [old]"])
    assert stop.value.code == 2 and "--only 'Bin packing: LDM [old]': no such line" in capsys.readouterr().err


def test_a_crowded_panel_keeps_its_lines_apart_and_its_legend_off_the_curves(tmp_path):
    import matplotlib.pyplot as plt

    def keep(stem, agent, task):
        with open(tmp_path / f"{stem}_curve.csv", "w", newline="") as f:
            f.write("updates,episodes,success_rate\n0,0,0.0\n10,20,0.5\n")
        (tmp_path / f"{stem}_final_metrics.json").write_text(json.dumps(
            {"task": task, "num_objects": 3, "agent": agent, "seed": 0, "episodes": 20, "success_rate": 0.5}))

    stacking, house = "ldm_rl/BlockStacking-v0", "ldm_rl/HouseBuilding-v0"
    for k in range(20):  # more variants of one agent than any fixed palette of ten
        keep(f"curves_block_stacking_ldm_seed0_v{k:02d}", "ldm", stacking)
    keep("curves_block_stacking_fcdqn_seed0_a", "fcdqn", stacking)
    keep("curves_house_building_ldm_seed0_v03", "ldm", house)  # a label met before, in another panel
    keep("curves_house_building_ldm_seed0_v05", "ldm", house)
    fig, _ = plot_learning_curves.draw(plot_learning_curves.group(
        [plot_learning_curves.read_result(c) for c in sorted(tmp_path.glob("*_curve.csv"))]))
    fig.canvas.draw()
    crowded, other = fig.axes[0], fig.axes[1]
    colours = [(tuple(plt.matplotlib.colors.to_rgba(line.get_color())), line.get_linestyle())
               for line in crowded.get_lines()]
    assert len(colours) == 21 and len(set(colours[:16])) == 16  # the palette's 16 colours, none repeated
    assert crowded.get_lines()[-1].get_linestyle() == "--"  # FC-DQN dashed beside the LDM's solid lines
    legend_left = crowded.get_legend().get_window_extent().x0
    assert legend_left > crowded.get_window_extent().x1  # beside the panel, not over its curves
    by_label = {line.get_label().split(",")[0]: line.get_color() for line in crowded.get_lines()}
    assert other.get_lines()[0].get_color() == by_label["LDM [v03]"]  # a label keeps its colour across panels
    plt.close(fig)


def test_a_results_folder_names_its_lines_by_tag_and_reads_the_final_weights(tmp_path):
    def keep(stem, seed, points, final):
        with open(tmp_path / f"{stem}_curve.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["updates", "episodes", "success_rate"])
            writer.writerows([10 * i, e, s] for i, (e, s) in enumerate(points))
        (tmp_path / f"{stem}_final_metrics.json").write_text(json.dumps(
            {"task": "ldm_rl/BlockStacking-v0", "num_objects": 3, "agent": "ldm", "seed": seed, "episodes": points[-1][0],
             "success_rate": final}))

    keep("curves_block_stacking_ldm_seed0_mix23", 0, [(0, 0.0), (10, 0.6), (20, 0.9), (20, 0.9)], 0.9)
    keep("curves_block_stacking_ldm_seed1_mix23", 1, [(0, 0.0), (10, 0.2), (20, 0.7), (20, 0.7)], 0.7)
    keep("curves_block_stacking_ldm_seed0_first", 0, [(0, 0.0), (20, 0.1)], 0.1)
    (tmp_path / "curves_block_stacking_ldm_seed2_mix23_curve.csv").write_text("episodes,success_rate\n0,0.0\n")  # unfinished
    table = tmp_path / "t.md"
    plot_learning_curves.main([str(tmp_path), "--out", str(tmp_path / "c.png"), "--table", str(table)])
    rows = {line.split(" | ")[1]: line.split(" | ") for line in table.read_text().splitlines()[2:]}
    assert set(rows) == {"LDM [mix23]", "LDM [first]"}
    # mean curve 0, 0.4, 0.8: 0.5 first reached at 20 episodes; final weights 0.8 ± 0.1 (two seeds)
    assert rows["LDM [mix23]"][2:] == ["0, 1", "20", "20", "0.80 ± 0.10", "20", "0.94 |"]
    assert rows["LDM [first]"][3:5] == ["never", "never"]


def test_the_documented_zero_shot_table_is_what_the_script_rebuilds_from_the_kept_results(tmp_path):
    """docs/results/policy/generalization.md and its pooled rows in docs/policy.md come from the kept
    curves_..._generalization.json files alone (no checkpoint is needed or evaluated)."""
    results = ROOT / "docs" / "results" / "policy"
    text = generalization_table.main([str(results), "--agents", "ldm,fcdqn,rs,dynaq", "--out", str(tmp_path)])
    assert text == (results / "generalization.md").read_text()
    pooled = [line for line in text.split("Per checkpoint:")[0].splitlines() if line.startswith("| ") and "[" in line[:20]]
    assert len(pooled) >= 4 and all(row in (ROOT / "docs" / "policy.md").read_text() for row in pooled)


def test_kept_zero_shot_results_are_rows_of_their_tag_and_bad_ones_one_error(tmp_path):
    def entry(n, successes, checkpoint):
        return {"checkpoint": checkpoint, "task": "ldm_rl/BlockStacking-v0", "num_objects": n, "trained_on": 3,
                "agent": "ldm", "episodes": 100, "successes": successes, "mean_length": 8.0}

    for seed, (four, five) in enumerate([(60, 30), (80, 50)]):
        (tmp_path / f"curves_block_stacking_ldm_seed{seed}_mix23_generalization.json").write_text(json.dumps(
            {"final_n4": entry(4, four, f"s{seed}/checkpoint.pt"), "final_n5": entry(5, five, f"s{seed}/checkpoint.pt")}))
    (tmp_path / "curves_block_stacking_ldm_seed0_first_generalization.json").write_text(json.dumps(
        {"final_n4": entry(4, 10, "old/checkpoint.pt")}))
    text = generalization_table.main([str(tmp_path), "--out", str(tmp_path / "out")])
    rows = {line.split(" | ")[0][2:]: line.split(" | ") for line in text.split("Per checkpoint:")[0].splitlines()
            if line.startswith("| LDM")}
    assert set(rows) == {"LDM [first]", "LDM [mix23]"}
    assert rows["LDM [mix23]"][1] == "70.0 [63.3–75.9] (k=2, n=200)" and rows["LDM [mix23]"][3].startswith("40.0 ")
    assert rows["LDM [first]"][1].startswith("10.0 ") and rows["LDM [first]"][3] == "–"
    (tmp_path / "curves_block_stacking_ldm_seed0_first_generalization.json").write_text(json.dumps({"best": {}}))
    with pytest.raises(SystemExit):
        generalization_table.main([str(tmp_path), "--out", str(tmp_path / "out")])
