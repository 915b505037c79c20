"""Whether a run's Q heads still have active hidden units, read on states of its replay (no env).

    python benchmarks/q_heads.py <run> [<checkpoint.pt> ...]      # default: the run's checkpoint.pt

The Q FCN's pick and place heads are a 3×3 conv to a few hidden units, a LeakyReLU and a 1×1 conv. The units see
non-negative features, so each is positive everywhere or almost nowhere; a head without an active unit outputs its
bias, a flat map that proposes wherever the argmax falls (docs/policy.md, "Q heads that go flat"). Prints, per
head, the share of pixels (over ``--states`` replay states of its primitive and every rotation) where each hidden
unit is positive, and the spread of the head's map over the pixels above ``--surface`` m (objects). A measurement
of a trained network, run by hand.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from tensordict import TensorDict

from ldm_rl import geometry


def replay_states(run: Path, holding: bool, count: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``count`` states of the newest replay of ``run`` with that hand state, evenly spread: heightmap
    ``[n, 1, 128, 128]`` m, in-hand ``[n, 1, 24, 24]`` m, holding ``[n, 1]`` bool."""
    replays = sorted(run.glob("replay-*"))
    if not replays:
        raise SystemExit(f"no replay-* folder in {run}: pass a training run's folder (hydra.run.dir)")
    meta = json.loads((replays[-1] / "frame_replay.json").read_text())
    frames = TensorDict.load_memmap(replays[-1] / "frames")
    rows = torch.nonzero(frames["holding"][: int(meta["num_frames"])].reshape(-1).bool() == holding).squeeze(1)
    rows = rows[torch.linspace(0, len(rows) - 1, min(count, len(rows))).long()]

    def decode(key):
        images = geometry.classes_to_heights(frames[key][rows], meta["max_height"], meta["num_classes"]).float()
        return images.reshape(len(rows), 1, *images.shape[-2:])

    return decode("heightmap"), decode("in_hand"), torch.full((len(rows), 1), holding)


def head_report(q, states, surface: float) -> tuple[list[float], float]:
    """(share of pixels where each hidden unit of the states' head is positive, mean over states of the std of the
    head's Q over object pixels)."""
    heightmap, in_hand, holding = states
    head = q.place_head if bool(holding.all()) else q.pick_head
    seen = []
    hook = head[0].register_forward_hook(lambda module, inputs, output: seen.append(output))
    with torch.no_grad():
        maps = q(heightmap, in_hand, holding)
    hook.remove()
    hidden = torch.cat(seen)
    shares = [float((hidden[:, c] > 0).float().mean()) for c in range(hidden.shape[1])]
    objects = (heightmap > surface).expand_as(maps) & torch.isfinite(maps)
    spread = [maps[i][objects[i]].std() for i in range(len(maps)) if objects[i].sum() > 1]
    return shares, float(torch.stack(spread).mean()) if spread else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a training run's folder (its replay-* inside)")
    parser.add_argument("checkpoints", type=Path, nargs="*", help="checkpoints to read (default: the run's checkpoint.pt)")
    parser.add_argument("--states", type=int, default=16, help="replay states per head")
    parser.add_argument("--surface", type=float, default=0.015, help="m: pixels above it count as objects")
    args = parser.parse_args()
    from ldm_rl.agents import load_agent

    torch.set_num_threads(1)
    states = {name: replay_states(args.run, name == "place", args.states) for name in ("pick", "place")}
    print("| checkpoint | head | hidden units: share of pixels where positive | Q std over object pixels |")
    print("|---|---|---|---|")
    for checkpoint in args.checkpoints or [args.run / "checkpoint.pt"]:
        agent, _ = load_agent(checkpoint)
        q = getattr(agent.greedy_policy, "q_network", None)
        if q is None or not hasattr(q, "pick_head"):
            raise SystemExit(f"{checkpoint}: agent {agent.name!r} has no Q FCN with pick and place heads")
        for name, batch in states.items():
            shares, spread = head_report(q.eval(), batch, args.surface)
            print(f"| {checkpoint} | {name} | {', '.join(f'{100 * s:.0f} %' for s in shares)} | {spread:.4f} |")


if __name__ == "__main__":
    main()
