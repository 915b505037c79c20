"""Headless PyBullet pick-and-place tasks as gymnasium and TorchRL envs (docs/environments.md).

Importing this package registers the gymnasium ids:

======================================  ===============================================
``ldm_rl/BlockStacking-v0``             stack ``num_objects`` cubes (3; 4 and 5 zero-shot)
``ldm_rl/HouseBuilding-v0``             two cubes side by side and a roof spanning both
``ldm_rl/BottleArrangement-v0``         ``num_objects`` bottles (6; 4, 5) into a 6-slot tray
``ldm_rl/BinPacking-v0``                8 blocks of 5 shapes into a bin, keep the pile low
======================================  ===============================================

``make_env(env_id, **kwargs)`` wraps one as a TorchRL env; ``make_env_from_config(cfg.env)`` does
the same from a Hydra node; ``expert_policy(env)`` plays the scripted expert in ``env.rollout``.
"""

from __future__ import annotations

from ldm_rl.envs.base import ExpertNoise, PickPlaceEnv
from ldm_rl.envs.registry import ENV_IDS, register_envs
from ldm_rl.envs.torchrl_env import expert_policy, make_env, make_env_from_config

__all__ = ["ENV_IDS", "ExpertNoise", "PickPlaceEnv", "expert_policy", "make_env", "make_env_from_config",
           "register_envs"]

register_envs()
