"""SE(2) pixel geometry of the top-down heightmap: the one place for pixels, angles and crops.

Conventions (docs/conventions.md)
---------------------------------
* Heightmap ``[*B, C, H, W]``; **row ↔ x, column ↔ y**; a pixel is a square cell and its centre is
  ``x = x_min + (row + 0.5)·res``, ``y = y_min + (col + 0.5)·res`` (``res`` = 3.125 mm by default).
* ``R(θ)`` rotates (row, col) offsets: ``(dr, dc) -> (dr·cosθ − dc·sinθ, dr·sinθ + dc·cosθ)``. Because
  row↔x and col↔y this is a counter-clockwise yaw in the world. A gripper at yaw θ closes its fingers
  along the world direction ``(cos θ, sin θ)``: the row axis of a crop taken at angle θ.
* Rotation bins: ``R`` angles ``k·π/R``; a parallel-jaw grasp is symmetric under π, so bin arithmetic
  is circular mod π. Image operations take *real* angles (radians, not wrapped): rotating an image by
  π is not the identity.
* Crops: ``crop(x, a, θ, d)[i, j] = x[a + R(θ)·(i − d//2, j − d//2)]``; the action pixel is
  ``[d//2, d//2]``; outside the image reads as 0.

Exactness
---------
Every angle is split into whole quarter turns (applied as exact swaps/negations) and a residual in
[0, π/2) snapped to 2⁻²⁰ of a quarter turn (≈1.5 µrad). Bilinear weights are ``1 − |w − n|`` per axis
(symmetric under negation) and the four corner terms are summed diagonal by diagonal. Together this
makes ``crop`` and ``paste`` *bit-exactly* equivariant to 90° rotations of the scene (with the action
rotated accordingly) and to whole-pixel translations, on CPU and CUDA.

All image functions batch over any leading dims (broadcasting images, centres and angles without
copying the source image), run on any device, and are differentiable w.r.t. image values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "HEIGHTMAP_SIZE",
    "HAND_SIZE",
    "NUM_ROTATIONS",
    "Workspace",
    "rotation_angles",
    "bin_to_angle",
    "angle_to_bin",
    "circular_bin_distance",
    "action_to_pose",
    "flat_to_action",
    "action_to_flat",
    "crop",
    "paste",
    "center_crop",
    "rotate",
    "quarter_turns",
    "shift",
    "mirror_crops",
    "raise_tallest",
    "rotate_stack",
    "unrotate_stack",
    "heights_to_classes",
    "classes_to_heights",
]

HEIGHTMAP_SIZE = 128  # pixels per side of the heightmap (0.4 m / 3.125 mm)
HAND_SIZE = 24  # pixels per side of the in-hand image
NUM_ROTATIONS = 8  # default R: rotation bins k·π/R

_MODES = ("bilinear", "nearest")
_SNAP = 2.0**20  # residual-angle grid, in fractions of a quarter turn


# --------------------------------------------------------------------------------------------
# Workspace: pixels <-> metres
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Workspace:
    """The square table area seen by the heightmap camera.

    Attributes: ``x_min``, ``y_min`` (metres, world frame), ``size`` (side, metres), ``pixels``
    (heightmap side). Defaults: the paper's 0.4 m × 0.4 m at (0.2..0.6, −0.2..0.2), 128 px.
    """

    x_min: float = 0.2
    y_min: float = -0.2
    size: float = 0.4
    pixels: int = 128

    def __post_init__(self):
        if not (isinstance(self.size, (int, float)) and self.size > 0 and math.isfinite(self.size)):
            raise ValueError(f"Workspace.size must be a positive number of metres, got {self.size!r}")
        if not (isinstance(self.pixels, int) and self.pixels > 0):
            raise ValueError(f"Workspace.pixels must be a positive int, got {self.pixels!r}")

    @property
    def resolution(self) -> float:
        """Metres per pixel (0.003125 by default)."""
        return self.size / self.pixels

    @property
    def center(self) -> tuple[float, float]:
        """(x, y) of the workspace centre, metres."""
        return (self.x_min + self.size / 2, self.y_min + self.size / 2)

    def pixel_to_metric(self, rc):
        """``[..., 2]`` (row, col) pixels -> ``[..., 2]`` (x, y) metres of the pixel centres.

        Accepts torch tensors (returns float64 tensors on the same device) or array-likes (returns
        a float64 numpy array). Fractional pixels are allowed.
        """
        t, to_numpy = _as_tensor(rc, "rc")
        res = self.resolution
        out = torch.stack((self.x_min + (t[..., 0] + 0.5) * res, self.y_min + (t[..., 1] + 0.5) * res), -1)
        return out.numpy() if to_numpy else out

    def metric_to_pixel(self, xy, clamp: bool = False):
        """``[..., 2]`` (x, y) metres -> ``[..., 2]`` int64 (row, col) of the pixel containing the point.

        Points outside the workspace raise ValueError unless ``clamp`` (then they snap to the border).
        Same input/output types as :meth:`pixel_to_metric`.
        """
        t, to_numpy = _as_tensor(xy, "xy")
        if not torch.isfinite(t).all():
            raise ValueError(f"xy must be finite metres, got {t.tolist()}")
        res = self.resolution
        rc = torch.stack((torch.floor((t[..., 0] - self.x_min) / res), torch.floor((t[..., 1] - self.y_min) / res)), -1)
        outside = (rc < 0) | (rc >= self.pixels)
        if outside.any():
            if not clamp:
                bad = t[outside.any(-1)][0].tolist()
                raise ValueError(
                    f"xy={bad} lies outside the workspace x∈[{self.x_min}, {self.x_min + self.size}), "
                    f"y∈[{self.y_min}, {self.y_min + self.size}); pass clamp=True to snap it to the border"
                )
            rc = rc.clamp(0, self.pixels - 1)
        rc = rc.long()
        return rc.numpy() if to_numpy else rc


def _as_tensor(value, name: str) -> tuple[Tensor, bool]:
    to_numpy = not torch.is_tensor(value)
    t = torch.as_tensor(np.asarray(value) if to_numpy else value).to(torch.float64)
    if t.shape[-1:] != (2,):
        raise ValueError(f"{name} must have a last dimension of size 2, got shape {tuple(t.shape)}")
    return t, to_numpy


# --------------------------------------------------------------------------------------------
# Rotation bins (circular mod π)
# --------------------------------------------------------------------------------------------
def _check_num_rotations(num_rotations) -> int:
    if not isinstance(num_rotations, int) or isinstance(num_rotations, bool) or num_rotations < 1:
        raise ValueError(f"num_rotations must be a positive int, got {num_rotations!r}")
    return num_rotations


def rotation_angles(num_rotations: int, device=None, dtype=torch.float32) -> Tensor:
    """``[R]`` angles ``k·π/R`` (radians), k = 0..R−1."""
    r = _check_num_rotations(num_rotations)
    return torch.arange(r, device=device, dtype=torch.float64).mul(math.pi / r).to(dtype)


def bin_to_angle(bins: Tensor, num_rotations: int) -> Tensor:
    """Rotation bin(s) (int) -> angle ``k·π/R`` (float32 radians). Bins outside 0..R−1 raise."""
    r = _check_num_rotations(num_rotations)
    bins = torch.as_tensor(bins)
    if bins.is_floating_point() or bins.dtype == torch.bool:
        raise ValueError(f"bins must be an integer tensor, got dtype {bins.dtype}")
    if bins.numel() and (bins.min() < 0 or bins.max() >= r):
        raise ValueError(f"rotation bins must lie in [0, {r}), got values in [{int(bins.min())}, {int(bins.max())}]")
    return (bins.to(torch.float64) * (math.pi / r)).to(torch.float32)


def angle_to_bin(angles: Tensor, num_rotations: int) -> Tensor:
    """Angle(s) in radians (any real value) -> nearest bin, circular mod π (int64 in 0..R−1).

    ``π − ε`` maps to bin 0, not R−1 (the reference code's missing wrap-around).
    """
    r = _check_num_rotations(num_rotations)
    a = torch.as_tensor(angles, dtype=torch.float64)
    if not torch.isfinite(a).all():
        raise ValueError("angles must be finite radians")
    return torch.round(a / (math.pi / r)).long().remainder(r)


def circular_bin_distance(a: Tensor, b: Tensor, num_rotations: int) -> Tensor:
    """Distance between rotation bins on the circle of R bins (int64 in 0..R//2)."""
    r = _check_num_rotations(num_rotations)
    d = (torch.as_tensor(a) - torch.as_tensor(b)).remainder(r)
    return torch.minimum(d, r - d)


def flat_to_action(index: Tensor, height: int, width: int) -> Tensor:
    """Flat indices ``rot·H·W + row·W + col`` ``[*B]`` (the order of a ``[B, R, H, W]`` map flattened)
    -> actions ``[*B, 3]`` int64 (row, col, rot)."""
    if not torch.is_tensor(index) or index.is_floating_point() or index.dtype == torch.bool:
        raise ValueError(f"index must be an integer tensor of flat indices, got {getattr(index, 'dtype', type(index))}")
    rot, rem = index.div(height * width, rounding_mode="floor"), index.remainder(height * width)
    return torch.stack((rem.div(width, rounding_mode="floor"), rem.remainder(width), rot), dim=-1)


def action_to_flat(action: Tensor, height: int, width: int) -> Tensor:
    """Actions ``[*B, 3]`` int64 (row, col, rot) -> flat indices ``rot·H·W + row·W + col`` ``[*B]``."""
    if not torch.is_tensor(action) or action.is_floating_point() or action.dtype == torch.bool or action.shape[-1:] != (3,):
        what = f"{tuple(action.shape)} {action.dtype}" if torch.is_tensor(action) else type(action).__name__
        raise ValueError(f"action must be an integer tensor [*B, 3] (row, col, rot), got {what}")
    return (action[..., 2] * height + action[..., 0]) * width + action[..., 1]


def action_to_pose(action: Tensor, num_rotations: int, image_size: Sequence[int] | None = None):
    """Spatial action ``[*B, 3]`` int64 (row, col, rot bin) -> (centres ``[*B, 2]`` int64, angles ``[*B]`` f32).

    With ``image_size`` = (H, W) the pixel components are range-checked too.
    """
    if not torch.is_tensor(action) or action.shape[-1:] != (3,):
        shape = tuple(action.shape) if torch.is_tensor(action) else type(action).__name__
        raise ValueError(f"action must be a [..., 3] integer tensor (row, col, rot), got {shape}")
    if action.is_floating_point() or action.dtype == torch.bool:
        raise ValueError(f"action must have an integer dtype, got {action.dtype}")
    centers = action[..., :2].long()
    if image_size is not None:
        _check_centers(centers, tuple(image_size), "action")
    return centers, bin_to_angle(action[..., 2], num_rotations)


# --------------------------------------------------------------------------------------------
# Exact angle decomposition and sampling core
# --------------------------------------------------------------------------------------------
def _quarter_split(angles: Tensor):
    """angles -> (quarter turns q ∈ {0,1,2,3} int64, cos φ, sin φ float64) with θ = q·π/2 + φ, φ ∈ [0, π/2)."""
    t = angles.to(torch.float64) / (math.pi / 2)
    q = torch.floor(t)
    frac = torch.round((t - q) * _SNAP) / _SNAP
    carry = frac >= 1.0
    q = torch.where(carry, q + 1, q)
    frac = torch.where(carry, torch.zeros_like(frac), frac)
    phi = frac * (math.pi / 2)
    return q.long().remainder(4), torch.cos(phi), torch.sin(phi)


def _quarter_turn(a: Tensor, b: Tensor, q: Tensor):
    """Apply R(q·π/2) to the (row, col) vector (a, b) exactly: q=1 maps (a, b) -> (−b, a)."""
    a, b, q = torch.broadcast_tensors(a, b, q)
    rows = torch.stack((a, -b, -a, b), -1).gather(-1, q.unsqueeze(-1)).squeeze(-1)
    cols = torch.stack((b, a, -b, -a), -1).gather(-1, q.unsqueeze(-1)).squeeze(-1)
    return rows, cols


def _rotate_offsets(u: Tensor, v: Tensor, angles: Tensor, dtype: torch.dtype):
    """R(θ)·(u, v) for a grid (u, v) ``[h, w]`` and angles ``[*B]`` -> two ``[*B, h, w]`` tensors of ``dtype``."""
    q, c, s = _quarter_split(angles)
    c, s, q = c.to(dtype)[..., None, None], s.to(dtype)[..., None, None], q[..., None, None]
    u, v = u.to(dtype), v.to(dtype)
    return _quarter_turn(c * u - s * v, s * u + c * v, q)


def _unrotate_offsets(du: Tensor, dv: Tensor, angles: Tensor, dtype: torch.dtype):
    """R(−θ)·(du, dv) for whole-pixel offsets ``[h, w]`` and angles ``[*B]`` -> two ``[*B, h, w]`` of ``dtype``."""
    q, c, s = _quarter_split(angles)
    c, s, q = c.to(dtype)[..., None, None], s.to(dtype)[..., None, None], q[..., None, None]
    a, b = _quarter_turn(du.to(dtype), dv.to(dtype), (4 - q).remainder(4))  # exact: undo the quarter turns first
    return c * a + s * b, c * b - s * a


def _sample(images: Tensor, batch: torch.Size, rows0: Tensor, cols0: Tensor, wr: Tensor, wc: Tensor, mode: str) -> Tensor:
    """Sample ``images [*Bi, C, H, W]`` at integer anchors ``(rows0, cols0)`` plus offsets ``(wr, wc) [*batch, h, w]``.

    ``Bi`` broadcasts against ``batch`` without copies; anchors broadcast against the offsets. Pixels
    outside the image read as 0 (the source is zero-padded once, just enough for the reads). Returns
    ``[*batch, C, h, w]``. Bilinear weights use the negation-symmetric form ``1 − |w − n|`` and the
    corner terms are summed diagonal by diagonal, which a quarter turn leaves bit-identical.
    """
    c, height, width = images.shape[-3:]
    h, w = wr.shape[-2:]
    n = math.prod(batch)
    if mode == "nearest":
        r0, c0, reach = rows0 + torch.round(wr).long(), cols0 + torch.round(wc).long(), 0
    else:
        nr, nc = torch.floor(wr), torch.floor(wc)
        r0, c0, reach = rows0 + nr.long(), cols0 + nc.long(), 1
    r0, c0 = r0.expand(*batch, h, w).reshape(n, h * w), c0.expand(*batch, h, w).reshape(n, h * w)
    top, left = max(0, -int(r0.min())), max(0, -int(c0.min()))
    bottom, right = max(0, int(r0.max()) + reach - height + 1), max(0, int(c0.max()) + reach - width + 1)
    if top or left or bottom or right:
        images = torch.nn.functional.pad(images, (left, right, top, bottom))
    hp, wp = images.shape[-2:]
    src_batch = images.shape[:-3]
    flat = images.reshape(-1, c, hp * wp).transpose(0, 1).reshape(c, -1)  # [C, M·Hp·Wp]
    src = torch.arange(max(1, math.prod(src_batch)), device=images.device).reshape(src_batch)
    base = src.expand(batch).reshape(n, 1) * (hp * wp) + (r0 + top) * wp + (c0 + left)  # [N, h·w]

    def read(shift: int) -> Tensor:  # [*batch, C, h·w]
        return flat[:, (base + shift).reshape(-1)].reshape(c, n, h * w).transpose(0, 1).reshape(*batch, c, h * w)

    if mode == "nearest":
        return read(0).reshape(*batch, c, h, w)
    wr0, wr1 = 1 - (wr - nr).abs(), 1 - (wr - (nr + 1)).abs()
    wc0, wc1 = 1 - (wc - nc).abs(), 1 - (wc - (nc + 1)).abs()

    def term(shift: int, a: Tensor, b: Tensor) -> Tensor:
        return read(shift) * (a * b).expand(*batch, h, w).reshape(*batch, 1, h * w)

    out = (term(0, wr0, wc0) + term(wp + 1, wr1, wc1)) + (term(1, wr0, wc1) + term(wp, wr1, wc0))
    return out.reshape(*batch, c, h, w)


# --------------------------------------------------------------------------------------------
# Input validation
# --------------------------------------------------------------------------------------------
def _check_images(images, name: str = "images") -> Tensor:
    if not torch.is_tensor(images) or images.dim() < 3:
        shape = tuple(images.shape) if torch.is_tensor(images) else type(images).__name__
        raise ValueError(f"{name} must be a [*B, C, H, W] tensor, got {shape}")
    return images


def _check_mode(mode: str, images: Tensor, name: str = "images") -> None:
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    if mode == "bilinear" and not images.is_floating_point():
        raise ValueError(f"mode='bilinear' needs floating-point {name}, got {images.dtype}; use mode='nearest'")


def _check_centers(centers, image_size: tuple[int, int], name: str = "centers") -> Tensor:
    if not torch.is_tensor(centers) or centers.shape[-1:] != (2,):
        shape = tuple(centers.shape) if torch.is_tensor(centers) else type(centers).__name__
        raise ValueError(f"{name} must be a [*B, 2] integer tensor (row, col), got {shape}")
    if centers.is_floating_point() or centers.dtype == torch.bool:
        raise ValueError(f"{name} must have an integer dtype (pixel indices), got {centers.dtype}")
    for axis, (label, size) in enumerate(zip(("row", "col"), image_size)):
        vals = centers[..., axis]
        if vals.numel() and (vals.min() < 0 or vals.max() >= size):
            raise ValueError(f"{name} {label} must lie in [0, {size}), got values in [{int(vals.min())}, {int(vals.max())}]")
    return centers.long()


def _check_angles(angles, device) -> Tensor:
    # python numbers and integer tensors become float64: float32 would round θ and θ + π/2 differently
    if not torch.is_tensor(angles) or not angles.is_floating_point():
        angles = torch.as_tensor(angles, dtype=torch.float64)
    angles = angles.to(device)
    if not torch.isfinite(angles).all():
        raise ValueError("angles must be finite radians")
    return angles


def _check_size(size, name: str = "size") -> int:
    if not isinstance(size, int) or isinstance(size, bool) or size < 1:
        raise ValueError(f"{name} must be a positive int (pixels), got {size!r}")
    return size


def _batch_shape(*shapes, what: str) -> torch.Size:
    try:
        return torch.broadcast_shapes(*shapes)
    except RuntimeError as err:
        raise ValueError(f"batch shapes do not broadcast ({what}): {[tuple(s) for s in shapes]}") from err


# --------------------------------------------------------------------------------------------
# Public image operations
# --------------------------------------------------------------------------------------------
def crop(images: Tensor, centers: Tensor, angles, size: int, mode: str = "bilinear") -> Tensor:
    """Rotated square crop B_a around each action: ``[*B, C, H, W] -> [*B, C, size, size]``.

    Args:
        images: ``[*Bi, C, H, W]`` scene (e.g. heightmap in metres, or uint8 classes with ``nearest``).
        centers: ``[*Bc, 2]`` int64 (row, col) action pixels, inside the image.
        angles: ``[*Ba]`` radians (real angles, not wrapped); float or tensor.
        size: crop side d in pixels; the action pixel lands at ``[d//2, d//2]``.
        mode: ``"bilinear"`` (float images) or ``"nearest"`` (any dtype).
    The leading dims broadcast to ``*B``. Pixels read outside the image are 0.
    """
    images = _check_images(images)
    _check_mode(mode, images)
    size = _check_size(size)
    centers = _check_centers(centers, tuple(images.shape[-2:]))
    angles = _check_angles(angles, images.device)
    batch = _batch_shape(images.shape[:-3], centers.shape[:-1], angles.shape, what="images, centers, angles")
    grid = torch.arange(size, device=images.device) - size // 2
    u, v = grid[:, None].expand(size, size), grid[None, :].expand(size, size)
    dtype = images.dtype if images.is_floating_point() else torch.float32
    wr, wc = _rotate_offsets(u, v, angles.expand(batch), dtype)
    rows0 = centers[..., 0].expand(batch)[..., None, None]
    cols0 = centers[..., 1].expand(batch)[..., None, None]
    return _sample(images, batch, rows0, cols0, wr, wc, mode)


def paste(images: Tensor, patches: Tensor, centers: Tensor, angles, mode: str = "bilinear") -> Tensor:
    """Write ``patches`` back into ``images`` inside the rotated squares B_a; nothing else changes.

    The inverse of :func:`crop`: scene pixel p belongs to B_a when ``R(−θ)·(p − a) + d//2`` falls in
    the patch's pixel footprint ``[−0.5, d − 0.5)²``; it then takes the patch value there (bilinear
    with border clamping, or nearest); every other pixel keeps its exact input value.

    Args:
        images: ``[*Bi, C, H, W]`` scenes. patches: ``[*Bp, C, d, d]``. centers ``[*Bc, 2]`` int64,
        angles ``[*Ba]`` radians: as in :func:`crop`. Returns ``[*B, C, H, W]`` (broadcast batch).
    """
    images = _check_images(images)
    patches = _check_images(patches, "patches")
    _check_mode(mode, patches, "patches")
    d = patches.shape[-1]
    if patches.shape[-2] != d:
        raise ValueError(f"patches must be square [*B, C, d, d], got {tuple(patches.shape)}")
    if patches.shape[-3] != images.shape[-3]:
        raise ValueError(f"patches have {patches.shape[-3]} channels but images have {images.shape[-3]}")
    if patches.dtype != images.dtype:
        raise ValueError(f"patches dtype {patches.dtype} differs from images dtype {images.dtype}")
    h, w = images.shape[-2:]
    centers = _check_centers(centers, (h, w))
    angles = _check_angles(angles, images.device)
    batch = _batch_shape(images.shape[:-3], patches.shape[:-3], centers.shape[:-1], angles.shape, what="images, patches, centers, angles")
    dtype = images.dtype if images.is_floating_point() else torch.float32
    # only a window around each action can change: the rotated square's bounding box, ±(d/√2 + 1) px
    m = math.ceil(d * math.sqrt(0.5)) + 1
    offsets = torch.arange(-m, m + 1, device=images.device)
    su, sv = _unrotate_offsets(offsets[:, None], offsets[None, :], angles.expand(batch), dtype)
    su, sv = su + d // 2, sv + d // 2  # patch coordinates of each window pixel, [*B, n, n]
    inside = (su >= -0.5) & (su < d - 0.5) & (sv >= -0.5) & (sv < d - 0.5)
    # clamped into the patch, a coordinate on the last pixel gives its outer neighbour weight 0, so
    # bilinear reads never blend in zero padding (border clamping)
    zero = torch.zeros((), dtype=torch.long, device=images.device)
    values = _sample(patches, batch, zero, zero, su.clamp(0, d - 1), sv.clamp(0, d - 1), mode)
    rows = centers[..., 0].expand(batch)[..., None, None] + offsets[:, None]
    cols = centers[..., 1].expand(batch)[..., None, None] + offsets[None, :]
    write = inside & (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    # scatter into the flattened scenes; window pixels that must not be written go to a dummy slot
    n_out, c = math.prod(batch), images.shape[-3]
    target = torch.where(write, rows * w + cols, h * w).reshape(n_out, 1, -1).expand(n_out, c, -1)
    scenes = images.expand(*batch, *images.shape[-3:]).reshape(n_out, c, h * w)
    scenes = torch.cat((scenes, scenes.new_zeros(n_out, c, 1)), -1)
    out = scenes.scatter(-1, target, values.reshape(n_out, c, -1))
    return out[..., : h * w].reshape(*batch, c, h, w)


def center_crop(patches: Tensor, size: int) -> Tensor:
    """Central ``size × size`` window of ``[*B, C, d, d]`` patches, aligned with :func:`crop`.

    ``center_crop(crop(x, a, θ, 64), 24) == crop(x, a, θ, 24)`` exactly: the window starts at
    ``d//2 − size//2`` so the action pixel stays at ``[size//2, size//2]``.
    """
    patches = _check_images(patches, "patches")
    size = _check_size(size)
    d = patches.shape[-1]
    if patches.shape[-2] != d or size > d:
        raise ValueError(f"center_crop needs square patches at least {size} px wide, got {tuple(patches.shape)}")
    start = d // 2 - size // 2
    return patches[..., start : start + size, start : start + size]


def rotate(images: Tensor, angles, mode: str = "bilinear") -> Tensor:
    """Rotate ``[*B, C, H, W]`` images about their centre: ``out[p] = images[c + R(θ)·(p − c)]``.

    ``c = ((H−1)/2, (W−1)/2)``. The content of a gripper at yaw θ appears at yaw 0 in the output
    (the same frame :func:`crop` uses). Corners come from outside the image and read as 0. Angles
    ``[*Ba]`` broadcast against the image batch; quarter turns are exact.
    """
    images = _check_images(images)
    _check_mode(mode, images)
    angles = _check_angles(angles, images.device)
    batch = _batch_shape(images.shape[:-3], angles.shape, what="images, angles")
    h, w = images.shape[-2:]
    dtype = images.dtype if images.is_floating_point() else torch.float32
    # offsets from the (possibly half-integer) centre are exact half-integers; anchor at floor(c)
    u = (torch.arange(h, device=images.device, dtype=torch.float64) - (h - 1) / 2)[:, None].expand(h, w)
    v = (torch.arange(w, device=images.device, dtype=torch.float64) - (w - 1) / 2)[None, :].expand(h, w)
    wr, wc = _rotate_offsets(u, v, angles.expand(batch), dtype)
    wr, wc = wr + ((h - 1) / 2 - (h - 1) // 2), wc + ((w - 1) / 2 - (w - 1) // 2)
    anchor_r = torch.full((), (h - 1) // 2, device=images.device)
    anchor_c = torch.full((), (w - 1) // 2, device=images.device)
    return _sample(images, batch, anchor_r, anchor_c, wr, wc, mode)


def quarter_turns(images: Tensor, turns: Tensor) -> Tensor:
    """Turn each of ``[B, C, H, W]`` images by its own whole number of quarter turns, ``turns`` ``[B]`` int
    (k → ``torch.rot90(image, k, (-2, -1))``, counter-clockwise as displayed; any integer, taken mod 4).
    Exact (a permutation of pixels); square images only, so every turn keeps the shape."""
    images = _check_images(images)
    if images.dim() != 4 or images.shape[-1] != images.shape[-2]:
        raise ValueError(f"images must be [B, C, H, H] (square), got {tuple(images.shape)}")
    if not torch.is_tensor(turns) or turns.is_floating_point() or tuple(turns.shape) != (images.shape[0],):
        shape = tuple(turns.shape) if torch.is_tensor(turns) else type(turns).__name__
        raise ValueError(f"turns must be [{images.shape[0]}] int (one count per image), got {shape}"
                         + (f" {turns.dtype}" if torch.is_tensor(turns) else ""))
    rows = torch.arange(images.shape[0], device=images.device)
    return torch.stack([images.rot90(k, (-2, -1)) for k in range(4)])[turns.remainder(4).to(images.device), rows]


def shift(images: Tensor, offsets: Tensor) -> Tensor:
    """Translate each of ``[B, C, H, W]`` images by its own whole-pixel offset, ``offsets`` ``[B, 2]`` int
    (rows, cols): ``out[b, :, r, c] = images[b, :, r − dr, c − dc]``, 0 where that pixel lies outside. Exact
    (pixels are moved, not resampled); a zero offset returns the image unchanged."""
    images = _check_images(images)
    if images.dim() != 4:
        raise ValueError(f"images must be [B, C, H, W], got {tuple(images.shape)}")
    b, _, h, w = images.shape
    if not torch.is_tensor(offsets) or offsets.is_floating_point() or tuple(offsets.shape) != (b, 2):
        shape = tuple(offsets.shape) if torch.is_tensor(offsets) else type(offsets).__name__
        raise ValueError(f"offsets must be [{b}, 2] int (rows, cols per image), got {shape}"
                         + (f" {offsets.dtype}" if torch.is_tensor(offsets) else ""))
    offsets = offsets.to(images.device)
    rows = torch.arange(h, device=images.device)[None] - offsets[:, :1]  # [B, H] source rows
    cols = torch.arange(w, device=images.device)[None] - offsets[:, 1:]  # [B, W] source cols
    inside = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]  # [B, H, W]
    picked = images[torch.arange(b, device=images.device)[:, None, None], :,
                    rows.clamp(0, h - 1)[:, :, None], cols.clamp(0, w - 1)[:, None, :]]  # [B, H, W, C]
    return picked.permute(0, 3, 1, 2) * inside[:, None].to(images.dtype)


def mirror_crops(crops: Tensor, rows: Tensor, cols: Tensor) -> Tensor:
    """Mirror each of ``[B, C, d, d]`` action-centred crops (even d, the action pixel at ``[d//2, d//2]`` as
    :func:`crop` puts it) about the action pixel: across its row axis where ``rows`` ``[B]`` bool is set (pixel row
    i -> d − i), across its column axis where ``cols`` is (both: the half turn). An exact permutation that keeps the
    action pixel in place, and its own inverse; row / column 0, whose mirror lies outside the crop, stays. On the
    gripper-aligned crops of the LDM these are the symmetries of a parallel-jaw gripper."""
    crops = _check_images(crops, "crops")
    if crops.dim() != 4 or crops.shape[-1] != crops.shape[-2] or crops.shape[-1] % 2:
        raise ValueError(f"crops must be [B, C, d, d] with even d, got {tuple(crops.shape)}")
    b = crops.shape[0]
    for name, flags in (("rows", rows), ("cols", cols)):
        if not torch.is_tensor(flags) or flags.dtype != torch.bool or tuple(flags.shape) != (b,):
            shape = tuple(flags.shape) if torch.is_tensor(flags) else type(flags).__name__
            raise ValueError(f"{name} must be a [{b}] bool tensor (one flag per crop), got {shape}")
    d = crops.shape[-1]
    source = (d - torch.arange(d, device=crops.device)) % d  # i -> d − i, 0 -> 0
    out = torch.where(rows.to(crops.device).view(b, 1, 1, 1), crops[:, :, source], crops)
    return torch.where(cols.to(crops.device).view(b, 1, 1, 1), out[:, :, :, source], out)


def raise_tallest(heightmaps: Tensor, lift: Tensor, floor: float, band: float | None = None) -> Tensor:
    """Raise the object standing under each heightmap's highest pixel by its own ``lift`` ``[B]`` (metres, ≥ 0), as
    if that many metres of object were slid under it: every pixel above ``floor`` m that is connected (8-neighbours,
    through pixels above ``floor``) to the highest one goes up by ``lift``; the rest is unchanged, and a heightmap
    with nothing above ``floor`` is returned as it is. ``heightmaps`` ``[B, 1, H, W]`` float, metres. Objects that
    touch the tallest one are raised with it (one region). ``band`` (metres > 0, or None = no limit): only pixels
    within ``band`` of the highest one count (connected through such pixels): the top object alone, slid up as if
    the lift went in under it, so what leans on the stack below its top (a cube beside a 2-stack, a lower cube's
    ledge) stays where it is. The region grows by one 3×3 dilation a step, so the cost is the region's diameter in
    pixels of max-pools over the batch."""
    heightmaps = _check_images(heightmaps, "heightmaps")
    if heightmaps.dim() != 4 or heightmaps.shape[1] != 1 or not heightmaps.is_floating_point():
        raise ValueError(f"heightmaps must be [B, 1, H, W] float metres, got {tuple(heightmaps.shape)} {heightmaps.dtype}")
    b = heightmaps.shape[0]
    if not torch.is_tensor(lift) or tuple(lift.shape) != (b,):
        shape = tuple(lift.shape) if torch.is_tensor(lift) else type(lift).__name__
        raise ValueError(f"lift must be a [{b}] tensor of metres (one per heightmap), got {shape}")
    if bool((lift < 0).any()):
        raise ValueError(f"lift must be >= 0 metres, got min {float(lift.min())}")
    if isinstance(floor, bool) or not isinstance(floor, (int, float)) or not math.isfinite(floor):
        raise ValueError(f"floor must be a finite number of metres, got {floor!r}")
    if band is not None and (isinstance(band, bool) or not isinstance(band, (int, float)) or not 0 < band < math.inf):
        raise ValueError(f"band must be a positive number of metres or None, got {band!r}")
    above = heightmaps > floor
    if band is not None:
        top = heightmaps.flatten(1).max(1).values.view(b, 1, 1, 1)
        above &= heightmaps >= top - band
    region = torch.zeros_like(above).flatten(1)
    region[torch.arange(b, device=heightmaps.device), heightmaps.flatten(1).argmax(1)] = True
    region = region.view_as(above) & above
    while True:
        grown = torch.nn.functional.max_pool2d(region.to(heightmaps.dtype), 3, 1, 1).bool() & above
        if torch.equal(grown, region):
            break
        region = grown
    return heightmaps + lift.to(heightmaps).view(b, 1, 1, 1) * region


def rotate_stack(images: Tensor, num_rotations: int, mode: str = "bilinear") -> Tensor:
    """``[*B, C, H, W] -> [*B, R, C, H, W]``: the images seen at each of the R bin angles k·π/R."""
    images = _check_images(images)
    angles = rotation_angles(num_rotations, device=images.device, dtype=torch.float64)
    return rotate(images.unsqueeze(-4), angles, mode)


def unrotate_stack(stack: Tensor, mode: str = "bilinear") -> Tensor:
    """Inverse of :func:`rotate_stack`: ``[*B, R, C, H, W]``, bin k rotated back by −k·π/R."""
    stack = _check_images(stack, "stack")
    if stack.dim() < 4:
        raise ValueError(f"stack must be [*B, R, C, H, W], got {tuple(stack.shape)}")
    angles = rotation_angles(stack.shape[-4], device=stack.device, dtype=torch.float64)
    return rotate(stack, -angles, mode)


# --------------------------------------------------------------------------------------------
# Heights <-> depth classes
# --------------------------------------------------------------------------------------------
def _check_class_params(max_height, num_classes) -> None:
    if not isinstance(num_classes, int) or isinstance(num_classes, bool) or not 2 <= num_classes <= 256:
        raise ValueError(f"num_classes must be an int in [2, 256] (stored as uint8), got {num_classes!r}")
    if not isinstance(max_height, (int, float)) or not (max_height > 0 and math.isfinite(max_height)):
        raise ValueError(f"max_height must be a positive number of metres, got {max_height!r}")


def heights_to_classes(heights: Tensor, max_height: float, num_classes: int) -> Tensor:
    """Heights (metres) -> depth classes ``round(clamp(h / max_height, 0, 1)·(K−1))`` as uint8.

    Computed in float64 whatever the input dtype (no float32/float64 skew); heights above
    ``max_height`` clamp to K−1, negative heights to 0; NaN raises ValueError.
    """
    _check_class_params(max_height, num_classes)
    if not torch.is_tensor(heights) or not heights.is_floating_point():
        raise ValueError(f"heights must be a floating-point tensor in metres, got {getattr(heights, 'dtype', type(heights))}")
    if torch.isnan(heights).any():
        raise ValueError("heights contain NaN")
    x = heights.to(torch.float64).div(max_height).clamp(0.0, 1.0).mul(num_classes - 1)
    return torch.round(x).to(torch.uint8)


def classes_to_heights(classes: Tensor, max_height: float, num_classes: int) -> Tensor:
    """Depth classes -> heights ``class·max_height/(K−1)`` (float32 metres). Classes ≥ K raise."""
    _check_class_params(max_height, num_classes)
    if not torch.is_tensor(classes) or classes.is_floating_point() or classes.dtype == torch.bool:
        raise ValueError(f"classes must be an integer tensor, got {getattr(classes, 'dtype', type(classes))}")
    if classes.numel() and (int(classes.min()) < 0 or int(classes.max()) >= num_classes):
        raise ValueError(f"classes must lie in [0, {num_classes}), got values in [{int(classes.min())}, {int(classes.max())}]")
    return (classes.to(torch.float64) * (max_height / (num_classes - 1))).to(torch.float32)
