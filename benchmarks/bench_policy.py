"""Agent benchmark: one training env step of ``experiment=stacking_lite`` split by phase; one planner
decision, one training update (with its batched lookahead targets), replay bytes per transition — paper
and lite presets.

    python benchmarks/bench_policy.py --training-step            # stacking_lite env steps, per phase, per lever
    python benchmarks/bench_policy.py                            # decision/update: both presets, 1 and 2 threads
    python benchmarks/bench_policy.py --presets lite --threads 1 --repeats 5
    python benchmarks/bench_policy.py --planners --presets lite        # one decision per planner option, 1 thread
    python benchmarks/bench_policy.py --device cuda --presets paper lite --threads 1   # decision/update on a GPU

A training env step (``--training-step``) is what ``recipes/train_policy.py`` does per step: the exploring
planner's decision on the real PyBullet env, the env step, and ``schedule.updates_per_step`` agent updates
from the prioritized replay (sample, LDM loss, targets, Q/V losses, backward, Adam, priorities). The replay
is seeded with the preset's expert episodes and the LDM pretrained as the recipe does; then ``--steps``
env steps are timed after ``--warmup`` untimed ones, for each lever setting (``--levers``): the bootstrap
cache off/on and the update-to-data ratio. One thread.

A decision = Q over R rotations → N candidates → LDM on N crops (one head each) → V on N states → argmax
(``ExplorationType.DETERMINISTIC``), for one state. An update = the LDM focal loss, the lookahead targets
of the whole batch (target Q over R rotations per next state, N_t candidates, LDM, V, one pass), the Q,
V and reward losses, backward and three Adam steps. The first timed call is reported apart (warm-up);
then the best and median of ``--repeats``. The reference's figures are printed beside ours as
documented for this kind of 2-core CPU (its planning call 0.73 s; one training step ≈ 60 s with its
per-sample target planning; float64 scenes ≈ 136 KB per transition) — they come from another run, so
compare orders of magnitude, not percent.

``--device`` (``cpu``, the default, or ``cuda``) puts the networks, their losses' target copies and
optimiser states, the update's batch and the decision's state on that device (the replay-bytes rows stay
on the CPU, where ``FrameReplay`` keeps its frames); each timed call, the warm-up one too, is bracketed by
``torch.cuda.synchronize()``, so a figure is the call's wall time with its kernels finished. Autocast
(``--autocast bf16``) follows the device. ``--threads`` still sets torch's CPU threads (on CUDA they only
drive the launches). ``--training-step`` runs the PyBullet env on the CPU and refuses ``--device cuda``.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import statistics
import time
import warnings

import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from ldm_rl.data.replay import FrameReplay
from ldm_rl.models.blocks import count_parameters
from ldm_rl.models.q_fcn import build_q_network
from ldm_rl.models.v_cnn import build_value_network
from ldm_rl.objectives import LDMLoss, LookaheadLoss
from ldm_rl.planning.planner import LookaheadPlanner
from ldm_rl.planning.tree_planner import TreePlanner
from ldm_rl.torch_utils import make_adam
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


def build(preset: str, num_candidates: int, num_target_candidates: int, autocast: str | None = None,
          device: torch.device | str = "cpu"):
    torch.manual_seed(0)
    width = 1.0 if preset == "paper" else 0.25
    dynamics = build_dynamics_model({"name": "ldm", "preset": preset, "width": width, "crop_size": 64},
                                    MAX_HEIGHT).to(device)
    q = build_q_network(preset, max_height=MAX_HEIGHT).to(device)
    value = build_value_network(preset, max_height=MAX_HEIGHT).to(device)
    planner = LookaheadPlanner(q, dynamics, value, num_candidates=num_candidates, tau=0.05, write_action_value=False,
                               autocast=autocast)
    loss = LookaheadLoss(q, dynamics, value, num_target_candidates=num_target_candidates).to(device)
    ldm_loss = LDMLoss(dynamics, write_logits=True).to(device)  # its class-count buffer
    optims = [make_adam(m.parameters(), lr=1e-4) for m in (q, value, dynamics)]  # as the agent
    return planner, loss, ldm_loss, optims


def timed(fn, repeats: int, device: torch.device | str = "cpu") -> tuple[float, float, float]:
    """(first call, best, median) seconds; on CUDA each call is bracketed by ``torch.cuda.synchronize``."""
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)

    def once() -> float:
        sync()
        t = time.perf_counter()
        fn()
        sync()
        return time.perf_counter() - t

    first = once()
    times = [once() for _ in range(repeats)]
    return first, min(times), statistics.median(times)


PHASES = ("act", "env", "replay", "imagine", "ldm loss", "targets", "q/v losses", "backward", "optimiser", "averaging")


def training_steps(overrides: list[str], steps: int, warmup: int, seed: int = 0) -> dict[str, float]:
    """Mean seconds per env step of each phase (and ``total``) over ``steps`` training env steps of the
    composed ``train_policy`` config, plus ``first`` (the first step, apart) and the cache hit rate."""
    import collections
    import contextlib
    import pathlib
    import sys

    from hydra import compose, initialize_config_dir
    from torchrl.envs.utils import step_mdp

    from ldm_rl.agents import build_agent
    from ldm_rl.envs import make_env_from_config
    from ldm_rl.models.compile import compile_inference
    from ldm_rl.torch_utils import seed_everything

    root = pathlib.Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(root / "recipes"))
    from train_policy import TRANSITION_KEYS, expert_episodes, updates_due  # noqa: E402

    with initialize_config_dir(config_dir=str(root / "conf"), version_base="1.3"):
        cfg = compose(config_name="train_policy", overrides=["experiment=stacking_lite", "schedule.progress=false", *overrides])
    seed_everything(seed)
    max_height = float(cfg.env.max_height)
    agent = build_agent(cfg, max_height)
    if cfg.compile:
        compile_inference(agent)
    replay = FrameReplay.from_config(cfg, in_ram=True)
    for episode in expert_episodes(cfg):
        replay.extend_episode(episode)  # its own per-step is_expert flags
    for _ in range(int(cfg.schedule.pretrain_updates)):
        agent.pretrain_update(replay.sample())
    agent.sync_targets()

    spent: dict[str, float] = collections.defaultdict(float)

    @contextlib.contextmanager
    def phase(name):
        start = time.perf_counter()
        yield
        spent[name] += time.perf_counter() - start

    def timed_method(obj, name, label, minus=()):
        method = getattr(obj, name)

        def wrapper(*args, **kwargs):
            before = sum(spent[m] for m in minus)
            start = time.perf_counter()
            out = method(*args, **kwargs)
            spent[label] += time.perf_counter() - start - (sum(spent[m] for m in minus) - before)
            return out
        setattr(obj, name, wrapper)

    # the lookahead loss's forward calls ``_targets`` (targets and the proposal fit's scores), the others ``targets``
    timed_method(agent.loss, "_targets" if hasattr(agent.loss, "_targets") else "targets", "targets")
    timed_method(agent.loss, "forward", "q/v losses", minus=("targets",))
    if hasattr(agent, "dynamics_loss"):  # every agent but FC-DQN trains an LDM
        timed_method(agent.dynamics_loss, "forward", "ldm loss")
    if hasattr(agent, "imagine"):  # agent=dynaq: the imagined transitions (the exploring Q map, LDM, reward head)
        timed_method(agent, "imagine", "imagine")
    for opt in agent.optimizers.values():
        timed_method(opt, "step", "optimiser")
    if agent.averaged_planner is not None:  # agent.greedy_ema_decay: the greedy policy's weight average
        timed_method(agent.averaged_planner, "update_parameters", "averaging")
    backward = torch.Tensor.backward

    def timed_backward(tensor, *args, **kwargs):
        with phase("backward"):
            return backward(tensor, *args, **kwargs)

    env = make_env_from_config(cfg.env)
    env.set_seed(seed)
    td = env.reset()
    totals, first, episode = [], None, []
    torch.Tensor.backward = timed_backward
    try:
        for n in range(1, warmup + steps + 1):
            if n == warmup + 1:
                spent.clear()
            start = time.perf_counter()
            with phase("act"), set_exploration_type(ExplorationType.RANDOM):
                td = agent.policy(td)
            with phase("env"):
                td = env.step(td)
            episode.append(td.select(*TRANSITION_KEYS).clone())
            td = step_mdp(td)
            if bool(td.get("done").any()):  # the finished episode goes into the replay, as in the recipe
                with phase("replay"):
                    replay.extend_episode(torch.stack(episode))
                episode.clear()
                td = env.reset()
            for _ in range(updates_due(n, float(cfg.schedule.updates_per_step))):
                with phase("replay"):
                    batch = replay.sample()
                agent.update(batch)
                with phase("replay"):
                    replay.update_priority(batch["index"], batch["td_error"])
            elapsed = time.perf_counter() - start
            if n == 1:
                first = elapsed
            if n > warmup:
                totals.append(elapsed)
    finally:
        torch.Tensor.backward = backward
    out = {name: spent[name] / steps for name in PHASES}
    out.update(total=statistics.fmean(totals), first=first, median=statistics.median(totals))
    cache = getattr(agent.loss, "bootstrap_cache", None)
    out["hit_rate"] = cache.hit_rate if cache is not None else float("nan")
    return out


def training_step_table(levers: list[str], steps: int, warmup: int) -> None:
    """Print the per-phase split of a stacking_lite training env step for each lever setting."""
    torch.set_num_threads(1)
    rows = []
    for lever in levers:
        overrides = [item for item in lever.split(",") if item]
        result = training_steps(overrides, steps, warmup)
        rows.append((lever or "(preset as shipped)", result))
        print(f"{lever or '(preset)':60s} {result['total']:.3f} s per env step", flush=True)
    print(f"\n| stacking_lite + setting, 1 thread, mean s per env step over {steps} steps | " + " | ".join(PHASES)
          + " | total | first step | cache hit rate |")
    print("|---" * (len(PHASES) + 4) + "|")
    for lever, r in rows:
        print(f"| {lever} | " + " | ".join(f"{r[name]:.3f}" for name in PHASES)
              + f" | **{r['total']:.3f}** | {r['first']:.2f} | {r['hit_rate']:.2f} |")


PLANNER_OPTIONS = (  # (label, planner class, keyword arguments beside the shared ones)
    ("one-step (the paper)", LookaheadPlanner, {}),
    ("one-step, V − λ·H", LookaheadPlanner, {"uncertainty_penalty": 0.25}),
    ("tree depth 2, K = 1", TreePlanner, {"depth": 2, "branching": 1, "gamma": 0.9}),
    ("tree depth 2, K = 3", TreePlanner, {"depth": 2, "branching": 3, "gamma": 0.9}),
    ("tree depth 3, K = 3", TreePlanner, {"depth": 3, "branching": 3, "gamma": 0.9}),
)


def planner_table(presets: list[str], candidates: int, repeats: int, device: torch.device | str = "cpu") -> None:
    """One greedy decision for one state per planner option (one thread), its cost against the paper's."""
    torch.set_num_threads(1)
    state = TensorDict(scenes(1), batch_size=[1]).to(device)

    def fmt(seconds: float) -> str:  # a GPU decision takes milliseconds: print those
        return f"{seconds * 1e3:.1f} ms" if torch.device(device).type == "cuda" else f"{seconds:.3f} s"

    print(f"\n| preset ({torch.device(device).type}) | planner | first (warm-up) | best | median | × one-step |")
    print("|---|---|---|---|---|---|")
    for preset in presets:
        planner, *_ = build(preset, candidates, candidates, device=device)
        nets = (planner.q_network, planner.dynamics, planner.value_network)
        base = None
        for label, cls, kwargs in PLANNER_OPTIONS:
            option = cls(*nets, num_candidates=candidates, tau=0.05, write_action_value=False, **kwargs)

            def decide():
                with set_exploration_type(ExplorationType.DETERMINISTIC):
                    option(state.clone())

            first, best, median = timed(decide, repeats, device)
            base = median if base is None else base
            print(f"| {preset} | {label} (N = {candidates}) | {fmt(first)} | {fmt(best)} | {fmt(median)} | "
                  f"{median / base:.1f} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--training-step", action="store_true", help="time stacking_lite training env steps by phase")
    parser.add_argument("--planners", action="store_true", help="time one decision of each planner option (1 thread)")
    parser.add_argument("--levers", nargs="+", default=[
        "agent.bootstrap_cache=0,schedule.updates_per_step=1", "schedule.updates_per_step=1", ""],
        help="comma-separated Hydra overrides per setting ('' = the preset as shipped)")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--presets", nargs="+", default=["lite", "paper"])
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--candidates", type=int, default=10)
    parser.add_argument("--target-candidates", type=int, nargs="+", default=[10])
    parser.add_argument("--autocast", nargs="+", default=["none"], choices=["none", "bf16"],
                        help="planner.autocast / agent.autocast settings to time (bf16: Q and LDM under bf16 autocast)")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                        help="where the networks, batch and state live (cuda: timings synchronize the GPU)")
    args = parser.parse_args()
    if args.device == "cuda":
        if args.training_step:
            parser.error("--training-step runs the PyBullet env on the CPU; it does not take --device cuda")
        if not torch.cuda.is_available():
            parser.error("--device cuda: torch.cuda.is_available() is False")
    device = torch.device(args.device)

    def fmt(seconds: float, width: int = 0) -> str:  # GPU calls take milliseconds: print those
        return f"{seconds * 1e3:{width}.1f} ms" if device.type == "cuda" else f"{seconds:{width}.2f} s"

    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"torch threads {torch.get_num_threads()}"
    print(f"device: {args.device} ({where}), torch {torch.__version__}", flush=True)
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # its INFO line (a buffer's storage initialised) is noise here
    # the phase timers wrap each optimiser's step, which torch's LR scheduler reports as an override
    warnings.filterwarnings("ignore", message="Seems like `optimizer.step\\(\\)` has been overridden", category=UserWarning)
    if args.training_step:
        training_step_table(args.levers, args.steps, args.warmup)
        return
    if args.planners:
        planner_table(args.presets, args.candidates, args.repeats, device)
        return

    rows = []
    state = TensorDict(scenes(1), batch_size=[1]).to(device)
    for preset, n_t, precision in itertools.product(args.presets, args.target_candidates, args.autocast):
        autocast = None if precision == "none" else precision
        planner, loss, ldm_loss, optims = build(preset, args.candidates, n_t, autocast, device)
        params = {name: count_parameters(m) for name, m in
                  (("Q", planner.q_network), ("V", planner.value_network), ("LDM", planner.dynamics))}
        batch = transitions(args.batch).to(device)

        def decide():
            with set_exploration_type(ExplorationType.DETERMINISTIC):
                planner(state.clone())

        def update():
            td = batch.clone()
            for m in (planner.q_network, planner.value_network, planner.dynamics):
                m.train()
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast is not None):
                out = ldm_loss(td)
                lk = loss(td)
            total = out["loss_dynamics"] + lk["loss_q"] + lk["loss_value"] + lk["loss_reward"]
            for opt in optims:
                opt.zero_grad()
            total.backward()
            for opt in optims:
                opt.step()

        def targets():
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast is not None):
                loss.targets(batch)

        for threads in args.threads:
            torch.set_num_threads(threads)
            for what, fn in (("decision (N=%d)" % args.candidates, decide),
                             (f"targets only (B={args.batch}, N_t={n_t})", targets),
                             (f"update incl. targets (B={args.batch}, N_t={n_t})", update)):
                first, best, median = timed(fn, args.repeats, device)
                what = what if autocast is None else f"{what}, {autocast}"
                rows.append((preset, threads, what, first, best, median))
                print(f"{preset:5s} {device.type:4s} {threads}t {what:44s} first {fmt(first, 6)}  best {fmt(best, 6)}  "
                      f"median {fmt(median, 6)}", flush=True)
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

    print(f"\n| preset ({args.device}) | threads | what | first (warm-up) | best | median | reference |")
    print("|---|---|---|---|---|---|---|")
    for preset, threads, what, first, best, median in rows:
        if what.startswith("replay"):
            print(f"| – | – | {what} | {first / 1000:.1f} KB | | | {REFERENCE['bytes']} |")
            continue
        ref = REFERENCE["decision"] if what.startswith("decision") else REFERENCE["update"] if what.startswith("update") else ""
        print(f"| {preset} | {threads} | {what} | {fmt(first)} | {fmt(best)} | {fmt(median)} | {ref} |")


if __name__ == "__main__":
    main()
