"""How squarely a block-stacking policy sets each cube on the one below, and what the offsets do to a tall tower.

    python benchmarks/tower_offsets.py <run>/checkpoint.pt [--objects 4] [--episodes 100] [--planner q_blend=0.25 ...]

Plays a block-stacking checkpoint's greedy policy on the held-out scenes of ``recipes/evaluate.py`` (``--seed``,
``--objects`` cubes, its step limit 2·N + 4), then the scripted expert on the same scenes. After every place that
leaves the cube on another, the tower under it is read from the simulator: the cube's horizontal offset from the cube
below (mm; a cube is 40 mm wide, so a single level tips past 20 mm) and, once the tower is three cubes or more, how
far the centre of mass of everything above the bottom cube stands from that cube's centre (mm: past 20 mm the tower
tips over its base's edge). Reported per player: the places' offsets (median, mean, the share at 15 mm or more), the
upper part's offset over the base at the tallest tower each episode reached, split by episodes that succeeded and
those that failed. A measurement of decisions, not of time; run by hand (docs/policy.md, "Why seed 0 falls short on
four blocks").
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/place_outcomes.py
from place_outcomes import key_values, recorder  # noqa: E402

CUBE = 0.04  # m: the stacking cubes' side
LEVEL_SLACK = 0.015  # m: a cube rests on another when its centre is one side higher, within this


def tower_below(positions: np.ndarray, top: int, side: float = CUBE) -> list[int]:
    """The chain of cubes under cube ``top``, bottom first and ``top`` last: each one's centre one ``side`` (±
    ``LEVEL_SLACK``) above the next one down and less than ``side`` away from it horizontally (the nearest such).
    ``positions``: ``[N, 3]`` cube centres, metres."""
    positions = np.asarray(positions, dtype=np.float64)
    chain = [int(top)]
    while True:
        upper = positions[chain[-1]]
        rise = upper[2] - positions[:, 2]
        apart = np.hypot(*(positions[:, :2] - upper[:2]).T)
        below = (np.abs(rise - side) < LEVEL_SLACK) & (apart < side)
        below[chain] = False
        if not below.any():
            return chain[::-1]
        chain.append(int(np.flatnonzero(below)[np.argmin(apart[below])]))


def level_offsets(positions: np.ndarray, chain: list[int]) -> np.ndarray:
    """``[len(chain) - 1]`` metres: each cube's horizontal offset from the one below it in ``chain`` (bottom first)."""
    xy = np.asarray(positions, dtype=np.float64)[chain, :2]
    return np.hypot(*(xy[1:] - xy[:-1]).T)


def upper_centre_offset(positions: np.ndarray, chain: list[int]) -> float:
    """Metres: the horizontal distance from the bottom cube's centre to the centre of mass of the cubes above it
    (equal masses); 0 for a single cube."""
    xy = np.asarray(positions, dtype=np.float64)[chain, :2]
    return float(np.hypot(*(xy[1:].mean(0) - xy[0]))) if len(chain) > 1 else 0.0


def place_rows(snapshots: list[dict]) -> list[dict]:
    """One row per place that leaves its cube on another, from per-decision ``snapshots`` (``held``: the index of
    the held cube or None; ``positions``: ``[N, 3]``; plus the one after the last decision): the tower's height under
    it, the cube's offset from the cube below and the upper part's offset over the base (metres)."""
    rows = []
    for before, after in zip(snapshots[:-1], snapshots[1:]):
        cube = before["held"]
        if cube is None or after["held"] is not None:
            continue
        chain = tower_below(after["positions"], cube)
        if len(chain) < 2:
            continue
        rows.append({"height": len(chain), "offset": float(level_offsets(after["positions"], chain)[-1]),
                     "upper": upper_centre_offset(after["positions"], chain)})
    return rows


def snapshot(task) -> dict:
    """The held cube's index among the task's objects (or None) and every cube's centre, ``[N, 3]`` metres."""
    bodies = [obj.body for obj in task.sim.objects]
    held = task.gripper.held
    return {"held": None if held is None else bodies.index(held.body), "positions": task.sim.positions()}


