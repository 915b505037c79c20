"""ldm_rl.plots: every figure is written from small tensors and says what it shows (titles, labels,
colour bars, legends); recipes/evaluate.py draws decisions and a GIF of a smoke checkpoint's episodes."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from dyn_helpers import MAX_HEIGHT, block_scenes, tiny_model, transitions
from ldm_rl import plots
from test_policy_recipe import run, smoke_run  # noqa: F401  (the module-scoped smoke checkpoint)


def texts(fig) -> dict[str, list[str]]:
    """Titles, axis labels and legend entries of every axes of ``fig`` (colour bars included)."""
    out: dict[str, list[str]] = {"title": [], "xlabel": [], "ylabel": [], "legend": []}
    for ax in fig.axes:
        out["title"].append(ax.get_title())
        out["xlabel"].append(ax.get_xlabel())
        out["ylabel"].append(ax.get_ylabel())
        if ax.get_legend() is not None:
            out["legend"] += [t.get_text() for t in ax.get_legend().get_texts()]
    return out


def is_png(path) -> bool:
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_prediction_grid_names_columns_rows_and_puts_error_on_its_own_scale(tmp_path):
    before = block_scenes(2)
    true = before.clone()
    true[:, :, 40:52, 40:52] = 0.08
    predicted = true.clone()
    predicted[1, :, 40:52, 40:52] = 0.0  # row 2 misses the block: 80 mm error
    predicted[0, :, 0, 0] = 0.003  # row 1 is off by 3 mm in one pixel
    actions = torch.tensor([[10, 20, 2], [46, 46, 4]])
    fig = plots.plot_prediction_grid(before, predicted, true, actions, tmp_path / "grid.png", max_height=MAX_HEIGHT,
                                     is_pick=torch.tensor([True, False]), correct=torch.tensor([True, False]), dpi=40)
    assert is_png(tmp_path / "grid.png")
    t = texts(fig)
    assert t["title"][:4] == ["before", "predicted next", "true next", "|predicted − true|"]
    first, second = fig.axes[0].get_ylabel(), fig.axes[4].get_ylabel()
    assert first.splitlines() == ["pick", "(r 10, c 20, 45°)", "right"]
    assert second.splitlines() == ["place", "(r 46, c 46, 90°)", "wrong"]
    assert fig.axes[0].yaxis.label.get_color() != fig.axes[4].yaxis.label.get_color()
    assert "height above the table (m)" in t["ylabel"] and "|error| (mm)" in t["ylabel"]
    heights, error = fig.axes[0].images[0], fig.axes[3].images[0]
    assert heights.get_cmap().name == "viridis" and heights.norm.vmax == pytest.approx(MAX_HEIGHT)
    assert error.get_cmap().name != heights.get_cmap().name
    assert error.norm.vmax == pytest.approx(80.0, abs=0.01)  # millimetres, its own scale
    assert fig.axes[3].images[0].get_array()[0, 0] == pytest.approx(3.0, abs=1e-3)


def test_a_single_block_stands_out_from_the_table_on_every_task_scale():
    """One 2.5 cm block on the tallest scale (block stacking, 0.25 m): its colour is far from the empty table's
    (a linear scale put it at 0.1 of viridis, dark blue on dark purple)."""
    import numpy as np
    from matplotlib import colormaps

    norm = plots._height_norm(0.25)
    table, block = (np.array(colormaps[plots.HEIGHT_CMAP](float(norm(h)))[:3]) for h in (0.0, 0.025))
    assert float(norm(0.025)) > 0.3 and np.abs(block - table).sum() > 0.5
    assert float(norm(0.25)) == pytest.approx(1.0) and float(norm(0.0)) == pytest.approx(0.0)


def test_prediction_grid_rejects_mismatched_inputs(tmp_path):
    scenes = block_scenes(2)
    with pytest.raises(ValueError, match=r"before, predicted and true must share one \[N>=1, H, W\] shape"):
        plots.plot_prediction_grid(scenes, scenes[:1], scenes, torch.zeros(2, 3, dtype=torch.long), tmp_path / "g.png",
                                   max_height=MAX_HEIGHT)
    with pytest.raises(ValueError, match=r"actions must be \[2, 3\]"):
        plots.plot_prediction_grid(scenes, scenes, scenes, torch.zeros(3, 3, dtype=torch.long), tmp_path / "g.png",
                                   max_height=MAX_HEIGHT)
    with pytest.raises(ValueError, match="must end in .png"):
        plots.plot_prediction_grid(scenes, scenes, scenes, torch.zeros(2, 3, dtype=torch.long), tmp_path / "g.jpg",
                                   max_height=MAX_HEIGHT)


def test_training_prediction_grid_labels_rows_by_the_metric(tmp_path):
    from ldm_rl.world_model.metrics import MetricSettings, transition_metrics
    from ldm_rl.world_model.training import prediction_grid

    model, data = tiny_model(), transitions(4)
    prediction_grid(model, data, tmp_path / "predictions.png", num_samples=3)
    assert is_png(tmp_path / "predictions.png")
    # the same labels straight from the plotting function, with the metric's verdicts
    pred = model.predict(data["heightmap"][:3], data["in_hand"][:3], data["holding"][:3], data["action"][:3])
    verdict = transition_metrics(pred.heightmap, pred.holding, data[:3], MetricSettings(max_height=MAX_HEIGHT))
    fig = plots.plot_prediction_grid(data["heightmap"][:3], pred.heightmap, data["next", "heightmap"][:3],
                                     data["action"][:3], tmp_path / "again.png", max_height=MAX_HEIGHT,
                                     is_pick=verdict["is_pick"], correct=verdict["correct"], dpi=40)
    labels = [fig.axes[4 * i].get_ylabel().splitlines() for i in range(3)]
    assert [lab[0] for lab in labels] == ["pick", "place", "pick"]
    assert [lab[-1] for lab in labels] == ["right" if c else "wrong" for c in verdict["correct"].tolist()]


def test_success_rate_plot_has_title_units_legend_floors_and_a_visible_zero_line(tmp_path):
    rows = [{"iteration": i, "sr": 0.1 * k, "sr_pick": 0.9, "sr_place": 0.0, "floor_sr": 0.45, "floor_sr_pick": 0.9,
             "floor_sr_place": 0.0} for k, i in enumerate((50, 100, 150))]
    fig = plots.plot_success_rate(rows, tmp_path / "sr.png")
    assert is_png(tmp_path / "sr.png")
    (ax,) = fig.axes
    assert ax.get_title() and "iteration" in ax.get_xlabel() and "(%)" in ax.get_ylabel()
    assert texts(fig)["legend"] == ["all transitions", "picks", "places", "floor (trivial predictor)"]
    assert ax.get_ylim()[0] < 0 < ax.get_ylim()[1]
    horizontal = [tuple(line.get_ydata()) for line in ax.get_lines() if len(set(line.get_ydata())) == 1]
    assert (0.0, 0.0) in horizontal and (45.0, 45.0) in horizontal  # the 0 % line and the overall floor, in %
    assert list(ax.get_lines()[0].get_ydata()) == pytest.approx([0.0, 10.0, 20.0])
    with pytest.raises(ValueError, match="rows is empty"):
        plots.plot_success_rate([], tmp_path / "none.png")


def test_expert_strip_labels_every_frame_and_names_the_task(tmp_path):
    frames = block_scenes(5)
    actions = torch.tensor([[20, 30, 0], [60, 60, 2], [25, 90, 4], [60, 60, 6]])
    fig = plots.plot_expert_strip(frames, actions, tmp_path / "strip.png", max_height=MAX_HEIGHT,
                                  is_pick=[True, False, True, False], title="BlockStacking (3 objects): the expert", dpi=40)
    assert is_png(tmp_path / "strip.png")
    t = texts(fig)
    assert t["title"][:5] == ["step 1: pick", "step 2: place", "step 3: pick", "step 4: place", "final state"]
    assert t["xlabel"][1] == "(r 60, c 60, 45°)"
    assert "height above the table (m)" in t["ylabel"]
    assert fig.get_suptitle() == "BlockStacking (3 objects): the expert"
    many = plots.plot_expert_strip(block_scenes(9), torch.zeros(8, 3, dtype=torch.long), tmp_path / "long.png",
                                   max_height=MAX_HEIGHT, max_columns=4, dpi=30)
    grid = [ax for ax in many.axes if ax.images]
    assert len(grid) == 9 and len({round(ax.get_position().y0, 3) for ax in grid}) == 3  # wrapped into 3 rows


def test_learning_curve_has_two_panels_in_percent_with_the_interval(tmp_path):
    rows = [{"episodes": e, "wall_s": 60.0 * e, "success_rate": e / 10, "ci_low": max(0.0, e / 10 - 0.2),
             "ci_high": min(1.0, e / 10 + 0.2), "eval_episodes": 10} for e in (0, 5, 10)]
    fig = plots.plot_learning_curve(rows, tmp_path / "learning_curve.png", title="ldm agent, seed 0")
    assert is_png(tmp_path / "learning_curve.png")
    t = texts(fig)
    assert t["xlabel"] == ["training episodes", "wall-clock time (min)"]
    assert t["ylabel"][0] == "success rate (%)"
    assert t["legend"] == ["95 % Wilson interval", "greedy success rate (10 episodes per point)"]
    assert fig.get_suptitle() == "ldm agent, seed 0"
    episodes, minutes = fig.axes
    assert list(episodes.get_lines()[0].get_xdata()) == [0, 5, 10]
    rows[-1]["eval_episodes"] = 100  # the final evaluation plays more episodes than the periodic ones
    mixed = plots.plot_learning_curve(rows, tmp_path / "mixed.png", title="ldm agent, seed 0")
    assert texts(mixed)["legend"][1] == "greedy success rate (10 or 100 episodes per point)"
    assert list(minutes.get_lines()[0].get_xdata()) == pytest.approx([0.0, 5.0, 10.0])
    assert list(episodes.get_lines()[0].get_ydata()) == pytest.approx([0.0, 50.0, 100.0])
    assert episodes.get_ylim()[0] < 0


def test_decision_shows_q_map_candidates_values_and_the_chosen_action(tmp_path):
    heightmap = block_scenes(1)[0]
    q_map = torch.zeros(8, 128, 128)
    q_map[3, 50, 60] = 2.0
    candidates = torch.tensor([[50, 60, 3], [20, 20, 0], [100, 30, 6]])
    values = torch.tensor([0.2, 0.7, -0.1])
    fig = plots.plot_decision(heightmap, q_map, candidates, values, candidates[0], tmp_path / "d.png",
                              max_height=MAX_HEIGHT, is_pick=True, title="ldm agent, episode 1, step 1/6", dpi=40)
    assert is_png(tmp_path / "d.png")
    t = texts(fig)
    assert t["title"][:3] == ["heightmap", "Q map (max over rotations)", "the 3 candidates' values"]
    assert fig.get_suptitle() == "ldm agent, episode 1, step 1/6: pick at (r 50, c 60, 67.5°)"
    assert "height above the table (m)" in t["ylabel"] and any(label.startswith("Q of the pick") for label in t["ylabel"])
    assert t["xlabel"][:3] == ["column (y), px", "column (y), px", "candidate (rank by value)"]
    legend = [entry.get_text() for entry in fig.legends[0].get_texts()]
    assert legend == ["candidate (number = rank by value)", "chosen action"] and t["legend"] == ["candidate", "chosen"]
    assert fig.axes[1].images[0].get_array().max() == pytest.approx(2.0)  # max over rotations
    others, chosen = fig.axes[2].collections
    assert list(fig.axes[2].get_lines()[0].get_ydata()) == pytest.approx([0.7, 0.2, -0.1])  # ranked by value
    assert others.get_offsets().flatten().tolist() == pytest.approx([1, 0.7, 3, -0.1])
    assert chosen.get_offsets().flatten().tolist() == pytest.approx([2, 0.2])  # the chosen one (rank 2) in red
    assert tuple(chosen.get_facecolor()[0]) == pytest.approx((1.0, 0.0, 0.0, 1.0))
    numbers = [c.get_text() for c in fig.axes[0].texts]
    assert numbers == ["1", "2", "3"]
    # agents without a Q network (RS) or without candidates (FC-DQN)
    no_q = plots.plot_decision(heightmap, None, candidates, values, candidates[1], tmp_path / "rs.png", dpi=30)
    assert [ax.get_title() for ax in no_q.axes if ax.get_title()] == ["heightmap", "the 3 candidates' values"]
    no_candidates = plots.plot_decision(heightmap, q_map, None, None, candidates[0], tmp_path / "fcdqn.png", dpi=30)
    assert [ax.get_title() for ax in no_candidates.axes if ax.get_title()] == ["heightmap", "Q map (max over rotations)"]
    with pytest.raises(ValueError, match=r"values must hold one value per candidate \(3\), got 2"):
        plots.plot_decision(heightmap, q_map, candidates, values[:2], candidates[0], tmp_path / "bad.png")


def test_episodes_gif_has_one_frame_per_step_with_prediction_beside_the_real_next(tmp_path):
    scenes = block_scenes(4)
    steps = [{"episode": 0, "step": t, "num_steps": 3, "heightmap": scenes[t, 0], "next_heightmap": scenes[t + 1, 0],
              "predicted_heightmap": scenes[t + 1, 0] + 0.001, "action": torch.tensor([40, 40, t]), "is_pick": t % 2 == 0,
              "reward": float(t == 2), **({"outcome": "success"} if t == 2 else {})} for t in range(3)]
    fig = plots.plot_episodes_gif(steps, tmp_path / "episodes.gif", max_height=MAX_HEIGHT, fps=2.0, title="ldm agent", dpi=40)
    with Image.open(tmp_path / "episodes.gif") as gif:
        assert gif.format == "GIF" and gif.n_frames == 3 and gif.info["duration"] == 500
    titles = [ax.get_title().splitlines()[0] for ax in fig.axes if ax.images]
    assert titles == ["before (the chosen action)", "predicted next (world model)", "real next"]
    assert fig.axes[1].get_title().splitlines()[1] == "largest |error| vs real: 1 mm"
    assert fig.get_suptitle() == "ldm agent · episode 1 · step 3/3 · pick at (r 40, c 40, 45°) · reward 1 · success"
    for row in steps:
        del row["predicted_heightmap"]
    fig = plots.plot_episodes_gif(steps, tmp_path / "real_only.gif", max_height=MAX_HEIGHT, dpi=30)
    assert [ax.get_title() for ax in fig.axes if ax.images] == ["before (the chosen action)", "real next"]
    with pytest.raises(ValueError, match=r"steps\[0\] is missing \['action'\]"):
        plots.plot_episodes_gif([{"heightmap": scenes[0, 0], "next_heightmap": scenes[1, 0]}], tmp_path / "x.gif",
                                max_height=MAX_HEIGHT)


def test_missing_matplotlib_is_one_line_naming_the_extra(tmp_path, monkeypatch):
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ImportError
    with pytest.raises(plots.PlotDependencyError) as caught:
        plots.plot_success_rate([{"iteration": 1, "sr": 0.5, "sr_pick": 0.5, "sr_place": 0.5}], tmp_path / "sr.png")
    assert str(caught.value) == "matplotlib is not installed: pip install 'ldm_rl[plot]' to draw figures"
    assert isinstance(caught.value, ImportError) and not (tmp_path / "sr.png").exists()


def test_render_episodes_beyond_the_played_ones_is_one_clear_error(tmp_path):
    checkpoint = tmp_path / "checkpoint.pt"
    checkpoint.write_bytes(b"")
    proc = run("evaluate.py", f"checkpoint={checkpoint}", "episodes=2", "render.episodes=3", f"hydra.run.dir={tmp_path}",
               cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1] == ("error: render.episodes=3 exceeds episodes=2: only played episodes "
                                                    "can be drawn")


@pytest.mark.slow
def test_evaluate_draws_decisions_and_a_gif_of_the_first_episodes(smoke_run, tmp_path):  # noqa: F811
    out, _ = smoke_run
    proc = run("evaluate.py", f"checkpoint={out / 'checkpoint.pt'}", "episodes=2", "render.episodes=1", "render.fps=4",
               "progress=false", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads((tmp_path / "evaluation.json").read_text())
    decisions = result["pictures"]["decisions"]
    assert decisions and all((tmp_path / name).stat().st_size > 10_000 and is_png(tmp_path / name) for name in decisions)
    assert decisions[0] == "decisions/episode01_step01.png"
    assert sorted(p.name for p in (tmp_path / "decisions").iterdir()) == sorted(name.split("/")[1] for name in decisions)
    assert all(name.startswith("decisions/episode01_") for name in decisions)  # only the first episode is drawn
    with Image.open(tmp_path / result["pictures"]["gif"]) as gif:
        assert gif.n_frames == len(decisions) and gif.info["duration"] == 250


@pytest.mark.slow
def test_episode_steps_carry_the_planner_outputs_and_the_world_models_prediction(smoke_run):  # noqa: F811
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from ldm_rl.agents import load_agent
    from ldm_rl.envs import make_env_from_config
    from ldm_rl.evaluation import episode_steps, evaluate_policy

    out, _ = smoke_run
    agent, cfg = load_agent(out / "checkpoint.pt")
    env = make_env_from_config(dict(cfg["env"]))
    kept = []
    result = evaluate_policy(env, agent.policy, 2, seed=5, on_episode=lambda i, rollout: kept.append((i, rollout)))
    assert [i for i, _ in kept] == [0, 1] and sum(r.shape[0] for _, r in kept) == 2 * result.mean_length
    rollout = kept[1][1]
    rows = episode_steps(rollout, episode=1, dynamics=agent.policy.dynamics)
    n, k = rollout.shape[0], cfg["planner"]["num_candidates"]
    assert [r["step"] for r in rows] == list(range(n)) and all(r["episode"] == 1 and r["num_steps"] == n for r in rows)
    assert rows[-1]["outcome"] in ("success", "failure") and all("outcome" not in r for r in rows[:-1])
    first = rows[0]
    assert first["is_pick"] and tuple(first["q_map"].shape) == (8, 128, 128)
    assert tuple(first["candidates"].shape) == (k, 3) and tuple(first["values"].shape) == (k,)
    assert torch.equal(first["action"], rollout["action"][0])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        expected = agent.policy.dynamics.predict(rollout["heightmap"][:1], rollout["in_hand"][:1], rollout["holding"][:1],
                                                 rollout["action"][:1]).heightmap[0, 0]
    assert torch.equal(first["predicted_heightmap"], expected)
    assert np.isfinite(first["reward"])


def test_render_expert_strip_writes_into_its_run_folder_not_the_repository(tmp_path):
    """The recipe's default output is the run folder; docs/img is written only when asked for."""
    import subprocess
    import sys
    from pathlib import Path

    pytest.importorskip("matplotlib")
    root = Path(__file__).resolve().parents[1]
    docs_img = sorted((root / "docs" / "img").iterdir())
    mtimes = [p.stat().st_mtime for p in docs_img]
    run = tmp_path / "run"
    result = subprocess.run([sys.executable, str(root / "recipes" / "render_expert_strip.py"), "env=block_stacking",
                             f"hydra.run.dir={run}", "demos.strip.scale=1"], cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]
    assert (run / "expert_BlockStacking.png").stat().st_size > 0
    assert sorted((root / "docs" / "img").iterdir()) == docs_img
    assert [p.stat().st_mtime for p in docs_img] == mtimes
