"""Top-down heightmap camera: a far, narrow-angle perspective camera that is nearly orthographic.

The eye sits 10 m above the workspace centre looking down with ``up = -x``, near plane 9 m, far
plane 10 m and a field of view that spans exactly the workspace on the table (depth 10 m). Then
image row i covers x in [x_min + i·res, x_min + (i+1)·res) and column j covers y likewise, i.e. the
pixel centres are ``Workspace.pixel_to_metric`` (row ↔ x, col ↔ y). Height = plane depth (10 m) −
linearised depth. The table has no visual shape, so empty pixels read exactly 0. The perspective
error is (10 − h)/10: an object 0.2 m tall appears 2 % closer to the image centre.
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb

from ldm_rl.geometry import Workspace

__all__ = ["HeightmapCamera"]

EYE_HEIGHT = 10.0  # m above the table
NEAR = 9.0  # m: anything higher than 1 m above the table is clipped (the parked gripper is far away)
FAR = 10.0
TABLE_RGB = (150, 140, 125)


class HeightmapCamera:
    """Renders ``[H, W] float32`` heightmaps (metres above the table, in [0, 1]) of a workspace."""

    def __init__(self, workspace: Workspace):
        self.workspace = workspace
        cx, cy = workspace.center
        self._view = pb.computeViewMatrix([cx, cy, EYE_HEIGHT], [cx, cy, 0.0], [-1.0, 0.0, 0.0])
        fov = math.degrees(2.0 * math.atan(0.5 * workspace.size / EYE_HEIGHT))
        self._projection = pb.computeProjectionMatrixFOV(fov, 1.0, NEAR, FAR)

    def heightmap(self, client: int) -> np.ndarray:
        """Render the scene of ``client``: ``[pixels, pixels] float32`` heights in metres."""
        n = self.workspace.pixels
        _, _, _, depth_buffer, _ = pb.getCameraImage(
            n, n, self._view, self._projection,
            renderer=pb.ER_TINY_RENDERER, flags=pb.ER_NO_SEGMENTATION_MASK, shadow=0,
            physicsClientId=client,
        )
        depth_buffer = np.asarray(depth_buffer, dtype=np.float64).reshape(n, n)
        depth = FAR * NEAR / (FAR - (FAR - NEAR) * depth_buffer)
        return np.clip(EYE_HEIGHT - depth, 0.0, EYE_HEIGHT - NEAR).astype(np.float32)

    def rgb(self, client: int, size: int = 256) -> np.ndarray:
        """Top-down colour image ``[size, size, 3] uint8`` (for ``render()``); the table is grey."""
        _, _, rgb, depth_buffer, _ = pb.getCameraImage(
            size, size, self._view, self._projection,
            renderer=pb.ER_TINY_RENDERER, flags=pb.ER_NO_SEGMENTATION_MASK, physicsClientId=client,
        )
        rgb = np.asarray(rgb, dtype=np.uint8).reshape(size, size, 4)[..., :3].copy()
        table = np.asarray(depth_buffer).reshape(size, size) >= 1.0
        rgb[table] = TABLE_RGB
        return rgb
