"""Diverse action proposals from a Q map: softmax (or argmax) draws with Gaussian inhibition.

The paper's planner proposes N actions per state: each is drawn from ``softmax(Q/τ)`` over every
(rotation, row, column) of the current primitive's Q map, after which a Gaussian of height β around
the drawn action is subtracted from the map, so the next draw is pushed elsewhere. ``mode="argmax"``
is the authors' released code (deterministic argmax, no temperature; its inhibition window is
clamped at the rotation range's ends). Unlike that code, the rotation
axis of the inhibition is circular: bins k·π/R live on a circle mod π (``geometry.circular_bin_distance``).

Pure tensor code: imports only torch and :mod:`ldm_rl.geometry`.
"""

from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

from ldm_rl.geometry import circular_bin_distance

__all__ = ["sample_candidates"]

_MODES = ("softmax", "argmax")


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
            rot, rem = idx.div(hw, rounding_mode="floor"), idx.remainder(hw)
            row, col = rem.div(w, rounding_mode="floor"), rem.remainder(w)
            out[:, k, 0], out[:, k, 1], out[:, k, 2] = row, col, rot
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
