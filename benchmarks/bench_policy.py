"""Agent benchmark: one planner decision, one training update (with its batched lookahead targets),
replay bytes per transition — paper and lite presets.

    python benchmarks/bench_policy.py                          # both presets, 1 and 2 threads
    python benchmarks/bench_policy.py --presets lite --threads 1 --repeats 5

A decision = Q over R rotations → N candidates → LDM on N crops (one head each) → V on N states → argmax
(``ExplorationType.DETERMINISTIC``), for one state. An update = the LDM focal loss, the lookahead targets
of the whole batch (target Q over R rotations per next state, N_t candidates, LDM, V, one pass), the Q,
V and reward losses, backward and three Adam steps. The first timed call is reported apart (warm-up);
then the best and median of ``--repeats``. The reference's figures are printed beside ours as
documented for this kind of 2-core CPU (its planning call 0.73 s; one training step ≈ 60 s with its
per-sample target planning; float64 scenes ≈ 136 KB per transition) — they come from another run, so
compare orders of magnitude, not percent.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import time

import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from ldm_rl.data.replay import FrameReplay
from ldm_rl.models.blocks import count_parameters
from ldm_rl.models.q_fcn import build_q_network
from ldm_rl.models.v_cnn import build_value_network
from ldm_rl.objectives import LDMLoss, LookaheadLoss
from ldm_rl.planning.planner import LookaheadPlanner
from ldm_rl.runtime import make_adam
from ldm_rl.world_model import build_dynamics_model

MAX_HEIGHT = 0.25
REFERENCE = {"decision": "0.73 s", "update": "≈ 60 s (9.1 s + per-sample targets)", "bytes": "≈ 136 KB"}


def scenes(n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    heightmap = torch.zeros(n, 1, 128, 128)
    for i in range(n):
        for _ in range(3):
            r, c = torch.randint(16, 100, (2,), generator=g).tolist()
            heightmap[i, 0, r : r + 13, c : c + 13] += 0.04
    holding = (torch.arange(n) % 2 == 1).view(n, 1)
    in_hand = torch.where(holding.view(n, 1, 1, 1), torch.full((n, 1, 24, 24), 0.04), torch.zeros(n, 1, 24, 24))
    return {"heightmap": heightmap, "in_hand": in_hand, "holding": holding}


def transitions(n: int) -> TensorDict:
    g = torch.Generator().manual_seed(1)
    action = torch.stack([torch.randint(16, 112, (n,), generator=g), torch.randint(16, 112, (n,), generator=g),
                          torch.randint(0, 8, (n,), generator=g)], -1)
    terminated = torch.zeros(n, 1, dtype=torch.bool)
    return TensorDict({**scenes(n, 0), "action": action,
                       "next": {**scenes(n, 2), "reward": torch.zeros(n, 1), "terminated": terminated}}, batch_size=[n])


def build(preset: str, num_candidates: int, num_target_candidates: int, autocast: str | None = None):
    torch.manual_seed(0)
    width = 1.0 if preset == "paper" else 0.25
    dynamics = build_dynamics_model({"name": "ldm", "preset": preset, "width": width, "crop_size": 64}, MAX_HEIGHT)
    q = build_q_network(preset, max_height=MAX_HEIGHT)
    value = build_value_network(preset, max_height=MAX_HEIGHT)
    planner = LookaheadPlanner(q, dynamics, value, num_candidates=num_candidates, tau=0.05, write_action_value=False,
                               autocast=autocast)
    loss = LookaheadLoss(q, dynamics, value, num_target_candidates=num_target_candidates)
    ldm_loss = LDMLoss(dynamics, write_logits=True)
    optims = [make_adam(m.parameters(), lr=1e-4) for m in (q, value, dynamics)]  # as the agent
    return planner, loss, ldm_loss, optims


def timed(fn, repeats: int) -> tuple[float, float, float]:
    """(first call, best, median) seconds."""
    t = time.perf_counter()
    fn()
    first = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return first, min(times), statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--presets", nargs="+", default=["lite", "paper"])
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--candidates", type=int, default=10)
    parser.add_argument("--target-candidates", type=int, nargs="+", default=[10])
    parser.add_argument("--autocast", nargs="+", default=["none"], choices=["none", "bf16"],
                        help="planner.autocast / agent.autocast settings to time (bf16: Q and LDM under bf16 autocast)")
    args = parser.parse_args()

    rows = []
    state = TensorDict(scenes(1), batch_size=[1])
    for preset, n_t, precision in itertools.product(args.presets, args.target_candidates, args.autocast):
        autocast = None if precision == "none" else precision
        planner, loss, ldm_loss, optims = build(preset, args.candidates, n_t, autocast)
        params = {name: count_parameters(m) for name, m in
                  (("Q", planner.q_network), ("V", planner.value_network), ("LDM", planner.dynamics))}
        batch = transitions(args.batch)

        def decide():
            with set_exploration_type(ExplorationType.DETERMINISTIC):
                planner(state.clone())

        def update():
            td = batch.clone()
            for m in (planner.q_network, planner.value_network, planner.dynamics):
                m.train()
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast is not None):
                out = ldm_loss(td)
                lk = loss(td)
            total = out["loss_dynamics"] + lk["loss_q"] + lk["loss_value"] + lk["loss_reward"]
            for opt in optims:
                opt.zero_grad()
            total.backward()
            for opt in optims:
                opt.step()

        def targets():
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast is not None):
                loss.targets(batch)

        for threads in args.threads:
            torch.set_num_threads(threads)
            for what, fn in (("decision (N=%d)" % args.candidates, decide),
                             (f"targets only (B={args.batch}, N_t={n_t})", targets),
                             (f"update incl. targets (B={args.batch}, N_t={n_t})", update)):
                first, best, median = timed(fn, args.repeats)
                what = what if autocast is None else f"{what}, {autocast}"
                rows.append((preset, threads, what, first, best, median))
                print(f"{preset:5s} {threads}t {what:44s} first {first:6.2f} s  best {best:6.2f} s  median {median:6.2f} s",
                      flush=True)
        print(f"{preset}: params " + ", ".join(f"{k} {v / 1e6:.2f} M" for k, v in params.items()), flush=True)

    replay = FrameReplay(1000, max_height=MAX_HEIGHT, batch_size=32)
    for length in (4, 8):
        ep = transitions(length)
        ep = ep.set(("next", "heightmap"), torch.cat([ep["heightmap"][1:], ep["next", "heightmap"][-1:]]))
        ep = ep.set(("next", "in_hand"), torch.cat([ep["in_hand"][1:], ep["next", "in_hand"][-1:]]))
        ep = ep.set(("next", "holding"), torch.cat([ep["holding"][1:], ep["next", "holding"][-1:]]))
        ep = ep.set(("next", "truncated"), torch.zeros(length, 1, dtype=torch.bool))
        ep = ep.set(("next", "done"), torch.zeros(length, 1, dtype=torch.bool))
        fresh = FrameReplay(1000, max_height=MAX_HEIGHT, batch_size=32)
        fresh.extend_episode(ep)
        rows.append(("-", "-", f"replay bytes/transition ({length}-step episodes)", fresh.bytes_per_transition(), 0, 0))
    del replay

    print("\n| preset | threads | what | first (warm-up) | best | median | reference |")
    print("|---|---|---|---|---|---|---|")
    for preset, threads, what, first, best, median in rows:
        if what.startswith("replay"):
            print(f"| – | – | {what} | {first / 1000:.1f} KB | | | {REFERENCE['bytes']} |")
            continue
        ref = REFERENCE["decision"] if what.startswith("decision") else REFERENCE["update"] if what.startswith("update") else ""
        print(f"| {preset} | {threads} | {what} | {first:.2f} s | {best:.2f} s | {median:.2f} s | {ref} |")


if __name__ == "__main__":
    main()
