"""Train an agent online (agent=ldm: the paper's Q → LDM → V lookahead) and evaluate its greedy policy.

    python recipes/train_policy.py                                     # LDM agent, 3-block stacking, lite
    python recipes/train_policy.py experiment=stacking_lite            # the 40-minute CPU acceptance run
    python recipes/train_policy.py env=house_building schedule.total_episodes=5000
    python recipes/train_policy.py -m seed=0,1 experiment=stacking_lite
    python recipes/train_policy.py resume=true hydra.run.dir=<run> schedule.total_episodes=1100  # a longer budget

The loop, in order: seed the replay buffer with expert episodes → (optional) LDM-only pretraining →
collect one step at a time with a TorchRL ``Collector`` running the planner (exploring) → push finished
episodes into prioritized replay → ``schedule.updates_per_step`` agent updates per step (new priorities
written back, β annealed) → every ``schedule.eval_every`` updates the greedy policy plays
``schedule.eval_episodes`` episodes on a separate env. Writes to the run folder: ``curve.csv`` (success
against episodes, env steps, updates and wall-clock), ``learning_curve.png``, ``checkpoint.pt`` (every
``schedule.checkpoint_every`` updates, at the end of an episode, and at the end), ``best_policy.pt``
(``schedule.keep_best``: the weights of the best in-training evaluation, scored again at the end on
held-out scenes under ``best`` in ``final_metrics.json``), ``final_metrics.json``,
the logger's scalars (``logger=csv|tensorboard|wandb|mlflow|none``: losses, learning rates,
``train/env_steps_per_s``, ``train/updates_per_s``, ``eval/success_rate``...; docs/logging.md),
``config_resolved.yaml`` and ``train_policy.log`` (what the console showed). ``schedule.progress``: bars
with ETA on a terminal, plain lines every 10 % or 30 s otherwise.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import sys
import time
from collections import deque
from fractions import Fraction

import hydra
from omegaconf import DictConfig, OmegaConf

from ldm_rl.config_schema import ConfigError, TrainPolicyConfig, validate_config
from ldm_rl.run.cli import check_command_line

TRANSITION_KEYS = ("heightmap", "in_hand", "holding", "action",
                   ("next", "heightmap"), ("next", "in_hand"), ("next", "holding"), ("next", "reward"),
                   ("next", "done"), ("next", "terminated"), ("next", "truncated"))
log = logging.getLogger("train_policy")
BEST_NAME = "best_policy.pt"
CURVE_FIELDS = ("updates", "episodes", "env_steps", "wall_s", "success_rate", "ci_low", "ci_high", "mean_length")
# bin packing's evaluations also score the packs (ldm_rl.envs.tasks.bin_packing.packing_scores): the pile and the
# returns under ours and the authors' reward, which the paper plots over training (success_rate is the packed fraction)
PACKING_FIELDS = ("mean_pile_top", "mean_return", "mean_return_authors", "mean_blocks_in_bin")


def expert_episodes(cfg: DictConfig) -> list:
    """``cfg.schedule.expert_episodes`` scripted-expert episodes, each a TensorDict ``[T]`` with the per-step
    ``is_expert`` flag (False where ``schedule.expert_noise`` replaced the expert's action: a random action, a
    turned rotation), which the replay keeps: such steps get no expert priority bonus and no expert margin."""
    import torch

    from ldm_rl.data.demos import collect_demos
    from ldm_rl.seeds import expert_scenes

    s = cfg.schedule
    demos = collect_demos(OmegaConf.to_container(cfg.env, resolve=True), num_episodes=int(s.expert_episodes),
                          seed=expert_scenes(cfg.seed), procedure=s.expert_procedure,
                          noise=OmegaConf.to_container(s.expert_noise, resolve=True), progress=bool(s.progress))
    lengths = torch.unique_consecutive(demos["episode"], return_counts=True)[1].tolist()
    return list(demos.select(*TRANSITION_KEYS, "is_expert").split(lengths))


def updates_due(env_steps: int, updates_per_step: float) -> int:
    """Updates after the ``env_steps``-th step: ``⌊n·u⌋ − ⌊(n−1)·u⌋`` in exact rational arithmetic, so a
    fraction u spreads its updates evenly (0.5: one every second step) and depends on the counter alone."""
    rate = Fraction(str(float(updates_per_step)))
    return math.floor(env_steps * rate) - math.floor((env_steps - 1) * rate)


def write_curve(rows: list[dict], out_dir, title: str) -> None:
    """curve.csv and learning_curve.png (``ldm_rl.plots.plot_learning_curve``), rewritten at every evaluation.
    Bin packing's rows add :data:`PACKING_FIELDS` (cells left empty in rows written before them, and for the pile
    of an evaluation that packed nothing)."""
    import csv

    from ldm_rl.plots import PlotDependencyError, plot_learning_curve
    from ldm_rl.run.outputs import atomic_path

    fields = CURVE_FIELDS + (PACKING_FIELDS if any(PACKING_FIELDS[0] in row for row in rows) else ())
    with atomic_path(out_dir / "curve.csv") as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, restval="")
        writer.writeheader()
        writer.writerows({k: "" if row.get(k) is None else row[k] for k in fields if k in row} for row in rows)
    try:
        plot_learning_curve(rows, out_dir / "learning_curve.png", title=f"Greedy success rate: {title}")
    except PlotDependencyError as err:  # say it once per run
        if len(rows) == 1:
            log.warning("%s: skipping learning_curve.png", err)


@hydra.main(version_base="1.3", config_path="../conf", config_name="train_policy")
def main(cfg: DictConfig) -> dict:
    """The run, with one-line reports of a stop signal or a bad checkpoint/config."""
    from ldm_rl.run.checkpoint import CheckpointError
    from ldm_rl.run.signals import RunStopped
    from ldm_rl.run.outputs import MissingExtraError, hydra_output_dir

    try:
        return train(cfg)
    except RunStopped as stopped:
        print(f"{stopped}; resume with: python {sys.argv[0]} resume=true hydra.run.dir={hydra_output_dir()}",
              file=sys.stderr, flush=True)
        raise SystemExit(stopped.exit_code) from None
    except (ConfigError, CheckpointError, MissingExtraError) as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None


def train(cfg: DictConfig) -> dict:
    """Seed, pretrain, collect, update, evaluate, checkpoint (see the module docstring)."""
    from hydra.utils import instantiate

    from ldm_rl.agents import build_agent
    from ldm_rl.run.checkpoint import CHECKPOINT_NAME, capture_rng_state, clean_stale_temporaries, load_checkpoint, restore_rng_state, save_checkpoint
    from ldm_rl.run.signals import RunStopped, StopSignals
    from ldm_rl.data.replay import FrameReplay
    from ldm_rl.envs import make_env_from_config
    from ldm_rl.collectors import EpisodeAssembler, TaskEnvFactory, collected_steps, make_collector, shutdown_collector
    from ldm_rl.evaluation import episode_record, evaluate_policy, is_bin_packing, packing_line, packing_report
    from ldm_rl.envs.tasks.bin_packing import packing_scores
    from ldm_rl.models.compile import compile_inference
    from ldm_rl.seeds import evaluation_scenes, held_out_scenes, training_scenes
    from ldm_rl.run.progress import progress_bar
    from ldm_rl.run.outputs import atomic_write_text, close_logger, hydra_output_dir, make_logger, save_resolved_config
    from ldm_rl.torch_utils import resolve_device, seed_everything, set_threads

    validate_config(cfg, TrainPolicyConfig)  # the command line was checked before Hydra; this covers sweep jobs
    set_threads(cfg.threads)
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # its INFO lines (a buffer's storage initialised) are noise here
    seed_everything(int(cfg.seed))
    device = resolve_device(cfg.device)
    out_dir = hydra_output_dir()
    clean_stale_temporaries(out_dir)
    checkpoint_path = out_dir / CHECKPOINT_NAME
    resuming = bool(cfg.resume) and checkpoint_path.exists()
    if cfg.resume and not resuming:
        log.info(f"resume=true: no checkpoint in {out_dir} yet; starting from episode 0")
    s = cfg.schedule
    save_resolved_config(cfg, out_dir)
    logger = make_logger(cfg.logger, out_dir, config=OmegaConf.to_container(cfg, resolve=True))
    start = time.perf_counter()
    max_height = float(cfg.env.max_height)
    agent = build_agent(cfg, max_height).to(device)
    if cfg.compile:  # inference passes (decisions, lookahead targets) through inductor, compiled on first use
        compile_inference(agent)
    replay = FrameReplay.from_config(cfg)
    beta = instantiate(cfg.replay.beta)
    task = f"{cfg.env.id} ({cfg.env.num_objects} objects)"
    # the k-th training episode's scene comes from seed reset_seed + k, so a resumed run replays the same scenes
    # (with collector.num_workers=N, worker w's scenes start at reset_seed + w * SEED_BLOCK // N: ldm_rl/collectors.py)
    env_factory = TaskEnvFactory(cfg.env, reset_seed=training_scenes(cfg.seed))
    eval_env = make_env_from_config(cfg.env)
    counters = {"episodes": 0, "env_steps": 0}
    curve, recent = [], deque(maxlen=100)
    metrics: dict[str, float] = {}
    meta = {"kind": "agent", "agent": agent.name, "preset": str(cfg.agent.preset or cfg.model.preset), "task": cfg.env.id,
            "config": OmegaConf.to_container(cfg, resolve=True)}

    best = {"success_rate": -1.0}  # the best in-training evaluation so far (schedule.keep_best)

    packing = is_bin_packing(eval_env)

    def evaluate(episodes: int) -> tuple[dict, list[float], list[int]]:
        """One greedy evaluation, appended to the curve: ``(row, returns, blocks in the bin)``, one per episode
        (bin packing's blocks; ``[]`` for the other tasks)."""
        returns: list[float] = []  # bin packing's pile top is read from the reward
        blocks: list[int] = []
        result = evaluate_policy(eval_env, agent.greedy_policy, episodes, seed=evaluation_scenes(cfg.seed), progress=bool(s.progress),
                                 on_episode=episode_record(eval_env, returns, blocks if packing else None))
        scores = {("eval_episodes" if key == "episodes" else key): value for key, value in result.as_dict().items()}
        row = {"updates": agent.updates, **counters, "wall_s": time.perf_counter() - start, **scores}
        if packing:
            row.update({key: value for key, value in packing_scores(returns, blocks).items() if key in PACKING_FIELDS})
        curve.append(row)
        if s.keep_best and row["success_rate"] > best["success_rate"]:  # the earliest of equal scores stays
            best.update(row)
            save_checkpoint(out_dir / BEST_NAME, {"agent": agent.policy_state_dict(), "evaluation": row}, meta=meta)
        write_curve(curve, out_dir, f"{agent.name} agent, {task}, seed {cfg.seed}")
        if logger is not None:
            logged = ("success_rate", "ci_low", "ci_high", "mean_length") + (PACKING_FIELDS if packing else ())
            logger.log_metrics({f"eval/{key}": row[key] for key in logged if row[key] is not None}, step=counters["episodes"])
        pile = f"; {packing_line({'packed': row['success_rate'], **row})}" if packing else ""
        log.info(f"[{row['wall_s'] / 60:6.1f} min] updates {agent.updates:6d}  episodes {counters['episodes']:5d}  eval {result}{pile}")
        return row, returns, blocks

    def save() -> None:
        """At an episode boundary: weights, optimisers, schedules, replay, every RNG, counters, curve.

        The replay goes to a folder named after the update count, which the checkpoint names; older
        folders are removed only once the checkpoint is on disk, so a kill between the two writes
        leaves the previous pair intact."""
        replay_dir = f"replay-{agent.updates:09d}"
        replay.dumps(out_dir / replay_dir)
        state = {"agent": agent.state_dict(), "training": agent.training_state(), "counters": dict(counters),
                 "curve": curve, "recent": list(recent), "wall_s": time.perf_counter() - start, "best": dict(best),
                 "rng": capture_rng_state({"replay": replay.generator}), "replay_dir": replay_dir}
        save_checkpoint(checkpoint_path, state, meta={**meta, "episodes": counters["episodes"], "updates": agent.updates})
        agent.drop_caches()  # a run resumed from here starts without them: recompute exactly as it will
        for old in out_dir.glob("replay-*"):
            if old.name != replay_dir:
                shutil.rmtree(old, ignore_errors=True)

    # from here on SIGINT/SIGTERM stop at the next episode end, with a checkpoint
    with StopSignals("the current episode (up to its step limit)") as stop:
        if resuming:
            checkpoint = load_checkpoint(checkpoint_path, expect={k: meta[k] for k in ("kind", "agent", "preset", "task")},
                                         map_location=device)
            agent.load_state_dict(checkpoint.state["agent"])
            agent.load_training_state(checkpoint.state["training"])
            replay.loads(out_dir / checkpoint.state["replay_dir"])
            counters.update(checkpoint.state["counters"])
            curve.extend(checkpoint.state["curve"])
            recent.extend(checkpoint.state["recent"])
            best.update(checkpoint.state.get("best", {}))
            start -= float(checkpoint.state["wall_s"])
            env_factory.start_episode = counters["episodes"]
            log.info(f"resumed {out_dir} at {counters['episodes']} episodes, {agent.updates} updates")
        else:
            log.info(f"{agent.name} agent on {task}: seeding replay with {s.expert_episodes} expert episodes")
            for episode in expert_episodes(cfg):
                replay.extend_episode(episode.to(device))  # its own per-step is_expert flags
            for _ in progress_bar(range(int(s.pretrain_updates)), desc="pretrain LDM", unit="update", enabled=bool(s.progress)):
                agent.pretrain_update(replay.sample())
            agent.sync_targets()  # the first targets come from the (pretrained) networks that act
            evaluate(int(s.eval_episodes))

        collector = make_collector(cfg.collector, env_factory, agent.policy, device=device, seed=int(cfg.seed))
        episodes = EpisodeAssembler(TRANSITION_KEYS)  # each worker's steps, until its episode ends
        if resuming:  # after the collector's first reset and policy probe, as in the uninterrupted run
            restore_rng_state(checkpoint.state["rng"], {"replay": replay.generator})
        next_eval = (agent.updates // int(s.eval_every) + 1) * int(s.eval_every)
        next_checkpoint = (agent.updates // int(s.checkpoint_every) + 1) * int(s.checkpoint_every)
        budget_min = None if s.max_wall_clock_s is None else float(s.max_wall_clock_s) / 60

        def minutes() -> float:
            return (time.perf_counter() - start) / 60

        if budget_min is None:  # the episode budget bounds the run
            bar = progress_bar(total=int(s.total_episodes), initial=counters["episodes"], desc="train", unit="episode",
                               enabled=bool(s.progress))
        else:  # the wall-clock budget bounds it (total_episodes is a cap): progress in its unit, minutes
            bar = progress_bar(total=round(budget_min, 2), initial=round(min(minutes(), budget_min), 2),
                               desc="train (wall-clock budget)", unit="min", enabled=bool(s.progress),
                               bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} min [{elapsed}<{remaining}{postfix}]")
        rate_t, rate_steps, rate_updates = time.perf_counter(), counters["env_steps"], agent.updates

        def budget_spent() -> bool:
            return counters["episodes"] >= int(s.total_episodes) or (
                s.max_wall_clock_s is not None and time.perf_counter() - start >= float(s.max_wall_clock_s))

        # a run stopped after its last checkpoint (in its final evaluation) resumes to that evaluation, no further episode
        spent = budget_spent()
        if spent:
            log.info(f"the budget was spent at {counters['episodes']} episodes: final evaluation only")
        elif resuming and (out_dir / "final_metrics.json").exists():  # a finished run given a larger budget
            earlier = out_dir / f"final_metrics_at_{counters['episodes']}_episodes.json"
            (out_dir / "final_metrics.json").replace(earlier)
            log.info(f"extending a finished run from {counters['episodes']} episodes: its final metrics moved to "
                     f"{earlier.name}")
        for step in () if spent else collected_steps(collector):  # one transition at a time; worker weights refreshed per batch
            episode = episodes.add(step)
            counters["env_steps"] += 1
            episode_over = episode is not None
            if episode_over:
                replay.extend_episode(episode)
                counters["episodes"] += 1
                recent.append(float(bool(step["next", "terminated"]) and float(step["next", "reward"]) > 0))
                done = {} if budget_min is None else {"episodes": counters["episodes"]}
                bar.set_postfix(**done, updates=agent.updates, success_last100=f"{sum(recent) / len(recent):.2f}",
                                refresh=False)
                bar.update(1 if budget_min is None else round(min(minutes(), budget_min) - bar.n, 2))
            for _ in range(updates_due(counters["env_steps"], s.updates_per_step)):
                batch = replay.sample()
                metrics = agent.update(batch)
                replay.update_priority(batch["index"], batch["td_error"])
                replay.beta = float(beta(agent.updates))
            if logger is not None and counters["env_steps"] % 10 == 0:
                now = time.perf_counter()  # rates over the last 10 env steps (an evaluation in between counts)
                rates = {"train/env_steps_per_s": (counters["env_steps"] - rate_steps) / (now - rate_t),
                         "train/updates_per_s": (agent.updates - rate_updates) / (now - rate_t)}
                rate_t, rate_steps, rate_updates = now, counters["env_steps"], agent.updates
                logger.log_metrics({**metrics, **agent.learning_rates(), **agent.planner.hyperparameters(), **rates,
                                    "train/success_last100": sum(recent) / max(1, len(recent))}, step=agent.updates)
            if agent.updates >= next_eval:
                evaluate(int(s.eval_episodes))
                next_eval += int(s.eval_every)
            if not episode_over:
                continue
            finished = budget_spent()
            if agent.updates >= next_checkpoint or stop.requested or finished:
                with stop.saving():
                    save()
                next_checkpoint = (agent.updates // int(s.checkpoint_every) + 1) * int(s.checkpoint_every)
            if stop.requested:
                shutdown_collector(collector)
                bar.close()
                position = None if budget_min is None else (
                    f"episode {counters['episodes']}, {minutes():.1f} of {budget_min:.1f} min of the wall-clock budget")
                raise RunStopped(stop.signal_name, counters["episodes"], int(s.total_episodes), checkpoint_path,
                                 unit="episode", position=position)
            if finished:
                break
    bar.close()
    shutdown_collector(collector)
    final, final_returns, final_blocks = evaluate(int(s.final_eval_episodes))
    summary = {"agent": agent.name, "task": cfg.env.id, "num_objects": int(cfg.env.num_objects), "seed": int(cfg.seed),
               "preset": str(cfg.agent.preset or cfg.model.preset), **{k: final[k] for k in CURVE_FIELDS},
               "episodes_final_eval": final["eval_episodes"], "replay_bytes_per_transition": replay.bytes_per_transition()}
    if packing:
        summary["packing"] = packing_report(eval_env, final_returns, final_blocks, seed=evaluation_scenes(cfg.seed),
                                            progress=bool(s.progress))
        log.info(f"bin packing, final weights: {packing_line(summary['packing'])}; the scripted expert on the same "
                 f"scenes: {packing_line(summary['packing']['expert'])}")
    if s.keep_best and (out_dir / BEST_NAME).exists():
        # the selected weights on scenes the selection never saw (evaluate.py's seed), not on the curve's
        agent.load_policy_state_dict(load_checkpoint(out_dir / BEST_NAME, map_location=device).state["agent"])
        result = evaluate_policy(eval_env, agent.greedy_policy, int(s.final_eval_episodes), seed=held_out_scenes(cfg.seed),
                                 progress=bool(s.progress))
        summary["best"] = {"selected_at": {k: best[k] for k in ("updates", "episodes", "env_steps", "wall_s", "success_rate")},
                           **{("eval_episodes" if k == "episodes" else k): v for k, v in result.as_dict().items()}}
        log.info(f"best in-training evaluation ({100 * best['success_rate']:.0f}% at {best['updates']} updates, "
                 f"{best['wall_s'] / 60:.1f} min) -> {BEST_NAME}: {result} on held-out scenes")
    close_logger(logger)
    summary["total_wall_s"] = time.perf_counter() - start  # training and every final evaluation
    atomic_write_text(out_dir / "final_metrics.json", json.dumps(summary, indent=2))
    log.info(f"done: greedy success {100 * final['success_rate']:.1f}% over {final['eval_episodes']} episodes "
             f"after {counters['episodes']} training episodes / {final['wall_s'] / 60:.1f} min; "
             f"{summary['total_wall_s'] / 60:.1f} min in all with the final evaluations -> {out_dir}")
    return summary


if __name__ == "__main__":
    sys.argv = check_command_line(__file__, config_name="train_policy", checkpoint_name="checkpoint.pt")
    main()
