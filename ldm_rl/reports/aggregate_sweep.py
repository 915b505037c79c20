"""Aggregate a Hydra sweep (``-m seed=0,1,2 ...``) into mean ± std tables and curves over seeds.

    python -m ldm_rl.reports.aggregate_sweep multirun/2026-11-21/10-00-00 [--out DIR] [--metrics a,b] [--x episodes]

Reads the sweep's job folders (``<sweep>/<n>/`` with Hydra's ``.hydra/overrides.yaml``), each run's
``final_metrics.json`` and its ``curve.csv``: greedy success rate per evaluation (``recipes/train_policy.py``)
or held-out SR per evaluation (``recipes/train_dynamics.py``; dynamics runs written before it had a curve.csv
fall back on the CSV logger's scalars, ``ldm_rl.run.outputs.read_scalars``). Runs
whose overrides differ only in ``seed`` (and ``resume``) form one group. Writes, by default into the
sweep folder:

* ``sweep_summary.md``: one row per group, ``mean ± std`` over its seeds (sample std, n = runs) of each
  metric (rates in %); jobs without ``final_metrics.json`` (failed or still running) are listed below it;
* ``sweep_summary.csv``: group, metric, n, mean, std, min, max, seeds (every numeric metric);
* ``sweep_curve.png`` / ``sweep_curve.csv``: per group, the mean ± std curve against ``--x`` (training
  episodes for policy runs, iterations for dynamics runs). Each seed's curve is interpolated linearly
  onto the union of the seeds' x values up to the shortest seed's last one, so every point averages all
  seeds.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import statistics
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from ldm_rl.run.outputs import atomic_path, atomic_write_text

# overrides that tell replicates apart rather than name a variant
REPLICATE_KEYS = ("seed", "resume")
# (table metrics, curve file, default x, y, x label, y label) per kind of run
KINDS = {
    "policy": (("success_rate", "mean_length", "episodes", "env_steps", "updates", "wall_s"),
               "curve.csv", "episodes", "success_rate", "training episodes", "greedy success rate (%)"),
    "dynamics": (("sr", "sr_pick", "sr_place", "l1_mm", "l1_region_mm", "floor_sr"),
                 None, "iteration", "sr", "training iterations (gradient steps)",
                 "held-out action success rate (%)"),
}
X_LABELS = {"episodes": "training episodes", "env_steps": "environment steps", "updates": "agent updates",
            "wall_s": "wall-clock (s)", "iteration": "training iterations (gradient steps)",
            "elapsed_s": "training wall-clock (s)"}
# recipes/train_dynamics.py logs its evaluations as dynamics/<metric> scalars, step = iteration
DYNAMICS_PREFIX = "dynamics/"


class SweepError(ValueError):
    """The folder is not a readable sweep."""


@dataclass
class Job:
    number: str
    path: Path
    overrides: list[str]
    group: str
    seed: int | None
    metrics: dict | None = None
    kind: str | None = None
    curve: list[dict] = field(default_factory=list)


def is_rate(name: str) -> bool:
    """Fractions shown in %: success rates and their interval bounds."""
    return name in ("success_rate", "ci_low", "ci_high") or name.startswith(("sr", "floor_sr"))


def parse_overrides(lines: list[str]) -> tuple[str, int | None]:
    """(group label = the overrides other than seed/resume, in order; the seed override's value)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(lines)
    kept, seed = [], None
    for override, line in zip(parsed, lines):
        if override.key_or_group in REPLICATE_KEYS:
            if override.key_or_group == "seed":
                seed = int(override.value())
            continue
        kept.append(line)
    return (" ".join(kept) or "(defaults)"), seed


def read_curve(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return [{k: float(v) for k, v in row.items() if v not in ("", None)} for row in csv.DictReader(f)]


def read_dynamics_curve(path: Path) -> list[dict]:
    """One row per logged iteration, ``{"iteration": step, "<metric>": value, ...}``, from the CSV logger's
    ``dynamics/*`` scalars of a ``recipes/train_dynamics.py`` run; [] without them (another logger)."""
    from ldm_rl.run.outputs import read_scalars

    try:
        scalars = read_scalars(path)
    except FileNotFoundError:
        return []
    rows: dict[int, dict] = {}
    for name, points in scalars.items():
        if name.startswith(DYNAMICS_PREFIX):
            for step, value in points:
                rows.setdefault(step, {"iteration": float(step)})[name[len(DYNAMICS_PREFIX):]] = value
    return [rows[step] for step in sorted(rows)]


def run_kind(path: Path, metrics: dict) -> tuple[str | None, list[dict]]:
    """("policy" | "dynamics" | None, the run's curve rows)."""
    curve = path / "curve.csv"  # both recipes write one; dynamics runs older than it have only the logger's scalars
    if "agent" in metrics:
        return "policy", read_curve(curve) if curve.is_file() else []
    if "sr" in metrics:
        return "dynamics", read_curve(curve) if curve.is_file() else read_dynamics_curve(path)
    return None, []


def find_jobs(sweep: Path) -> list[Job]:
    """The sweep's job folders (any child with ``.hydra/overrides.yaml``), in job-number order."""
    from omegaconf import OmegaConf

    if not sweep.is_dir():
        raise SweepError(f"{sweep} is not a folder: pass a Hydra multirun folder such as multirun/2026-01-01/12-00-00")
    folders = [p for p in sweep.iterdir() if (p / ".hydra" / "overrides.yaml").is_file()]
    if not folders:
        raise SweepError(f"{sweep} holds no Hydra job folders (<n>/.hydra/overrides.yaml): pass the folder of one "
                         "sweep, such as multirun/2026-01-01/12-00-00")
    jobs = []
    for path in sorted(folders, key=lambda p: (not p.name.isdigit(), int(p.name) if p.name.isdigit() else 0, p.name)):
        lines = [str(x) for x in OmegaConf.to_container(OmegaConf.load(path / ".hydra" / "overrides.yaml"))]
        group, seed = parse_overrides(lines)
        job = Job(path.name, path, lines, group, seed)
        final = path / "final_metrics.json"
        if final.is_file():
            try:
                job.metrics = json.loads(final.read_text())
            except json.JSONDecodeError as err:
                raise SweepError(f"{final} is not valid JSON ({err}); expected a recipe's final_metrics.json") from None
            if not isinstance(job.metrics, dict):
                raise SweepError(f"{final} holds a {type(job.metrics).__name__}; expected a JSON object of metrics")
            if isinstance(job.metrics.get("seed"), int):
                job.seed = job.metrics["seed"]
            job.kind, job.curve = run_kind(path, job.metrics)
        jobs.append(job)
    return jobs


def mean_std(values: list[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (NaN for one value)."""
    return statistics.fmean(values), (statistics.stdev(values) if len(values) > 1 else math.nan)


def numeric(metrics: dict) -> dict[str, float]:
    return {k: float(v) for k, v in metrics.items()
            if isinstance(v, (int, float)) and not isinstance(v, bool) and k != "seed" and math.isfinite(float(v))}


def group_jobs(jobs: list[Job]) -> dict[str, list[Job]]:
    groups: dict[str, list[Job]] = defaultdict(list)
    for job in jobs:
        if job.metrics is not None:
            groups[job.group].append(job)
    return dict(groups)


def summary_rows(groups: dict[str, list[Job]]) -> list[dict]:
    """Long-form rows: group, metric, n, mean, std, min, max, seeds."""
    rows = []
    for group, members in groups.items():
        names = sorted(set().union(*(numeric(j.metrics) for j in members)))
        for name in names:
            values = [numeric(j.metrics)[name] for j in members if name in numeric(j.metrics)]
            mean, std = mean_std(values)
            rows.append({"group": group, "metric": name, "n": len(values), "mean": mean, "std": std,
                         "min": min(values), "max": max(values),
                         "seeds": " ".join(str(j.seed) for j in members if name in numeric(j.metrics))})
    return rows


def fmt(name: str, mean: float, std: float) -> str:
    """``mean ± std``: rates in % with one decimal, values >= 10 with one decimal, others 3 significant digits."""
    if is_rate(name):
        mean, std, spec = 100.0 * mean, 100.0 * std, ".1f"
    else:
        spec = ".1f" if abs(mean) >= 10 else ".3g"
    return f"{mean:{spec}} ± " + (f"{std:{spec}}" if std == std else "–")


def labels(groups: dict[str, list[Job]]) -> tuple[dict[str, str], list[str]]:
    """(short label per group = its overrides that not every group shares; the shared overrides)."""
    members = [m[0].overrides for m in groups.values()]
    common = [o for o in members[0] if all(o in other for other in members[1:])]
    short = {}
    for group, jobs in groups.items():
        own = [o for o in jobs[0].overrides if o not in common and o.split("=", 1)[0].lstrip("+~") not in REPLICATE_KEYS]
        short[group] = " ".join(own) or "all runs"
    return short, [o for o in common if o.split("=", 1)[0].lstrip("+~") not in REPLICATE_KEYS]


def markdown(sweep: Path, jobs: list[Job], groups: dict[str, list[Job]], metrics: list[str]) -> str:
    stats = {(r["group"], r["metric"]): r for r in summary_rows(groups)}
    out = io.StringIO()
    short, common = labels(groups)
    out.write(f"# Sweep {sweep}\n\nmean ± std over seeds (sample std; rates in %), n = runs with results.\n\n")
    if common:
        out.write(f"Overrides of every run: `{' '.join(common)}`\n\n")
    header = ["group", "n", "seeds"] + [f"{m} (%)" if is_rate(m) else m for m in metrics]
    out.write("| " + " | ".join(header) + " |\n|" + "---|" * len(header) + "\n")
    for group, members in groups.items():
        cells = [f"`{short[group]}`", str(len(members)), " ".join(str(j.seed) for j in members)]
        for m in metrics:
            r = stats.get((group, m))
            cells.append(fmt(m, r["mean"], r["std"]) if r else "–")
        out.write("| " + " | ".join(cells) + " |\n")
    missing = [j for j in jobs if j.metrics is None]
    if missing:
        out.write("\nJobs without final_metrics.json (failed or still running): "
                  + ", ".join(f"{j.number} (`{' '.join(j.overrides)}`)" for j in missing) + "\n")
    return out.getvalue()


def mean_curve(curves: list[list[dict]], x: str, y: str) -> list[tuple[float, float, float]]:
    """(x, mean, std) on the union of the curves' x values up to the shortest curve's end (linear interpolation;
    at a repeated x a curve's last value counts)."""
    import numpy as np

    series = []
    for rows in curves:
        points = {}
        for row in rows:
            if x in row and y in row:
                points[row[x]] = row[y]
        if points:
            xs = np.array(sorted(points))
            series.append((xs, np.array([points[v] for v in xs])))
    if not series:
        return []
    lo, hi = max(s[0][0] for s in series), min(s[0][-1] for s in series)
    grid = np.unique(np.concatenate([s[0] for s in series]))
    grid = grid[(grid >= lo) & (grid <= hi)]
    ys = np.stack([np.interp(grid, xs, vs) for xs, vs in series])
    std = ys.std(0, ddof=1) if len(series) > 1 else np.full(len(grid), np.nan)
    return [(float(g), float(m), float(s)) for g, m, s in zip(grid, ys.mean(0), std)]


def write_curves(groups: dict[str, list[Job]], out_dir: Path, x_key: str | None) -> Path | None:
    """sweep_curve.csv and sweep_curve.png (mean ± std band per group); None when no run has a curve."""
    from ldm_rl.plots import require_matplotlib

    lines, kinds = [], set()
    short, common = labels(groups)
    for group, members in groups.items():
        with_curves = [j for j in members if j.curve]
        if not with_curves:
            continue
        kind = with_curves[0].kind
        kinds.add(kind)
        _, _, default_x, y, _, _ = KINDS[kind]
        x = x_key or default_x
        points = mean_curve([j.curve for j in with_curves], x, y)
        if points:
            lines.append((group, len(with_curves), kind, x, y, points))
    if not lines:
        return None
    with atomic_path(out_dir / "sweep_curve.csv") as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["group", "n", "x", "x_value", "y", "mean", "std"])
        for group, n, _, x, y, points in lines:
            writer.writerows([group, n, x, px, y, m, s] for px, m, s in points)
    require_matplotlib()
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.5, 4.5), layout="constrained")
    ax = fig.subplots()
    for i, (group, n, kind, x, y, points) in enumerate(lines):
        xs = [p[0] for p in points]
        mean = [100.0 * p[1] for p in points]
        std = [0.0 if p[2] != p[2] else 100.0 * p[2] for p in points]
        colour = f"C{i % 10}"
        ax.plot(xs, mean, marker="o", ms=3, color=colour, label=f"{short[group]} (n={n})")
        ax.fill_between(xs, [m - s for m, s in zip(mean, std)], [m + s for m, s in zip(mean, std)], color=colour,
                        alpha=0.2, lw=0)
    ax.fill_between([], [], [], color="0.6", alpha=0.3, label="± 1 std over seeds")
    kind = lines[0][2]
    x = lines[0][3]
    ax.axhline(0.0, color="0.35", lw=0.9, zorder=0)
    ax.set_ylim(-5.0, 105.0)
    ax.set_xlabel(X_LABELS.get(x, x) if len(kinds) == 1 else x)
    ax.set_ylabel(KINDS[kind][5] if len(kinds) == 1 else "success rate (%)")
    what = "greedy success rate" if kind == "policy" else "held-out action success rate"
    ax.set_title(f"{what}, mean ± std over seeds", fontsize=11)
    if common:
        text = " ".join(common)
        fig.suptitle(text if len(text) <= 110 else text[:107] + "...", fontsize=7, color="0.35")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    path = out_dir / "sweep_curve.png"
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    return path


def aggregate(sweep: Path, out_dir: Path | None = None, metrics: list[str] | None = None,
              x_key: str | None = None) -> dict[str, Path]:
    """Write the summary table (md, csv) and the curves of ``sweep``; returns the written paths."""
    jobs = find_jobs(sweep)
    groups = group_jobs(jobs)
    if not groups:
        raise SweepError(f"none of the {len(jobs)} jobs in {sweep} has a final_metrics.json yet (failed or still running)")
    out_dir = out_dir or sweep
    out_dir.mkdir(parents=True, exist_ok=True)
    kinds = {j.kind for m in groups.values() for j in m}
    if metrics is None:
        present = set().union(*(numeric(j.metrics) for m in groups.values() for j in m))
        defaults = [name for kind in ("policy", "dynamics") if kind in kinds for name in KINDS[kind][0]]
        metrics = [name for name in dict.fromkeys(defaults) if name in present] or sorted(present)
    else:
        present = set().union(*(numeric(j.metrics) for m in groups.values() for j in m))
        unknown = [name for name in metrics if name not in present]
        if unknown:
            raise SweepError(f"--metrics {','.join(unknown)}: no run has them; numeric keys of final_metrics.json: "
                             f"{', '.join(sorted(present))}")
    written = {"md": atomic_write_text(out_dir / "sweep_summary.md", markdown(sweep, jobs, groups, metrics))}
    with atomic_path(out_dir / "sweep_summary.csv") as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["group", "metric", "n", "mean", "std", "min", "max", "seeds"])
        writer.writeheader()
        writer.writerows(summary_rows(groups))
    written["csv"] = out_dir / "sweep_summary.csv"
    png = write_curves(groups, out_dir, x_key)
    if png is not None:
        written["png"] = png
        written["curve_csv"] = out_dir / "sweep_curve.csv"
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m ldm_rl.reports.aggregate_sweep", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="Writes sweep_summary.md/.csv and sweep_curve.png/.csv (docs/scaling.md).")
    parser.add_argument("sweep", type=Path, help="a Hydra multirun folder: multirun/<date>/<time>")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: the sweep folder)")
    parser.add_argument("--metrics", default=None,
                        help="comma-separated final_metrics.json keys for the markdown table (default: the run kind's)")
    parser.add_argument("--x", default=None, choices=sorted(X_LABELS),
                        help="curve x axis (default: episodes for policy runs, iteration for dynamics runs)")
    args = parser.parse_args(argv)
    metrics = [m.strip() for m in args.metrics.split(",") if m.strip()] if args.metrics else None
    try:
        written = aggregate(args.sweep, args.out, metrics, args.x)
    except (SweepError, ImportError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(written["md"].read_text())
    print("wrote " + ", ".join(str(p) for p in written.values()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
