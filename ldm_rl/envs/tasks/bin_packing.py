"""Bin packing: put 8 blocks of five shapes into a bin, keeping the pile low.

Reward (the paper's "positive reward inversely proportional to the highest point"): 0 on every
intermediate step (we drop the anchor's +0.1 bonus for ending a step holding an object, which rewards
picking rather than packing), 0 on a failure or a timeout, and on the successful terminal step (every
block's centre inside the bin, hand empty) ``MIN_PILE_TOP / max(pile_top, MIN_PILE_TOP)``, with
``pile_top`` the highest point of any block in metres (AABB top) and ``MIN_PILE_TOP`` = 0.03 m, the
lowest pile top a success can have (see ``pile_reward``). So every success earns a reward in (0, 1],
strictly smaller for taller piles; the noiseless expert's 8-block piles (seeds 0–29: 9.1–12.1 cm)
earn 0.25–0.33.

Optional progress term (``progress_reward=c`` > 0, off by default; not in the paper): each step also earns
``c × (change in the number of blocks resting in the bin)`` (the held block not counted), and a failure's
step gives back all of it (``−c ×`` the blocks resting before it). An episode's undiscounted return is
then the pack's reward plus ``c ×`` the blocks resting in the bin at its end, and a failure's 0 as without
the term. A block taken out and put back earns ``−c + γc < 0`` (discounted), so no loop pays; unlike the
anchor's +0.1 for ending a step holding a block, picking alone earns nothing. ``pack_reward`` keeps the
task's reward without the term, which the packing report (``packing_scores``) reads.
"""

from __future__ import annotations

import math

import numpy as np

from ldm_rl.envs.base import PickPlaceEnv, SpawnError, PrimitiveTarget
from ldm_rl.envs.objects import BIN_BLOCKS, ContainerFrame, ContainerSpec, add_container, spawn

__all__ = ["BinPackingEnv", "BIN", "MIN_PILE_TOP", "pile_reward", "pile_top_from_reward", "packing_scores"]

BIN = ContainerSpec(inner_x=0.18, inner_y=0.14, height=0.1)
# The lowest top a successful pile can have (0.03 m): a block whose centre is inside the bin rests on
# the bin floor (top at 1 cm) or higher, and its AABB is at least as tall as its thinnest dimension
# (2 cm: the flat brick and the half cube; the prism is 3.9 cm) in any orientation.
MIN_PILE_TOP = BIN.floor_top + 2 * min(min(spec.half_extents) for spec in BIN_BLOCKS)
BIN_MARGIN = 0.055  # m between the bin's outer walls and spawned block centres (open fingers reach 4.5 cm)
BLOCK_DISTANCE = 0.085  # m between spawned block centres
FINGER_ZONE = 0.025  # m beyond the held block (along the closing direction) the fingers need
GRID_STEP = 0.005  # m between candidate place positions


def pile_reward(pile_top: float) -> float:
    """A successful pack's reward: ``MIN_PILE_TOP / max(pile_top, MIN_PILE_TOP)``, in (0, 1].

    Inversely proportional to the pile's highest point ``pile_top`` (m, an AABB top, finite), 1 for
    the lowest possible pile (3 cm); the ``max`` only absorbs sub-millimetre contact penetration.
    Always above the 0 of a failure or a timeout.
    """
    return MIN_PILE_TOP / max(float(pile_top), MIN_PILE_TOP)


def pile_top_from_reward(reward: float) -> float:
    """The pile top (m) of a successful pack from its reward (the inverse of :func:`pile_reward`)."""
    if not 0 < reward <= 1:
        raise ValueError(f"reward must be a successful pack's, in (0, 1], got {reward!r}")
    return MIN_PILE_TOP / float(reward)


def pile_tops(returns: list[float]) -> list[float | None]:
    """Each episode's pile top (m) where it packed (a positive return under our reward), else ``None``."""
    return [pile_top_from_reward(r) if r > 0 else None for r in returns]


