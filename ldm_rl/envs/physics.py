"""One headless PyBullet world: physics parameters, the table, a shape cache and object bodies.

Every env owns one ``Simulation`` (its own DIRECT client). Each env reset rebuilds the world with
``resetSimulation`` (bit-identical episodes per seed, and it frees every shape: memory stays flat);
within an episode collision/visual shapes are created once per kind and reused (``shape``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Hashable

import numpy as np
import pybullet as pb

__all__ = ["PhysicsConfig", "Simulation", "BodyInfo"]


@dataclass(frozen=True)
class PhysicsConfig:
    """Physics settings (docs/environments.md; the anchor's 'slow' mode)."""

    time_step: float = 1.0 / 240.0  # s
    solver_iterations: int = 200
    gravity: float = -10.0  # m/s^2
    damping: float = 0.04  # linear and angular
    contact_stiffness: float = 3000.0
    contact_damping: float = 100.0


@dataclass
class BodyInfo:
    """A spawned movable object: its body id, kind ('cube', 'roof', 'bottle', ...) and half extents (m)."""

    body: int
    kind: str
    half_extents: tuple[float, float, float]  # (along local x, local y, z), metres


class Simulation:
    """A DIRECT PyBullet client with the table plane, a shape cache and the movable objects."""

    def __init__(self, physics: PhysicsConfig = PhysicsConfig()):
        self.physics = physics
        self.client = pb.connect(pb.DIRECT)
        self._shapes: dict[Hashable, tuple[int, int]] = {}
        self.objects: list[BodyInfo] = []
        self._static: list[int] = []
        self.reset_world()

    def reset_world(self) -> None:
        """Empty the world (``resetSimulation``: frees every body and shape) and rebuild the table.

        Used on every env reset: a fresh world makes episodes bit-identical for a given seed
        (removing bodies one by one leaves solver/broadphase state that changes later contacts)."""
        physics, cid = self.physics, self.client
        pb.resetSimulation(physicsClientId=cid)
        pb.setPhysicsEngineParameter(
            numSubSteps=0,
            numSolverIterations=physics.solver_iterations,
            solverResidualThreshold=1e-7,
            constraintSolverType=pb.CONSTRAINT_SOLVER_LCP_SI,
            deterministicOverlappingPairs=1,
            physicsClientId=cid,
        )
        pb.setTimeStep(physics.time_step, physicsClientId=cid)
        pb.setGravity(0, 0, physics.gravity, physicsClientId=cid)
        self._shapes.clear()
        self.objects.clear()
        self._static.clear()
        # The table: an infinite collision plane at z = 0 with no visual, so the camera sees it as
        # "nothing" (maximal depth = height 0) and renders faster.
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=cid)
        self.table = pb.createMultiBody(0, plane, -1, [0, 0, 0], physicsClientId=cid)
        self.set_contact_dynamics(self.table, -1, friction=1.0)

    # --- shapes and bodies -------------------------------------------------------------------
    def shape(self, key: Hashable, build: Callable[[int], tuple[int, int]]) -> tuple[int, int]:
        """(collision id, visual id) for ``key``, built once per client by ``build(client)``."""
        if key not in self._shapes:
            self._shapes[key] = build(self.client)
        return self._shapes[key]

    def set_contact_dynamics(self, body: int, link: int, *, friction: float, mass_damping: bool = True,
                             spinning_friction: float = 0.0) -> None:
        """Apply the tuned contact model (stiffness/damping, no restitution), lateral friction and torsional
        (``spinning_friction``: about the contact normal) friction to a link."""
        p = self.physics
        kwargs = dict(
            lateralFriction=friction,
            spinningFriction=spinning_friction,
            restitution=0.0,
            contactStiffness=p.contact_stiffness,
            contactDamping=p.contact_damping,
            physicsClientId=self.client,
        )
        if mass_damping:
            kwargs.update(linearDamping=p.damping, angularDamping=p.damping)
        pb.changeDynamics(body, link, **kwargs)

    def add_object(
        self,
        kind: str,
        shape: tuple[int, int],
        half_extents: tuple[float, float, float],
        position,
        yaw: float,
        *,
        mass: float = 0.1,
        friction: float = 1.0,
        base_orientation=None,
    ) -> BodyInfo:
        """Spawn a movable object with its collision/visual shape pair at (x, y, z) and yaw (rad)."""
        orientation = base_orientation if base_orientation is not None else yaw_quaternion(yaw)
        body = pb.createMultiBody(
            mass, shape[0], shape[1], list(position), orientation, physicsClientId=self.client
        )
        self.set_contact_dynamics(body, -1, friction=friction)
        info = BodyInfo(body, kind, tuple(half_extents))
        self.objects.append(info)
        return info

    def add_static(self, shape: tuple[int, int], position, yaw: float) -> int:
        """Spawn a fixed body (tray, bin); removed with the objects on the next ``clear``."""
        body = pb.createMultiBody(0, shape[0], shape[1], list(position), yaw_quaternion(yaw), physicsClientId=self.client)
        self.set_contact_dynamics(body, -1, friction=1.0, mass_damping=False)
        self._static.append(body)
        return body

    def clear(self) -> None:
        """Remove every object and static fixture (shape ids stay cached)."""
        for info in self.objects:
            pb.removeBody(info.body, physicsClientId=self.client)
        for body in self._static:
            pb.removeBody(body, physicsClientId=self.client)
        self.objects.clear()
        self._static.clear()

    # --- stepping and queries ----------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        for _ in range(n):
            pb.stepSimulation(physicsClientId=self.client)

    def settle(self, max_steps: int, *, tol: float = 2e-3, check_every: int = 10, min_steps: int = 10) -> int:
        """Step until every object moves slower than ``tol`` m/s (checked every few steps). Returns steps."""
        done = 0
        while done < max_steps:
            n = min(check_every, max_steps - done)
            self.step(n)
            done += n
            if done >= min_steps and self.max_speed() < tol:
                break
        return done

    def max_speed(self) -> float:
        """Largest linear speed over the objects, m/s."""
        speeds = [np.linalg.norm(pb.getBaseVelocity(o.body, physicsClientId=self.client)[0]) for o in self.objects]
        return float(max(speeds, default=0.0))

    def pose(self, body: int) -> tuple[np.ndarray, np.ndarray]:
        """(position [3] m, quaternion xyzw [4]) of a body."""
        pos, quat = pb.getBasePositionAndOrientation(body, physicsClientId=self.client)
        return np.asarray(pos), np.asarray(quat)

    def positions(self) -> np.ndarray:
        """[N, 3] float64 object positions, in spawn order."""
        return np.array([self.pose(o.body)[0] for o in self.objects]).reshape(-1, 3)

    def yaw(self, body: int) -> float:
        return float(pb.getEulerFromQuaternion(self.pose(body)[1])[2])

    def tilt(self, body: int) -> float:
        """Angle (rad) between the body's z axis and the world vertical."""
        rot = np.asarray(pb.getMatrixFromQuaternion(self.pose(body)[1])).reshape(3, 3)
        return float(math.acos(np.clip(rot[2, 2], -1.0, 1.0)))

    def aabb(self, body: int) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = pb.getAABB(body, physicsClientId=self.client)
        return np.asarray(lo), np.asarray(hi)

    def touching(self, a: int, b: int, link_b: int | None = None) -> bool:
        """True when bodies a and b have contact points (valid after a stepSimulation)."""
        kwargs = {} if link_b is None else {"linkIndexB": link_b}
        return len(pb.getContactPoints(a, b, physicsClientId=self.client, **kwargs)) > 0

    def close(self) -> None:
        if self.client is not None and pb.isConnected(self.client):
            pb.disconnect(self.client)
        self.client = None


def yaw_quaternion(yaw: float) -> list[float]:
    return list(pb.getQuaternionFromEuler([0.0, 0.0, float(yaw)]))
