"""Procedural object geometry (boxes, triangular prisms, cylinders, open containers); no mesh files.

Convention for every graspable object: its local x axis is the grasp direction (the narrow
horizontal side, ``half_extents[0]``), so the gripper yaw that grasps it squarely equals the object
yaw (mod the object's symmetry). The body origin is the centre of mass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pybullet as pb

from ldm_rl.envs.physics import BodyInfo, Simulation

__all__ = ["ObjectSpec", "CUBE", "ROOF", "bottle_spec", "BIN_BLOCKS", "spawn", "add_container", "ContainerSpec"]

RED = (0.85, 0.2, 0.2, 1.0)
BLUE = (0.2, 0.35, 0.85, 1.0)
GREEN = (0.2, 0.7, 0.3, 1.0)
WHITE = (0.9, 0.9, 0.9, 1.0)


@dataclass(frozen=True)
class ObjectSpec:
    """A movable object: ``shape`` is 'box', 'prism' (ridge along local x) or 'cylinder'."""

    kind: str
    shape: str
    half_extents: tuple[float, float, float]  # m
    mass: float = 0.1  # kg
    friction: float = 1.0
    color: tuple[float, float, float, float] = RED

    @property
    def rest_z(self) -> float:
        """Height of the origin when resting upright on the table."""
        return self.half_extents[2] * (2.0 / 3.0 if self.shape == "prism" else 1.0)


CUBE = ObjectSpec("cube", "box", (0.02, 0.02, 0.02))
# The house roof: a triangular prism 4 cm along its ridge (local x, the grasp direction), 11.2 cm
# across (local y, spanning both cubes) and 3.9 cm tall (the anchor's roof at scale 0.8).
ROOF = ObjectSpec("roof", "prism", (0.02, 0.056, 0.0195), color=GREEN)


def bottle_spec(height: float) -> ObjectSpec:
    """A bottle: an upright cylinder of diameter 4.5 cm, 0.5 kg, very grippy (anchor: friction 10)."""
    return ObjectSpec(f"bottle{round(height * 1000)}", "cylinder", (0.0225, 0.0225, 0.5 * height), mass=0.5,
                      friction=10.0, color=BLUE)


# Bin packing: five shapes (the anchor's random blocks at scale 0.8, built from primitives).
BIN_BLOCKS = (
    ObjectSpec("block_cube", "box", (0.02, 0.02, 0.02)),
    ObjectSpec("block_brick", "box", (0.02, 0.04, 0.02), color=BLUE),
    ObjectSpec("block_flat_brick", "box", (0.02, 0.04, 0.01), color=GREEN),
    ObjectSpec("block_half_cube", "box", (0.02, 0.02, 0.01), color=(0.9, 0.7, 0.2, 1.0)),
    ObjectSpec("block_prism", "prism", (0.02, 0.0375, 0.0195), color=(0.6, 0.3, 0.7, 1.0)),
)


def _prism_mesh(hx: float, hy: float, hz: float):
    """Vertices (origin at the centroid) and outward triangles of a prism with its ridge along x."""
    h = 2.0 * hz
    lo, hi = -h / 3.0, 2.0 * h / 3.0
    v = [(-hx, -hy, lo), (-hx, hy, lo), (-hx, 0.0, hi), (hx, -hy, lo), (hx, hy, lo), (hx, 0.0, hi)]
    tris = [0, 2, 1, 3, 4, 5,  # end caps (-x, +x)
            0, 1, 4, 0, 4, 3,  # bottom
            1, 2, 5, 1, 5, 4,  # +y slope
            0, 3, 5, 0, 5, 2]  # -y slope
    return v, tris


def _build(spec: ObjectSpec):
    def build(client: int) -> tuple[int, int]:
        hx, hy, hz = spec.half_extents
        if spec.shape == "box":
            col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[hx, hy, hz], physicsClientId=client)
            vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=[hx, hy, hz], rgbaColor=spec.color,
                                       physicsClientId=client)
        elif spec.shape == "cylinder":
            col = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=hx, height=2 * hz, physicsClientId=client)
            vis = pb.createVisualShape(pb.GEOM_CYLINDER, radius=hx, length=2 * hz, rgbaColor=spec.color,
                                       physicsClientId=client)
        elif spec.shape == "prism":
            vertices, triangles = _prism_mesh(hx, hy, hz)
            col = pb.createCollisionShape(pb.GEOM_MESH, vertices=vertices, physicsClientId=client)
            vis = pb.createVisualShape(pb.GEOM_MESH, vertices=vertices, indices=triangles, rgbaColor=spec.color,
                                       physicsClientId=client)
        else:
            raise ValueError(f"unknown shape {spec.shape!r}")
        return col, vis

    return build


def spawn(sim: Simulation, spec: ObjectSpec, x: float, y: float, yaw: float, z: float | None = None) -> BodyInfo:
    """Create ``spec`` at (x, y) resting on the table (or at origin height ``z``) with yaw (rad)."""
    shape = sim.shape(("object", spec), _build(spec))
    height = spec.rest_z if z is None else z
    return sim.add_object(spec.kind, shape, spec.half_extents, (x, y, height), yaw, mass=spec.mass,
                          friction=spec.friction)


@dataclass(frozen=True)
class ContainerSpec:
    """An open box (tray or bin) built from five boxes: inner size (x, y), wall height (m)."""

    inner_x: float
    inner_y: float
    height: float
    wall: float = 0.005  # half-thickness of walls and floor
    color: tuple[float, float, float, float] = WHITE

    @property
    def floor_top(self) -> float:
        return 2 * self.wall


@dataclass(frozen=True)
class ContainerFrame:
    """Where a container stands (centre ``xy`` in metres, ``yaw`` in radians) and its 2-D frame.

    Container coordinates (u, v) run along its inner x and y sides, origin at its centre.
    """

    spec: ContainerSpec
    xy: tuple[float, float] = (0.0, 0.0)
    yaw: float = 0.0

    def to_local(self, xy) -> np.ndarray:
        """``[..., ≥2]`` world points (metres; extra components ignored) -> ``[..., 2]`` (u, v)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        d = np.asarray(xy, dtype=float)[..., :2] - np.asarray(self.xy)
        return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)

    def to_world(self, uv) -> np.ndarray:
        """``[..., 2]`` container points (u, v) -> ``[..., 2]`` world (x, y), metres."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        uv = np.asarray(uv, dtype=float)
        return np.asarray(self.xy) + np.stack([c * uv[..., 0] - s * uv[..., 1], s * uv[..., 0] + c * uv[..., 1]], -1)

    def contains(self, xy) -> bool:
        """Whether one world point lies strictly inside the inner rectangle (seen from above)."""
        u, v = self.to_local(xy)
        return abs(u) < self.spec.inner_x / 2 and abs(v) < self.spec.inner_y / 2


def add_container(sim: Simulation, spec: ContainerSpec, x: float, y: float, yaw: float) -> int:
    """Spawn a static container whose floor lies on the table, centred at (x, y) with yaw."""

    def build(client: int) -> tuple[int, int]:
        w, hx, hy, h = spec.wall, spec.inner_x / 2, spec.inner_y / 2, spec.height
        half = [[hx + 2 * w, hy + 2 * w, w],
                [w, hy + 2 * w, h / 2], [w, hy + 2 * w, h / 2],
                [hx, w, h / 2], [hx, w, h / 2]]
        pos = [[0, 0, w], [hx + w, 0, h / 2], [-hx - w, 0, h / 2], [0, hy + w, h / 2], [0, -hy - w, h / 2]]
        col = pb.createCollisionShapeArray([pb.GEOM_BOX] * 5, halfExtents=half, collisionFramePositions=pos,
                                           physicsClientId=client)
        vis = pb.createVisualShapeArray([pb.GEOM_BOX] * 5, halfExtents=half, visualFramePositions=pos,
                                        rgbaColors=[spec.color] * 5, physicsClientId=client)
        return col, vis

    shape = sim.shape(("container", spec), build)
    return sim.add_static(shape, (x, y, 0.0), yaw)
