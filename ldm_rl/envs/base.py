"""``PickPlaceEnv``: the gymnasium env shared by every task (spaces, step logic, rendering, experts).

One step = one primitive, implied by the hand state: a pick when the hand is empty, a place when
it holds an object. The action is a pixel and a rotation bin, ``[row, col, rot]``; the height of the
primitive is read from the current heightmap (no z in the action):

* pick: fingertips at ``max(heightmap within pick_window of the pixel) − pick_depth`` (≥ 1 cm);
* place: the held object's bottom 5 mm above the max of the heightmap within a disk of the held
  object's largest horizontal half extent around the pixel.

Observations (docs/conventions.md): ``heightmap`` ``[1, 128, 128] float32`` m in [0, 1] (the camera clips
above 1 m), ``in_hand`` ``[1, 24, 24] float32`` m (the pre-pick heightmap cropped at the pick pixel
in the gripper frame, zeros when empty) and ``holding`` ``MultiBinary(1)`` (int8 0/1; the TorchRL
env casts it to ``[1] bool``). ``terminated`` on success or an invalid scene, ``truncated`` at
``max_steps``. ``info``: ``action_metric`` (x, y, z, yaw) float32 m/rad, ``primitive``
("pick"/"place"), ``primitive_success``, ``is_success`` and ``invalid`` (reason or "").

Subclasses (one per task) implement ``_build_scene``, ``_is_success`` and ``_expert_pose`` and may
extend ``_invalid_reason`` and ``_reward``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Callable, Sequence

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from ldm_rl import geometry
from ldm_rl.envs.camera import HeightmapCamera
from ldm_rl.envs.gripper import GripperConfig, ParallelJawGripper
from ldm_rl.envs.physics import BodyInfo, PhysicsConfig, Simulation

__all__ = ["PickPlaceEnv", "ExpertNoise", "PrimitiveTarget", "SpawnError", "IN_HAND_SIZE"]

IN_HAND_SIZE = geometry.HAND_SIZE
PLACE_CLEARANCE = 0.005  # m between the held object's bottom and the surface below when released
MAX_SPAWN_TRIES = 100


class SpawnError(RuntimeError):
    """A scene could not be sampled (the reset retries with fresh randomness)."""


@dataclass(frozen=True)
class ExpertNoise:
    """Noise of the scripted expert: per-axis position jitter uniform in ±``position`` metres, a
    uniformly random action with probability ``random_action_prob``, and otherwise, with probability
    ``rotation_prob``, the expert's position at a uniformly random other rotation bin (a grasp across an
    object's long side: failed picks on objects, which the noiseless expert never shows)."""

    position: float = 0.0
    random_action_prob: float = 0.0
    rotation_prob: float = 0.0

    def __post_init__(self):
        if not (self.position >= 0.0 and math.isfinite(self.position)):
            raise ValueError(f"noise.position must be a finite non-negative number of metres, got {self.position!r}")
        if not 0.0 <= self.random_action_prob <= 1.0:
            raise ValueError(f"noise.random_action_prob must be in [0, 1], got {self.random_action_prob!r}")
        if not 0.0 <= self.rotation_prob <= 1.0:
            raise ValueError(f"noise.rotation_prob must be in [0, 1], got {self.rotation_prob!r}")


@dataclass
class PrimitiveTarget:
    """A planned primitive: gripper centre (x, y) in metres and yaw in radians (z comes from the
    heightmap, as for any action)."""

    x: float
    y: float
    yaw: float


