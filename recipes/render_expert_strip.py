"""Render one noiseless expert episode of ``cfg.env`` as a PNG strip of heightmaps (for the docs).

    python recipes/render_expert_strip.py env=house_building seed=3
    python recipes/render_expert_strip.py env=bottle_arrangement env.num_objects=4 demos.strip.out=/tmp/b.png

Each frame is the heightmap before a step (colour = height, 0 … ``cfg.env.max_height``), with the
expert's action drawn on it: a circle at the pixel and a bar along the finger-closing direction
(white = pick, black = place); the last frame is the final state.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)
REPO = Path(__file__).resolve().parents[1]


def strip_image(frames, actions, num_rotations: int, max_height: float, scale: int):
    """``frames`` [T+1] heightmaps ``[H, W]`` m, ``actions`` [T] ``[row, col, rot]`` -> BGR uint8 image."""
    import math

    import cv2
    import numpy as np

    tiles = []
    for k, frame in enumerate(frames):
        gray = (np.clip(frame / max_height, 0.0, 1.0) * 255).astype(np.uint8)
        tile = cv2.applyColorMap(cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST),
                                 cv2.COLORMAP_VIRIDIS)
        if k < len(actions):
            row, col, rot = (int(v) for v in actions[k])
            angle = rot * math.pi / num_rotations
            color = (255, 255, 255) if k % 2 == 0 else (0, 0, 0)
            centre = np.array([col + 0.5, row + 0.5]) * scale  # cv2 points are (x=col, y=row)
            # the fingers close along (row, col) direction (cos θ, sin θ)
            half = 8 * scale * np.array([math.sin(angle), math.cos(angle)])
            cv2.line(tile, tuple(int(v) for v in centre - half), tuple(int(v) for v in centre + half), color, 2)
            cv2.circle(tile, tuple(int(v) for v in centre), 3 * scale, color, 2)
        tiles.append(cv2.copyMakeBorder(tile, 2, 2, 2, 2, cv2.BORDER_CONSTANT, value=(255, 255, 255)))
    return np.concatenate(tiles, axis=1)


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> None:
    import cv2
    import gymnasium as gym

    from ldm_rl.envs import register_envs
    from ldm_rl.envs.torchrl_env import env_kwargs_from_config
    from ldm_rl.runtime import atomic_path

    register_envs()
    env_id, kwargs = env_kwargs_from_config(OmegaConf.to_container(cfg.env, resolve=True))
    env = gym.make(env_id, **kwargs).unwrapped
    obs, _ = env.reset(seed=cfg.seed)
    frames, actions = [obs["heightmap"][0]], []
    for _ in range(env.max_steps):
        action = env.expert_action()
        obs, reward, terminated, truncated, info = env.step(action)
        frames.append(obs["heightmap"][0])
        actions.append(action)
        if terminated or truncated:
            break
    env.close()
    image = strip_image(frames, actions, env.num_rotations, float(cfg.env.max_height), int(cfg.demos.strip.scale))
    task = env_id.split("/")[-1].split("-")[0]
    out = Path(cfg.demos.strip.out) if cfg.demos.strip.out else REPO / "docs" / "img" / f"expert_{task}.png"
    if out.suffix.lower() != ".png":
        raise ValueError(f"demos.strip.out must end in .png, got {str(out)!r}")
    with atomic_path(out) as tmp:  # the temporary keeps the name, so cv2 sees the .png suffix
        if not cv2.imwrite(str(tmp), image):
            raise RuntimeError(f"cv2 could not write {out}")
    log.info("%s: %d steps, success=%s, strip -> %s", env_id, len(actions), info["is_success"], out)


if __name__ == "__main__":
    main()
