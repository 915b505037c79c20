"""More world-model updates on a run's own data: does the LDM foresee more of what the places do?

    python benchmarks/fit_world_model.py <run> --steps 2000 --save <fitted>.pt
    python benchmarks/place_outcomes.py <fitted>.pt --episodes 30 --planner greedy_uncertainty_penalty=1.0

Loads an LDM agent's run (``checkpoint.pt``: weights and optimizer state; its newest ``replay-*``), then takes
``--steps`` LDM-only steps (the agent's ``pretrain_update``: the focal loss, the run's dynamics optimizer and batch)
on batches drawn as the run drew them (its priorities), Q and V untouched, printing the focal loss and pixel accuracy
of the batches every ``--report-every`` steps, and writes the weights as a checkpoint to play (``--save``). A run
with averaged greedy weights (``agent.greedy_ema_decay``) has its greedy planner's LDM replaced by the fitted online
one (``--steps 0``: the online LDM alone, the control). The test
is on new scenes: ``place_outcomes.py``'s reading of the saved weights (its missed rises: the real pile top more than
1 cm above the predicted) against the run's own: whether more updates on the same data let the world model foresee
what the places do, and whether the pile follows. A measurement of the world model's update budget, not of time;
run by hand (docs/policy.md, "Bin packing").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch


def load_run(run: Path):
    """``(agent, cfg, replay)`` of ``run``: the agent with the checkpoint's weights and optimizer state, the replay
    restored from the newest ``replay-*`` the checkpoint names."""
    from ldm_rl.agents import build_agent
    from ldm_rl.data.replay import FrameReplay
    from ldm_rl.run.checkpoint import load_checkpoint

    checkpoint = load_checkpoint(run / "checkpoint.pt", expect={"kind": "agent", "agent": "ldm"})
    cfg = checkpoint.meta["config"]
    agent = build_agent(cfg, float(cfg["env"]["max_height"]))
    agent.load_state_dict(checkpoint.state["agent"])
    agent.load_training_state(checkpoint.state["training"])
    replay = FrameReplay.from_config(cfg, in_ram=True)
    replay.loads(run / checkpoint.state["replay_dir"])
    return agent, cfg, replay


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="an LDM agent's run folder (checkpoint.pt and replay-* inside)")
    parser.add_argument("--steps", type=int, default=2000, help="LDM-only steps (default 2000; 0: the online LDM as it is)")
    parser.add_argument("--report-every", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--save", type=Path, default=None, help="write the fitted weights here (a checkpoint to play)")
    args = parser.parse_args()
    if args.steps < 0 or args.report_every < 1:
        parser.error(f"--steps must be >= 0 and --report-every >= 1, got {args.steps} and {args.report_every}")
    if not (args.run / "checkpoint.pt").is_file():
        parser.error(f"{args.run}: no checkpoint.pt (pass a training run's folder)")
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    from ldm_rl.run.checkpoint import CheckpointError

    try:
        agent, cfg, replay = load_run(args.run)
    except CheckpointError as err:  # another agent's run, or a damaged checkpoint
        parser.error(str(err))
    replay.generator.manual_seed(args.seed)
    print(f"{args.run}: {len(replay)} transitions; {args.steps} LDM-only steps, batch {cfg['replay']['batch_size']}")
    print("| steps | focal loss (mean over the batches since the last row) | pixel accuracy (the same) |")
    print("|---|---|---|")
    losses, accuracies = [], []
    for step in range(1, args.steps + 1):
        out = agent.pretrain_update(replay.sample())
        losses.append(out["loss_dynamics"])
        accuracies.append(out["pixel_accuracy"])
        if step % args.report_every == 0 or step == args.steps:
            print(f"| {step} | {sum(losses) / len(losses):.4f} | {sum(accuracies) / len(accuracies):.4f} |", flush=True)
            losses, accuracies = [], []
    if agent.averaged_planner is not None:  # a run with averaged greedy weights: its greedy planner plans with this LDM
        agent.averaged_planner.module.dynamics.load_state_dict(agent.planner.dynamics.state_dict())
    if args.save is not None:
        from ldm_rl.run.checkpoint import read_checkpoint_meta, save_checkpoint

        meta = {**read_checkpoint_meta(args.run / "checkpoint.pt"),
                "note": f"fit_world_model.py: {args.steps} more LDM-only steps on the run's replay"}
        args.save.parent.mkdir(parents=True, exist_ok=True)
        save_checkpoint(args.save, {"agent": agent.policy_state_dict()}, meta=meta)
        print(f"saved the fitted weights to {args.save}")


if __name__ == "__main__":
    main()
