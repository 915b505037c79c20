"""Block stacking: stack ``num_objects`` 4 cm cubes into one tower (3 for training, 4-5 zero-shot)."""

from __future__ import annotations

import math

import numpy as np

from ldm_rl.envs.base import PickPlaceEnv, PrimitiveTarget
from ldm_rl.envs.objects import CUBE, spawn

__all__ = ["BlockStackingEnv", "on_top_objects", "is_column"]

CUBE_SIZE = 2 * CUBE.half_extents[0]
SPAWN_DISTANCE = 0.096  # m between cube centres and from the workspace border (anchor: 2.4·b)


def on_top_objects(env: PickPlaceEnv, objects=None) -> list:
    """Objects with nothing resting on them (no other object above within a cube size in xy)."""
    objects = env._scene_objects() if objects is None else objects
    pos = {o.body: env.sim.pose(o.body)[0] for o in objects}
    top = []
    for o in objects:
        p = pos[o.body]
        covered = any(
            q[2] > p[2] + 0.01 and np.linalg.norm(q[:2] - p[:2]) < CUBE_SIZE for b, q in pos.items() if b != o.body
        )
        if not covered:
            top.append(o)
    return top


class BlockStackingEnv(PickPlaceEnv):
    """Success: every cube in one vertical column (each on the one below, xy within 2 cm)."""

    max_height = 0.25

    def __init__(self, num_objects: int = 3, **kwargs):
        super().__init__(num_objects, **kwargs)

    def _build_scene(self, rng: np.random.Generator) -> None:
        positions = self._sample_positions(rng, self.num_objects, padding=SPAWN_DISTANCE / 2,
                                           min_distance=SPAWN_DISTANCE)
        for x, y in positions:
            spawn(self.sim, CUBE, x, y, rng.uniform(0, 2 * math.pi))

    def _build_goal_scene(self, rng: np.random.Generator) -> None:
        """A finished tower at a random spot, all cubes sharing one random yaw."""
        (x, y), = self._sample_positions(rng, 1, padding=0.06, min_distance=0.0)
        yaw = rng.uniform(0, 2 * math.pi)
        for i in range(self.num_objects):
            spawn(self.sim, CUBE, x, y, yaw, z=CUBE.rest_z + i * CUBE_SIZE)

    def _is_success(self) -> bool:
        return is_column(self.sim.positions())

    def expert_target(self) -> PrimitiveTarget:
        """Pick the highest loose top cube outside the tallest stack; place it on the tallest."""
        tops = sorted(on_top_objects(self), key=lambda o: (-round(self.sim.pose(o.body)[0][2], 3), o.body))
        held = self.holding
        if held is None:
            # the tallest stack is kept; pick the highest other top cube
            return self._grasp(tops[1] if len(tops) > 1 else tops[0], math.pi / 2)
        base = tops[0]
        bx, by = self.sim.pose(base.body)[0][:2]
        return self._place_held(bx, by, self.sim.yaw(base.body), math.pi / 2)


def is_column(positions: np.ndarray, size: float = CUBE_SIZE) -> bool:
    """True when the [N, 3] cube centres form one tower: bottom on the table, each cube one size
    above the previous (±25 %) and within half a size in xy."""
    order = np.argsort(positions[:, 2])
    p = positions[order]
    if p[0, 2] > 0.75 * size:
        return False
    dz = np.diff(p[:, 2])
    dxy = np.linalg.norm(np.diff(p[:, :2], axis=0), axis=1)
    return bool(np.all(np.abs(dz - size) < 0.25 * size) and np.all(dxy < 0.5 * size))
