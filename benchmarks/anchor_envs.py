"""Time the anchor's (BulletArm) pick-and-place envs with the protocol of ``bench_envs.py``.

    python benchmarks/anchor_envs.py PATH stack3 --episodes 10      # one JSON line

PATH is a BulletArm checkout (the folder holding ``bulletarm/``, github.com/ColinKohler/BulletArm) whose
requirements (pybullet, scipy, scikit-image, opencv-python) are importable. Used only by
``benchmarks/bench_envs.py --anchor PATH``, which runs it in a child process; the ``ldm_rl`` package never
imports it and no anchor code is copied here: the env is built through BulletArm's own
``env_factory.createEnvs`` and driven by its own planner (``getNextAction``).

Settings are the paper's (``fast_mode``, ``physics_mode='slow'``, kuka, 128 px heightmap, 24 px in-hand,
``pxyr`` actions, object scale 0.8, 0.75 for bin packing) with ours' episode budget ``2·N + 4`` steps.
Protocol as ours: one reset + one expert step of warm-up, then K episodes; CPU time
(``time.process_time``) per reset and per step, the step counted as a pick or a place by the planner's
primitive (0 = pick, 1 = place); success = an episode ending with reward > 0. Unlike ours (seeds 0..K−1),
BulletArm seeds its RNG once at creation (seed 0) and draws every episode from it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

# case -> (BulletArm env type, number of objects, object scale, extra config)
ANCHOR_CASES = {
    "stack3": ("block_stacking", 3, 0.8, {}),
    "stack4": ("block_stacking", 4, 0.8, {}),
    "stack5": ("block_stacking", 5, 0.8, {}),
    "house": ("house_building_2", 3, 0.8, {}),
    "bottles4": ("bottle_tray", 4, 0.8, {"kuka_adjust_gripper_offset": 0.0025}),
    "bottles5": ("bottle_tray", 5, 0.8, {"kuka_adjust_gripper_offset": 0.0025}),
    "bottles6": ("bottle_tray", 6, 0.8, {"kuka_adjust_gripper_offset": 0.0025}),
    "bins8": ("block_bin_packing", 8, 0.75, {}),
}


def check_checkout(path: str) -> Path:
    """The checkout folder, or ValueError naming what is missing."""
    root = Path(path).expanduser().resolve()
    if not (root / "bulletarm" / "env_factory.py").is_file():
        raise ValueError(f"the anchor path must be a BulletArm checkout holding bulletarm/env_factory.py, got {path!r}")
    return root


def run_anchor_case(root: Path, case: str, episodes: int) -> dict:
    """{'success', 'reset_ms', 'pick_ms', 'place_ms', 'steps'} of the anchor's expert on ``case``."""
    sys.path.insert(0, str(root))
    from bulletarm import env_factory  # noqa: PLC0415  (the anchor, from PATH)

    env_type, n, scale, extra = ANCHOR_CASES[case]
    config = {
        "workspace": np.asarray([[0.2, 0.6], [-0.2, 0.2], [0, 1]]), "max_steps": 2 * n + 4, "obs_size": 128,
        "in_hand_size": 24, "action_sequence": "pxyr", "fast_mode": True, "physics_mode": "slow", "robot": "kuka",
        "num_objects": n, "object_scale_range": (scale, scale), "render": False, "random_orientation": True,
        "seed": 0, **extra,
    }
    env = env_factory.createEnvs(0, env_type, config, {"random_orientation": True})
    env.reset()
    env.step(env.getNextAction(), auto_reset=False)  # warm-up (imports, first render), not timed
    times = {"reset": [], "pick": [], "place": []}
    successes, lengths = 0, []
    for _ in range(episodes):
        t = time.process_time()
        env.reset()
        times["reset"].append(time.process_time() - t)
        reward, steps = 0.0, 0
        for steps in range(1, config["max_steps"] + 1):
            action = env.getNextAction()
            t = time.process_time()
            _, reward, done = env.step(action, auto_reset=False)
            times["pick" if int(round(float(action[0]))) == 0 else "place"].append(time.process_time() - t)
            if done:
                break
        successes += float(reward) > 0
        lengths.append(steps)
    env.close()
    ms = {f"{k}_ms": 1000 * float(np.mean(v)) if v else float("nan") for k, v in times.items()}
    return {"success": successes / episodes, **ms, "steps": float(np.mean(lengths))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", help="BulletArm checkout (folder holding bulletarm/)")
    parser.add_argument("case", choices=list(ANCHOR_CASES))
    parser.add_argument("--episodes", type=int, default=10)
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    try:
        root = check_checkout(args.path)
    except ValueError as err:
        parser.error(str(err))
    print(json.dumps(run_anchor_case(root, args.case, args.episodes)))


if __name__ == "__main__":
    main()
