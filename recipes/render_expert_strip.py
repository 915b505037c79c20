"""Render one noiseless expert episode of ``cfg.env`` as a PNG of heightmaps, frame by frame (for the docs).

    python recipes/render_expert_strip.py env=house_building seed=3
    python recipes/render_expert_strip.py env=bottle_arrangement env.num_objects=4 demos.strip.out=/tmp/b.png

Each frame is the heightmap before a step, titled with the step number and pick/place, with the expert's
action drawn on it: a ring at the pixel and a bar along the finger-closing direction (white = pick,
black = place); the last frame is the final state; one colour bar in metres (0 … ``cfg.env.max_height``).
The title names the task, the object count, the steps and the outcome. Drawn by
``ldm_rl.plots.plot_expert_strip`` (needs matplotlib: ``pip install 'ldm_rl[plot]'``).
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from ldm_rl.run.cli import check_command_line  # registers the schema

log = logging.getLogger(__name__)
DPI = 100


@hydra.main(version_base="1.3", config_path="../conf", config_name="render_expert_strip")
def main(cfg: DictConfig) -> None:
    import gymnasium as gym
    import numpy as np

    from ldm_rl.envs import register_envs
    from ldm_rl.envs.torchrl_env import env_kwargs_from_config
    from ldm_rl.plots import plot_expert_strip, require_matplotlib
    from ldm_rl.torch_utils import set_threads

    require_matplotlib()
    set_threads(cfg.threads)
    task_name = str(cfg.env.id).split("/")[-1].split("-")[0]
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    out = Path(cfg.demos.strip.out) if cfg.demos.strip.out else run_dir / f"expert_{task_name}.png"
    if out.suffix.lower() != ".png":
        raise ValueError(f"demos.strip.out must end in .png, got {str(out)!r}")
    register_envs()
    env_id, kwargs = env_kwargs_from_config(OmegaConf.to_container(cfg.env, resolve=True))
    env = gym.make(env_id, **kwargs).unwrapped
    obs, _ = env.reset(seed=cfg.seed)
    frames, actions, picks = [obs["heightmap"][0]], [], []
    for _ in range(env.max_steps):
        action = env.expert_action()
        picks.append(not bool(np.asarray(obs["holding"]).any()))
        obs, reward, terminated, truncated, info = env.step(action)
        frames.append(obs["heightmap"][0])
        actions.append(action)
        if terminated or truncated:
            break
    env.close()
    outcome = "success" if info["is_success"] else "failure"
    title = (f"{task_name} ({cfg.env.num_objects} objects): the scripted expert, {len(actions)} steps, {outcome} "
             f"(seed {cfg.seed})")
    plot_expert_strip(np.stack(frames), np.asarray(actions), out, max_height=float(cfg.env.max_height),
                      num_rotations=env.num_rotations, is_pick=picks, title=title,
                      panel_inches=128 * int(cfg.demos.strip.scale) / DPI, dpi=DPI)
    log.info("%s: %d steps, success=%s, strip -> %s", env_id, len(actions), info["is_success"], out)


if __name__ == "__main__":
    sys.argv = check_command_line(__file__, config_name="render_expert_strip")
    main()