def packing_scores(returns: list[float], blocks_in_bin: list[int] | None = None) -> dict:
    """Episode returns (our reward: a success's ``pile_reward``, else 0) -> the bin-packing report.

    ``packed``: fraction of episodes with all blocks in the bin; ``mean_pile_top`` (m) over the packed ones
    (None when none); ``mean_return`` under our reward and ``mean_return_authors`` under the authors'
    terminal reward ``100·(0.1 m − pile top)`` (0 for an episode that never packed; the paper plots it).
    ``blocks_in_bin`` (optional, one count per episode, :meth:`BinPackingEnv.blocks_in_bin` at its end) adds
    ``mean_blocks_in_bin``: the progress of the episodes that did not pack them all.
    """
    if not returns:
        raise ValueError("returns must hold at least one episode's return")
    if blocks_in_bin is not None and len(blocks_in_bin) != len(returns):
        raise ValueError(f"blocks_in_bin must hold one count per episode ({len(returns)}), got {len(blocks_in_bin)}")
    tops = [top for top in pile_tops(returns) if top is not None]
    scores = {
        "episodes": len(returns),
        "packed": len(tops) / len(returns),
        "mean_pile_top": sum(tops) / len(tops) if tops else None,
        "mean_return": sum(returns) / len(returns),
        "mean_return_authors": sum(100 * (0.1 - top) for top in tops) / len(returns),
    }
    if blocks_in_bin is not None:
        scores["mean_blocks_in_bin"] = sum(blocks_in_bin) / len(blocks_in_bin)
    return scores


