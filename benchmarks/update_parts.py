"""What one update of an LDM agent costs, term by term, on a training run's own replay.

    python benchmarks/update_parts.py <run>/checkpoint.pt [--updates 8] [--warmup 2] [--no-cache] [--threads 1]

Rebuilds the agent and its replay from a checkpoint written by ``recipes/train_policy.py`` (``agent=ldm``), samples
batches as the run does, and times each term of ``LDMAgent.update`` on its own: the LDM's focal loss (forward,
backward), the lookahead targets (the target networks: Q maps of the next states, the LDM and V on their proposals;
``--no-cache`` empties the bootstrap cache so every row is computed, as early in a run), Q's TD term on the batch's
actions, the options' terms where the run has them — Q fitted on its own proposals (``agent.q_proposal_fit``), the
expert margin for Q (``agent.expert_margin_weight``) and for V (``agent.value_margin_weight``) — and V's and the reward
head's Huber terms (the rest of the loss's forward). Each forward and backward is timed apart; the terms' sum is
not the update's time to the millisecond (the update shares one backward), so the whole update is timed too.
Medians over ``--updates`` batches after ``--warmup`` untimed ones; one table. Run by hand, not by CI; compare rows
measured in one run (docs/policy.md, "Measured").
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
from collections import defaultdict

import torch


def build(checkpoint: str):
    """``(agent, replay, config)`` of an LDM agent's checkpoint, the replay as it was saved."""
    from pathlib import Path

    from ldm_rl.agents import load_agent
    from ldm_rl.data.replay import FrameReplay
    from ldm_rl.run.checkpoint import load_checkpoint

    agent, cfg = load_agent(checkpoint)
    if agent.name != "ldm":
        raise SystemExit(f"{checkpoint} holds agent {agent.name!r}: this benchmark splits the LDM agent's update")
    replay = FrameReplay.from_config(cfg, in_ram=True)
    state = load_checkpoint(checkpoint).state
    replay.loads(Path(checkpoint).parent / state["replay_dir"])
    return agent, replay, cfg


def split_update(agent, batch, spent: dict[str, float]) -> None:
    """Add each term's forward and backward seconds for ``batch`` to ``spent`` (gradients cleared after each)."""
    loss, k = agent.loss, agent.loss.tensor_keys

    def timed(name, fn):
        start = time.perf_counter()
        out = fn()
        spent[name] += time.perf_counter() - start
        return out

    def backward(name, value):
        if value is not None and value.requires_grad:
            timed(name, value.backward)
        for opt in agent.optimizers.values():
            opt.zero_grad(set_to_none=True)

    agent._train_mode()
    dyn = timed("LDM loss: forward", lambda: agent.dynamics_loss(batch))
    backward("LDM loss: backward", dyn["loss_dynamics"])
    _, _, fit = timed("targets (target networks)", lambda: loss._targets(batch))
    state = [batch.get(key) for key in (k.heightmap, k.in_hand, k.holding)]
    q = timed("Q TD term: forward", lambda: loss.q_network.action_values(*state, batch.get(k.action)))
    backward("Q TD term: backward", q.sum())
    if fit is not None:
        weight = torch.ones(batch.shape[0], 1)
        term = timed("Q on its proposals: forward", lambda: loss._proposal_fit_loss(batch, weight, *fit))
        backward("Q on its proposals: backward", term)
    if loss.expert_margin_weight:
        term = timed("Q expert margin: forward", lambda: loss.expert_margin_loss(loss.q_network, batch))
        backward("Q expert margin: backward", term)
    if loss.value_margin_weight:
        term = timed("V expert margin: forward", lambda: loss.value_margin_loss(batch))
        backward("V expert margin: backward", term)


def whole_update(agent, batch, spent: dict[str, float]) -> None:
    start = time.perf_counter()
    agent.update(batch)
    spent["whole update (LDMAgent.update)"] += time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--updates", type=int, default=8)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--no-cache", action="store_true", help="empty the bootstrap cache before each batch")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    agent, replay, cfg = build(args.checkpoint)
    cache = agent.loss.bootstrap_cache
    times: dict[str, list[float]] = defaultdict(list)
    state = copy.deepcopy(agent.state_dict())  # every batch meets the same weights and optimiser states
    for n in range(args.warmup + args.updates):
        for measure in (split_update, whole_update):  # each its own batch: the second would hit the first's cache rows
            if cache is not None and args.no_cache:
                cache.clear()
            spent: dict[str, float] = defaultdict(float)
            measure(agent, replay.sample(), spent)
            agent.load_state_dict(state)
            if n >= args.warmup:
                for name, seconds in spent.items():
                    times[name].append(seconds)
    agent_cfg = cfg["agent"]
    print(f"\n{args.checkpoint}: batch {replay.batch_size}, {args.threads} thread(s), bootstrap cache "
          f"{'emptied per batch' if args.no_cache or cache is None else 'as it fills'}; q_proposal_fit "
          f"{agent_cfg.get('q_proposal_fit') or 0}, expert_margin_weight {agent_cfg.get('expert_margin_weight') or 0} "
          f"({agent_cfg.get('expert_margin_rows')} rows), value_margin_weight {agent_cfg.get('value_margin_weight') or 0}, "
          f"q_frame_pad {agent_cfg.get('q_frame_pad') or 0}")
    print(f"\n| term (median of {args.updates} batches after {args.warmup}) | seconds |\n|---|---|")
    for name, values in times.items():
        print(f"| {name} | {statistics.median(values):.3f} |")


if __name__ == "__main__":
    main()
