"""Focal loss over per-pixel depth classes and the reference's class-weight rule."""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["focal_loss", "depth_class_weights"]


def focal_loss(
    logits: torch.Tensor,
    target: torch.Tensor,
    *,
    gamma: float = 2.0,
    weight: torch.Tensor | None = None,
    label_smoothing: float = 0.0,
) -> torch.Tensor:
    """Per-sample focal loss (Lin et al.) over K classes, averaged over pixels.

    ``loss_px = w[t] · Σ_c q_c · (1 − p_c)^γ · (−log p_c)`` with ``p = softmax(logits)``, ``t`` the target
    class, ``q = (1 − ε)·onehot(t) + ε/K`` (label smoothing ε) and ``w`` the class weights (1 if None).
    With γ = 0, ε = 0 and no weights this is exactly the cross-entropy.

    Args:
        logits: [N, K, *S] float, N ≥ 1. target: [N, *S] integer classes in [0, K). weight: [K] or None.
    Returns:
        [N] float32, mean over the pixels of each sample. Bad shapes, dtypes or classes raise ``ValueError``.
    """
    if gamma < 0 or not 0.0 <= label_smoothing < 1.0:
        raise ValueError(f"need gamma >= 0 and label_smoothing in [0, 1), got {gamma}, {label_smoothing}")
    if not torch.is_tensor(logits) or logits.dim() < 2 or not logits.is_floating_point() or logits.shape[0] == 0:
        got = tuple(logits.shape) if torch.is_tensor(logits) else type(logits).__name__
        raise ValueError(f"logits must be a non-empty [N, K, *S] float tensor, got {got}")
    k = logits.shape[1]
    if not torch.is_tensor(target) or target.shape != logits.shape[:1] + logits.shape[2:] or target.is_floating_point():
        got = tuple(target.shape) if torch.is_tensor(target) else type(target).__name__
        raise ValueError(f"target must be [N, *S] = {list(logits.shape[:1] + logits.shape[2:])} integer classes, got {got}")
    if weight is not None and (not torch.is_tensor(weight) or weight.shape != (k,)):
        raise ValueError(f"weight must be a [{k}] tensor (one per class) or None, got {getattr(weight, 'shape', weight)}")
    target = target.long()
    if target.numel() and (target.min() < 0 or target.max() >= k):
        raise ValueError(f"target classes must lie in [0, {k}), got [{int(target.min())}, {int(target.max())}]")
    log_p = F.log_softmax(logits.float(), dim=1)
    log_p_t = log_p.gather(1, target.unsqueeze(1)).squeeze(1)
    if label_smoothing == 0:  # only the target class contributes: modulate [N, *S], not [N, K, *S]
        per_px = -log_p_t if gamma == 0 else -((1 - log_p_t.exp()).clamp_min(0).pow(gamma) * log_p_t)
    else:
        modulation = (1 - log_p.exp()).clamp_min(0).pow(gamma)
        smooth_term = -(modulation * log_p).sum(1) * (label_smoothing / k)
        target_term = -(modulation.gather(1, target.unsqueeze(1)).squeeze(1) * log_p_t) * (1 - label_smoothing)
        per_px = target_term + smooth_term
    if weight is not None:
        per_px = per_px * weight.to(per_px)[target]
    return per_px.flatten(1).mean(1)


def depth_class_weights(counts: torch.Tensor, fraction: float = 0.05) -> torch.Tensor:
    """The reference's class weights from class counts: ``w_c = max(1, ln(fraction·N / n_c))``, 1 where n_c = 0.

    counts: [K] (any numeric dtype) -> [K] float32. Rare classes (the objects) get larger weights.
    """
    counts = counts.double()
    weights = torch.ones_like(counts)
    seen = counts > 0
    weights[seen] = torch.log(fraction * counts.sum() / counts[seen]).clamp_min(1.0)
    return weights.float()
