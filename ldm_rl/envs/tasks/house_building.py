"""House building (the paper's "house building 2"): two cubes side by side and a roof spanning both."""

from __future__ import annotations

import math

import numpy as np

from ldm_rl.envs.base import PickPlaceEnv, SpawnError, PrimitiveTarget
from ldm_rl.envs.objects import CUBE, ROOF, spawn

__all__ = ["HouseBuildingEnv"]

CUBE_SIZE = 2 * CUBE.half_extents[0]
CUBE_GAP = 0.07  # m between the cube centres of the finished house (anchor 1.7-2.0 cube sizes)
MAX_TILT = math.pi / 9  # a roof tilted more than 20° ends the episode
ROOF_REST_ON_CUBES = CUBE_SIZE + ROOF.rest_z  # roof origin height when it lies on the cubes


class HouseBuildingEnv(PickPlaceEnv):
    """Success (the anchor's check): both cubes on the table, the roof upright on top of both, touching both.

    How far apart the cubes stand is not checked: a roof that rests upright on both is a house at whatever
    spacing the physics lets it rest (the expert builds at 7 cm; the 11.2 cm roof rests on both cubes up to
    ≈ 15 cm between their centres)."""

    max_height = 0.15

    def __init__(self, num_objects: int = 3, **kwargs):
        super().__init__(num_objects, **kwargs)

    @classmethod
    def _check_object_count(cls, n: int) -> None:
        if n != 3:
            raise ValueError(f"num_objects must be 3 for house building (2 cubes + roof), got {n!r}")

    @property
    def cubes(self):
        return [o for o in self.sim.objects if o.kind == "cube"]

    @property
    def roof(self):
        return next(o for o in self.sim.objects if o.kind == "roof")

    def _build_scene(self, rng: np.random.Generator) -> None:
        cubes = self._sample_positions(rng, 2, padding=0.048, min_distance=0.16)
        (roof_xy,) = self._sample_positions(rng, 1, padding=0.068, min_distance=0.136, existing=cubes)
        for x, y in cubes:
            spawn(self.sim, CUBE, x, y, rng.uniform(0, 2 * math.pi))
        spawn(self.sim, ROOF, *roof_xy, rng.uniform(0, 2 * math.pi))

    def _build_goal_scene(self, rng: np.random.Generator) -> None:
        """A finished house: cubes 7-8 cm apart (anchor: 1.9-2.0 cube sizes), roof across them."""
        (mid,) = self._sample_positions(rng, 1, padding=0.1, min_distance=0.0)
        angle = rng.uniform(0, 2 * math.pi)
        d = 0.5 * rng.uniform(CUBE_GAP, 0.08) * np.array([math.cos(angle), math.sin(angle)])
        for p in (mid - d, mid + d):
            spawn(self.sim, CUBE, p[0], p[1], angle)
        spawn(self.sim, ROOF, mid[0], mid[1], angle - math.pi / 2, z=ROOF_REST_ON_CUBES)

    def _invalid_reason(self) -> str:
        reason = super()._invalid_reason()
        if reason:
            return reason
        roof = self.roof
        if self.holding is not roof and self.sim.tilt(roof.body) > MAX_TILT:
            return "roof tipped over"
        return ""

    def _cubes_on_table(self) -> bool:
        """Both cubes on the table (neither on the other, so both free on top: the roof is the only load)."""
        return all(self.sim.pose(c.body)[0][2] < 0.75 * CUBE_SIZE for c in self.cubes)

    def _cubes_arranged(self) -> bool:
        """The expert's plan: both cubes on the table 5.5-9 cm apart, where its roof placement spans them."""
        a, b = (self.sim.pose(c.body)[0][:2] for c in self.cubes)
        return self._cubes_on_table() and bool(0.055 < np.linalg.norm(a - b) < 0.09)

    def _is_success(self) -> bool:
        roof = self.roof
        z = self.sim.pose(roof.body)[0][2]
        return bool(
            self._cubes_on_table()
            and abs(z - ROOF_REST_ON_CUBES) < 0.01
            and self.sim.tilt(roof.body) < MAX_TILT
            and all(self.sim.touching(roof.body, c.body) for c in self.cubes)
        )

    def expert_target(self) -> PrimitiveTarget:
        """Move one cube beside the other, then put the roof across both."""
        held, roof = self.holding, self.roof
        if held is None:
            if self._cubes_arranged():
                return self._grasp(roof, math.pi)
            if self.sim.pose(roof.body)[0][2] > 0.03:  # the roof rests on a cube: clear it first
                return self._grasp(roof, math.pi)
            return self._grasp(self._cube_to_move(), math.pi / 2)
        if held is roof:
            if not self._cubes_arranged():
                x, y = self._free_spot(0.09)
                return self._place_held(x, y, self.sim.yaw(roof.body), math.pi)
            a, b = (self.sim.pose(c.body)[0][:2] for c in self.cubes)
            mid, d = 0.5 * (a + b), b - a
            return self._place_held(mid[0], mid[1], math.atan2(d[1], d[0]) - math.pi / 2, math.pi)
        anchor = next(c for c in self.cubes if c is not held)
        x, y = self._beside(anchor)
        return self._place_held(x, y, self.sim.yaw(anchor.body), math.pi / 2)

    def _cube_to_move(self):
        """The cube on top of the other if stacked, else the one with the more cramped surroundings."""
        a, b = self.cubes
        za, zb = self.sim.pose(a.body)[0][2], self.sim.pose(b.body)[0][2]
        if abs(za - zb) > 0.5 * CUBE_SIZE:
            return a if za > zb else b
        return b if self._beside_score(a) >= self._beside_score(b) else a

    def _beside_candidates(self, anchor) -> tuple[np.ndarray, np.ndarray]:
        """[16, 2] spots at the house spacing around ``anchor`` and their clearance (m)."""
        p = self.sim.pose(anchor.body)[0][:2]
        angles = np.arange(16) * (2 * math.pi / 16) + self.sim.yaw(anchor.body)
        spots = p + CUBE_GAP * np.stack([np.cos(angles), np.sin(angles)], -1)
        mid = 0.5 * (spots + p)
        others = [self.sim.pose(o.body)[0][:2] for o in self._scene_objects() if o.kind != "cube"]
        ws = self.workspace
        # the roof will span 5.6 cm either side of the midpoint; keep it in the workspace
        border = np.minimum.reduce([
            mid[:, 0] - ws.x_min, ws.x_min + ws.size - mid[:, 0], mid[:, 1] - ws.y_min, ws.y_min + ws.size - mid[:, 1],
        ]) - ROOF.half_extents[1]
        clearance = border
        for q in others:
            clearance = np.minimum(clearance, np.linalg.norm(spots - q, axis=1) - 0.06)
            clearance = np.minimum(clearance, np.linalg.norm(mid - q, axis=1) - 0.08)
        return spots, clearance

    def _beside_score(self, anchor) -> float:
        return float(self._beside_candidates(anchor)[1].max())

    def _beside(self, anchor) -> np.ndarray:
        spots, clearance = self._beside_candidates(anchor)
        return spots[int(np.argmax(clearance))]

    def _free_spot(self, min_distance: float) -> np.ndarray:
        try:
            return self._free_position(self._expert_rng, padding=0.06, min_distance=min_distance)
        except SpawnError:
            ws = self.workspace
            return np.array(ws.center)
