"""Held-out accuracy of a dynamics model: height L1, action success rate (SR), and the SR's trivial floors.

Definitions (all per transition; ``s`` = current state, ``s'`` = true next state, ``ŝ'`` = prediction):

* **L1** (metres; logs and JSON also show mm): the mean over pixels of ``|ŝ'.heightmap − s'.heightmap|``,
  i.e. an average height error *per pixel*, over the whole 128×128 image (``l1``) and over B_a only
  (``l1_region``: the rotated ``region_size``² square of the action, 64 px by default for every model,
  so LDM(64), LDM(128) and Naive are compared alike). The per-transition values are then averaged.
* **SR**: the fraction of transitions whose prediction counts as correct:
  - a **pick** (``holding`` False) is correct when the predicted holding flag equals the true one;
  - a **place** (``holding`` True) is correct when the changed-pixel footprints agree: with depth
    classes ``c(·)`` (``round(clamp(h/max_height,0,1)·(K−1))``), the changed set of a next heightmap is
    ``{p : c(next)[p] ≠ c(s)[p]}`` over the whole image; the place is correct when
    ``IoU(changed_pred, changed_true) ≥ iou_threshold`` (0.75) **and** the mean absolute class
    difference ``|c(ŝ')−c(s')|`` over the intersection of the two changed sets is ``≤
    height_tolerance`` classes (1). Two empty changed sets count as correct (nothing happened, and
    nothing was predicted). ``sr_place_iou50`` / ``_iou75`` / ``_iou90`` repeat the place rule at the
    IoU thresholds of ``report_iou_thresholds`` (same height tolerance).
* **Floors** (:func:`floor_transition_metrics`, :func:`summarize_floors`): what trivial predictors score
  on the same transitions under the same rules, computed from the data alone:
  - ``floor_sr_pick``, the *majority-class floor* of picks: a model that always predicts the most common
    true pick outcome of these transitions (``holding'`` True = "the pick succeeds"; a tie counts as
    success) scores ``max(q, 1 − q)``, ``q`` = fraction of the picks that succeed;
  - ``floor_sr_place``, the *no-change floor* of places: the model ``ŝ'.heightmap = s.heightmap`` (nothing
    changes inside B_a, hence nowhere) predicts an empty changed set, so it is right exactly on the places
    whose true changed set is empty, at every IoU threshold;
  - ``floor_sr``, the *no-change floor* overall: that same model, with the majority pick outcome as its
    hand state (the place rule does not read the hand state), over all transitions;
  - ``floor_l1_mm`` / ``floor_l1_region_mm``: L1 of the no-change model.
* **Uncertainty** (when the per-transition metrics carry ``entropy``, the model's mean pixel entropy inside
  B_a, :func:`~ldm_rl.world_model.core.pixel_entropy`): ``entropy_auroc`` is the AUROC of entropy as a
  detector of a *wrong* prediction (the SR rule above): the probability that a wrong transition has a higher
  entropy than a right one (ties count one half; 0.5 = no better than chance); ``entropy_auroc_pick`` /
  ``_place`` the same within picks / places; ``entropy_right`` / ``entropy_wrong`` the mean entropies (nats).
  A key is left out where it is undefined (no wrong, or no right, predictions among those transitions).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ldm_rl import geometry

__all__ = ["MetricSettings", "action_region_mask", "auroc", "height_l1", "pick_correct", "place_scores", "place_correct",
           "transition_metrics", "summarize", "floor_transition_metrics", "summarize_floors", "iou_key", "format_report"]


def iou_key(threshold: float) -> str:
    """Metric name of the place SR at an IoU threshold: 0.75 -> ``sr_place_iou75``."""
    return f"sr_place_iou{round(100 * threshold):02d}"


@dataclass(frozen=True)
class MetricSettings:
    """Tolerances and class settings of the metrics (see the module docstring).

    ``iou_threshold`` decides ``sr`` / ``sr_place`` (``dynamics.metrics.iou_threshold`` in the recipe);
    ``report_iou_thresholds`` only adds the ``sr_place_iouXX`` columns.
    """

    max_height: float
    num_classes: int = 21
    num_rotations: int = geometry.NUM_ROTATIONS
    region_size: int = 64
    iou_threshold: float = 0.75
    height_tolerance: float = 1.0
    report_iou_thresholds: tuple[float, ...] = (0.5, 0.75, 0.9)

    def __post_init__(self) -> None:
        for t in (self.iou_threshold, *self.report_iou_thresholds):
            if not 0.0 < float(t) <= 1.0:
                raise ValueError(f"IoU thresholds must be in (0, 1], got {t}")
        keys = [iou_key(t) for t in self.report_iou_thresholds]
        if len(set(keys)) != len(keys):
            raise ValueError(f"report_iou_thresholds must differ by at least 0.01, got {self.report_iou_thresholds}")


def action_region_mask(action: torch.Tensor, size: int, num_rotations: int, image_size: int = 128) -> torch.Tensor:
    """[N,3] actions -> [N,1,H,W] bool mask of B_a (the pixels ``geometry.paste`` would write)."""
    n = action.shape[0]
    centers, angles = geometry.action_to_pose(action.long(), num_rotations)
    ones = torch.ones(n, 1, size, size, dtype=torch.uint8, device=action.device)
    blank = torch.zeros(n, 1, image_size, image_size, dtype=torch.uint8, device=action.device)
    return geometry.paste(blank, ones, centers, angles, mode="nearest").bool()


def height_l1(pred: torch.Tensor, true: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """[N,1,H,W] metres -> [N] mean absolute error per pixel in metres (over ``mask`` pixels when given)."""
    err = (pred.float() - true.float()).abs()
    if mask is None:
        return err.flatten(1).mean(1)
    mask = mask.to(err.dtype)
    return (err * mask).flatten(1).sum(1) / mask.flatten(1).sum(1).clamp_min(1)


def pick_correct(pred_holding: torch.Tensor, true_holding: torch.Tensor) -> torch.Tensor:
    """[N,1] or [N] bools -> [N] bool: the predicted hand state matches the true one."""
    return pred_holding.reshape(-1).bool() == true_holding.reshape(-1).bool()


def place_scores(before: torch.Tensor, pred_next: torch.Tensor, true_next: torch.Tensor,
                 settings: MetricSettings) -> tuple[torch.Tensor, torch.Tensor]:
    """[N,1,H,W] heightmaps (metres) -> ([N] footprint IoU, [N] mean class error on the intersection).

    IoU is 1 when both changed sets are empty; the class error is 0 on an empty intersection.
    """
    to_classes = lambda h: geometry.heights_to_classes(h, settings.max_height, settings.num_classes).long()  # noqa: E731
    c0, cp, ct = to_classes(before), to_classes(pred_next), to_classes(true_next)
    changed_pred, changed_true = (cp != c0).flatten(1), (ct != c0).flatten(1)
    both = changed_pred & changed_true
    inter, union = both.sum(1), (changed_pred | changed_true).sum(1)
    iou = torch.where(union > 0, inter / union.clamp_min(1), torch.ones_like(inter, dtype=torch.float32))
    diff = ((cp - ct).abs().flatten(1) * both).sum(1) / inter.clamp_min(1)
    return iou.float(), diff.float()


def place_correct(before: torch.Tensor, pred_next: torch.Tensor, true_next: torch.Tensor, settings: MetricSettings,
                  iou_threshold: float | None = None) -> torch.Tensor:
    """[N,1,H,W] heightmaps (metres) -> [N] bool place correctness (footprint IoU and class agreement);
    ``iou_threshold`` overrides ``settings.iou_threshold``."""
    iou, diff = place_scores(before, pred_next, true_next, settings)
    threshold = settings.iou_threshold if iou_threshold is None else iou_threshold
    return (iou >= threshold) & (diff <= settings.height_tolerance)


def transition_metrics(pred_heightmap, pred_holding, batch, settings: MetricSettings,
                       entropy: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Per-transition metrics of a prediction for a TensorDict ``batch`` of real transitions.

    Returns [N] tensors: ``l1`` and ``l1_region`` (metres), ``correct`` (bool, pick or place rule),
    ``is_pick`` (bool), ``iou`` and ``class_error`` (the place rule's two scores; computed for every
    transition, read for places only) and, when given, the prediction's ``entropy`` ([N] nats).
    """
    heightmap, action = batch["heightmap"], batch["action"]
    true_next, true_holding = batch["next", "heightmap"], batch["next", "holding"]
    region = action_region_mask(action, settings.region_size, settings.num_rotations, heightmap.shape[-1])
    is_pick = ~batch["holding"].reshape(-1).bool()
    iou, class_error = place_scores(heightmap, pred_heightmap, true_next, settings)
    place_ok = (iou >= settings.iou_threshold) & (class_error <= settings.height_tolerance)
    out = {
        "l1": height_l1(pred_heightmap, true_next),
        "l1_region": height_l1(pred_heightmap, true_next, region),
        "correct": torch.where(is_pick, pick_correct(pred_holding, true_holding), place_ok),
        "is_pick": is_pick,
        "iou": iou,
        "class_error": class_error,
    }
    if entropy is not None:
        out["entropy"] = entropy.reshape(-1).float()
    return out


