"""Draw the paper's learning-curve figure from ``recipes/train_policy.py`` runs.

    python -m ldm_rl.reports.plot_learning_curves multirun/<date>/<time> [more sweeps or run folders] [--out curves.png]

Reads every run below the given folders (a run folder holds ``curve.csv`` and Hydra's ``.hydra/config.yaml``):
one panel per task (env id and object count), one line per agent, the greedy success rate against training
episodes as the mean ± standard error over the agent's seeds. Each seed's curve
(one point per evaluation) is interpolated linearly onto the union of the seeds' episode counts, up to the
shortest seed's last evaluation, so every plotted point averages all seeds. Runs of one agent are seeds of one
line when their resolved configs agree on everything but the run's budget and bookkeeping (:data:`BUDGET_KEYS`:
seed, episode / wall-clock budget, checkpoints, progress, logger, threads, device), whichever preset or override
set it: a run stopped by a wall-clock budget joins the seeds of a preset with an episode budget. Runs of one agent
whose configs differ elsewhere (e.g. two sweeps with different ``agent.lr.q``) get separate lines, each labelled
with its values of the keys that differ.
Writes the figure (PNG) and a CSV of the plotted points (task, objects, agent, label, episodes, mean, se,
n_seeds); default ``<first folder>/learning_curves.png`` and ``.csv``; ``--table T.md`` also writes the
comparison table (one row per line: seeds, episodes to a mean success of 0.5 and 0.8, the final weights'
success on 100 held-out episodes, the paper's end value). ``--only LABEL ...`` keeps only the lines of those
labels (as the legend names them, e.g. ``"LDM [mix23ema]"``), in every panel that has them, or, prefixed by a task's
name, in that task's panels only (``"House building: LDM [gamma08]"``): a headline figure of the current presets
drawn from a results folder that also keeps their history.

A folder may also be a results folder (``docs/results/policy``): the finished runs kept there as
``curves_<task>_<agent>_seed<k>[_<tag>]_curve.csv`` beside their ``_final_metrics.json`` (which names the task,
object count, agent and seed); the tag, if any, names the line (``LDM [mix23]``), so the figure and the table
are rebuilt from the repository's files without the runs.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from ldm_rl.reports import kept_file
from ldm_rl.run.outputs import atomic_path

# panel order and names of the paper's tasks (env ids of conf/env/*.yaml)
TASKS = {
    "ldm_rl/BlockStacking-v0": ("Block stacking", "blocks"),
    "ldm_rl/HouseBuilding-v0": ("House building", "objects"),
    "ldm_rl/BottleArrangement-v0": ("Bottle arrangement", "bottles"),
    "ldm_rl/BinPacking-v0": ("Bin packing", "blocks"),
}
# line order, names and colours of the agents (conf/agent/*.yaml)
AGENTS = {"ldm": ("LDM", "C0"), "fcdqn": ("FC-DQN", "C1"), "rs": ("RS", "C2"), "dynaq": ("Dyna-Q", "C3")}
# one line style per agent, so that an agent's variants read apart from another agent's in a crowded panel
LINE_STYLES = {"ldm": "-", "fcdqn": "--", "rs": ":", "dynaq": "-."}
# a panel with more lines than this gets its legend beside it, outside the axes, where it hides no curve
LEGEND_INSIDE_MAX = 4
# config keys (or groups, by prefix) that set a run's seed, budget or bookkeeping: they tell the seeds of one
# experiment apart, or how long and where it ran, but not what it learns up to the shorter run's end
BUDGET_KEYS = ("seed", "resume", "schedule.total_episodes", "schedule.max_wall_clock_s", "schedule.checkpoint_every",
               "schedule.progress", "logger", "threads", "device", "hydra", "replay.scratch_dir")
CSV_FIELDS = ("task", "num_objects", "agent", "label", "episodes", "mean", "se", "n_seeds")
# the paper's end values (3 seeds, read from the authors' project page, ±0.03): success rate; bin packing its reward
PAPER_END = {
    "ldm_rl/BlockStacking-v0": {"ldm": 0.94, "fcdqn": 0.87, "dynaq": 0.72, "rs": 0.52},
    "ldm_rl/HouseBuilding-v0": {"ldm": 0.84, "fcdqn": 0.62, "dynaq": 0.24, "rs": 0.08},
    "ldm_rl/BottleArrangement-v0": {"ldm": 0.86, "fcdqn": 0.72, "dynaq": 0.39, "rs": 0.10},
    "ldm_rl/BinPacking-v0": {"ldm": 0.58, "fcdqn": 0.62, "dynaq": 0.11, "rs": 0.02},
}
# a finished run kept in a results folder: its curve; the final metrics beside it name what it is
RESULT_CURVE = kept_file("curve.csv")


@dataclass
class Run:
    """One training run: its task, agent, seed, config and evaluated curve (episodes, success rate)."""

    path: Path
    task: str
    num_objects: int
    agent: str
    seed: int
    config: dict[str, str]  # the resolved config as dotted key -> value text, without BUDGET_KEYS
    episodes: list[float] = field(default_factory=list)
    success: list[float] = field(default_factory=list)
    tag: str | None = None  # a results folder's run: the name of its line (None: lines from the configs)
    final: dict | None = None  # its final_metrics.json, when there is one


def _result_curves(folder: Path) -> list[Path]:
    """The finished runs' curves kept in a results folder (those with a ``_final_metrics.json`` beside them)."""
    return [p for p in sorted(folder.glob("curves_*_curve.csv"))
            if RESULT_CURVE.fullmatch(p.name) and _final_of(p).is_file()]


