"""The gymnasium ids of the tasks and their registration (imported by the package face and by the TorchRL
wrappers, which never import the face back)."""

from __future__ import annotations

import gymnasium as gym

__all__ = ["ENV_IDS", "register_envs"]

ENV_IDS = {
    "ldm_rl/BlockStacking-v0": "ldm_rl.envs.tasks.block_stacking:BlockStackingEnv",
    "ldm_rl/HouseBuilding-v0": "ldm_rl.envs.tasks.house_building:HouseBuildingEnv",
    "ldm_rl/BottleArrangement-v0": "ldm_rl.envs.tasks.bottle_arrangement:BottleArrangementEnv",
    "ldm_rl/BinPacking-v0": "ldm_rl.envs.tasks.bin_packing:BinPackingEnv",
}


def register_envs() -> None:
    """Register every task id with gymnasium (idempotent; call it in spawned worker processes)."""
    for env_id, entry_point in ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, disable_env_checker=True)
