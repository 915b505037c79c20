"""Evaluate a trained agent's greedy policy on its task or a zero-shot variant (more objects).

    python recipes/evaluate.py checkpoint=outputs/<date>/<time>/checkpoint.pt                 # 100 episodes
    python recipes/evaluate.py checkpoint=... num_objects=4          # a 3-block agent on 4 blocks (Table 2)
    python recipes/evaluate.py -m checkpoint=... num_objects=4,5
    python recipes/evaluate.py checkpoint=... planner.name=tree            # the same weights, 2 steps ahead
    python recipes/evaluate.py checkpoint=... online_weights=true    # agent.greedy_ema_decay runs: not the average
    python recipes/evaluate.py checkpoint=... q_pick_min_height=0.015   # Q proposes no pick on bare table
    python recipes/evaluate.py checkpoint=... hand_rule=removal        # the world model reads holding' another way

Rebuilds the agent from the configuration stored in the checkpoint, plays ``episodes`` episodes under
``ExplorationType.DETERMINISTIC`` and logs the success rate with a 95 % Wilson interval (bin packing adds
``packing``: packed fraction, mean pile top, mean return under ours and the authors' reward, blocks in the
bin at the end, for the agent and for the scripted expert on the same scenes; ``played_with``: Q's pick mask
and the LDM agent's planner settings the decisions used, the checkpoint's own unless overridden; ``picks``: the
primitives taken with an empty hand and how many held an object, in all and per episode; ``undone``: the places
that put back what the pick before them took, half of a 2-cycle, in all and the episodes with one); writes
``evaluation.json``, ``config_resolved.yaml`` and ``evaluate.log`` (what the console showed) to the run folder.
``progress``: a bar with ETA on a terminal, else plain lines every 10 % or 30 s.

Pictures of the first ``render.episodes`` episodes (needs matplotlib: ``pip install 'ldm_rl[plot]'``):

    python recipes/evaluate.py checkpoint=... render.episodes=2               # decisions/*.png + episodes.gif

``decisions/episodeEE_stepTT.png``: the heightmap, the Q map (max over rotations), the N candidates and their
values, the chosen action; ``episodes.gif``: each step's heightmap before, the world model's predicted next
heightmap for the chosen action, and the real next one. The pictures are drawn after the episodes from
what ``env.rollout`` already returns, so ``render.episodes=0`` (the default) costs nothing.
"""

from __future__ import annotations

import json
import logging
import re
import sys

import hydra
from omegaconf import DictConfig

from ldm_rl.config_schema import EvaluateConfig, validate_config
from ldm_rl.run.cli import check_command_line

log = logging.getLogger("evaluate")


@hydra.main(version_base="1.3", config_path="../conf", config_name="evaluate")
def main(cfg: DictConfig) -> dict:
    from ldm_rl.run.checkpoint import CheckpointError
    from ldm_rl.plots import PlotDependencyError

    try:
        return evaluate(cfg)
    except (CheckpointError, PlotDependencyError) as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None


