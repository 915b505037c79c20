"""Candidate actions: diverse proposals from a Q map, and uniform draws near the scene's objects.

The paper's planner proposes N actions per state: each is drawn from ``softmax(Q/τ)`` over every
(rotation, row, column) of the current primitive's Q map, after which a Gaussian of height β around
the drawn action is subtracted from the map, so the next draw is pushed elsewhere. ``mode="argmax"``
is the authors' released code (deterministic argmax, no temperature; its inhibition window is
clamped at the rotation range's ends). Unlike that code, the rotation
axis of the inhibition is circular: bins k·π/R live on a circle mod π (``geometry.circular_bin_distance``).

The Random Shooting baseline draws its candidates without a Q map (:func:`sample_near_objects`,
:class:`NearObjectSampler`, ``docs/policy.md`` § Baselines):

1. object pixels are those whose height exceeds ``height_threshold`` metres;
2. that mask is dilated by ``dilation`` pixels (a square window of side ``2·dilation + 1``), so picks on
   an object's edge and places on top of or beside an object are covered;
3. N distinct actions are drawn uniformly, without replacement, over the masked pixels × all R rotation
   bins;
4. a state with fewer than N such actions (an empty table, say) draws uniformly over every pixel × rotation.

Actions are ``(row, col, rot)`` int64 everywhere; the flat index of an action is ``rot·H·W + row·W + col``
(the order of a ``[B, R, H, W]`` Q map, ``geometry.flat_to_action``). Pure tensor code: imports only torch and :mod:`ldm_rl.geometry`.
"""

from __future__ import annotations

import math
import numbers

import torch
import torch.nn.functional as F
from torch import Tensor

from ldm_rl.geometry import circular_bin_distance, flat_to_action

__all__ = ["sample_candidates", "mask_actions", "near_actions", "sweep_rotations", "object_mask", "sample_near_objects",
           "NearObjectSampler"]

_MODES = ("softmax", "argmax")


def mask_actions(q: Tensor, actions: Tensor, *, radius: float = 4.0, rot_radius: int = 1) -> Tensor:
    """``q`` with ``-inf`` around each of ``actions``: every entry within ``radius`` pixels and ``rot_radius``
    rotation bins (circular) of one of them, so that :func:`sample_candidates` and an argmax never propose it.

    Args:
        q: ``[B, R, H, W]`` floating Q map.
        actions: ``[B, M, 3]`` int64 ``(row, col, rot)``; rows holding a ``-1`` are ignored.
        radius: pixels (≥ 0; 4 px = 1.25 cm on the 128-px heightmap).
        rot_radius: rotation bins (≥ 0).

    Returns:
        a new ``[B, R, H, W]`` map (``q`` is not modified).
    """
    if q.ndim != 4 or actions.ndim != 3 or actions.shape[-1] != 3 or actions.shape[0] != q.shape[0] \
            or actions.is_floating_point() or actions.dtype == torch.bool:
        raise ValueError(f"q must be [B, R, H, W] and actions [B, M, 3] integer with the same B, got {tuple(q.shape)} "
                         f"and {actions.dtype} {tuple(actions.shape)}")
    if not radius >= 0 or not (isinstance(rot_radius, int) and rot_radius >= 0):
        raise ValueError(f"radius must be >= 0 pixels and rot_radius an int >= 0 bins, got {radius!r}, {rot_radius!r}")
    b, r, h, w = q.shape
    valid = (actions >= 0).all(-1)  # [B, M]
    row, col, rot = actions.clamp_min(0).unbind(-1)
    d_row = torch.arange(h, device=q.device)[None, None, :] - row[..., None]  # [B, M, H]
    d_col = torch.arange(w, device=q.device)[None, None, :] - col[..., None]  # [B, M, W]
    near_px = d_row[..., :, None] ** 2 + d_col[..., None, :] ** 2 <= radius**2  # [B, M, H, W]
    near_rot = circular_bin_distance(torch.arange(r, device=q.device), rot[..., None], r) <= rot_radius  # [B, M, R]
    near = (near_rot[..., :, None, None] & near_px[..., None, :, :] & valid[..., None, None, None]).any(1)
    return q.masked_fill(near, -math.inf)


