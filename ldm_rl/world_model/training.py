"""Supervised training of a dynamics model on demo transitions: the pieces ``recipes/train_dynamics.py``
holds its loop over (the loop itself is in the recipe, in view).

:class:`PrimitiveBalancedSampler` (half picks, half places), :func:`split_transitions` (held-out split by
episode), :func:`dynamics_update` (one gradient step of an ``LDMLoss``: the recipe's, the LDM agent's
model-only pretraining and ``benchmarks/bench_ldm.py`` share it), :func:`evaluate` (L1 / SR of
``ldm_rl.world_model.metrics`` over a dataset), :func:`prediction_grid` (predicts, then draws with ``ldm_rl.plots``),
:func:`write_curve`, and the loss' own state beside the model's for checkpoints (:func:`loss_own_state`,
:func:`load_loss_state`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import torch
from tensordict import TensorDictBase

from ldm_rl.world_model.metrics import (MetricSettings, floor_transition_metrics, summarize, summarize_floors,
                                        transition_metrics)
from ldm_rl.world_model.core import DynamicsModel

__all__ = ["PrimitiveBalancedSampler", "REQUIRED_KEYS", "split_transitions", "dynamics_update", "evaluate",
           "prediction_grid", "write_curve", "loss_own_state", "load_loss_state", "model_label", "data_fingerprint",
           "CURVE_NAME", "CURVE_FIELDS"]

REQUIRED_KEYS = ("heightmap", "in_hand", "holding", "action", ("next", "heightmap"), ("next", "holding"))


def model_label(model_cfg: Mapping[str, Any]) -> str:
    """Table-1 row name of a model config: ``LDM(64)``, ``LDM(128)`` or ``Naive``."""
    return "Naive" if model_cfg.get("name") == "naive" else f"LDM({int(model_cfg.get('crop_size', 64))})"


class PrimitiveBalancedSampler:
    """Minibatch indices with a fixed pick/place split: ``batch_size // 2`` picks, the rest places.

    Both heads then train on every step with constant batch shapes (steady CPU kernels); with only
    one primitive in the data, all indices come from it.
    """

    def __init__(self, holding: torch.Tensor, batch_size: int, seed: int) -> None:
        holding = holding.reshape(-1).bool().cpu()
        self.picks, self.places = (~holding).nonzero().squeeze(1), holding.nonzero().squeeze(1)
        self.batch_size, self.generator = batch_size, torch.Generator().manual_seed(seed)

    def _draw(self, pool: torch.Tensor, n: int) -> torch.Tensor:
        return pool[torch.randint(len(pool), (n,), generator=self.generator)]

    def sample(self) -> torch.Tensor:
        if len(self.picks) == 0 or len(self.places) == 0:
            return self._draw(self.picks if len(self.picks) else self.places, self.batch_size)
        n_pick = self.batch_size // 2
        return torch.cat((self._draw(self.picks, n_pick), self._draw(self.places, self.batch_size - n_pick)))


def data_fingerprint(data: TensorDictBase) -> str:
    """SHA-256 of every tensor of ``data`` (keys, dtypes, shapes, bytes): a resumed run checks that it
    trains on the same transitions as the run it continues."""
    import hashlib

    digest = hashlib.sha256()
    leaves = sorted(((k if isinstance(k, tuple) else (k,)), v) for k, v in data.items(include_nested=True, leaves_only=True)
                    if isinstance(v, torch.Tensor))
    for key, value in leaves:
        value = value.detach().cpu().contiguous()
        digest.update(f"{'/'.join(key)}|{value.dtype}|{tuple(value.shape)}|".encode())
        digest.update(value.view(torch.uint8).numpy().tobytes() if value.numel() else b"")
    return digest.hexdigest()


def split_transitions(data: TensorDictBase, val_fraction: float, seed: int) -> tuple[TensorDictBase, TensorDictBase]:
    """Held-out split: whole episodes (``episode`` key) go to validation, else single transitions.

    Returns (train, val); val holds about ``val_fraction`` of the transitions and at least one.
    """
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}")
    n = data.shape[0]
    if n < 2:
        raise ValueError(f"need at least 2 transitions to split, got {n}")
    g = torch.Generator().manual_seed(seed)
    if "episode" in data.keys():
        episodes = data["episode"].reshape(n)
        ids = episodes.unique()
        ids = ids[torch.randperm(len(ids), generator=g)]
        val_ids = ids[: max(1, round(val_fraction * len(ids)))]
        is_val = torch.isin(episodes, val_ids)
        if is_val.all():
            is_val[torch.nonzero(is_val)[0]] = False
    else:
        is_val = torch.zeros(n, dtype=torch.bool)
        is_val[torch.randperm(n, generator=g)[: max(1, round(val_fraction * n))]] = True
    return data[~is_val], data[is_val]


@torch.inference_mode()
def evaluate(model: DynamicsModel, data: TensorDictBase, settings: MetricSettings, batch_size: int = 64) -> dict[str, float]:
    """Metrics of ``model`` on every transition of ``data`` and, beside them, the floors of ``data``.

    Returns (see ``ldm_rl.world_model.metrics``): ``l1_m`` / ``l1_mm`` / ``l1_region_m`` / ``l1_region_mm`` (per-pixel
    means), ``sr`` / ``sr_pick`` / ``sr_place`` (fractions), ``sr_place_iouXX`` per
    ``settings.report_iou_thresholds``, ``entropy_auroc`` (``_pick`` / ``_place``) and ``entropy_right`` /
    ``entropy_wrong`` (how well the model's pixel entropy flags its wrong predictions), and the floors of the same transitions: ``floor_sr`` /
    ``floor_sr_pick`` / ``floor_sr_place``, ``floor_pick_majority_success``, ``floor_l1_*``, ``n_pick`` / ``n_place``.
    """
    was_training = model.training
    model.eval()
    parts: dict[str, list[torch.Tensor]] = {}
    floor_parts: dict[str, list[torch.Tensor]] = {}
    for start in range(0, data.shape[0], batch_size):
        batch = data[start : start + batch_size]
        pred = model.predict(batch["heightmap"], batch["in_hand"], batch["holding"], batch["action"])
        for key, value in transition_metrics(pred.heightmap, pred.holding, batch, settings, pred.entropy()).items():
            parts.setdefault(key, []).append(value)
        for key, value in floor_transition_metrics(batch, settings).items():
            floor_parts.setdefault(key, []).append(value)
    model.train(was_training)
    metrics = summarize({k: torch.cat(v) for k, v in parts.items()}, settings)
    return {**metrics, **summarize_floors({k: torch.cat(v) for k, v in floor_parts.items()})}


@torch.inference_mode()
def prediction_grid(model: DynamicsModel, data: TensorDictBase, path: str | Path, num_samples: int = 6,
                    settings: MetricSettings | None = None) -> Path:
    """Predict the first ``num_samples`` transitions of ``data`` and draw them with
    :func:`ldm_rl.plots.plot_prediction_grid` (before | predicted next | true next | |error|, rows labelled
    pick/place, action, right/wrong by ``settings``' rule; default settings from the model). Needs matplotlib.
    """
    from ldm_rl.plots import plot_prediction_grid

    batch = data[: min(num_samples, data.shape[0])]
    if settings is None:
        settings = MetricSettings(max_height=model.max_height, num_classes=model.num_classes,
                                  num_rotations=model.num_rotations)
    was_training = model.training
    model.eval()
    pred = model.predict(batch["heightmap"], batch["in_hand"], batch["holding"], batch["action"])
    model.train(was_training)
    scores = transition_metrics(pred.heightmap, pred.holding, batch, settings)
    plot_prediction_grid(batch["heightmap"], pred.heightmap, batch["next", "heightmap"], batch["action"], path,
                         max_height=model.max_height, is_pick=scores["is_pick"], correct=scores["correct"],
                         num_rotations=model.num_rotations)
    return Path(path)


def dynamics_update(loss_module, optimizer: torch.optim.Optimizer, batch: TensorDictBase, *,
                    autocast: str | None = None) -> TensorDictBase:
    """One gradient step of ``loss_module`` (an :class:`~ldm_rl.objectives.LDMLoss`) on ``batch``: the forward
    (under bf16 autocast with ``autocast="bf16"``: ≈ 1.5× faster for the paper preset on an AVX-512-bf16 CPU),
    ``zero_grad``, ``backward``, ``optimizer.step()``. Returns the loss' output (``loss_dynamics``,
    ``pixel_accuracy``); the LR schedule is the caller's."""
    if autocast not in (None, "bf16"):
        raise ValueError(f"autocast must be None or 'bf16', got {autocast!r}")
    device = batch.device.type if batch.device is not None else "cpu"
    with torch.autocast(device, dtype=torch.bfloat16, enabled=autocast == "bf16"):
        out = loss_module(batch)
    optimizer.zero_grad(set_to_none=True)
    out["loss_dynamics"].backward()
    optimizer.step()
    return out


def _prefix_of(module: torch.nn.Module, parent: torch.nn.Module) -> str | None:
    """The state_dict prefix of ``module`` inside ``parent`` ("" if it is ``parent``), None if absent."""
    for name, child in parent.named_modules():
        if child is module:
            return f"{name}." if name else ""
    return None


def loss_own_state(loss_module: torch.nn.Module, model: torch.nn.Module) -> dict:
    """``loss_module``'s state without ``model``'s (its own buffers: the class counts), for a checkpoint that
    stores the model apart."""
    state, prefix = loss_module.state_dict(), _prefix_of(model, loss_module)
    return state if prefix is None else {k: v for k, v in state.items() if not k.startswith(prefix)}


def load_loss_state(loss_module: torch.nn.Module, model: torch.nn.Module, model_state: dict, loss_state: dict) -> None:
    """Load ``model_state`` into ``model`` and :func:`loss_own_state`'s ``loss_state`` into ``loss_module``."""
    model.load_state_dict(model_state)
    prefix = _prefix_of(model, loss_module)
    if prefix:
        loss_module.load_state_dict({**{prefix + k: v for k, v in model.state_dict().items()}, **loss_state})
    elif prefix is None:
        loss_module.load_state_dict(loss_state)


CURVE_NAME = "curve.csv"
CURVE_FIELDS = ("iteration", "loss", "sr", "sr_pick", "sr_place", "sr_place_iou50", "sr_place_iou75", "sr_place_iou90",
                "l1_mm", "l1_region_mm", "floor_sr", "floor_sr_pick", "floor_sr_place", "elapsed_s")


def write_curve(rows: list[dict], path: Path) -> None:
    """``curve.csv``: one line per evaluation (:data:`CURVE_FIELDS`; SR as fractions, L1 in mm), rewritten atomically."""
    import csv

    from ldm_rl.run.outputs import atomic_path

    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CURVE_FIELDS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows({key: row.get(key, "") for key in CURVE_FIELDS} for row in rows)