def evaluate(cfg: DictConfig) -> dict:
    """Rebuild, play, report."""
    from ldm_rl.agents import load_agent
    from ldm_rl.envs import make_env_from_config
    from ldm_rl.envs.tasks.bin_packing import pile_tops
    from ldm_rl.run.checkpoint import CheckpointError
    from ldm_rl.evaluation import (episode_record, episode_succeeded, evaluate_policy, is_bin_packing, packing_line,
                                   packing_report, pick_counts, undone_places)
    from ldm_rl.seeds import held_out_scenes
    from ldm_rl.run.outputs import atomic_write_text, hydra_output_dir, save_resolved_config
    from ldm_rl.torch_utils import resolve_device, seed_everything, set_threads

    validate_config(cfg, EvaluateConfig)
    keep = int(cfg.render.episodes)
    if keep:
        from ldm_rl.plots import require_matplotlib

        require_matplotlib()  # before any episode is played
    set_threads(cfg.threads)
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # its INFO lines (a buffer's storage initialised) are noise here
    seed_everything(int(cfg.seed))
    save_resolved_config(cfg, hydra_output_dir())
    path = hydra.utils.to_absolute_path(str(cfg.checkpoint))
    planner = {key: value for key, value in cfg.planner.items() if value is not None}
    # these decisions are all greedy: an overridden λ or w is theirs, over a greedy one the checkpoint's planner may hold
    greedy = {f"greedy_{key}": planner[key] for key in ("uncertainty_penalty", "q_blend") if key in planner}
    agent, train_cfg = load_agent(path, preset=cfg.preset, device=resolve_device(cfg.device),
                                  planner={**planner, **greedy},
                                  q_pick_min_height=cfg.q_pick_min_height, hand_rule=cfg.hand_rule,
                                  height_anchor=cfg.height_anchor)
    env_cfg = dict(train_cfg["env"])
    for key in ("num_objects", "max_steps", "failed_pick_memory", "scene_memory"):
        if cfg[key] is not None:
            env_cfg[key] = int(cfg[key])
    if cfg.finger_spinning_friction is not None:
        env_cfg["finger_spinning_friction"] = float(cfg.finger_spinning_friction)
    if cfg.num_objects is not None and cfg.max_steps is None:
        env_cfg["max_steps"] = None  # 2·objects + slack for the new object count
    if getattr(getattr(agent, "planner", None), "revisits_last", False) and not env_cfg.get("scene_memory"):
        raise CheckpointError(f"planner.revisits_last=true reads the scenes the env remembers, but scene_memory is "
                              f"{env_cfg.get('scene_memory', 0)} for {path}: set scene_memory=8 (or another count > 0)")
    env = make_env_from_config(env_cfg)
    recorded: list = []
    returns: list[float] = []
    blocks_in_bin: list[int] | None = [] if is_bin_packing(env) else None
    record = episode_record(env, returns, blocks_in_bin)
    # in scene order, for paired comparisons; picks: primitives taken with an empty hand, picks_held: those that held,
    # undone: places that put back what the pick before them took (half a 2-cycle: pick, put back, pick again)
    per_episode: dict[str, list] = {"success": [], "length": [], "picks": [], "picks_held": [], "undone": []}
    if blocks_in_bin is not None:
        per_episode["blocks_in_bin"] = blocks_in_bin  # bin packing: the blocks in the bin at each episode's end

    def on_episode(index, rollout) -> None:
        record(index, rollout)
        per_episode["success"].append(int(episode_succeeded(rollout)))
        per_episode["length"].append(int(rollout.shape[0]))
        picks, held = pick_counts(rollout)
        per_episode["picks"].append(picks)
        per_episode["picks_held"].append(held)
        per_episode["undone"].append(undone_places(rollout))
        if index < keep:
            recorded.append(rollout)

    scenes = held_out_scenes(cfg.seed)
    try:
        policy = agent.evaluation_policy(online_weights=bool(cfg.online_weights))
    except ValueError as err:
        raise CheckpointError(f"online_weights=true {err}: {path}") from None
    result = evaluate_policy(env, policy, int(cfg.episodes), seed=scenes, progress=bool(cfg.progress),
                             on_episode=on_episode)
    summary = {"checkpoint": path, "scene_seed": int(cfg.seed), "task": env_cfg["id"],
               "num_objects": env_cfg["num_objects"],
               "trained_on": train_cfg["env"]["num_objects"], "agent": agent.name,
               "finger_spinning_friction": float(env_cfg.get("finger_spinning_friction", 0.0)), **result.as_dict()}
    picks, held = sum(per_episode["picks"]), sum(per_episode["picks_held"])
    summary["picks"] = {"picks": picks, "held": held, "held_rate": held / picks if picks else None}
    log.info(f"picks: {held} of {picks} held an object" + (f" ({100 * held / picks:.0f}%)" if picks else ""))
    undone = per_episode["undone"]
    summary["undone"] = {"places": sum(undone), "episodes": sum(n > 0 for n in undone)}
    log.info(f"places that put back what the pick before took: {sum(undone)}, in {summary['undone']['episodes']} "
             f"of {len(undone)} episodes")
    if blocks_in_bin is not None:  # and the scripted expert on the same scenes
        per_episode["pile_top"] = pile_tops(returns)  # m where it packed, else None: the pile scene by scene
        summary["packing"] = packing_report(env, returns, blocks_in_bin, seed=scenes, progress=bool(cfg.progress))
        log.info(f"bin packing: {packing_line(summary['packing'])}; the scripted expert on the same scenes: "
                 f"{packing_line(summary['packing']['expert'])}")
    if planner:
        summary["planner"] = planner
    summary["played_with"] = played_with(agent, train_cfg)
    if cfg.failed_pick_memory is not None:
        summary["failed_pick_memory"] = int(cfg.failed_pick_memory)
    if cfg.scene_memory is not None:
        summary["scene_memory"] = int(cfg.scene_memory)
    if cfg.hand_rule is not None:
        summary["hand_rule"] = str(cfg.hand_rule)
    if cfg.height_anchor is not None:
        summary["height_anchor"] = float(cfg.height_anchor)
    if cfg.q_pick_min_height is not None:
        summary["q_pick_min_height"] = float(cfg.q_pick_min_height)
    if cfg.online_weights:
        summary["online_weights"] = True
    summary["per_episode"] = per_episode
    if recorded:
        summary["pictures"] = render_episodes(recorded, agent, cfg, hydra_output_dir(), max_height=float(env_cfg["max_height"]),
                                              num_rotations=int(env_cfg["num_rotations"]),
                                              label=f"{agent.name} agent, {env_cfg['id']} ({env_cfg['num_objects']} objects)")
    atomic_write_text(hydra_output_dir() / "evaluation.json", one_line_lists(json.dumps(summary, indent=2)))
    log.info(f"{agent.name} agent on {env_cfg['id']} with {env_cfg['num_objects']} objects: {result}")
    return summary


