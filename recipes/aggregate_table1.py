"""Aggregate Table-1 runs (``recipes/train_dynamics.py -m ...``) into a markdown table.

    python recipes/aggregate_table1.py multirun/2026-11-21/10-00-00 [more folders] [--out table1.md]

Reads every ``final_metrics.json`` below the given folders (one per run: task, model, seed, sr, l1_mm)
and writes rows = models, columns = tasks, cells = held-out action success rate ``mean ± std`` over
seeds (%, sample std; n = number of seeds) with the paper's number beside it, plus an L1 table.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from ldm_rl.runtime import atomic_write_text  # noqa: E402

TASKS = ("block_stacking", "house_building", "bottle_arrangement", "bin_packing")
MODELS = ("LDM(64)", "LDM(128)", "Naive")
# Table 1 of the paper (held-out action success rate %, 5k noisy expert steps)
PAPER_SR = {
    "LDM(64)": (83.4, 77.9, 66.0, 65.9),
    "LDM(128)": (70.0, 70.7, 58.6, 60.4),
    "Naive": (38.0, 39.1, 43.8, 35.4),
}


def collect(folders: list[Path]) -> list[dict]:
    """All run summaries below ``folders``."""
    runs = []
    for folder in folders:
        for path in sorted(folder.rglob("final_metrics.json")):
            run = json.loads(path.read_text())
            run["path"] = str(path.parent)
            runs.append(run)
    return runs


def _cell(values: list[float], scale: float, digits: int) -> str:
    if not values:
        return "–"
    mean = statistics.fmean(values) * scale
    std = statistics.stdev(values) * scale if len(values) > 1 else 0.0
    return f"{mean:.{digits}f} ± {std:.{digits}f} (n={len(values)})"


def table(runs: list[dict]) -> str:
    """Markdown: SR table (with the paper's numbers) and L1 table."""
    groups: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for run in runs:
        groups[(run["model"], run["task"])].append(run)
    tasks = list(TASKS) + sorted({t for _, t in groups} - set(TASKS))
    models = list(MODELS) + sorted({m for m, _ in groups} - set(MODELS))
    lines = ["Held-out action success rate (%), mean ± std over seeds; paper's Table 1 in brackets.", ""]
    lines.append("| model | " + " | ".join(tasks) + " |")
    lines.append("|---|" + "---|" * len(tasks))
    for model in models:
        cells = []
        for i, task in enumerate(tasks):
            ours = _cell([r["sr"] for r in groups.get((model, task), [])], 100, 1)
            paper = PAPER_SR.get(model, ())[i] if model in PAPER_SR and i < len(TASKS) else None
            cells.append(ours + (f" [{paper}]" if paper is not None else ""))
        lines.append(f"| {model} | " + " | ".join(cells) + " |")
    lines += ["", "Held-out L1 height error over the whole heightmap (mm), mean ± std over seeds.", ""]
    lines.append("| model | " + " | ".join(tasks) + " |")
    lines.append("|---|" + "---|" * len(tasks))
    for model in models:
        lines.append(f"| {model} | " + " | ".join(_cell([r["l1_mm"] for r in groups.get((model, t), [])], 1, 2) for t in tasks) + " |")
    presets = sorted({r.get("preset", "?") for r in runs})
    lines += ["", f"Runs: {len(runs)}; model presets: {', '.join(presets)}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", type=Path, help="multirun folder(s) of train_dynamics.py")
    parser.add_argument("--out", type=Path, default=None, help="markdown file (default: <first folder>/table1.md)")
    args = parser.parse_args(argv)
    runs = collect(args.folders)
    if not runs:
        parser.error(f"no final_metrics.json found under {[str(f) for f in args.folders]}")
    text = table(runs)
    out = args.out or args.folders[0] / "table1.md"
    atomic_write_text(out, text)
    print(text)
    print(f"written to {out}")
    return text


if __name__ == "__main__":
    main()
