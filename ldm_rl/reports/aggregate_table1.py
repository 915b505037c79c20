"""Aggregate Table-1 runs (``recipes/train_dynamics.py -m ...``) into markdown tables, with the floors.

    python -m ldm_rl.reports.aggregate_table1 multirun/2026-11-21/10-00-00 [more folders] [--out table1.md]

Reads every ``final_metrics.json`` below the given folders (one per run: task, model, seed and the
metrics of ``ldm_rl.world_model.training.evaluate``) and writes, without re-running anything:

1. rows = models, columns = tasks, cells = held-out action success rate ``mean ± std`` over seeds
   (%, sample std; n = number of runs) with the paper's number beside it, and a last row with the
   no-change floor of the same held-out sets (what "predict nothing changes, and the majority pick
   outcome" scores under the same rule);
2. per task: SR overall / picks / places at IoU 0.5, 0.75 and 0.9, and L1 per pixel (image, B_a), one
   row per model and a floor row (majority pick outcome, no-change places and L1);
3. L1 per pixel over the whole image (mm), models × tasks.

A floor is a property of a held-out set, not of a model: runs that share one (same task, seed and
floor values) count once in the floor cells. Runs written before the floors existed show "–" there.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from collections import defaultdict
from pathlib import Path

from ldm_rl.run.outputs import atomic_write_text

TASKS = ("block_stacking", "house_building", "bottle_arrangement", "bin_packing")
MODELS = ("LDM(64)", "LDM(128)", "Naive")
# Table 1 of the paper (held-out action success rate %, 5k noisy expert steps)
PAPER_SR = {
    "LDM(64)": (83.4, 77.9, 66.0, 65.9),
    "LDM(128)": (70.0, 70.7, 58.6, 60.4),
    "Naive": (38.0, 39.1, 43.8, 35.4),
}
FLOOR_KEYS = ("floor_sr", "floor_sr_pick", "floor_sr_place", "floor_l1_mm", "floor_l1_region_mm")
IOU_COLUMNS = ("sr_place_iou50", "sr_place_iou75", "sr_place_iou90")


def collect(folders: list[Path]) -> list[dict]:
    """All run summaries below ``folders``."""
    runs = []
    for folder in folders:
        if not folder.is_dir():
            raise SystemExit(f"error: {folder} is not a folder (expected a multirun folder of train_dynamics.py)")
        for path in sorted(folder.rglob("final_metrics.json")):
            run = json.loads(path.read_text())
            missing = [k for k in ("task", "model", "sr") if k not in run]
            if missing:
                raise SystemExit(f"error: {path} lacks {missing}; expected a final_metrics.json of recipes/train_dynamics.py")
            run["path"] = str(path.parent)
            runs.append(run)
    return runs


def _values(runs: list[dict], key: str) -> list[float]:
    """``run[key]`` of every run that has it as a number (NaN, None and absent left out)."""
    return [float(r[key]) for r in runs if isinstance(r.get(key), (int, float)) and not math.isnan(float(r[key]))]


def _cell(values: list[float], scale: float, digits: int) -> str:
    if not values:
        return "–"
    mean = statistics.fmean(values) * scale
    if len(values) == 1:  # one seed: no spread to report
        return f"{mean:.{digits}f} (n=1)"
    return f"{mean:.{digits}f} ± {statistics.stdev(values) * scale:.{digits}f} (n={len(values)})"


def held_out_sets(runs: list[dict]) -> list[dict]:
    """One run per distinct held-out set (task, seed and floor values): the floors' samples."""
    seen, unique = set(), []
    for run in runs:
        if not _values([run], "floor_sr"):
            continue
        key = (run.get("task"), run.get("seed"), run.get("val_transitions"), *(run.get(k) for k in FLOOR_KEYS))
        if key not in seen:
            seen.add(key)
            unique.append(run)
    return unique


def _header(first: str, columns) -> list[str]:
    return [f"| {first} | " + " | ".join(columns) + " |", "|---|" + "---|" * len(columns)]


def table(runs: list[dict]) -> str:
    """Markdown: SR table (paper's numbers and the floor row), per-task breakdown, L1 table."""
    groups: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for run in runs:
        groups[(run["model"], run["task"])].append(run)
    tasks = list(TASKS) + sorted({t for _, t in groups} - set(TASKS))
    models = list(MODELS) + sorted({m for m, _ in groups} - set(MODELS))
    floors = {task: held_out_sets([r for r in runs if r["task"] == task]) for task in tasks}

    lines = ["Held-out action success rate (%), mean ± std over seeds; paper's Table 1 in brackets. Floor: the",
             "no-change model (next = current state; picks get the majority outcome) on the same held-out sets.", ""]
    lines += _header("model", tasks)
    for model in models:
        cells = []
        for i, task in enumerate(tasks):
            ours = _cell(_values(groups.get((model, task), []), "sr"), 100, 1)
            paper = PAPER_SR[model][i] if model in PAPER_SR and i < len(TASKS) else None
            cells.append(ours + (f" [{paper}]" if paper is not None else ""))
        lines.append(f"| {model} | " + " | ".join(cells) + " |")
    lines.append("| *floor (no change)* | " + " | ".join(_cell(_values(floors[t], "floor_sr"), 100, 1) for t in tasks) + " |")

    columns = ("SR all", "SR pick", "SR place @ IoU 0.5", "SR place @ IoU 0.75", "SR place @ IoU 0.9",
               "L1 image (mm/px)", "L1 in B_a (mm/px)")
    for task in tasks:
        if not any(groups.get((m, task)) for m in models):
            continue
        lines += ["", f"**{task}**: SR (%) and L1 per pixel (mm), mean ± std over seeds. \"SR all\" uses the run's "
                      "place threshold (`dynamics.metrics.iou_threshold`, 0.75 by default); the floor row scores the "
                      "majority pick outcome on picks and \"no change\" on places (the same at every IoU).", ""]
        lines += _header("model", columns)
        for model in models:
            rs = groups.get((model, task), [])
            if not rs:
                continue
            keys = ("sr", "sr_pick", *IOU_COLUMNS)
            cells = [_cell(_values(rs, k), 100, 1) for k in keys] + [_cell(_values(rs, k), 1, 2) for k in ("l1_mm", "l1_region_mm")]
            lines.append(f"| {model} | " + " | ".join(cells) + " |")
        fs = floors[task]
        place = _cell(_values(fs, "floor_sr_place"), 100, 1)
        cells = [_cell(_values(fs, "floor_sr"), 100, 1), _cell(_values(fs, "floor_sr_pick"), 100, 1), place, place, place,
                 _cell(_values(fs, "floor_l1_mm"), 1, 2), _cell(_values(fs, "floor_l1_region_mm"), 1, 2)]
        lines.append("| *floor* | " + " | ".join(cells) + " |")

    lines += ["", "Held-out L1 height error, mean per pixel over the whole 128×128 heightmap (mm), mean ± std over seeds",
              "(not the paper's L1 column: see docs/dynamics.md).", ""]
    lines += _header("model", tasks)
    for model in models:
        lines.append(f"| {model} | " + " | ".join(_cell(_values(groups.get((model, t), []), "l1_mm"), 1, 2) for t in tasks) + " |")
    lines.append("| *floor (no change)* | " + " | ".join(_cell(_values(floors[t], "floor_l1_mm"), 1, 2) for t in tasks) + " |")
    presets = sorted({str(r.get("preset", "?")) for r in runs})
    lines += ["", f"Runs: {len(runs)}; model presets: {', '.join(presets)}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(prog="python -m ldm_rl.reports.aggregate_table1", description=__doc__.splitlines()[0])
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