def _final_of(curve: Path) -> Path:
    return curve.with_name(curve.name[: -len("_curve.csv")] + "_final_metrics.json")


def _run_folders(paths: list[Path]) -> list[Path]:
    """Every folder holding a curve.csv at or below ``paths``, and every finished run's curve file of a results
    folder among ``paths``."""
    found: list[Path] = []
    for path in paths:
        if not path.is_dir():
            raise ValueError(f"{path}: not a folder (give a multirun sweep folder or run folders of train_policy.py)")
        found += [p.parent for p in sorted(path.rglob("curve.csv"))] + _result_curves(path)
    return sorted(set(found))


def _read_curve(path: Path, run: Run) -> Run:
    """``run`` with the (episodes, success rate) points of the curve CSV ``path``: one per episode count, the
    last evaluation at that count (e.g. the final 100-episode one)."""
    points: dict[float, float] = {}
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            points[float(row["episodes"])] = float(row["success_rate"])
    if not points:
        raise ValueError(f"{path}: no evaluation rows yet")
    run.episodes, run.success = zip(*sorted(points.items()))
    return run


def read_result(curve: Path) -> Run:
    """A finished run kept in a results folder (``curves_..._curve.csv`` and its ``_final_metrics.json``)."""
    final = json.loads(_final_of(curve).read_text())
    missing = [key for key in ("task", "num_objects", "agent", "seed") if key not in final]
    if missing:
        raise ValueError(f"{_final_of(curve)}: lacks {', '.join(missing)} (not a final_metrics.json of train_policy.py)")
    tag = RESULT_CURVE.fullmatch(curve.name).group("tag")
    run = Run(curve, str(final["task"]), int(final["num_objects"]), str(final["agent"]), int(final["seed"]), {},
              tag=tag or "", final=final)
    return _read_curve(curve, run)


def _flat(node, prefix: str = "") -> dict[str, str]:
    """A nested config (dicts, lists, scalars) -> {dotted key: value text}, without :data:`BUDGET_KEYS`."""
    if any(prefix == key or prefix.startswith(key + ".") for key in BUDGET_KEYS):
        return {}
    if isinstance(node, dict):
        out: dict[str, str] = {}
        for key, value in node.items():
            out.update(_flat(value, f"{prefix}.{key}" if prefix else str(key)))
        return out
    return {prefix: str(node)}