def near_actions(actions: Tensor, others: Tensor, num_rotations: int, *, radius: float = 4.0,
                 rot_radius: int = 1) -> Tensor:
    """``[B, N]`` bool: whether each of ``actions`` ``[B, N, 3]`` lies within ``radius`` pixels and ``rot_radius``
    rotation bins (circular over ``num_rotations``) of one of ``others`` ``[B, M, 3]`` (rows holding a ``-1``
    ignored): the entries :func:`mask_actions` sets to ``-inf``."""
    _check_actions(actions, "actions")
    _check_actions(others, "others")
    if others.shape[0] != actions.shape[0]:
        raise ValueError(f"actions and others must have the same batch size, got {tuple(actions.shape)} and "
                         f"{tuple(others.shape)}")
    valid = (others >= 0).all(-1)  # [B, M]
    d = actions[:, :, None, :2] - others[:, None, :, :2]  # [B, N, M, 2]
    near_px = d.square().sum(-1) <= radius**2
    near_rot = circular_bin_distance(actions[:, :, None, 2], others[:, None, :, 2], num_rotations) <= rot_radius
    return (near_px & near_rot & valid[:, None, :]).any(-1)


def sweep_rotations(candidates: Tensor, num_rotations: int, sweep: int, *, active: Tensor,
                    avoid: Tensor | None = None) -> Tensor:
    """Each candidate at ``sweep`` rotations of its pixel: ``[B, N, 3] -> [B, N·K, 3]`` int64, K = ``sweep``.

    In the rows where ``active`` ``[B]`` bool is set, candidate ``i`` becomes entries ``i·K … i·K + K − 1``: its own
    action, then the same pixel at the rotations ``rot + j·R/K`` (mod R, j = 1 … K − 1; R = ``num_rotations``,
    which K divides), evenly spaced over π. Inactive rows repeat each candidate K times, so a softmax over their
    scores draws every original with the probability it had. A swept action near one of ``avoid`` ``[B, M, 3]``
    (:func:`near_actions`: an action :func:`mask_actions` kept from the proposals) is its candidate again.
    """
    if isinstance(sweep, bool) or not isinstance(sweep, int) or sweep < 1 or num_rotations % sweep:
        raise ValueError(f"sweep must be an int >= 1 dividing num_rotations={num_rotations}, got {sweep!r}")
    _check_actions(candidates, "candidates")
    if active.shape != candidates.shape[:1]:
        raise ValueError(f"candidates must be [B, N, 3] and active [B] with the same B, got "
                         f"{tuple(candidates.shape)} and {tuple(active.shape)}")
    repeated = candidates.repeat_interleave(sweep, dim=1)  # [B, N·K, 3]
    if sweep == 1:
        return repeated
    step = torch.arange(sweep, device=candidates.device).repeat(candidates.shape[1]) * (num_rotations // sweep)
    swept = torch.cat((repeated[..., :2], (repeated[..., 2:] + step[:, None]).remainder(num_rotations)), dim=-1)
    keep = ~active.view(-1, 1, 1).bool()
    if avoid is not None:
        keep = keep | near_actions(swept, avoid, num_rotations)[..., None]
    return torch.where(keep, repeated, swept)


def _check_actions(actions, name: str) -> None:
    if not torch.is_tensor(actions) or actions.ndim != 3 or actions.shape[-1] != 3 or actions.is_floating_point() \
            or actions.dtype == torch.bool:
        what = f"{actions.dtype} {tuple(actions.shape)}" if torch.is_tensor(actions) else type(actions).__name__
        raise ValueError(f"{name} must be [B, N, 3] integer (row, col, rot) actions, got {what}")


def sample_candidates(
    q: Tensor,
    num: int,
    *,
    tau: float = 1.0,
    beta: float = 1.0,
    sigma: float = 2.0,
    sigma_rot: float = 1.0,
    mode: str = "softmax",
    generator: torch.Generator | None = None,
) -> Tensor:
    """Draw ``num`` distinct, spread-out actions per Q map: ``[B, R, H, W] -> [B, N, 3]`` int64 (row, col, rot).

    A working map ``M = q`` (float32 copy) is updated after each draw ``a_k = (r_k, c_k, k_k)``::

        M -= β · exp(−((row − r_k)² + (col − c_k)²) / (2σ²)) · exp(−Δrot(rot, k_k)² / (2σ_rot²))
        M[a_k] = −inf                                  # never drawn twice

    where ``Δrot`` is the circular bin distance (bins 0 and R−1 are neighbours). The draw itself is
    one sample of ``softmax(M/τ)`` over all R·H·W entries (``mode="softmax"``; inverse CDF, two
    uniforms per row and draw) or ``argmax M`` (``mode="argmax"``: the reference planner; first index
    on ties; τ and generator unused). Rows are independent; the loop over the N draws is the only
    Python loop, and the inhibition is built from separable row/col/rot factors.

    Args:
        q: ``[B, R, H, W]`` floating Q map of the current primitive (any R, H, W; any device). No NaN
            or +inf; ``-inf`` marks actions never to propose (each row needs ≥ ``num`` others).
        num: N, number of proposals per row, ``1 ≤ N ≤ R·H·W``.
        tau: softmax temperature (> 0, same units as q).
        beta: inhibition height (≥ 0, units of q); 0 gives N draws without replacement from softmax(q/τ).
        sigma: inhibition width in pixels (≥ 0; 0 = only the drawn pixel).
        sigma_rot: inhibition width in rotation bins (≥ 0; 0 = only the drawn rotation).
        mode: ``"softmax"`` or ``"argmax"``.
        generator: optional ``torch.Generator`` on q's device; the result is deterministic given it.

    Returns:
        ``[B, N, 3]`` int64 on q's device, in draw order; the N actions of a row are distinct.
    """
    _check(q, num, tau, beta, sigma, sigma_rot, mode, generator)
    b, r, h, w = q.shape
    device, hw = q.device, h * w
    out = torch.empty(b, num, 3, dtype=torch.long, device=device)
    picked = torch.empty(b, num, dtype=torch.float32, device=device)  # M at each draw, checked once (no syncs)
    with torch.no_grad():
        m = q.detach().to(torch.float32, copy=True).reshape(b, r * hw)
        m4 = m.view(b, r, h, w)
        if mode == "softmax":
            probs = torch.empty_like(m)
            rows_b = torch.arange(b, device=device)
        rows_ax = torch.arange(h, device=device, dtype=torch.float32)
        cols_ax = torch.arange(w, device=device, dtype=torch.float32)
        rot_ax = torch.arange(r, device=device)
        for k in range(num):
            if mode == "softmax":
                # exp((M − max M)/τ) ∈ [0, 1]: drawn entries are exactly 0, the max is 1 (no overflow for any τ)
                torch.sub(m, m.amax(1, keepdim=True), out=probs).div_(tau).exp_()
                p3 = probs.view(b, r * h, w)
                u = torch.rand(b, 2, dtype=torch.float64, device=device, generator=generator)
                # two-level inverse CDF (a row of W pixels, then a pixel in it) keeps every cumsum short
                line = _inverse_cdf(p3.sum(-1).to(torch.float64), u[:, 0])
                pixel = _inverse_cdf(p3[rows_b, line].to(torch.float64), u[:, 1])
                idx = line * w + pixel
            else:
                idx = m.argmax(1)
            picked[:, k] = m.gather(1, idx[:, None]).squeeze(1)
            out[:, k] = flat_to_action(idx, h, w)
            row, col, rot = out[:, k].unbind(-1)
            if k == num - 1:
                break
            if beta > 0:
                f_row = _kernel(rows_ax - row[:, None].to(torch.float32), sigma)  # [B, H]
                f_col = _kernel(cols_ax - col[:, None].to(torch.float32), sigma)  # [B, W]
                d_rot = circular_bin_distance(rot_ax, rot[:, None], r).to(torch.float32)  # [B, R]
                f_rot_row = (_kernel(d_rot, sigma_rot)[:, :, None] * f_row[:, None, :]).mul_(beta)  # [B, R, H]
                m4.addcmul_(f_rot_row[..., None], f_col[:, None, None, :], value=-1.0)
            m.scatter_(1, idx[:, None], -math.inf)
    if not bool(torch.isfinite(picked).all()):
        raise ValueError("a draw found no finite entry left in the working map: q or beta*num overflows float32")
    return out


def _inverse_cdf(weights: Tensor, u: Tensor) -> Tensor:
    """Per row, index ``i`` with probability ``weights[:, i] / weights.sum(1)``.

    ``weights`` ``[B, n]`` float64 ≥ 0 (each row with a positive entry), ``u`` ``[B]`` uniforms in [0, 1).

    ``cum[i−1] ≤ x < cum[i]`` with ``x = u·total`` kept below ``total``, so an index of zero weight is
    never returned.
    """
    cum = weights.cumsum(1)
    total = cum[:, -1:]
    x = torch.minimum(u[:, None] * total, torch.nextafter(total, torch.zeros_like(total)))
    return torch.searchsorted(cum, x, right=True).squeeze(1).clamp_(0, weights.shape[1] - 1)


def _kernel(d: Tensor, sigma: float) -> Tensor:
    """Unnormalised Gaussian ``exp(−d²/(2σ²))`` of float offsets; σ = 0 is the Kronecker delta."""
    if sigma == 0:
        return (d == 0).to(torch.float32)
    return torch.exp(d.square() * (-0.5 / sigma**2))


def _real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)


