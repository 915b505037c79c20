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
        logits: [N, K, *S] float. target: [N, *S] integer classes in [0, K). weight: [K] or None.
    Returns:
        [N] float32, mean over the pixels of each sample.
    """
    if gamma < 0 or not 0.0 <= label_smoothing < 1.0:
        raise ValueError(f"need gamma >= 0 and label_smoothing in [0, 1), got {gamma}, {label_smoothing}")
    k = logits.shape[1]
    target = target.long()
    log_p = F.log_softmax(logits.float(), dim=1)
    log_p_t = log_p.gather(1, target.unsqueeze(1)).squeeze(1)
    if gamma == 0 and label_smoothing == 0:
        per_px = -log_p_t
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
