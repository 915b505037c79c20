"""Held-out accuracy of a dynamics model: height L1 and action success rate (SR).

Definitions (all per transition; ``s`` = current state, ``s'`` = true next state, ``ŝ'`` = prediction):

* **L1** (metres; logs also show mm): mean over pixels of ``|ŝ'.heightmap − s'.heightmap|``, over the
  whole 128×128 image (``l1``) and over B_a only (``l1_region``: the rotated ``region_size``² square of
  the action, 64 px by default for every model, so LDM(64), LDM(128) and Naive are compared alike).
* **SR**: the fraction of transitions whose prediction counts as correct:
  - a **pick** (``holding`` False) is correct when the predicted holding flag equals the true one;
  - a **place** (``holding`` True) is correct when the changed-pixel footprints agree: with depth
    classes ``c(·)`` (``round(clamp(h/max_height,0,1)·(K−1))``), the changed set of a next heightmap is
    ``{p : c(next)[p] ≠ c(s)[p]}`` over the whole image; the place is correct when
    ``IoU(changed_pred, changed_true) ≥ iou_threshold`` (0.75) **and** the mean absolute class
    difference ``|c(ŝ')−c(s')|`` over the intersection of the two changed sets is ``≤
    height_tolerance`` classes (1). Two empty changed sets count as correct (nothing happened, and
    nothing was predicted).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ldm_rl import geometry

__all__ = ["MetricSettings", "action_region_mask", "height_l1", "pick_correct", "place_correct", "transition_metrics", "summarize"]


@dataclass(frozen=True)
class MetricSettings:
    """Tolerances and class settings of the metrics (see the module docstring)."""

    max_height: float
    num_classes: int = 21
    num_rotations: int = 8
    region_size: int = 64
    iou_threshold: float = 0.75
    height_tolerance: float = 1.0


def action_region_mask(action: torch.Tensor, size: int, num_rotations: int, image_size: int = 128) -> torch.Tensor:
    """[N,3] actions -> [N,1,H,W] bool mask of B_a (the pixels ``geometry.paste`` would write)."""
    n = action.shape[0]
    centers, angles = geometry.action_to_pose(action.long(), num_rotations)
    ones = torch.ones(n, 1, size, size, dtype=torch.uint8, device=action.device)
    blank = torch.zeros(n, 1, image_size, image_size, dtype=torch.uint8, device=action.device)
    return geometry.paste(blank, ones, centers, angles, mode="nearest").bool()


def height_l1(pred: torch.Tensor, true: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """[N,1,H,W] metres -> [N] mean absolute error in metres (over ``mask`` pixels when given)."""
    err = (pred.float() - true.float()).abs()
    if mask is None:
        return err.flatten(1).mean(1)
    mask = mask.to(err.dtype)
    return (err * mask).flatten(1).sum(1) / mask.flatten(1).sum(1).clamp_min(1)


def pick_correct(pred_holding: torch.Tensor, true_holding: torch.Tensor) -> torch.Tensor:
    """[N,1] or [N] bools -> [N] bool: the predicted hand state matches the true one."""
    return pred_holding.reshape(-1).bool() == true_holding.reshape(-1).bool()


def place_correct(before: torch.Tensor, pred_next: torch.Tensor, true_next: torch.Tensor, settings: MetricSettings) -> torch.Tensor:
    """[N,1,H,W] heightmaps (metres) -> [N] bool place correctness (footprint IoU and class agreement)."""
    to_classes = lambda h: geometry.heights_to_classes(h, settings.max_height, settings.num_classes).long()  # noqa: E731
    c0, cp, ct = to_classes(before), to_classes(pred_next), to_classes(true_next)
    changed_pred, changed_true = (cp != c0).flatten(1), (ct != c0).flatten(1)
    inter, union = (changed_pred & changed_true).sum(1), (changed_pred | changed_true).sum(1)
    iou = torch.where(union > 0, inter / union.clamp_min(1), torch.ones_like(inter, dtype=torch.float32))
    diff = ((cp - ct).abs().flatten(1) * (changed_pred & changed_true)).sum(1) / inter.clamp_min(1)
    return (iou >= settings.iou_threshold) & (diff <= settings.height_tolerance)


def transition_metrics(pred_heightmap, pred_holding, batch, settings: MetricSettings) -> dict[str, torch.Tensor]:
    """Per-transition metrics of a prediction for a TensorDict ``batch`` of real transitions.

    Returns [N] tensors: ``l1`` and ``l1_region`` (metres), ``correct`` (bool, pick or place rule) and
    ``is_pick`` (bool).
    """
    heightmap, action = batch["heightmap"], batch["action"]
    true_next, true_holding = batch["next", "heightmap"], batch["next", "holding"]
    region = action_region_mask(action, settings.region_size, settings.num_rotations, heightmap.shape[-1])
    is_pick = ~batch["holding"].reshape(-1).bool()
    correct = torch.where(
        is_pick,
        pick_correct(pred_holding, true_holding),
        place_correct(heightmap, pred_heightmap, true_next, settings),
    )
    return {
        "l1": height_l1(pred_heightmap, true_next),
        "l1_region": height_l1(pred_heightmap, true_next, region),
        "correct": correct,
        "is_pick": is_pick,
    }


def summarize(per_transition: dict[str, torch.Tensor]) -> dict[str, float]:
    """Aggregate :func:`transition_metrics` outputs: L1 in m and mm, SR overall / picks / places (NaN if none)."""
    correct, is_pick = per_transition["correct"].float(), per_transition["is_pick"]
    nan = float("nan")
    out = {
        "l1_m": per_transition["l1"].mean().item(),
        "l1_region_m": per_transition["l1_region"].mean().item(),
        "sr": correct.mean().item(),
        "sr_pick": correct[is_pick].mean().item() if is_pick.any() else nan,
        "sr_place": correct[~is_pick].mean().item() if (~is_pick).any() else nan,
    }
    out["l1_mm"], out["l1_region_mm"] = 1000 * out["l1_m"], 1000 * out["l1_region_m"]
    return out