class BinPackingEnv(PickPlaceEnv):
    """Terminates when all blocks are in the bin, hand empty; reward ``pile_reward(pile_top)`` then.

    ``pile_reward(top) = MIN_PILE_TOP / max(top, MIN_PILE_TOP)`` with ``MIN_PILE_TOP = 0.03`` m (bin
    floor 1 cm + the shortest block side 2 cm, the lowest top any successful pile can have): in (0, 1]
    for every successful pile, smaller for taller piles. 0 on intermediate steps, failures and timeouts.
    """

    max_height = 0.15
    pick_depth = 0.012

    def __init__(self, num_objects: int = 8, *, progress_reward: float = 0.0, **kwargs):
        if (isinstance(progress_reward, bool) or not isinstance(progress_reward, (int, float))
                or not 0 <= progress_reward <= 1):
            raise ValueError(f"progress_reward must be a number in [0, 1] (reward per block resting in the bin), "
                             f"got {progress_reward!r}")
        self.progress_reward = float(progress_reward)
        self.pack_reward = 0.0  # the last step's pack reward (pile_reward on a success, else 0), no progress term
        self._resting_before = 0
        super().__init__(num_objects, **kwargs)
        self.bin = ContainerFrame(BIN)

    # --- scene -----------------------------------------------------------------------------------
    def _build_scene(self, rng: np.random.Generator) -> None:
        outer = np.array([BIN.inner_x / 2 + 2 * BIN.wall, BIN.inner_y / 2 + 2 * BIN.wall])
        (xy,) = self._sample_positions(rng, 1, padding=float(np.hypot(*outer)), min_distance=0.0)
        self.bin = ContainerFrame(BIN, (float(xy[0]), float(xy[1])), float(rng.uniform(0, math.pi)))
        add_container(self.sim, BIN, *self.bin.xy, self.bin.yaw)
        placed = self._sample_positions(
            rng, self.num_objects, padding=0.035, min_distance=BLOCK_DISTANCE, tries=200,
            accept=lambda p: bool(np.any(np.abs(self.bin.to_local(p)) > outer + BIN_MARGIN)),
        )
        shapes = rng.permutation(np.resize(np.arange(len(BIN_BLOCKS)), self.num_objects))
        for p, k in zip(placed, shapes):
            spawn(self.sim, BIN_BLOCKS[k], p[0], p[1], rng.uniform(0, 2 * math.pi))

    def _is_success(self) -> bool:
        return self.blocks_in_bin() == len(self.sim.objects)

    def blocks_in_bin(self) -> int:
        """Blocks whose centre lies inside the bin (seen from above), the held one included."""
        return sum(self.bin.contains(self.sim.pose(o.body)[0]) for o in self.sim.objects)

    def blocks_resting_in_bin(self) -> int:
        """Blocks whose centre lies inside the bin (seen from above), the held one excluded."""
        held = self.gripper.held
        return sum(self.bin.contains(self.sim.pose(o.body)[0]) for o in self.sim.objects
                   if held is None or o.body != held.body)

    def pile_top(self) -> float:
        """Highest point of any block, m."""
        return float(max(self.sim.aabb(o.body)[1][2] for o in self.sim.objects))

    def step(self, action):
        if self.progress_reward:
            self._resting_before = self.blocks_resting_in_bin()
        return super().step(action)

    def _reward(self, success: bool, invalid: str) -> float:
        self.pack_reward = pile_reward(self.pile_top()) if success else 0.0
        if not self.progress_reward:
            return self.pack_reward
        if invalid:  # a failure gives back what the episode earned: its return is 0, as without the term
            return -self.progress_reward * self._resting_before
        return self.pack_reward + self.progress_reward * (self.blocks_resting_in_bin() - self._resting_before)

    # --- expert ----------------------------------------------------------------------------------
    def expert_target(self) -> PrimitiveTarget:
        """Pick the largest block outside the bin; place it where it ends lowest (fingers free)."""
        held = self.holding
        if held is None:
            outside = [o for o in self._scene_objects() if not self.bin.contains(self.sim.pose(o.body)[0])]
            pool = outside or self._scene_objects()
            target = max(pool, key=lambda o: (o.half_extents[0] * o.half_extents[1] * o.half_extents[2], -o.body))
            return self._grasp(target, math.pi)
        yaw = self.snap_yaw(self.bin.yaw)
        uv = self._best_spot(held, yaw)
        x, y = self.bin.to_world(uv)
        return self._place_held_with_yaw(x, y, yaw)

    def _best_spot(self, held, gripper_yaw: float) -> np.ndarray:
        """Bin-frame (u, v) where the held block rests lowest with both finger zones clear.

        Candidates on a 5 mm grid of the bin interior; the heightmap is sampled under the block's
        footprint and under the two finger zones (batched over candidates × samples)."""
        hx, hy, hz = held.half_extents
        us = np.arange(-BIN.inner_x / 2 + hx + 0.005, BIN.inner_x / 2 - hx - 0.005 + 1e-9, GRID_STEP)
        vs = np.arange(-BIN.inner_y / 2 + hy + 0.005, BIN.inner_y / 2 - hy - 0.005 + 1e-9, GRID_STEP)
        cand = np.stack(np.meshgrid(us, vs, indexing="ij"), -1).reshape(-1, 2)
        world = self.bin.to_world(cand)  # [C, 2]
        c, s = math.cos(gripper_yaw), math.sin(gripper_yaw)
        axis_a, axis_b = np.array([c, s]), np.array([-s, c])  # closing direction, across it
        res = self.workspace.resolution
        a = np.arange(-hx, hx + 1e-9, res)
        b = np.arange(-hy, hy + 1e-9, res)
        body = (a[:, None, None] * axis_a + b[None, :, None] * axis_b).reshape(-1, 2)
        fa = np.concatenate([np.arange(hx, hx + FINGER_ZONE, res), -np.arange(hx, hx + FINGER_ZONE, res)])
        fb = np.arange(-0.012, 0.0121, res)
        fingers = (fa[:, None, None] * axis_a + fb[None, :, None] * axis_b).reshape(-1, 2)
        surface = self._sample_heights(world[:, None] + body[None]).max(1)
        finger_top = self._sample_heights(world[:, None] + fingers[None]).max(1)
        tip = surface + 0.005 + self.gripper.tip_to_bottom
        fits = finger_top < tip - 0.003
        score = np.where(fits, surface, surface + 1.0)
        # lowest resting height (to 5 mm), then fill from one end of the bin
        order = np.lexsort((cand[:, 1], cand[:, 0], np.round(score / 0.005)))
        return cand[order[0]]

    def _sample_heights(self, xy: np.ndarray) -> np.ndarray:
        """Heightmap values at metric points ``[..., 2]``; points off the workspace read 1 m."""
        ws = self.workspace
        rc = np.floor((xy - np.array([ws.x_min, ws.y_min])) / ws.resolution).astype(np.int64)
        inside = np.all((rc >= 0) & (rc < ws.pixels), -1)
        rc = np.clip(rc, 0, ws.pixels - 1)
        return np.where(inside, self.heightmap[rc[..., 0], rc[..., 1]], 1.0)
