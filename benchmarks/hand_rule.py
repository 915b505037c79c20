"""How well each hand-state rule reads holding' off depth frames: on the true frames (the rule's ceiling) and,
given checkpoints, on what their world models predict.

    python benchmarks/hand_rule.py                                   # every task, true frames, one table
    python benchmarks/hand_rule.py --tasks bin_packing --checkpoint bin_packing=<run>/checkpoint.pt

Data: per task, ``--episodes`` scripted-expert episodes with noise (``--position`` m of pick/place jitter,
``--random`` probability of a uniformly random action; seeded), so the picks include held ones and empty ones.
Only the picks are scored (a place always opens the hand in the env). Per rule: held picks read as empty
(misses) and empty picks read as held (false holds). Rules: the reference's ``occupancy`` and ``removal``
(``ldm_rl.world_model.HandStateRule``), on depth classes of the task's ``max_height`` and K = 21.
A measurement of accuracy, not of time; run by hand (docs/dynamics.md, "The hand-state rule").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from omegaconf import OmegaConf

from ldm_rl import geometry
from ldm_rl.data.demos import collect_demos
from ldm_rl.world_model import DynamicsModel, HandStateRule

ROOT = Path(__file__).resolve().parents[1]
TASKS = {"stack3": ("block_stacking", 3), "stack5": ("block_stacking", 5), "house": ("house_building", None),
         "bottles4": ("bottle_arrangement", 4), "bottles6": ("bottle_arrangement", 6), "bin_packing": ("bin_packing", None)}
RULES = {"occupancy": HandStateRule(), "removal": HandStateRule(kind="removal")}
NUM_CLASSES, CROP = 21, 64


def transitions(task: str, episodes: int, seed: int, position: float, random_prob: float):
    env_name, count = TASKS[task]
    cfg = OmegaConf.load(ROOT / "conf" / "env" / f"{env_name}.yaml")
    if count is not None:
        cfg.num_objects = count
    td = collect_demos(cfg, num_episodes=episodes, seed=seed, progress=False,
                       noise={"position": position, "random_action_prob": random_prob})
    picks = ~td["holding"].reshape(-1)
    return td[picks], float(cfg.max_height)


def true_frames(td, max_height: float):
    """[N, 1, 64, 64] uint8 classes of the true frames before and after, at each action (rotated)."""
    centers, angles = geometry.action_to_pose(td["action"], geometry.NUM_ROTATIONS)

    def frame(heights):
        classes = geometry.heights_to_classes(heights, max_height, NUM_CLASSES)
        return geometry.crop(classes, centers, angles, CROP, mode="nearest")

    return frame(td["heightmap"]), frame(td["next", "heightmap"])


def model_holding(checkpoint: str, td, rule: HandStateRule) -> torch.Tensor:
    from ldm_rl.agents import load_agent

    agent, _ = load_agent(checkpoint)
    # the world model the greedy decisions plan with: the averaged copy under agent.greedy_ema_decay, else the online one
    model = next(m for m in agent.greedy_policy.modules() if isinstance(m, DynamicsModel))
    model.hand_rule = rule
    out = []
    with torch.no_grad():
        for start in range(0, td.shape[0], 64):
            part = td[start:start + 64]
            out.append(model.predict(part["heightmap"], part["in_hand"], part["holding"], part["action"]).holding.reshape(-1))
    return torch.cat(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--position", type=float, default=0.01, help="m of expert jitter")
    parser.add_argument("--random", type=float, default=0.3, help="probability of a random action")
    parser.add_argument("--checkpoint", nargs="*", default=[], metavar="TASK=PATH",
                        help="also score this agent checkpoint's world model on TASK's transitions")
    args = parser.parse_args()
    torch.set_num_threads(1)
    checkpoints = dict(item.split("=", 1) for item in args.checkpoint)
    print(f"picks of {args.episodes} noisy expert episodes per task (jitter {args.position} m, random actions "
          f"{args.random:.0%}, seed {args.seed}); misses = held picks read as empty, false = empty picks read as held\n")
    print("| task | frames | held / empty picks | " + " | ".join(f"{name} misses / false" for name in RULES) + " |")
    print("|---|---|---|" + "---|" * len(RULES))
    for task in args.tasks:
        td, max_height = transitions(task, args.episodes, args.seed, args.position, args.random)
        held = td["next", "holding"].reshape(-1)
        before, after = true_frames(td, max_height)
        picking = torch.ones_like(held)
        rows = {"true": {name: rule(before, after, picking) for name, rule in RULES.items()}}
        if task in checkpoints:
            rows[f"predicted ({Path(checkpoints[task]).parent.name})"] = {
                name: model_holding(checkpoints[task], td, rule) for name, rule in RULES.items()}
        for source, reads in rows.items():
            cells = [f"{int((held & ~read).sum())} / {int((~held & read).sum())}" for read in reads.values()]
            print(f"| {task} | {source} | {int(held.sum())} / {int((~held).sum())} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
