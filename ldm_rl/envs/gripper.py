"""A procedural floating parallel-jaw gripper and the simulated pick / place primitives.

Body layout (one fixed-base multibody, no arm, no IK):

    base (massless anchor, teleported) --prismatic z--> palm --prismatic ±x--> two fingers

Free-space motions teleport the anchor (carrying a held object with its relative pose); the final
approach, the finger closing (position motors with a force limit), the lift, the release and the
retreat are simulated. At yaw θ the fingers close along the world direction (cos θ, sin θ).
Between primitives the gripper is parked far outside the camera's view.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet as pb

from ldm_rl.envs.physics import BodyInfo, Simulation, yaw_quaternion

__all__ = ["GripperConfig", "ParallelJawGripper"]

SLIDE, FINGER_A, FINGER_B = 0, 1, 2
PARK_POSITION = (0.4, 3.0, 0.5)  # far outside the camera frustum


@dataclass(frozen=True)
class GripperConfig:
    """Geometry (m), motor limits (N, m/s) and step budgets of the gripper."""

    finger_length: float = 0.05
    finger_thickness: float = 0.01  # along the closing direction
    finger_width: float = 0.02
    open_half_gap: float = 0.035  # inner finger face to centre when open (7 cm opening)
    finger_force: float = 15.0
    finger_speed: float = 0.25
    slide_force: float = 60.0
    slide_speed: float = 0.4
    finger_friction: float = 1.0
    # torsional friction at the finger pads (the anchor's finger contacts: 0.1). Point contacts without it let a
    # part gripped off its centre pivot about the finger axis: of 230 roofs gripped 0-10 mm off centre at 0-20° yaw
    # error, 43 hung > 20° tilted (none with it), and a tilted roof tips off the cubes (docs/environments.md)
    finger_spinning_friction: float = 0.1
    approach: float = 0.03  # simulated descent before grasping / releasing
    lift: float = 0.06  # simulated lift after closing
    place_approach: float = 0.02
    retreat: float = 0.03
    max_motion_steps: int = 40
    max_close_steps: int = 30
    hold_steps: int = 8

    def __post_init__(self):
        if not self.finger_spinning_friction >= 0:
            raise ValueError(f"finger_spinning_friction must be >= 0, got {self.finger_spinning_friction!r}")


class ParallelJawGripper:
    """Pick and place with a physical two-finger gripper in a ``Simulation``."""

    def __init__(self, sim: Simulation, config: GripperConfig = GripperConfig()):
        self.sim = sim
        self.config = config
        self.held: BodyInfo | None = None
        self.tip_to_bottom = 0.0  # fingertip z − held object's lowest z, m
        self.held_offset = np.zeros(2)  # held object's xy centre in the gripper frame, m
        self.held_yaw = 0.0  # held object's yaw relative to the gripper's, rad
        c = config
        self._open_q = c.open_half_gap + 0.5 * c.finger_thickness
        cid = sim.client

        def build_palm(client):
            col = pb.createCollisionShape(
                pb.GEOM_BOX, halfExtents=[self._open_q + 0.01, 0.015, 0.01],
                collisionFramePosition=[0, 0, 0.01], physicsClientId=client,
            )
            return col, -1

        def build_finger(client):
            half = [0.5 * c.finger_thickness, 0.5 * c.finger_width, 0.5 * c.finger_length]
            col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=client)
            return col, -1

        palm, _ = sim.shape("gripper_palm", build_palm)
        finger, _ = sim.shape(("gripper_finger", c.finger_length, c.finger_thickness, c.finger_width), build_finger)
        finger_offset = [0, 0, -0.5 * c.finger_length]
        self.body = pb.createMultiBody(
            0, -1, -1, list(PARK_POSITION), [0, 0, 0, 1],
            linkMasses=[0.3, 0.05, 0.05],
            linkCollisionShapeIndices=[palm, finger, finger],
            linkVisualShapeIndices=[-1, -1, -1],
            linkPositions=[[0, 0, 0], finger_offset, finger_offset],
            linkOrientations=[[0, 0, 0, 1]] * 3,
            linkInertialFramePositions=[[0, 0, 0]] * 3,
            linkInertialFrameOrientations=[[0, 0, 0, 1]] * 3,
            linkParentIndices=[0, 1, 1],
            linkJointTypes=[pb.JOINT_PRISMATIC] * 3,
            linkJointAxis=[[0, 0, 1], [1, 0, 0], [-1, 0, 0]],
            physicsClientId=cid,
        )
        for link in (SLIDE, FINGER_A, FINGER_B):
            sim.set_contact_dynamics(self.body, link, friction=c.finger_friction, mass_damping=False,
                                     spinning_friction=c.finger_spinning_friction)
        self._teleport(PARK_POSITION, 0.0, slide=0.0, fingers=self._open_q)

    # --- public primitives -------------------------------------------------------------------
    def pick(self, x: float, y: float, tip_z: float, yaw: float) -> BodyInfo | None:
        """Descend to fingertips at ``tip_z``, close, lift; return the object held by both fingers."""
        if self.held is not None:
            raise RuntimeError("pick called while holding an object")
        c = self.config
        start = self._positions()
        self._teleport((x, y, tip_z + c.approach + c.finger_length), yaw, slide=0.0, fingers=self._open_q)
        self._move_slide(-c.approach)
        self._close()
        self._move_slide(c.lift)
        self.sim.step(c.hold_steps)
        held = self._held_object(start)
        if held is None:
            self._open()
            self.park()
            return None
        self.held = held
        self.tip_to_bottom = self._tip_z() - self.sim.aabb(held.body)[0][2]
        obj_xy = self.sim.pose(held.body)[0][:2] - np.array([x, y])
        cos, sin = np.cos(yaw), np.sin(yaw)
        self.held_offset = np.array([cos * obj_xy[0] + sin * obj_xy[1], -sin * obj_xy[0] + cos * obj_xy[1]])
        self.held_yaw = self.sim.yaw(held.body) - yaw
        self.park()
        return held

    def place(self, x: float, y: float, tip_z: float, yaw: float) -> BodyInfo:
        """Carry the held object to fingertips at ``tip_z`` above (x, y), descend, open, retreat."""
        if self.held is None:
            raise RuntimeError("place called while not holding an object")
        c = self.config
        released = self.held
        self._teleport((x, y, tip_z + c.place_approach + c.finger_length), yaw, slide=0.0, fingers=None)
        self._move_slide(-c.place_approach)
        self._open()
        self.held = None
        self._move_slide(-c.place_approach + c.retreat)
        self.park()
        return released

    def park(self) -> None:
        """Teleport (with the held object) out of the camera's view; velocities are zeroed."""
        self._teleport(PARK_POSITION, 0.0, slide=0.0, fingers=None)

    def held_offset_at(self, yaw: float) -> np.ndarray:
        """World xy offset (m) of the held object's centre from the gripper centre at gripper yaw ``yaw``."""
        cos, sin = np.cos(yaw), np.sin(yaw)
        ox, oy = self.held_offset
        return np.array([cos * ox - sin * oy, sin * ox + cos * oy])

    def drop(self) -> None:
        """Forget the held object (it is removed from the hand by the caller)."""
        self.held = None

    # --- internals ---------------------------------------------------------------------------
    def _teleport(self, position, yaw: float, *, slide: float, fingers: float | None) -> None:
        cid = self.sim.client
        held_rel = None
        if self.held is not None:
            base_pos, base_quat = pb.getBasePositionAndOrientation(self.body, physicsClientId=cid)
            inv_pos, inv_quat = pb.invertTransform(base_pos, base_quat)
            obj_pos, obj_quat = pb.getBasePositionAndOrientation(self.held.body, physicsClientId=cid)
            held_rel = pb.multiplyTransforms(inv_pos, inv_quat, obj_pos, obj_quat)
            slide_q = pb.getJointState(self.body, SLIDE, physicsClientId=cid)[0]
            held_rel = pb.multiplyTransforms([0, 0, -slide_q], [0, 0, 0, 1], *held_rel)
        quat = yaw_quaternion(yaw)
        pb.resetBasePositionAndOrientation(self.body, list(position), quat, physicsClientId=cid)
        pb.resetJointState(self.body, SLIDE, slide, 0.0, physicsClientId=cid)
        if fingers is not None:
            for j in (FINGER_A, FINGER_B):
                pb.resetJointState(self.body, j, fingers, 0.0, physicsClientId=cid)
        else:
            for j in (FINGER_A, FINGER_B):
                q = pb.getJointState(self.body, j, physicsClientId=cid)[0]
                pb.resetJointState(self.body, j, q, 0.0, physicsClientId=cid)
        self._command(SLIDE, slide, self.config.slide_force, self.config.slide_speed)
        if held_rel is not None:
            moved = pb.multiplyTransforms(list(position), quat, [0, 0, slide], [0, 0, 0, 1])
            obj_pos, obj_quat = pb.multiplyTransforms(*moved, *held_rel)
            pb.resetBasePositionAndOrientation(self.held.body, obj_pos, obj_quat, physicsClientId=cid)
            pb.resetBaseVelocity(self.held.body, [0, 0, 0], [0, 0, 0], physicsClientId=cid)

    def _command(self, joint: int, target: float, force: float, speed: float) -> None:
        pb.setJointMotorControl2(
            self.body, joint, pb.POSITION_CONTROL, targetPosition=target, force=force,
            maxVelocity=speed, physicsClientId=self.sim.client,
        )

    def _joint(self, joint: int) -> tuple[float, float]:
        q, v = pb.getJointState(self.body, joint, physicsClientId=self.sim.client)[:2]
        return q, v

    def _move_slide(self, target: float) -> None:
        """Drive the palm to ``target`` (m, relative to the anchor); stop early when it stalls."""
        c = self.config
        self._command(SLIDE, target, c.slide_force, c.slide_speed)
        for i in range(c.max_motion_steps):
            self.sim.step()
            q, v = self._joint(SLIDE)
            if abs(q - target) < 1e-3 or (i >= 4 and abs(v) < 0.02):
                break

    def _close(self) -> None:
        c = self.config
        for j in (FINGER_A, FINGER_B):
            self._command(j, 0.0, c.finger_force, c.finger_speed)
        for i in range(c.max_close_steps):
            self.sim.step()
            (_, va), (_, vb) = self._joint(FINGER_A), self._joint(FINGER_B)
            if i >= 3 and abs(va) < 5e-3 and abs(vb) < 5e-3:
                break

    def _open(self) -> None:
        c = self.config
        for j in (FINGER_A, FINGER_B):
            self._command(j, self._open_q, c.finger_force, c.finger_speed)
        for _ in range(c.max_close_steps):
            self.sim.step()
            if self._joint(FINGER_A)[0] > self._open_q - 0.01 and self._joint(FINGER_B)[0] > self._open_q - 0.01:
                break

    def _tip_z(self) -> float:
        pos = pb.getBasePositionAndOrientation(self.body, physicsClientId=self.sim.client)[0]
        return pos[2] + self._joint(SLIDE)[0] - self.config.finger_length

    def _positions(self) -> dict[int, float]:
        return {o.body: self.sim.pose(o.body)[0][2] for o in self.sim.objects}

    def _held_object(self, start_z: dict[int, float]) -> BodyInfo | None:
        """The object touching both fingers that rose with the lift, else None."""
        cid = self.sim.client
        for obj in self.sim.objects:
            touches_a = pb.getContactPoints(self.body, obj.body, FINGER_A, physicsClientId=cid)
            touches_b = pb.getContactPoints(self.body, obj.body, FINGER_B, physicsClientId=cid)
            risen = self.sim.pose(obj.body)[0][2] - start_z[obj.body] > 0.5 * self.config.lift
            if touches_a and touches_b and risen:
                return obj
        return None
