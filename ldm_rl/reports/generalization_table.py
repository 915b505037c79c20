"""Zero-shot generalization table (the paper's Table 2) from trained agents' checkpoints.

    python -m ldm_rl.reports.generalization_table multirun/<date>/<time> [more folders or checkpoint.pt files]
                                           [--episodes 100] [--seed 0] [--out DIR]

Each checkpoint given (a ``checkpoint.pt``, or every one below a folder) of an agent trained on 3-block
stacking or 4-bottle arrangement is played greedily on the larger object counts of its task's preset
(``conf/experiment/generalization_<task>.yaml``: 4 and 5 blocks, 5 and 6 bottles) by ``recipes/evaluate.py``
with that preset, one ``evaluate.py -m`` process per checkpoint, into
``DIR/evaluations/<agent>-seed<seed>-<id>/objects-<n>/evaluation.json``. Evaluations already written (there,
or any ``evaluation.json`` below the given folders, e.g. an ``evaluate.py -m`` sweep) are read instead, unless
their episode count differs from ``--episodes`` or the checkpoint is newer. Every agent plays the same scenes
(evaluate.py's ``seed``). Writes ``DIR/generalization.md`` (default ``DIR``: ``<first folder>/generalization``):
the success rate (%) with its 95 % Wilson interval per agent and object count, pooled over the agent's
checkpoints, beside the paper's Table 2 number; then one row per checkpoint and object count.

A folder may also be a results folder (``docs/results/policy``): the zero-shot evaluations kept there as
``curves_<task>_<agent>_seed<k>[_<tag>]_generalization.json`` (``{"final_n<objects>": <evaluation.json>, ...}``)
are read as they are, and each tag is a row of its own (``LDM [mix23]``), so the table is rebuilt from the
repository's files without checkpoints or runs.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # the repository (conf/, recipes/)
from ldm_rl.evaluation import wilson_interval
from ldm_rl.reports import kept_file
from ldm_rl.run.outputs import atomic_write_text

EVALUATE = ROOT / "recipes" / "evaluate.py"
# the paper's protocol: the object count each task's agent is trained on (its zero-shot counts are in the preset)
TRAINED_ON = {"block_stacking": 3, "bottle_arrangement": 4}
UNITS = {"block_stacking": "blocks", "bottle_arrangement": "bottles"}
AGENTS = {"ldm": "LDM", "fcdqn": "FC-DQN", "rs": "RS", "dynaq": "Dyna-Q"}
TABLE_AGENTS = ("ldm", "fcdqn", "rs")  # the paper's rows
# the paper's Table 2 (success %, 100 episodes), by agent and (task, objects); the paper has no Dyna-Q row (n/a)
PAPER = {"ldm": {("block_stacking", 4): 99, ("block_stacking", 5): 84,
                 ("bottle_arrangement", 5): 86, ("bottle_arrangement", 6): 65},
         "fcdqn": {("block_stacking", 4): 98, ("block_stacking", 5): 89,
                   ("bottle_arrangement", 5): 82, ("bottle_arrangement", 6): 48},
         "rs": {("block_stacking", 4): 48, ("block_stacking", 5): 23,
                ("bottle_arrangement", 5): 8, ("bottle_arrangement", 6): 4}}


@dataclass(frozen=True)
class Protocol:
    """One task of the table: its preset, env id, training count and zero-shot counts."""

    task: str  # conf/env/<task>.yaml
    env_id: str
    trained_on: int
    counts: tuple[int, ...]

    @property
    def preset(self) -> str:
        return f"generalization_{self.task}"


@dataclass
class Evaluation:
    """One evaluation.json of recipes/evaluate.py (and the checkpoint's seed when the checkpoint is at hand)."""

    path: Path
    checkpoint: str
    agent: str
    task: str  # env id
    trained_on: int
    num_objects: int
    episodes: int
    successes: int
    mean_length: float
    seed: int | None
    tag: str | None = None  # a kept evaluation's tag: its row of the table (None: the agent's row)

    @property
    def row(self) -> str:
        name = AGENTS.get(self.agent, self.agent)
        return name if self.tag is None else f"{name} [{self.tag}]"


# a kept zero-shot result in a results folder
KEPT = kept_file("generalization.json")


def read_kept(path: Path) -> list[Evaluation]:
    """The evaluations of a kept ``curves_..._<tag>_generalization.json`` (seed and tag from its name)."""
    match = KEPT.fullmatch(path.name)
    try:
        entries = json.loads(path.read_text())
        out = []
        for key, data in entries.items():
            if not re.fullmatch(r"final_n\d+", key):
                raise ValueError(f"entry {key!r} (expected final_n<objects>)")
            out.append(Evaluation(path, str(data["checkpoint"]), data["agent"], data["task"], int(data["trained_on"]),
                                  int(data["num_objects"]), int(data["episodes"]), int(data["successes"]),
                                  float(data["mean_length"]), int(match.group("seed")), match.group("tag")))
    except (ValueError, KeyError, TypeError, AttributeError) as err:
        raise ValueError(f"{path}: not a kept zero-shot result ({type(err).__name__}: {err})") from None
    return out


def protocols(conf: Path = ROOT / "conf") -> dict[str, Protocol]:
    """env id -> :class:`Protocol`, from ``conf/experiment/generalization_<task>.yaml`` (its swept
    ``num_objects``) and ``conf/env/<task>.yaml`` (its id)."""
    from omegaconf import OmegaConf

    out = {}
    for task, trained in TRAINED_ON.items():
        preset = OmegaConf.load(conf / "experiment" / f"generalization_{task}.yaml")
        counts = tuple(int(c) for c in str(preset.hydra.sweeper.params.num_objects).split(","))
        env_id = str(OmegaConf.load(conf / "env" / f"{task}.yaml").id)
        out[env_id] = Protocol(task, env_id, trained, counts)
    return out


def _quote(value: str) -> str:
    """A Hydra override value: as is when plain, else single-quoted with escapes."""
    if re.fullmatch(r"[\w./:+-]+", value):
        return value
    return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"


def _uses_plus(conf: Path = ROOT / "conf") -> bool:
    """Whether conf/evaluate.yaml lacks an ``experiment`` default (then the preset is added with ``+experiment=``)."""
    from omegaconf import OmegaConf

    defaults = OmegaConf.to_container(OmegaConf.load(conf / "evaluate.yaml")).get("defaults", [])
    return not any(isinstance(d, dict) and "experiment" in d for d in defaults)


def find_inputs(paths: list[Path]) -> tuple[list[Path], list[Path], list[Path], list[Path]]:
    """(checkpoints given as files, checkpoints found below folders, evaluation.json files below folders, kept
    zero-shot results in the folders)."""
    files, found, evaluations, kept = [], [], [], []
    for path in paths:
        if path.is_file():
            if path.suffix != ".pt":
                raise ValueError(f"{path}: expected a checkpoint.pt of recipes/train_policy.py or a folder")
            files.append(path.resolve())
        elif path.is_dir():
            found += [p.resolve() for p in sorted(path.rglob("checkpoint.pt"))]
            evaluations += [p.resolve() for p in sorted(path.rglob("evaluation.json"))]
            kept += [p.resolve() for p in sorted(path.glob("curves_*_generalization.json")) if KEPT.fullmatch(p.name)]
        else:
            raise ValueError(f"{path}: no such file or folder")
    return files, sorted(set(found) - set(files)), sorted(set(evaluations)), sorted(set(kept))


def checkpoint_info(path: Path) -> dict:
    """agent, task (env id), trained object count and seed of an agent checkpoint (its meta; no torch)."""
    from ldm_rl.run.checkpoint import read_checkpoint_meta

    meta = read_checkpoint_meta(path)
    if meta.get("kind") != "agent":
        raise ValueError(f"{path}: a {meta.get('kind')!r} checkpoint, expected an agent's (recipes/train_policy.py)")
    cfg = meta["config"]
    return {"agent": meta["agent"], "task": meta["task"], "trained_on": int(cfg["env"]["num_objects"]),
            "seed": int(cfg["seed"])}


def read_evaluation(path: Path) -> Evaluation:
    """An ``evaluation.json`` of recipes/evaluate.py; the seed comes from its checkpoint when that is at hand."""
    try:
        data = json.loads(path.read_text())
        checkpoint = Path(data["checkpoint"])
        fields = (data["agent"], data["task"], int(data["trained_on"]), int(data["num_objects"]), int(data["episodes"]),
                  int(data["successes"]), float(data["mean_length"]))
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not an evaluation.json of recipes/evaluate.py ({type(err).__name__}: {err})") from None
    seed = None
    if checkpoint.is_file():
        try:
            seed = checkpoint_info(checkpoint)["seed"]
        except (ValueError, KeyError, OSError):  # a checkpoint since replaced by something unreadable: the result stands
            seed = None
    return Evaluation(path, str(checkpoint.resolve()), *fields, seed)


def evaluate_checkpoint(checkpoint: Path, info: dict, protocol: Protocol, counts: list[int], *, episodes: int, seed: int,
                        out: Path) -> None:
    """``recipes/evaluate.py -m experiment=<preset> checkpoint=... num_objects=<counts>`` into ``out``."""
    plus = "+" if _uses_plus() else ""
    command = [sys.executable, str(EVALUATE), "-m", f"{plus}experiment={protocol.preset}",
               f"checkpoint={_quote(str(checkpoint))}", f"num_objects={','.join(map(str, counts))}",
               f"episodes={episodes}", f"seed={seed}", f"hydra.sweep.dir={_quote(str(out))}",
               "hydra.sweep.subdir=objects-${num_objects}"]
    print(f"evaluating {info['agent']} (seed {info['seed']}) on {', '.join(map(str, counts))} "
          f"{UNITS[protocol.task]}, {episodes} episodes each: {checkpoint}", flush=True)
    done = subprocess.run(command)
    if done.returncode != 0:
        raise RuntimeError(f"recipes/evaluate.py stopped with exit code {done.returncode} on {checkpoint} (its message "
                           "is above)")


def _run_id(checkpoint: Path, info: dict) -> str:
    return f"{info['agent']}-seed{info['seed']}-{hashlib.sha1(str(checkpoint).encode()).hexdigest()[:8]}"


def gather(paths: list[Path], out: Path, *, episodes: int, seed: int,
           agents: tuple[str, ...] = TABLE_AGENTS) -> tuple[list[Evaluation], list[str]]:
    """Every evaluation of the table: read where written and fresh, run (recipes/evaluate.py) where not.
    Returns the evaluations (one per checkpoint and object count) and notes on what was left out."""
    table = protocols()
    files, found, json_files, kept = find_inputs(paths)
    json_files = sorted(set(json_files) | {p.resolve() for p in (out / "evaluations").rglob("evaluation.json")})
    notes: list[str] = []
    written: dict[tuple[str, int], Evaluation] = {}
    # per checkpoint and object count: one with the asked episode count if there is one, else the newest
    for ev in sorted(map(read_evaluation, json_files), key=lambda e: (e.episodes == episodes, e.path.stat().st_mtime)):
        written[(ev.checkpoint, ev.num_objects)] = ev
    for checkpoint in files + found:
        try:
            info = checkpoint_info(checkpoint)
        except ValueError as err:  # e.g. a recipes/train_dynamics.py checkpoint in the same folder
            if checkpoint in files:
                raise
            notes.append(f"skipped {err}")
            continue
        protocol = table.get(info["task"])
        message = None
        if protocol is None or info["trained_on"] != protocol.trained_on:
            expected = " or ".join(f"{p.env_id} with {p.trained_on} objects" for p in table.values())
            message = (f"{checkpoint}: a {info['agent']} agent trained on {info['task']} with {info['trained_on']} objects; "
                       f"the table takes agents trained on {expected}")
        elif info["agent"] not in agents:
            message = f"{checkpoint}: agent {info['agent']} is not one of --agents {','.join(agents)}"
        if message is not None:
            if checkpoint in files:
                raise ValueError(message)
            notes.append(f"skipped {message}")
            continue

        def fresh(n: int) -> bool:
            ev = written.get((str(checkpoint), n))
            return ev is not None and ev.episodes == episodes and ev.path.stat().st_mtime >= checkpoint.stat().st_mtime

        missing = [n for n in protocol.counts if not fresh(n)]
        if missing:
            target = out / "evaluations" / _run_id(checkpoint, info)
            evaluate_checkpoint(checkpoint, info, protocol, missing, episodes=episodes, seed=seed, out=target)
            for n in missing:
                written[(str(checkpoint), n)] = read_evaluation(target / f"objects-{n}" / "evaluation.json")
    evaluations = []
    kept_evaluations = [ev for path in kept for ev in read_kept(path)]
    for (_, n), ev in sorted(written.items()) + [((ev.checkpoint, ev.num_objects), ev) for ev in kept_evaluations]:
        protocol = table.get(ev.task)
        if protocol is None or ev.trained_on != protocol.trained_on or n not in protocol.counts:
            notes.append(f"left out {ev.path}: {ev.agent} trained on {ev.trained_on}, evaluated on {n} objects of {ev.task} "
                         "(not a column of the table)")
            continue
        if ev.agent not in agents:
            notes.append(f"left out {ev.path}: agent {ev.agent} is not one of --agents {','.join(agents)}")
            continue
        evaluations.append(ev)
    return evaluations, notes


def _pct(x: float) -> str:
    return f"{100 * x:.1f}"


def markdown(evaluations: list[Evaluation], notes: list[str] | None = None,
             agents: tuple[str, ...] = TABLE_AGENTS) -> str:
    """The table (agents x zero-shot counts, ours beside the paper's) and the per-checkpoint rows."""
    table = protocols()
    columns = [(p, n) for p in table.values() for n in p.counts]
    pooled: dict[tuple[str, str, int], list[Evaluation]] = defaultdict(list)
    for ev in evaluations:
        pooled[(ev.row, ev.task, ev.num_objects)].append(ev)
    # one row per agent (and per tag of the kept results): the paper's agents first, each agent's rows together
    rows = {AGENTS[a]: a for a in agents if not any(ev.agent == a and ev.tag is not None for ev in evaluations)}
    rows.update({ev.row: ev.agent for ev in evaluations})
    order = list(AGENTS)
    rows = dict(sorted(rows.items(), key=lambda item: (order.index(item[1]), item[0])))
    trained = ", ".join(f"{p.trained_on} {UNITS[p.task]} for {p.task.replace('_', ' ')}" for p in table.values())
    lines = ["Zero-shot generalization (the paper's Table 2): greedy success rate (%) on more objects than in training "
             f"(trained on {trained}), with its 95 % Wilson interval in brackets, pooled over each agent's checkpoints "
             "(k checkpoints, n episodes in all); the paper's number (100 episodes) beside it.", ""]
    header = ["agent"] + [h for p, n in columns for h in (f"{n} {UNITS[p.task]}", "paper")]
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row, agent in rows.items():
        cells = [row]
        for protocol, n in columns:
            group = pooled.get((row, protocol.env_id, n), [])
            if group:
                successes, episodes = sum(ev.successes for ev in group), sum(ev.episodes for ev in group)
                low, high = wilson_interval(successes, episodes)
                cells.append(f"{_pct(successes / episodes)} [{_pct(low)}–{_pct(high)}] (k={len(group)}, n={episodes})")
            else:
                cells.append("–")
            paper = PAPER.get(agent, {}).get((protocol.task, n))
            cells.append("n/a" if paper is None else str(paper))
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "–: not evaluated here. n/a: no paper number to compare with (the paper's table has no Dyna-Q row).",
              "", "Per checkpoint:", "",
              "| agent | seed | task | trained on | evaluated on | success (%) | 95 % interval (%) | episodes | mean length "
              "(primitives) | checkpoint |", "|---|---|---|---|---|---|---|---|---|---|"]
    for ev in sorted(evaluations, key=lambda e: (e.task, list(AGENTS).index(e.agent) if e.agent in AGENTS else 9,
                                                 e.row, e.seed if e.seed is not None else -1, e.checkpoint, e.num_objects)):
        low, high = wilson_interval(ev.successes, ev.episodes)
        seed = "?" if ev.seed is None else str(ev.seed)
        lines.append(f"| {ev.row} | {seed} | {ev.task} | {ev.trained_on} | {ev.num_objects} | "
                     f"{_pct(ev.successes / ev.episodes)} | {_pct(low)}–{_pct(high)} | {ev.episodes} | "
                     f"{ev.mean_length:.2f} | {ev.checkpoint} |")
    if notes:
        lines += ["", *[f"Note: {note}." for note in notes]]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(prog="python -m ldm_rl.reports.generalization_table", description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", type=Path,
                        help="train_policy.py run or sweep folders, checkpoint.pt files, or folders of evaluation.json")
    parser.add_argument("--episodes", type=int, default=100, help="greedy episodes per checkpoint and object count")
    parser.add_argument("--seed", type=int, default=0, help="evaluate.py's seed (the same scenes for every agent)")
    parser.add_argument("--agents", default=",".join(TABLE_AGENTS),
                        help=f"comma-separated agents to evaluate and tabulate (default: the paper's rows; of {','.join(AGENTS)})")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default <first folder>/generalization)")
    args = parser.parse_args(argv)
    agents = tuple(a.strip() for a in args.agents.split(",") if a.strip())
    unknown = [a for a in agents if a not in AGENTS]
    if unknown or not agents:
        parser.error(f"--agents {args.agents}: expected a comma-separated subset of {','.join(AGENTS)}")
    if args.episodes < 1:
        parser.error(f"--episodes {args.episodes}: expected a positive number of episodes")
    if args.seed < 0:
        parser.error(f"--seed {args.seed}: expected a seed >= 0")
    first = args.paths[0]
    out = (args.out or (first if first.is_dir() else first.parent) / "generalization").resolve()
    try:
        evaluations, notes = gather(args.paths, out, episodes=args.episodes, seed=args.seed, agents=agents)
    except (ValueError, RuntimeError) as err:
        parser.exit(2, f"error: {err}\n")
    if not evaluations:
        parser.exit(2, f"error: no checkpoint or evaluation.json of a {args.agents} agent trained on 3 blocks or 4 "
                       f"bottles under {', '.join(str(p) for p in args.paths)}\n")
    text = markdown(evaluations, notes, agents)
    atomic_write_text(out / "generalization.md", text)
    print(text)
    print(f"written to {out / 'generalization.md'}")
    return text


if __name__ == "__main__":
    main()