class PickPlaceEnv(gym.Env):
    """Base class of the tabletop pick-and-place tasks (see module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}
    default_max_steps_slack = 4
    pick_depth = 0.02  # m below the local top where the fingertips close
    pick_window = 0.02  # m, radius of the disk searched for the pick height
    max_height = 0.25  # m, depth-class range for this task (tallest expected structure)

    def __init__(
        self,
        num_objects: int,
        *,
        max_steps: int | None = None,
        num_rotations: int = geometry.NUM_ROTATIONS,
        render_mode: str | None = None,
        expert_noise: ExpertNoise | dict | None = None,
        workspace: geometry.Workspace | None = None,
        physics: PhysicsConfig | None = None,
        gripper: GripperConfig | dict | None = None,
        settle_steps: int = 60,
        reset_seed: int | None = None,
        object_counts: Sequence[int] | None = None,
    ):
        if not isinstance(num_objects, int) or num_objects < 1:
            raise ValueError(f"num_objects must be a positive int, got {num_objects!r}")
        if object_counts is not None:
            object_counts = tuple(object_counts)
            if not object_counts or any(not isinstance(n, int) or isinstance(n, bool) or n < 1 for n in object_counts):
                raise ValueError(f"object_counts must be a non-empty list of positive ints or None, got {object_counts!r}")
        for n in {num_objects, *(object_counts or ())}:
            self._check_object_count(n)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if not isinstance(num_rotations, int) or num_rotations < 1:
            raise ValueError(f"num_rotations must be a positive int, got {num_rotations!r}")
        self.num_objects = num_objects
        # with object_counts, every reset draws the scene's object count from it (the task stays "all of them")
        self.object_counts = object_counts
        most = max(object_counts) if object_counts else num_objects
        self.max_steps = max_steps if max_steps is not None else 2 * most + self.default_max_steps_slack
        if not isinstance(self.max_steps, int) or self.max_steps < 1:
            raise ValueError(f"max_steps must be a positive int, got {max_steps!r}")
        self.num_rotations = num_rotations
        self.render_mode = render_mode
        if isinstance(expert_noise, dict):
            expert_noise = ExpertNoise(**expert_noise)
        self.expert_noise = expert_noise or ExpertNoise()
        self.workspace = workspace or geometry.Workspace()
        self.settle_steps = settle_steps
        n = self.workspace.pixels
        self.observation_space = spaces.Dict(
            heightmap=spaces.Box(0.0, 1.0, (1, n, n), np.float32),
            in_hand=spaces.Box(0.0, 1.0, (1, IN_HAND_SIZE, IN_HAND_SIZE), np.float32),
            holding=spaces.MultiBinary(1),
        )
        self.action_space = spaces.MultiDiscrete([n, n, num_rotations])
        if isinstance(gripper, dict):  # e.g. {"finger_spinning_friction": 0.0} from a config
            known = {f.name for f in fields(GripperConfig)}
            if set(gripper) - known:
                raise ValueError(f"gripper has no setting {sorted(set(gripper) - known)}; the settings are {sorted(known)}")
            gripper = GripperConfig(**gripper)
        self._gripper_config = gripper or GripperConfig()
        self.sim = Simulation(physics or PhysicsConfig())
        self.gripper = ParallelJawGripper(self.sim, self._gripper_config)
        self.camera = HeightmapCamera(self.workspace)
        self._heightmap = np.zeros((n, n), np.float32)
        self._in_hand = np.zeros((IN_HAND_SIZE, IN_HAND_SIZE), np.float32)
        self._steps = 0
        self._expert_rng = np.random.default_rng(0)
        if reset_seed is not None and (not isinstance(reset_seed, int) or reset_seed < 0):
            raise ValueError(f"reset_seed must be a non-negative int or None, got {reset_seed!r}")
        # with reset_seed, the k-th reset without an explicit seed uses seed reset_seed + k: the scene
        # stream is a function of the episode index, which a resumed run sets back (episode_index)
        self.reset_seed, self.episode_index = reset_seed, 0

    # --- task hooks ------------------------------------------------------------------------
    @classmethod
    def _check_object_count(cls, n: int) -> None:
        """Raise ValueError when the task cannot hold ``n`` objects (the constructor's own check)."""

    def _build_scene(self, rng: np.random.Generator) -> None:
        """Spawn the task's objects (raise SpawnError to resample)."""
        raise NotImplementedError

    def _is_success(self) -> bool:
        raise NotImplementedError

    def expert_target(self) -> PrimitiveTarget:
        """The direct scripted planner's next primitive, from the true object poses."""
        raise NotImplementedError

    def _invalid_reason(self) -> str:
        """'' when the scene is valid; else why (any object outside the workspace, ...)."""
        ws = self.workspace
        for obj in self._scene_objects():
            x, y, _ = self.sim.pose(obj.body)[0]
            if not (ws.x_min < x < ws.x_min + ws.size and ws.y_min < y < ws.y_min + ws.size):
                return f"{obj.kind} left the workspace"
        return ""

    def _reward(self, success: bool, invalid: str) -> float:
        return 1.0 if success else 0.0

    def _build_goal_scene(self, rng: np.random.Generator) -> None:
        """Spawn the finished structure (tasks with a deconstruct demo procedure)."""
        raise NotImplementedError(f"{type(self).__name__} has no deconstruct procedure")

    def is_scattered(self, min_distance: float = 0.096) -> bool:
        """Every object resting on the table, centres pairwise farther apart than ``min_distance`` m."""
        if self.holding is not None:
            return False
        objs = self.sim.objects
        pos = self.sim.positions()
        on_table = all(p[2] < o.half_extents[2] + 0.01 for o, p in zip(objs, pos))
        d = np.linalg.norm(pos[:, None, :2] - pos[None, :, :2], axis=-1) + np.eye(len(objs))
        return bool(on_table and d.min() > min_distance)

    def deconstruct_target(self) -> PrimitiveTarget:
        """The deconstruction planner: pick the highest object (or one too close to another) and put it
        down at a random free spot with a random rotation bin."""
        held = self.holding
        rng = self._expert_rng
        if held is not None:
            xy = self._free_position(rng, padding=0.045, min_distance=0.108)
            return self._place_held_with_yaw(xy[0], xy[1], float(rng.integers(self.num_rotations)) * math.pi
                                             / self.num_rotations)
        objs = self._scene_objects()
        pos = self.sim.positions()
        raised = [o for o, p in zip(objs, pos) if p[2] > o.half_extents[2] + 0.01]
        if raised:
            target = max(raised, key=lambda o: self.sim.pose(o.body)[0][2])
        else:
            d = np.linalg.norm(pos[:, None, :2] - pos[None, :, :2], axis=-1) + np.eye(len(objs))
            target = objs[int(np.argmin(d.min(1)))]
        return self._grasp(target, math.pi / 2 if target.kind == "cube" else math.pi)

    # --- gymnasium API -------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is None and self.reset_seed is not None:
            seed = self.reset_seed + self.episode_index
        self.episode_index += 1
        super().reset(seed=seed)
        self._draw_object_count()
        self._spawn(self._build_scene)
        return self._observation(), {}

    def reset_to_goal(self, *, seed: int | None = None) -> dict:
        """Reset to a *finished* structure (for the deconstruct demo procedure); returns the obs."""
        super().reset(seed=seed)
        self._draw_object_count()
        self._spawn(self._build_goal_scene)
        return self._observation()

    def _draw_object_count(self) -> None:
        if self.object_counts:
            self.num_objects = int(self.object_counts[self.np_random.integers(len(self.object_counts))])

    def restart_clock(self) -> dict:
        """Start a new episode from the current scene (step count 0, empty in-hand image)."""
        self._steps = 0
        self._in_hand[:] = 0.0
        return self._observation()

    def _spawn(self, build) -> None:
        for _ in range(MAX_SPAWN_TRIES):
            self.sim.reset_world()
            self.gripper = ParallelJawGripper(self.sim, self._gripper_config)
            try:
                build(self.np_random)
            except SpawnError:
                continue
            self.sim.settle(self.settle_steps)
            if not self._invalid_reason():
                break
        else:
            raise RuntimeError(f"{type(self).__name__}: no valid scene after {MAX_SPAWN_TRIES} tries")
        self._expert_rng = np.random.default_rng(int(self.np_random.integers(2**62)))
        self._steps = 0
        self._in_hand[:] = 0.0
        self._heightmap = self.camera.heightmap(self.sim.client)

    def step(self, action):
        row, col, rot = self._check_action(action)
        pose = self.action_to_target(np.array([row, col, rot]))
        x, y, yaw = pose.x, pose.y, pose.yaw
        if self.gripper.held is None:
            primitive = "pick"
            z = self._pick_height(row, col)
            held = self.gripper.pick(x, y, z, yaw)
            success = held is not None
            if success:
                self._in_hand = self._crop_in_hand(self._heightmap, row, col, yaw)
        else:
            primitive = "place"
            held = self.gripper.held
            z = self._place_height(row, col, held)
            self.gripper.place(x, y, z, yaw)
            self._in_hand[:] = 0.0
        self.sim.settle(self.settle_steps)
        if primitive == "place":
            pos = self.sim.pose(held.body)[0]
            success = bool(math.hypot(pos[0] - x, pos[1] - y) < max(held.half_extents[:2]) + 0.01)
        self._steps += 1
        self._heightmap = self.camera.heightmap(self.sim.client)
        invalid = self._invalid_reason()
        is_success = not invalid and self.gripper.held is None and self._is_success()
        reward = self._reward(is_success, invalid)
        terminated = bool(is_success or invalid)
        truncated = bool(not terminated and self._steps >= self.max_steps)
        info = {
            "action_metric": np.array([x, y, z, yaw], np.float32),
            "primitive": primitive,
            "primitive_success": bool(success),
            "is_success": bool(is_success),
            "invalid": invalid,
        }
        return self._observation(), float(reward), terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return self.camera.rgb(self.sim.client)

    def close(self):
        if getattr(self, "sim", None) is not None:
            self.sim.close()

    # --- experts ---------------------------------------------------------------------------
    def expert_action(self, noise: ExpertNoise | None = None) -> np.ndarray:
        """The direct scripted expert's next action ``[row, col, rot] int64`` for the current state
        (true object poses), with ``noise`` (default: the env's ``expert_noise``)."""
        return self.noisy_action(self.expert_target(), noise)[0]

    def noisy_action(self, target: PrimitiveTarget, noise: ExpertNoise | None = None) -> tuple[np.ndarray, bool]:
        """(``target`` as an action jittered per ``noise``, False); with probability
        ``noise.random_action_prob`` (a uniformly random action, True); else with probability
        ``noise.rotation_prob`` (the jittered action at a uniformly random other rotation bin, True)."""
        noise = noise or self.expert_noise
        rng = self._expert_rng
        if noise.random_action_prob > 0 and rng.random() < noise.random_action_prob:
            return np.array([rng.integers(n) for n in self.action_space.nvec], dtype=np.int64), True
        xy = np.array([target.x, target.y])
        if noise.position > 0:
            xy = xy + rng.uniform(-noise.position, noise.position, size=2)
        action = self.pose_to_action(xy[0], xy[1], target.yaw)
        if noise.rotation_prob > 0 and self.num_rotations > 1 and rng.random() < noise.rotation_prob:
            action[2] = (action[2] + rng.integers(1, self.num_rotations)) % self.num_rotations
            return action, True
        return action, False

    def action_to_target(self, action: np.ndarray) -> PrimitiveTarget:
        """``[row, col, rot]`` -> the metric pose it commands (pixel centre, bin angle)."""
        x, y = (float(v) for v in self.workspace.pixel_to_metric(np.asarray(action[:2], dtype=np.int64)))
        yaw = float(geometry.bin_to_angle(torch.tensor(int(action[2])), self.num_rotations))
        return PrimitiveTarget(x, y, yaw)

    def pose_to_action(self, x: float, y: float, yaw: float) -> np.ndarray:
        """Metric (x, y, yaw) -> ``[row, col, rot] int64`` (clamped into the workspace, nearest bin)."""
        row, col = self.workspace.metric_to_pixel(np.array([x, y]), clamp=True)
        rot = int(geometry.angle_to_bin(torch.tensor(yaw, dtype=torch.float64), self.num_rotations))
        return np.array([row, col, rot], dtype=np.int64)

    def snap_yaw(self, yaw: float) -> float:
        """The rotation-bin angle nearest to ``yaw`` (rad, circular mod π)."""
        k = geometry.angle_to_bin(torch.tensor(yaw, dtype=torch.float64), self.num_rotations)
        return float(geometry.bin_to_angle(k, self.num_rotations))

    def _grasp(self, obj: BodyInfo, symmetry: float) -> PrimitiveTarget:
        """Pick ``obj`` at its centre, fingers closing along its local x (yaw mod ``symmetry``)."""
        x, y = self.sim.pose(obj.body)[0][:2]
        return PrimitiveTarget(x, y, self.sim.yaw(obj.body) % symmetry)

    def _place_held(self, x: float, y: float, object_yaw: float, symmetry: float) -> PrimitiveTarget:
        """Place so the held object's centre lands on (x, y) with yaw ≡ ``object_yaw`` (mod ``symmetry``),
        compensating its offset and yaw inside the hand."""
        return self._place_held_with_yaw(x, y, (object_yaw - self.gripper.held_yaw) % symmetry)

    def _place_held_with_yaw(self, x: float, y: float, gripper_yaw: float) -> PrimitiveTarget:
        """Place so the held object's centre lands on (x, y), the gripper at ``gripper_yaw`` (snapped)."""
        yaw = self.snap_yaw(gripper_yaw)
        off = self.gripper.held_offset_at(yaw)
        return PrimitiveTarget(x - off[0], y - off[1], yaw)

    # --- helpers shared by the tasks -----------------------------------------------------------
    @property
    def holding(self) -> BodyInfo | None:
        return self.gripper.held

    @property
    def heightmap(self) -> np.ndarray:
        """The latest ``[H, W] float32`` heightmap (m)."""
        return self._heightmap

    def _scene_objects(self) -> list[BodyInfo]:
        """Objects on the table (the held one excluded)."""
        held = self.gripper.held
        return [o for o in self.sim.objects if held is None or o.body != held.body]

    def _observation(self) -> dict:
        return {
            "heightmap": self._heightmap[None].copy(),
            "in_hand": self._in_hand[None].copy(),
            "holding": np.array([self.gripper.held is not None], dtype=np.int8),
        }

    def _check_action(self, action) -> tuple[int, int, int]:
        a = np.asarray(action)
        if a.shape != (3,) or not np.issubdtype(a.dtype, np.integer):
            if a.shape == (3,) and np.issubdtype(a.dtype, np.floating) and np.all(a == np.round(a)):
                a = a.astype(np.int64)
            else:
                raise ValueError(f"action must be 3 integers [row, col, rot], got {action!r}")
        names = ("row", "col", "rot")
        for name, value, n in zip(names, a, self.action_space.nvec):
            if not 0 <= value < n:
                raise ValueError(f"action component {name}={int(value)} is outside [0, {int(n) - 1}]")
        return int(a[0]), int(a[1]), int(a[2])

    def _disk_max(self, row: int, col: int, radius: float) -> float:
        """Max height (m) of the heightmap within ``radius`` metres of pixel (row, col)."""
        n, res = self.workspace.pixels, self.workspace.resolution
        half = int(math.ceil(radius / res))
        r0, r1 = max(row - half, 0), min(row + half + 1, n)
        c0, c1 = max(col - half, 0), min(col + half + 1, n)
        rr, cc = np.ogrid[r0:r1, c0:c1]
        inside = (rr - row) ** 2 + (cc - col) ** 2 <= (radius / res) ** 2
        return float(np.where(inside, self._heightmap[r0:r1, c0:c1], 0.0).max())

    def _pick_height(self, row: int, col: int) -> float:
        return max(self._disk_max(row, col, self.pick_window) - self.pick_depth, 0.01)

    def _place_height(self, row: int, col: int, held: BodyInfo) -> float:
        surface = self._disk_max(row, col, max(held.half_extents[:2]))
        return surface + self.gripper.tip_to_bottom + PLACE_CLEARANCE

    def _crop_in_hand(self, heightmap: np.ndarray, row: int, col: int, yaw: float) -> np.ndarray:
        image = torch.from_numpy(heightmap)[None]
        center = torch.tensor([row, col], dtype=torch.int64)
        patch = geometry.crop(image, center, torch.tensor(yaw), IN_HAND_SIZE)
        return patch[0].numpy().astype(np.float32)

    def _sample_positions(
        self,
        rng: np.random.Generator,
        count: int,
        *,
        padding: float,
        min_distance: float,
        existing: list | None = None,
        tries: int = 100,
        accept: Callable[[np.ndarray], bool] | None = None,
    ) -> list[np.ndarray]:
        """``count`` xy points uniform in the workspace shrunk by ``padding``, pairwise (and to
        ``existing``) farther apart than ``min_distance`` (m), each passing ``accept`` when given
        (e.g. "away from the tray"). Raises SpawnError."""
        ws = self.workspace
        taken = [np.asarray(p, dtype=np.float64)[:2] for p in (existing or [])]
        out = []
        for _ in range(count):
            for _ in range(tries):
                p = np.array([
                    rng.uniform(ws.x_min + padding, ws.x_min + ws.size - padding),
                    rng.uniform(ws.y_min + padding, ws.y_min + ws.size - padding),
                ])
                if (accept is None or accept(p)) and all(np.linalg.norm(p - q) > min_distance for q in taken):
                    break
            else:
                raise SpawnError("no free position")
            taken.append(p)
            out.append(p)
        return out

    def _free_position(self, rng: np.random.Generator, *, padding: float, min_distance: float) -> np.ndarray:
        """A random table position far from every object (for the experts); SpawnError if none."""
        existing = [self.sim.pose(o.body)[0] for o in self._scene_objects()]
        return self._sample_positions(rng, 1, padding=padding, min_distance=min_distance, existing=existing)[0]