def play(env, task, policy, episodes: int, seed: int) -> list[dict]:
    """Greedy episodes on the held-out scenes of ``seed``: per episode its success and place rows."""
    from ldm_rl.evaluation import episode_succeeded, evaluate_policy
    from ldm_rl.seeds import held_out_scenes

    module, played = recorder(policy, lambda step: snapshot(task)), []

    def record(index, rollout):
        played.append({"success": bool(episode_succeeded(rollout)),
                       "places": place_rows(module.snapshots + [snapshot(task)])})
        module.snapshots = []

    evaluate_policy(env, module, episodes, seed=held_out_scenes(seed), on_episode=record)
    return played


def summary(name: str, played: list[dict]) -> str:
    """One markdown row: successes, the places' offsets from the cube below (mm) and the upper part's offset over
    the base at each episode's tallest tower of three or more, in successes and failures (median, mm)."""
    offsets = 1000 * np.array([p["offset"] for e in played for p in e["places"]])

    def tallest_upper(success: bool) -> str:
        values = [1000 * max(e["places"], key=lambda p: (p["height"], -p["upper"]))["upper"] for e in played
                  if e["success"] == success and e["places"] and max(p["height"] for p in e["places"]) >= 3]
        return f"{np.median(values):.0f} ({len(values)})" if values else "-"

    wins = sum(e["success"] for e in played)
    stats = (f"{np.median(offsets):.0f} / {np.mean(offsets):.1f} | {100 * np.mean(offsets >= 15):.0f} %"
             if len(offsets) else "- | -")
    return (f"| {name} | {wins} / {len(played)} | {len(offsets)} | {stats} | {tallest_upper(True)} "
            f"| {tallest_upper(False)} |")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", help="a block-stacking run's checkpoint.pt (or best_policy.pt)")
    parser.add_argument("--objects", type=int, default=None, help="cubes per scene (default: the checkpoint's)")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0, help="the held-out scenes of recipes/evaluate.py seed=...")
    parser.add_argument("--planner", nargs="*", default=[], metavar="KEY=VALUE",
                        help="greedy planner settings over the checkpoint's (as recipes/evaluate.py planner.KEY=VALUE)")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if args.objects is not None and args.objects < 2:
        parser.error(f"--objects must be >= 2 (a tower), got {args.objects}")
    args.planner = key_values(parser, "--planner", args.planner)
    return args


def greedy_settings(settings: dict) -> dict:
    """recipes/evaluate.py's reading of planner overrides: λ and Q's vote set the greedy decisions' own keys too."""
    out = dict(settings)
    for key, greedy in (("uncertainty_penalty", "greedy_uncertainty_penalty"), ("q_blend", "greedy_q_blend")):
        if key in out:
            out[greedy] = out[key]
    return out


def main(argv=None) -> None:
    args = parse_args(argv)
    from ldm_rl.agents import load_agent
    from ldm_rl.envs import expert_policy, make_env_from_config
    from ldm_rl.envs.torchrl_env import unwrap
    from ldm_rl.run.checkpoint import CheckpointError
    from ldm_rl.torch_utils import seed_everything, set_threads

    set_threads(1)
    seed_everything(args.seed)
    try:
        agent, cfg = load_agent(args.checkpoint, planner=greedy_settings(args.planner) or None)
    except (CheckpointError, ValueError) as err:
        sys.exit(f"error: {err}")
    if "BlockStacking" not in cfg["env"]["id"]:
        sys.exit(f"error: {args.checkpoint} plays {cfg['env']['id']}, not block stacking")
    env_cfg = dict(cfg["env"])
    if args.objects is not None:
        env_cfg.update(num_objects=args.objects, max_steps=None)  # 2·N + 4, as recipes/evaluate.py
    env = make_env_from_config(env_cfg)
    task = unwrap(env)
    with torch.no_grad():
        agent_played = play(env, task, agent.evaluation_policy(), args.episodes, args.seed)
        expert_played = play(env, task, expert_policy(env), args.episodes, args.seed)
    print(f"{args.checkpoint}, {task.num_objects} cubes, {args.episodes} held-out scenes (seed {args.seed})"
          + (f", planner {args.planner}" if args.planner else ""))
    print("| who | stacked | places onto a cube | offset from the cube below, median / mean (mm) | at 15 mm or more "
          "| the upper part over the base, tallest tower, successes: median mm (episodes) | failures |")
    print("|---|---|---|---|---|---|---|")
    print(summary(f"{agent.name} agent", agent_played))
    print(summary("scripted expert", expert_played))


if __name__ == "__main__":
    main()