def one_line_lists(text: str) -> str:
    """``json.dumps(..., indent=2)`` output with every list of scalars on one line (per-episode lists stay short)."""
    return re.sub(r"\[\n\s*([^\[\]{}]*?)\n\s*\]", lambda m: "[" + re.sub(r",\n\s*", ", ", m.group(1)) + "]", text)


# the settings of the greedy decisions that a checkpoint's own config and the overrides decide together, read from
# the planner as built (a tree selected by override has its constructor's depth and branching, in no config;
# uncertainty_penalty, q_blend: the greedy decisions' λ and w)
PLAYED_PLANNER_KEYS = ("num_candidates", "empty_picks_last", "pick_outcome", "pick_rotations", "revisits_last",
                       "uncertainty_penalty_on")
PLAYED_TREE_KEYS = ("depth", "branching", "penalty_depth")


def played_with(agent, cfg: dict) -> dict:
    """What the evaluated ``agent`` decided with (``cfg``: the config ``load_agent`` built it from): Q's empty-pick
    mask (m, 0 = off) for an agent with a Q network, the LDM agent's planner settings as its planner holds them, and
    the hand-state rule of the world model (where the agent has one)."""
    played = {}
    if agent.name != "rs":
        played["q_pick_min_height"] = float(cfg["agent"].get("q_pick_min_height") or 0.0)
    if agent.name == "ldm":
        planner = agent.planner
        name = cfg["planner"].get("name") or "diverse"
        keys = PLAYED_PLANNER_KEYS + (PLAYED_TREE_KEYS if name == "tree" else ())
        played["planner"] = {"name": name, **{key: getattr(planner, key) for key in keys},
                             "uncertainty_penalty": planner.penalty(greedy=True), "q_blend": planner.blend_weight(greedy=True)}
    model = world_model(agent)
    if model is not None:
        played["hand_rule"] = model.hand_rule.kind
        if model.height_anchor is not None:
            played["height_anchor"] = model.height_anchor
    return played


def world_model(agent):
    """The agent's dynamics model (its planner's, else its LDM loss'), or None (FC-DQN has none)."""
    from ldm_rl.world_model import DynamicsModel

    for owner in (agent.greedy_policy, getattr(agent, "dynamics_loss", None)):
        model = getattr(owner, "dynamics", None)
        if isinstance(model, DynamicsModel):
            return model
    return None


def render_episodes(rollouts: list, agent, cfg: DictConfig, out_dir, *, max_height: float, num_rotations: int,
                    label: str) -> dict:
    """``decisions/*.png`` (if ``render.decisions``) and ``episodes.gif`` (if ``render.gif``) of the recorded
    episodes in ``out_dir``; returns what was written (paths relative to ``out_dir``)."""
    from ldm_rl.evaluation import episode_steps
    from ldm_rl.plots import plot_decision, plot_episodes_gif
    from ldm_rl.run.progress import progress_bar

    dynamics, q_network = world_model(agent), getattr(agent.greedy_policy, "q_network", None)
    steps = [row for index, rollout in enumerate(rollouts)
             for row in episode_steps(rollout, episode=index, dynamics=dynamics, q_network=q_network)]
    written: dict = {}
    if cfg.render.decisions:
        names = []
        for row in progress_bar(steps, desc="decisions", unit="png", enabled=bool(cfg.progress)):
            name = f"decisions/episode{row['episode'] + 1:02d}_step{row['step'] + 1:02d}.png"
            plot_decision(row["heightmap"], row.get("q_map"), row.get("candidates"), row.get("values"), row["action"],
                          out_dir / name, max_height=max_height, num_rotations=num_rotations, is_pick=row["is_pick"],
                          title=f"{label}, episode {row['episode'] + 1}, step {row['step'] + 1}/{row['num_steps']}")
            names.append(name)
        written["decisions"] = names
    if cfg.render.gif:
        plot_episodes_gif(steps, out_dir / "episodes.gif", max_height=max_height, num_rotations=num_rotations,
                          fps=float(cfg.render.fps), title=label)
        written["gif"] = "episodes.gif"
    log.info(f"pictures of {len(rollouts)} episode(s) ({len(steps)} steps) -> {out_dir}")
    return written


if __name__ == "__main__":
    sys.argv = check_command_line(__file__, config_name="evaluate")
    main()
