"""Speed, expert success and memory of the pick-and-place tasks.

    python benchmarks/bench_envs.py --episodes 100          # the acceptance measurement
    python benchmarks/bench_envs.py --episodes 5 --resets 100 --cases stack3 house

Per case: mean CPU ms (``time.process_time``) per reset / pick / place with expert actions,
noiseless expert success over K seeded episodes (seeds 0..K-1), and the success under the
default demo noise (conf/demos/default.yaml); then the deconstruct-and-replay procedure's success
(stacking, house) and the process RSS before/after N resets.

With ``--anchor PATH`` (a BulletArm checkout, github.com/ColinKohler/BulletArm, with its requirements
importable, e.g. scikit-image) the anchor's reset / pick / place CPU ms and expert success are measured in
the same run, same protocol, by ``benchmarks/anchor_envs.py`` in a child process, and printed beside ours;
without it the anchor columns read "not measured in this run".

    python benchmarks/bench_envs.py --episodes 10 --cases stack3 house --anchor ~/src/BulletArm
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/anchor_envs.py

from anchor_envs import check_checkout  # noqa: E402

CASES = {
    "stack3": ("ldm_rl/BlockStacking-v0", 3),
    "stack4": ("ldm_rl/BlockStacking-v0", 4),
    "stack5": ("ldm_rl/BlockStacking-v0", 5),
    "house": ("ldm_rl/HouseBuilding-v0", 3),
    "bottles4": ("ldm_rl/BottleArrangement-v0", 4),
    "bottles5": ("ldm_rl/BottleArrangement-v0", 5),
    "bottles6": ("ldm_rl/BottleArrangement-v0", 6),
    "bins8": ("ldm_rl/BinPacking-v0", 8),
}
DEFAULT_NOISE = {"position": 0.01, "random_action_prob": 0.05}


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def run_case(env_id: str, num_objects: int, episodes: int, noise: dict | None):
    """(success rate, reset ms, pick ms, place ms, mean steps) over seeded expert episodes."""
    import gymnasium as gym

    import ldm_rl.envs  # noqa: F401

    env = gym.make(env_id, num_objects=num_objects, expert_noise=noise).unwrapped
    env.reset(seed=10_000)
    env.step(env.expert_action())  # warm-up (lazy imports, first render)
    times = {"reset": [], "pick": [], "place": []}
    successes, lengths = 0, []
    for seed in range(episodes):
        t = time.process_time()
        env.reset(seed=seed)
        times["reset"].append(time.process_time() - t)
        for step in range(env.max_steps):
            action = env.expert_action()
            t = time.process_time()
            _, _, terminated, truncated, info = env.step(action)
            times[info["primitive"]].append(time.process_time() - t)
            if terminated or truncated:
                break
        successes += info["is_success"]
        lengths.append(step + 1)
    env.close()
    ms = {k: 1000 * float(np.mean(v)) if v else float("nan") for k, v in times.items()}
    return successes / episodes, ms, float(np.mean(lengths))


def run_anchor(path: Path, case: str, episodes: int) -> tuple[str, str]:
    """(anchor 'reset / pick / place' ms, anchor expert success) measured now in a child process,
    or ('not measured in this run: <reason>', '-') if the anchor fails there."""
    script = Path(__file__).resolve().parent / "anchor_envs.py"
    result = subprocess.run([sys.executable, str(script), str(path), case, "--episodes", str(episodes)],
                            capture_output=True, text=True)
    lines = result.stdout.strip().splitlines()
    if result.returncode != 0 or not lines:
        reason = (result.stderr.strip().splitlines() or [f"exit status {result.returncode}"])[-1]
        return f"not measured in this run: {reason}", "-"
    m = json.loads(lines[-1])
    return f"{m['reset_ms']:.1f} / {m['pick_ms']:.1f} / {m['place_ms']:.1f}", f"{m['success']:.1%}"


def deconstruct_rate(env_id: str, num_objects: int, episodes: int) -> tuple[float, int]:
    """(success rate of the replayed episodes, number of discarded deconstructions)."""
    import gymnasium as gym

    from ldm_rl.envs.episodes import run_deconstruct_episode

    env = gym.make(env_id, num_objects=num_objects).unwrapped
    results = [run_deconstruct_episode(env, seed) for seed in range(episodes)]
    env.close()
    kept = [ep for ep in results if ep is not None]
    rate = float(np.mean([ep[-1].terminated and ep[-1].reward > 0 for ep in kept])) if kept else float("nan")
    return rate, len(results) - len(kept)


def memory_over_resets(resets: int) -> tuple[float, float]:
    import gymnasium as gym

    import ldm_rl.envs  # noqa: F401

    env = gym.make("ldm_rl/BlockStacking-v0").unwrapped
    for seed in range(20):
        env.reset(seed=seed)
    before = rss_mb()
    for seed in range(resets):
        env.reset(seed=seed)
        if seed % 10 == 0:
            env.step(env.expert_action())
    after = rss_mb()
    env.close()
    return before, after


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=10, help="seeded episodes per case (acceptance: 100)")
    parser.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES))
    parser.add_argument("--resets", type=int, default=1000, help="resets for the memory check (0 skips it)")
    parser.add_argument("--no-noise", action="store_true", help="skip the noisy-expert runs")
    parser.add_argument("--anchor", metavar="PATH", help="BulletArm checkout: measure the anchor in this run too")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    anchor = None
    if args.anchor:
        try:
            anchor = check_checkout(args.anchor)
        except ValueError as err:
            parser.error(str(err))

    import torch

    torch.set_num_threads(1)
    if anchor is None:
        print("anchor (BulletArm): not measured in this run (pass --anchor PATH to a BulletArm checkout)\n")
    else:
        print(f"anchor (BulletArm) measured in this run from {anchor}, same protocol, its own seed-0 RNG\n")
    header = (f"| case | reset ms | pick ms | place ms | expert success (K={args.episodes}) | steps "
              f"| success, default noise | anchor reset / pick / place ms | anchor expert success |")
    print(header)
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.cases:
        env_id, n = CASES[name]
        rate, ms, steps = run_case(env_id, n, args.episodes, None)
        noisy = "-" if args.no_noise else f"{run_case(env_id, n, args.episodes, DEFAULT_NOISE)[0]:.1%}"
        if anchor is None:
            anchor_ms, anchor_rate = "not measured in this run", "-"
        else:
            anchor_ms, anchor_rate = run_anchor(anchor, name, args.episodes)
        print(f"| {name} | {ms['reset']:.1f} | {ms['pick']:.1f} | {ms['place']:.1f} | {rate:.1%} | {steps:.1f} "
              f"| {noisy} | {anchor_ms} | {anchor_rate} |", flush=True)
    deconstructable = [c for c in args.cases if c.startswith(("stack", "house"))]
    if deconstructable:
        print(f"\n| case | deconstruct + reversed replay success (K={args.episodes}) | discarded |\n|---|---|---|")
        for name in deconstructable:
            rate, discarded = deconstruct_rate(*CASES[name], args.episodes)
            print(f"| {name} | {rate:.1%} | {discarded} |", flush=True)
    if args.resets:
        before, after = memory_over_resets(args.resets)
        print(f"\nRSS over {args.resets} block-stacking resets: {before:.1f} MB -> {after:.1f} MB "
              f"({after - before:+.1f} MB)")


if __name__ == "__main__":
    main()