def read_run(folder: Path) -> Run:
    """A run folder of ``recipes/train_policy.py`` (its ``curve.csv`` and ``.hydra/config.yaml``) -> :class:`Run`
    (one curve point per episode count: the last evaluation at that count, e.g. the final 100-episode one)."""
    from omegaconf import OmegaConf

    if folder.is_file():
        return read_result(folder)
    config_file = folder / ".hydra" / "config.yaml"
    if not config_file.is_file():
        raise ValueError(f"{folder}: has curve.csv but no .hydra/config.yaml (not a run of recipes/train_policy.py)")
    cfg = OmegaConf.load(config_file)
    config = _flat(OmegaConf.to_container(cfg, resolve=False))
    run = Run(folder, str(cfg.env.id), int(cfg.env.num_objects), str(cfg.agent.name), int(cfg.seed), config)
    final = folder / "final_metrics.json"
    run.final = json.loads(final.read_text()) if final.is_file() else None
    return _read_curve(folder / "curve.csv", run)


def mean_curve(runs: list[Run]) -> list[tuple[float, float, float]]:
    """(episodes, mean, standard error) over the runs' seeds on their common episode range; se = sample std /
    sqrt(n), NaN for a single seed."""
    import numpy as np

    end = min(run.episodes[-1] for run in runs)
    grid = np.array(sorted({x for run in runs for x in run.episodes if x <= end}))
    values = np.stack([np.interp(grid, run.episodes, run.success) for run in runs])  # [seeds, points]
    n = len(runs)
    se = values.std(axis=0, ddof=1) / math.sqrt(n) if n > 1 else np.full(len(grid), math.nan)
    return [(float(x), float(m), float(e)) for x, m, e in zip(grid, values.mean(axis=0), se)]


def varying_keys(runs: list[Run]) -> list[str]:
    """Config keys whose values differ among ``runs`` (a key some runs lack, e.g. one added to the configs
    after an older run was made, is not compared)."""
    shared = set.intersection(*(set(run.config) for run in runs))
    return sorted(key for key in shared if len({run.config[key] for run in runs}) > 1)


def group(runs: list[Run]) -> dict[tuple[str, int], dict[str, list[Run]]]:
    """Panels (task, objects) -> line label -> runs (one per seed). An agent's runs form one line when their
    configs agree outside :data:`BUDGET_KEYS`; otherwise one line per configuration, labelled with its values of
    the keys that differ among that agent's runs."""
    panels: dict[tuple[str, int], list[Run]] = defaultdict(list)
    for run in runs:
        panels[(run.task, run.num_objects)].append(run)
    order = {task: i for i, task in enumerate(TASKS)}
    agent_order = {agent: i for i, agent in enumerate(AGENTS)}
    out: dict[tuple[str, int], dict[str, list[Run]]] = {}
    for key in sorted(panels, key=lambda k: (order.get(k[0], len(order)), k)):
        by_agent: dict[str, list[Run]] = defaultdict(list)
        for run in panels[key]:
            by_agent[run.agent].append(run)
        lines: dict[str, list[Run]] = {}
        for agent in sorted(by_agent, key=lambda a: (agent_order.get(a, len(agent_order)), a)):
            members = by_agent[agent]
            differ = varying_keys(members)
            name = AGENTS.get(agent, (agent,))[0]
            variants: dict[str, list[Run]] = defaultdict(list)
            for run in members:
                if run.tag is not None:  # a results folder's run: its file's tag names the line
                    variants[f"{name} [{run.tag}]" if run.tag else name].append(run)
                    continue
                values = ", ".join(f"{k}={run.config[k]}" for k in differ)
                variants[f"{name} ({values})" if values else name].append(run)
            for label in sorted(variants):
                line = sorted(variants[label], key=lambda r: r.seed)
                seeds = [r.seed for r in line]
                if len(set(seeds)) != len(seeds):
                    paths = ", ".join(str(r.path) for r in line)
                    raise ValueError(f"{TASKS.get(key[0], (key[0],))[0]}, {label}: the same seed twice ({paths}); give "
                                     "runs that differ in their seed, or in a setting that names a variant")
                lines[label] = line
        out[key] = lines
    return out


