"""Draw the paper's sample-efficiency figure of a dynamics task from ``recipes/train_dynamics.py`` runs.

    python -m ldm_rl.reports.plot_sample_efficiency docs/results/table1 --task bin_packing --out docs/img/sample_efficiency.png

Reads every run folder at or below the given folders that holds ``final_metrics.json`` (task, model, seed)
and ``curve.csv`` (one line per evaluation), keeps the runs of ``--task``, and draws two panels: place SR
and overall SR on the held-out set against training iterations, one line per model (LDM(64), LDM(128),
Naive) as the mean ± standard error over its seeds (the band is absent where a model has one seed), and
the held-out set's no-change floor as a dashed grey line. A model's seeds are averaged at the iterations
they all evaluated. Writes the PNG and a CSV of the plotted points (model, iteration, metric, mean, se,
n_seeds) beside it.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import statistics
from collections import defaultdict
from pathlib import Path

from ldm_rl.run.outputs import atomic_path

MODELS = {"LDM(64)": "C0", "LDM(128)": "C1", "Naive": "C2"}
PANELS = (("sr_place", "floor_sr_place", "Place actions"), ("sr", "floor_sr", "All actions"))
TASK_NAMES = {"block_stacking": "block stacking", "house_building": "house building",
              "bottle_arrangement": "bottle arrangement", "bin_packing": "bin packing"}
CSV_FIELDS = ("model", "iteration", "metric", "mean", "se", "n_seeds")


def load_runs(folders: list[Path], task: str) -> dict[str, list[dict[int, dict[str, float]]]]:
    """``{model: [curve per seed]}``, a curve being ``{iteration: {metric: value}}``, for the runs of ``task``."""
    runs: dict[str, list[dict[int, dict[str, float]]]] = defaultdict(list)
    for folder in folders:
        if not folder.exists():
            raise SystemExit(f"error: {str(folder)!r} does not exist")
        for metrics_file in sorted([*folder.rglob("final_metrics.json")]):
            meta = json.loads(metrics_file.read_text())
            curve_file = metrics_file.parent / "curve.csv"
            if meta.get("task") != task or not curve_file.exists():
                continue
            with open(curve_file, newline="") as f:
                curve = {int(row["iteration"]): {k: float(v) for k, v in row.items() if k != "iteration" and v != ""}
                         for row in csv.DictReader(f)}
            runs[meta["model"]].append(curve)
    return runs


def aggregate(curves: list[dict[int, dict[str, float]]], metric: str) -> list[tuple[int, float, float, int]]:
    """``(iteration, mean, standard error, n)`` at the iterations every seed evaluated."""
    common = sorted(set.intersection(*(set(c) for c in curves)))
    points = []
    for it in common:
        values = [c[it][metric] for c in curves if metric in c[it]]
        if not values:
            continue
        se = statistics.stdev(values) / math.sqrt(len(values)) if len(values) > 1 else 0.0
        points.append((it, statistics.fmean(values), se, len(values)))
    return points


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(prog="python -m ldm_rl.reports.plot_sample_efficiency", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("folders", nargs="+", type=Path, help="run folders or folders holding them")
    parser.add_argument("--task", default="bin_packing", choices=sorted(TASK_NAMES))
    parser.add_argument("--out", type=Path, default=None, help="PNG (default <first folder>/sample_efficiency_<task>.png)")
    args = parser.parse_args(argv)
    runs = load_runs(args.folders, args.task)
    if not runs:
        raise SystemExit(f"error: no run of task {args.task!r} with final_metrics.json and curve.csv below "
                         f"{[str(f) for f in args.folders]}")
    out = args.out or args.folders[0] / f"sample_efficiency_{args.task}.png"

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    rows = []
    for ax, (metric, floor_key, title) in zip(axes, PANELS):
        floors = set()
        for model in [m for m in MODELS if m in runs] + sorted(set(runs) - set(MODELS)):
            points = aggregate(runs[model], metric)
            if not points:
                continue
            it, mean, se, n = (list(col) for col in zip(*points))
            label = f"{model} (n = {min(n)} seed{'s' if min(n) > 1 else ''})"
            pct = [100 * v for v in mean]
            ax.plot(it, pct, marker="o", color=MODELS.get(model), label=label)
            if max(n) > 1:
                ax.fill_between(it, [100 * (m - s) for m, s in zip(mean, se)], [100 * (m + s) for m, s in zip(mean, se)],
                                color=MODELS.get(model), alpha=0.2)
            rows += [{"model": model, "iteration": i, "metric": metric, "mean": m, "se": s, "n_seeds": k}
                     for i, m, s, k in points]
            floors |= {round(c[i][floor_key], 4) for c in runs[model] for i in c if floor_key in c[i]}
        for k, floor in enumerate(sorted(floors)):
            ax.axhline(100 * floor, color="grey", linestyle="--", linewidth=1,
                       label="no-change floor" if k == 0 else None)
        ax.set_title(title)
        ax.set_xlabel("training iterations (batches of 32)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("held-out action success rate (%)")
    fig.suptitle(f"Sample efficiency of the dynamics models: {TASK_NAMES[args.task]} (mean ± standard error over seeds)")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
    with atomic_path(out.with_suffix(".csv")) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {out} and {out.with_suffix('.csv')} ({', '.join(f'{m}: {len(c)} seeds' for m, c in runs.items())})")
    return out


if __name__ == "__main__":
    main()
