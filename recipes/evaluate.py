"""Evaluate a trained agent's greedy policy on its task or a zero-shot variant (more objects).

    python recipes/evaluate.py checkpoint=outputs/<date>/<time>/checkpoint.pt                 # 100 episodes
    python recipes/evaluate.py checkpoint=... num_objects=4          # a 3-block agent on 4 blocks (Table 2)
    python recipes/evaluate.py -m checkpoint=... num_objects=4,5

Rebuilds the agent from the configuration stored in the checkpoint, plays ``episodes`` episodes under
``ExplorationType.DETERMINISTIC`` and prints the success rate with a 95 % Wilson interval; writes
``evaluation.json`` to the run folder.
"""

from __future__ import annotations

import json
import sys

import hydra
from omegaconf import DictConfig

from ldm_rl.config_schema import EvaluateConfig, check_command_line, validate_config


@hydra.main(version_base="1.3", config_path="../conf", config_name="evaluate")
def main(cfg: DictConfig) -> dict:
    from ldm_rl.checkpoint import CheckpointError

    try:
        return evaluate(cfg)
    except CheckpointError as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None


def evaluate(cfg: DictConfig) -> dict:
    """Rebuild, play, report."""
    from ldm_rl.agents import load_agent
    from ldm_rl.envs import make_env_from_config
    from ldm_rl.evaluation import evaluate_policy
    from ldm_rl.runtime import atomic_write_text, hydra_output_dir, resolve_device, seed_everything, set_threads

    validate_config(cfg, EvaluateConfig)
    set_threads(cfg.threads)
    seed_everything(int(cfg.seed))
    path = hydra.utils.to_absolute_path(str(cfg.checkpoint))
    agent, train_cfg = load_agent(path, preset=cfg.preset, device=resolve_device(cfg.device))
    env_cfg = dict(train_cfg["env"])
    for key in ("num_objects", "max_steps"):
        if cfg[key] is not None:
            env_cfg[key] = int(cfg[key])
    if cfg.num_objects is not None and cfg.max_steps is None:
        env_cfg["max_steps"] = None  # 2·objects + slack for the new object count
    env = make_env_from_config(env_cfg)
    result = evaluate_policy(env, agent.policy, int(cfg.episodes), seed=int(cfg.seed) + 2_000_000, progress=bool(cfg.progress))
    summary = {"checkpoint": path, "task": env_cfg["id"], "num_objects": env_cfg["num_objects"],
               "trained_on": train_cfg["env"]["num_objects"], "agent": agent.name, **result.as_dict()}
    atomic_write_text(hydra_output_dir() / "evaluation.json", json.dumps(summary, indent=2))
    print(f"{agent.name} agent on {env_cfg['id']} with {env_cfg['num_objects']} objects: {result}")
    return summary


if __name__ == "__main__":
    sys.argv = check_command_line(__file__, config_name="evaluate")
    main()