def select(panels: dict, only: list[str]) -> dict:
    """``panels`` with only the lines labelled in ``only`` (panels left without a line are dropped). A label keeps
    its line in every panel; ``"<task name>: <label>"`` (``"House building: LDM [gamma08]"``) only in that task's
    panels. A label that names no line is an error, so a typo does not drop a line silently."""
    def qualified(key, label: str) -> str:
        return f"{TASKS.get(key[0], (key[0],))[0]}: {label}"

    def wanted(key, label: str) -> bool:
        return label in only or qualified(key, label) in only

    known = {name for key, lines in panels.items() for label in lines for name in (label, qualified(key, label))}
    unknown = [label for label in only if label not in known]
    if unknown:
        raise ValueError(f"--only {', '.join(repr(u) for u in unknown)}: no such line; the lines are "
                         f"{', '.join(sorted({label for lines in panels.values() for label in lines}))} "
                         "(each may be prefixed by its task's name and a colon, e.g. 'House building: ')")
    kept = {key: {label: runs for label, runs in lines.items() if wanted(key, label)} for key, lines in panels.items()}
    return {key: lines for key, lines in kept.items() if lines}


def panel_title(task: str, num_objects: int) -> str:
    name, unit = TASKS.get(task, (task, "objects"))
    return f"{name} ({num_objects} {unit})"