def _check(q, num, tau, beta, sigma, sigma_rot, mode, generator) -> None:
    if not torch.is_tensor(q) or q.dim() != 4:
        shape = tuple(q.shape) if torch.is_tensor(q) else type(q).__name__
        raise ValueError(f"q must be a [B, R, H, W] Q-map tensor, got {shape}")
    if not q.is_floating_point():
        raise ValueError(f"q must have a floating-point dtype, got {q.dtype}")
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    if not _real(tau) or tau <= 0:
        raise ValueError(f"tau must be a positive finite temperature, got {tau!r}")
    for name, value in (("beta", beta), ("sigma", sigma), ("sigma_rot", sigma_rot)):
        if not _real(value) or value < 0:
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    size = math.prod(q.shape[1:])
    if not isinstance(num, numbers.Integral) or isinstance(num, bool) or not 1 <= num <= size:
        raise ValueError(f"num must be an int in [1, R*H*W = {size}] for q of shape {tuple(q.shape)}, got {num!r}")
    if generator is not None:
        if not isinstance(generator, torch.Generator):
            raise ValueError(f"generator must be a torch.Generator or None, got {type(generator).__name__}")
        if generator.device.type != q.device.type:
            raise ValueError(f"generator is on {generator.device} but q is on {q.device}")
    if bool(torch.isfinite(q).all()):
        return
    if torch.isnan(q).any():
        raise ValueError("q contains NaN")
    if torch.isposinf(q).any():
        raise ValueError("q contains +inf; only -inf (never propose) is allowed")
    drawable = int((q.reshape(q.shape[0], -1) > -math.inf).sum(1).min())
    if drawable < num:
        raise ValueError(f"num={num} but a row of q has only {drawable} entries above -inf")


# ----------------------------------------------------------------------------------------- near objects (RS)
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
    ``(row, col, rot)`` on heightmap's device (the rule: :class:`NearObjectSampler`).

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
    return flat_to_action(idx, h, w)


class NearObjectSampler:
    """:func:`sample_near_objects` with fixed settings, checked once here: ``sampler(heightmap, num)``."""

    def __init__(self, num_rotations: int, height_threshold: float, dilation: int) -> None:
        self.num_rotations, self.dilation = int(num_rotations), int(dilation)
        self.height_threshold = float(height_threshold)
        sample_near_objects(torch.zeros(1, 1, 8, 8), 1, num_rotations=self.num_rotations,
                            height_threshold=self.height_threshold, dilation=self.dilation)  # validates the settings

    def __call__(self, heightmap: Tensor, num: int) -> Tensor:
        return sample_near_objects(heightmap, num, num_rotations=self.num_rotations,
                                   height_threshold=self.height_threshold, dilation=self.dilation)