def auroc(scores: torch.Tensor, labels: torch.Tensor) -> float:
    """Area under the ROC curve of ``scores`` [N] as a detector of ``labels`` [N] bool (True = positive).

    The Mann-Whitney form: the fraction of (positive, negative) pairs ranked right, ties counting one half
    (average ranks). NaN when either class is empty.
    """
    if scores.numel() != labels.numel():
        raise ValueError(f"auroc needs one label per score, got {scores.numel()} scores and {labels.numel()} labels")
    scores, labels = scores.reshape(-1).double(), labels.reshape(-1).bool()
    n_pos, n_neg = int(labels.sum()), int((~labels).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    order = scores.argsort()
    sorted_scores = scores[order]
    ranks = torch.empty_like(scores)
    # tied scores share the mean of their ranks
    _, group, counts = torch.unique_consecutive(sorted_scores, return_inverse=True, return_counts=True)
    first = torch.cumsum(counts, 0) - counts + 1
    ranks[order] = (first + (counts - 1) / 2.0).double()[group]
    return float((ranks[labels].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def _mean_where(values: torch.Tensor, mask: torch.Tensor) -> float:
    """Mean of ``values[mask]`` as a float; NaN when the mask is empty."""
    return values[mask].float().mean().item() if mask.any() else float("nan")


def summarize(per_transition: dict[str, torch.Tensor], settings: MetricSettings | None = None) -> dict[str, float]:
    """Aggregate :func:`transition_metrics` outputs: L1 in m and mm (per pixel), SR overall / picks / places
    (NaN if none) and, with ``settings``, the place SR at each of ``settings.report_iou_thresholds``."""
    correct, is_pick = per_transition["correct"].float(), per_transition["is_pick"]
    out = {
        "l1_m": per_transition["l1"].mean().item(),
        "l1_region_m": per_transition["l1_region"].mean().item(),
        "sr": correct.mean().item(),
        "sr_pick": _mean_where(correct, is_pick),
        "sr_place": _mean_where(correct, ~is_pick),
    }
    out["l1_mm"], out["l1_region_mm"] = 1000 * out["l1_m"], 1000 * out["l1_region_m"]
    if settings is not None and "iou" in per_transition:
        size_ok = per_transition["class_error"] <= settings.height_tolerance
        for t in settings.report_iou_thresholds:
            out[iou_key(t)] = _mean_where((per_transition["iou"] >= t) & size_ok, ~is_pick)
    if "entropy" in per_transition:  # only what is defined: no NaN reaches a checkpoint's JSON meta
        entropy, wrong = per_transition["entropy"], ~per_transition["correct"].bool()
        scores = {"entropy_auroc": auroc(entropy, wrong),
                  "entropy_auroc_pick": auroc(entropy[is_pick], wrong[is_pick]),
                  "entropy_auroc_place": auroc(entropy[~is_pick], wrong[~is_pick]),
                  "entropy_right": _mean_where(entropy, ~wrong), "entropy_wrong": _mean_where(entropy, wrong)}
        out.update({key: value for key, value in scores.items() if value == value})
    return out


def floor_transition_metrics(batch, settings: MetricSettings) -> dict[str, torch.Tensor]:
    """Per-transition facts behind the floors, from a TensorDict ``batch`` of real transitions alone.

    The no-change model ``ŝ' = s`` is scored with the metric's own place rule and L1. Returns [N]
    tensors: ``is_pick`` and ``next_holding`` (bool), ``place_correct`` (bool: the no-change prediction
    passes the place rule, i.e. no pixel changes depth class), ``l1`` and ``l1_region`` (metres).
    """
    heightmap, action, true_next = batch["heightmap"], batch["action"], batch["next", "heightmap"]
    region = action_region_mask(action, settings.region_size, settings.num_rotations, heightmap.shape[-1])
    return {
        "is_pick": ~batch["holding"].reshape(-1).bool(),
        "next_holding": batch["next", "holding"].reshape(-1).bool(),
        "place_correct": place_correct(heightmap, heightmap, true_next, settings),
        "l1": height_l1(heightmap, true_next),
        "l1_region": height_l1(heightmap, true_next, region),
    }


def summarize_floors(per_transition: dict[str, torch.Tensor]) -> dict[str, float]:
    """The floors of the SR (fractions) and L1 (m, mm) from :func:`floor_transition_metrics` outputs.

    ``floor_sr_pick`` (majority pick outcome), ``floor_sr_place`` (no change), ``floor_sr`` (no change,
    majority pick outcome: the floor to read beside ``sr``), ``floor_pick_majority_success`` (1.0 when the
    majority pick outcome is "the pick succeeds"), ``floor_l1_mm`` / ``floor_l1_region_mm`` (no change),
    ``n_pick`` / ``n_place`` (counts). NaN where there are no picks / places.
    """
    is_pick, success = per_transition["is_pick"], per_transition["next_holding"]
    n_pick = int(is_pick.sum())
    success_rate = success[is_pick].float().mean() if n_pick else torch.tensor(1.0)
    majority = bool(success_rate >= 0.5)  # a tie predicts success
    correct = torch.where(is_pick, success == majority, per_transition["place_correct"]).float()
    out = {
        "floor_sr": correct.mean().item(),
        "floor_sr_pick": _mean_where(correct, is_pick),
        "floor_sr_place": _mean_where(correct, ~is_pick),
        "floor_pick_majority_success": float(majority) if n_pick else float("nan"),
        "floor_l1_m": per_transition["l1"].mean().item(),
        "floor_l1_region_m": per_transition["l1_region"].mean().item(),
        "n_pick": n_pick,
        "n_place": int(is_pick.numel() - n_pick),
    }
    out["floor_l1_mm"], out["floor_l1_region_mm"] = 1000 * out["floor_l1_m"], 1000 * out["floor_l1_region_m"]
    return out


def format_report(metrics: dict, iou_threshold: float = 0.75) -> str:
    """Multi-line text of a model's held-out metrics beside the floors (an ``evaluate`` dict).

    ``iou_threshold`` is the one ``sr`` / ``sr_place`` were computed at (for the label only).
    """
    def pct(key: str) -> str:
        value = metrics.get(key, float("nan"))
        return "–" if value != value else f"{100 * value:.1f}%"

    def row(label: str, model: str, floor: str = "", note: str = "") -> str:
        return f"  {label:<32}{model:>15}{floor:>15}  {note}".rstrip()

    outcome = {1.0: 'always "the pick succeeds"', 0.0: 'always "the pick fails"'}.get(
        metrics.get("floor_pick_majority_success"), "majority outcome")
    lines = [f"held-out set: {metrics.get('n_pick', '?')} picks, {metrics.get('n_place', '?')} places",
             row("", "model", "floor"),
             row("SR overall", pct("sr"), pct("floor_sr"), "(no change + majority pick outcome)"),
             row("SR pick", pct("sr_pick"), pct("floor_sr_pick"), f"({outcome})"),
             row(f"SR place (IoU >= {iou_threshold:g})", pct("sr_place"), pct("floor_sr_place"), "(no change, at any IoU)")]
    for key in sorted(k for k in metrics if k.startswith("sr_place_iou")):
        lines.append(row(f"SR place at IoU {int(key[len('sr_place_iou'):]) / 100:g}", pct(key)))
    if "entropy_auroc" in metrics:
        def auc(key: str) -> str:
            return f"{metrics[key]:.3f}" if key in metrics else "–"

        lines.append(row("entropy flags wrong: AUROC", auc("entropy_auroc"), "0.5",
                         f"(picks {auc('entropy_auroc_pick')}, places {auc('entropy_auroc_place')}; chance)"))
    if "l1_mm" in metrics:
        floor_l1 = (f"{metrics['floor_l1_mm']:.2f} | {metrics['floor_l1_region_mm']:.2f}" if "floor_l1_mm" in metrics else "")
        lines.append(row("L1 per pixel, image | B_a (mm)", f"{metrics['l1_mm']:.2f} | {metrics['l1_region_mm']:.2f}", floor_l1,
                         "(no change)" if floor_l1 else ""))
    return "\n".join(lines)
