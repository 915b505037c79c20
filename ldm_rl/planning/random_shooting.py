"""Random Shooting candidates: actions drawn uniformly near the objects of the scene.

The rule (the Random Shooting baseline, ``docs/policy.md`` § Baselines):

1. object pixels are those whose height exceeds ``height_threshold`` metres;
2. that mask is dilated by ``dilation`` pixels (a square window of side ``2·dilation + 1``), so picks on
   an object's edge and places on top of or beside an object are covered;
3. N distinct actions are drawn uniformly, without replacement, over the masked pixels × all R rotation
   bins;
4. a state with fewer than N such actions (an empty table, say) draws uniformly over every pixel × rotation.

Pure tensor code: imports only torch. Actions are ``(row, col, rot)`` int64, as everywhere in ``ldm_rl``;
the flat index of an action is ``rot·H·W + row·W + col`` (the order of a ``[B, R, H, W]`` Q map).
"""

from __future__ import annotations

import math
import numbers

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["object_mask", "sample_near_objects"]


def _check_common(heightmap, height_threshold, dilation) -> None:
    if not torch.is_tensor(heightmap) or heightmap.dim() != 4 or heightmap.shape[1] != 1:
        shape = tuple(heightmap.shape) if torch.is_tensor(heightmap) else type(heightmap).__name__
        raise ValueError(f"heightmap must be a [B, 1, H, W] float tensor (metres), got {shape}")
    if not heightmap.is_floating_point():
        raise ValueError(f"heightmap must be floating point (metres), got dtype {heightmap.dtype}")
    real = isinstance(height_threshold, numbers.Real) and not isinstance(height_threshold, bool)
    if not real or not math.isfinite(height_threshold) or height_threshold < 0:
        raise ValueError(f"height_threshold must be a finite number of metres >= 0, got {height_threshold!r}")
    if not isinstance(dilation, numbers.Integral) or isinstance(dilation, bool) or dilation < 0:
        raise ValueError(f"dilation must be an int >= 0 (pixels), got {dilation!r}")


def object_mask(heightmap: Tensor, *, height_threshold: float = 0.01, dilation: int = 8) -> Tensor:
    """``[B, 1, H, W]`` metres -> ``[B, H, W]`` bool: pixels within ``dilation`` px (Chebyshev distance)
    of a pixel higher than ``height_threshold``."""
    _check_common(heightmap, height_threshold, dilation)
    mask = (heightmap > height_threshold).to(torch.float32)
    if dilation:
        mask = F.max_pool2d(mask, kernel_size=2 * dilation + 1, stride=1, padding=dilation)
    return mask[:, 0] > 0


def sample_near_objects(
    heightmap: Tensor,
    num: int,
    *,
    num_rotations: int,
    height_threshold: float = 0.01,
    dilation: int = 8,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Draw ``num`` distinct actions per state near its objects: ``[B, 1, H, W] -> [B, N, 3]`` int64
    ``(row, col, rot)`` on heightmap's device (see the module docstring for the rule).

    Args:
        heightmap: ``[B, 1, H, W]`` float metres.
        num: N, actions per state, ``1 ≤ N ≤ R·H·W``.
        num_rotations: R rotation bins.
        height_threshold: metres above which a pixel belongs to an object.
        dilation: pixels by which the object mask grows.
        generator: optional ``torch.Generator`` on heightmap's device (deterministic draws given it).
    """
    _check_common(heightmap, height_threshold, dilation)
    if not isinstance(num_rotations, numbers.Integral) or isinstance(num_rotations, bool) or num_rotations < 1:
        raise ValueError(f"num_rotations must be a positive int, got {num_rotations!r}")
    b, _, h, w = heightmap.shape
    size = num_rotations * h * w
    if not isinstance(num, numbers.Integral) or isinstance(num, bool) or not 1 <= num <= size:
        raise ValueError(f"num must be an int in [1, R*H*W = {size}], got {num!r}")
    mask = object_mask(heightmap, height_threshold=height_threshold, dilation=dilation).reshape(b, h * w)
    too_few = mask.sum(1) * num_rotations < num  # fall back to the whole map
    weights = (mask | too_few[:, None]).to(torch.float32)
    weights = weights.unsqueeze(1).expand(b, num_rotations, h * w).reshape(b, size)
    if b == 0:
        return torch.empty(0, num, 3, dtype=torch.long, device=heightmap.device)
    idx = torch.multinomial(weights, num, replacement=False, generator=generator)  # [B, N]
    rot, rem = idx.div(h * w, rounding_mode="floor"), idx.remainder(h * w)
    return torch.stack((rem.div(w, rounding_mode="floor"), rem.remainder(w), rot), dim=-1)
