"""Bottle arrangement: put ``num_objects`` bottles (6; 4 and 5 too) upright into a 6-slot tray."""

from __future__ import annotations

import math

import numpy as np

from ldm_rl.envs.base import PickPlaceEnv, SpawnError, PrimitiveTarget
from ldm_rl.envs.objects import ContainerFrame, ContainerSpec, add_container, bottle_spec, spawn

__all__ = ["BottleArrangementEnv", "TRAY", "BOTTLES"]

TRAY = ContainerSpec(inner_x=0.22, inner_y=0.14, height=0.05)  # outer 0.24 × 0.16 m (the anchor's tray)
SLOTS = np.array([[sx, sy] for sy in (-0.04, 0.04) for sx in (-0.08, 0.0, 0.08)])  # tray frame, m
BOTTLES = tuple(bottle_spec(h) for h in (0.10, 0.115, 0.13))
MAX_TILT = math.pi / 9  # a bottle tilted more than 20° ends the episode
TRAY_MARGIN = 0.045  # m between the tray's outer walls and spawned bottle centres
BOTTLE_DISTANCE = 0.09  # m between spawned bottle centres


class BottleArrangementEnv(PickPlaceEnv):
    """Success: every bottle upright on the tray floor. A tipped bottle terminates (reward 0)."""

    max_height = 0.2
    pick_depth = 0.03

    def __init__(self, num_objects: int = 6, **kwargs):
        super().__init__(num_objects, **kwargs)
        self.tray = ContainerFrame(TRAY)

    @classmethod
    def _check_object_count(cls, n: int) -> None:
        if not 1 <= n <= len(SLOTS):
            raise ValueError(f"num_objects must be in 1..{len(SLOTS)} (tray slots), got {n!r}")

    # --- scene -----------------------------------------------------------------------------------
    def _build_scene(self, rng: np.random.Generator) -> None:
        half_diag = math.hypot(TRAY.inner_x / 2 + 0.01, TRAY.inner_y / 2 + 0.01)
        (xy,) = self._sample_positions(rng, 1, padding=half_diag, min_distance=0.0)
        self.tray = ContainerFrame(TRAY, (float(xy[0]), float(xy[1])), float(rng.uniform(0, math.pi)))
        add_container(self.sim, TRAY, *self.tray.xy, self.tray.yaw)
        outer = np.array([TRAY.inner_x / 2 + 0.01, TRAY.inner_y / 2 + 0.01])
        placed = self._sample_positions(
            rng, self.num_objects, padding=BOTTLE_DISTANCE / 2, min_distance=BOTTLE_DISTANCE, tries=200,
            accept=lambda p: bool(np.any(np.abs(self.tray.to_local(p)) > outer + TRAY_MARGIN)),
        )
        for p in placed:
            spawn(self.sim, BOTTLES[rng.integers(len(BOTTLES))], p[0], p[1], rng.uniform(0, 2 * math.pi))

    def _invalid_reason(self) -> str:
        reason = super()._invalid_reason()
        if reason:
            return reason
        for o in self._scene_objects():
            if self.sim.tilt(o.body) > MAX_TILT:
                return "bottle tipped over"
        return ""

    def _is_success(self) -> bool:
        for o in self.sim.objects:
            pos = self.sim.pose(o.body)[0]
            on_floor = pos[2] - o.half_extents[2] < TRAY.floor_top + 0.01
            if not (self.tray.contains(pos) and on_floor and self.sim.tilt(o.body) < MAX_TILT):
                return False
        return True

    # --- expert ----------------------------------------------------------------------------------
    def expert_target(self) -> PrimitiveTarget:
        """Pick a bottle outside the tray (fingers parallel to the nearest tray wall); place it in the
        first free slot with the fingers along the tray diagonal (clear of the neighbours)."""
        held = self.holding
        if held is None:
            outside = [o for o in self._scene_objects() if not self.tray.contains(self.sim.pose(o.body)[0])]
            target = (outside or self._scene_objects())[0]
            x, y = self.sim.pose(target.body)[0][:2]
            u, v = np.abs(self.tray.to_local(np.array([x, y])))
            beyond_ends = u - TRAY.inner_x / 2 > v - TRAY.inner_y / 2
            yaw = self.tray.yaw + (math.pi / 2 if beyond_ends else 0.0)
            return PrimitiveTarget(x, y, self.snap_yaw(yaw % math.pi))
        slot = self._free_slot()
        return self._place_held_with_yaw(slot[0], slot[1], (self.tray.yaw + math.pi / 4) % math.pi)

    def _free_slot(self) -> np.ndarray:
        """World xy of the first slot with no bottle within 3 cm."""
        slots = self.tray.to_world(SLOTS)
        bottles = [self.sim.pose(o.body)[0][:2] for o in self._scene_objects()]
        for s in slots:
            if all(np.linalg.norm(s - b) > 0.03 for b in bottles):
                return s
        return slots[0]