def plot(panels: dict, png: Path, csv_path: Path) -> list[dict]:
    """Draw the figure to ``png`` and write the plotted points to ``csv_path``; returns the CSV rows."""
    import matplotlib.pyplot as plt

    fig, rows = draw(panels)
    with atomic_path(png) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
    with atomic_path(csv_path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    return rows


def draw(panels: dict):
    """The figure, a panel per (task, object count), and its points as CSV rows: ``(figure, rows)``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(panels)
    ncols = n if n <= 2 else 2
    nrows = math.ceil(n / ncols)
    legend_outside = max(len(lines) for lines in panels.values()) > LEGEND_INSIDE_MAX
    panel_width = 5.2 + 3.0 * legend_outside  # room for the legend beside each panel
    fig, axes = plt.subplots(nrows, ncols, figsize=(panel_width * ncols, 3.9 * nrows), squeeze=False)
    rows: list[dict] = []
    # variants' colours: tab10's last six, then tab20's lighter shades; a label keeps its colour in every panel
    tab20 = plt.get_cmap("tab20").colors
    palette = [f"C{i}" for i in range(4, 10)] + [tab20[i] for i in range(1, 20, 2)]
    colours: dict[str, object] = {}
    for ax, ((task, objects), lines) in zip(axes.flat, panels.items()):
        per_agent = defaultdict(int)
        for runs in lines.values():
            per_agent[runs[0].agent] += 1
        taken: list = []
        for label, runs in lines.items():
            agent = runs[0].agent
            if agent in AGENTS and per_agent[agent] == 1:  # an agent's only line in the panel: the agent's colour
                colour = AGENTS[agent][1]
            else:  # one of several variants (or an unknown agent): its colour of another panel where still free here
                colour = colours.get(label)
                if colour is None or colour in taken:
                    free = [c for c in palette if c not in taken] or palette
                    colour = colours[label] = free[0]
            taken.append(colour)
            points = mean_curve(runs)
            xs, means, ses = zip(*points)
            seeds = len(runs)
            ax.plot(xs, means, marker="o", ms=3, linestyle=LINE_STYLES.get(agent, "-"), color=colour,
                    label=f"{label}, {seeds} seed{'s' * (seeds > 1)}")
            if seeds > 1:
                ax.fill_between(xs, [m - s for m, s in zip(means, ses)], [m + s for m, s in zip(means, ses)],
                                color=colour, alpha=0.2, linewidth=0)
            for x, m, s in points:
                rows.append({"task": task, "num_objects": objects, "agent": agent, "label": label, "episodes": x,
                             "mean": m, "se": s, "n_seeds": seeds})
        ax.set_title(panel_title(task, objects))
        ax.set_xlabel("training episodes")
        ax.set_ylabel("greedy success rate (fraction)")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        if legend_outside:
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, borderaxespad=0)
        else:
            ax.legend(loc="upper left", fontsize=8)
    for ax in list(axes.flat)[n:]:
        ax.remove()
    title = "Greedy success rate against training episodes (mean ± standard error over seeds)"
    fig.suptitle(title if ncols > 1 else title.replace(" (", "\n("))  # one panel: two lines fit its width
    fig.tight_layout()
    return fig, rows


def _first_reaching(points: list[tuple[float, float, float]], level: float) -> str:
    return next((f"{x:g}" for x, mean, _ in points if mean >= level), "never")


def _mean_se(values: list[float]) -> str:
    mean = sum(values) / len(values)
    if len(values) == 1:
        return f"{mean:.2f}"
    se = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1) / len(values))
    return f"{mean:.2f} ± {se:.2f}"


def comparison_table(panels: dict) -> str:
    """The comparison as a markdown table: one row per line of the figure (task, agent and tag), with the
    episodes at which its mean curve first reaches 0.5 and 0.8 (in-training evaluations), the final weights'
    success on the final evaluation (mean ± standard error over seeds, from final_metrics.json) after how
    many training episodes, and the paper's end value."""
    lines = ["| task | agent | seeds | first mean ≥ 0.5 (episodes) | first mean ≥ 0.8 (episodes) | final weights: success "
             "(mean ± s.e.) | after (episodes) | paper's end value |", "|---|---|---|---|---|---|---|---|"]
    for (task, objects), by_label in panels.items():
        for label, runs in by_label.items():
            points = mean_curve(runs)
            finals = [run.final for run in runs if run.final is not None]
            end = _mean_se([float(f["success_rate"]) for f in finals]) if len(finals) == len(runs) else "–"
            after = sorted({int(f["episodes"]) for f in finals})
            paper = PAPER_END.get(task, {}).get(runs[0].agent)
            lines.append(f"| {panel_title(task, objects)} | {label} | {', '.join(str(r.seed) for r in runs)} | "
                         f"{_first_reaching(points, 0.5)} | {_first_reaching(points, 0.8)} | {end} | "
                         f"{', '.join(map(str, after)) or '–'} | {'–' if paper is None else f'{paper:.2f}'} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(prog="python -m ldm_rl.reports.plot_learning_curves", description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", type=Path, help="multirun sweep folder(s) or run folders of train_policy.py")
    parser.add_argument("--out", type=Path, default=None,
                        help="figure path (.png; the CSV goes beside it, .csv); default <first folder>/learning_curves.png")
    parser.add_argument("--table", type=Path, default=None, help="also write the comparison table (markdown) here (.md)")
    parser.add_argument("--only", nargs="+", default=None, metavar="LABEL",
                        help='draw and tabulate only the lines of these labels, e.g. "LDM [mix23ema]" "FC-DQN [ema]"; '
                             '"House building: LDM [gamma08]" keeps a line in that task only')
    args = parser.parse_args(argv)
    if args.out is not None and args.out.suffix.lower() != ".png":
        parser.error(f"--out {args.out}: expected a .png path")
    if args.table is not None and args.table.suffix.lower() != ".md":
        parser.error(f"--table {args.table}: expected a .md path")
    try:
        runs = [read_run(folder) for folder in _run_folders(args.folders)]
        if not runs:
            raise ValueError(f"no curve.csv found under {', '.join(str(f) for f in args.folders)}")
        panels = group(runs)
        if args.only:
            panels = select(panels, args.only)
    except ValueError as err:
        parser.exit(2, f"error: {err}\n")
    png = args.out or args.folders[0] / "learning_curves.png"
    rows = plot(panels, png, png.with_suffix(".csv"))
    for (task, objects), lines in panels.items():
        for label, line in lines.items():
            last = [r for r in rows if r["task"] == task and r["num_objects"] == objects and r["label"] == label][-1]
            se = "" if math.isnan(last["se"]) else f" ± {last['se']:.2f}"
            print(f"{panel_title(task, objects)}, {label}: {len(line)} seed(s) up to {last['episodes']:g} episodes "
                  f"(the shortest run), success {last['mean']:.2f}{se}")
    print(f"written to {png} and {png.with_suffix('.csv')}")
    if args.table is not None:
        with atomic_path(args.table) as tmp:
            tmp.write_text(comparison_table(panels))
        print(f"comparison table written to {args.table}")
    return rows


if __name__ == "__main__":
    main()
