"""Supervised training of a dynamics model on demo transitions (used by ``recipes/train_dynamics.py``).

Pieces: :func:`split_transitions` (held-out split by episode), :func:`evaluate` (L1 / SR of
``ldm_rl.metrics`` over a dataset), :func:`prediction_grid` (predicts, then draws with ``ldm_rl.plots``),
and :func:`train_dynamics` (the loop: Adam, step decay, periodic eval,
scalars to a TorchRL logger, a progress bar, periodic checkpoints in the ``ldm_rl.checkpoint`` format, exact
resume, a clean stop on SIGINT/SIGTERM).
"""

from __future__ import annotations

import contextlib

import logging
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from tensordict import TensorDictBase

from ldm_rl.checkpoint import Checkpoint, RunStopped, StopSignals, capture_rng_state, restore_rng_state, save_checkpoint
from ldm_rl.metrics import MetricSettings, floor_transition_metrics, summarize, summarize_floors, transition_metrics
from ldm_rl.plots import PlotDependencyError, plot_success_rate
from ldm_rl.progress import progress_bar
from ldm_rl.runtime import make_adam
from ldm_rl.world_model.core import DynamicsModel

__all__ = ["PrimitiveBalancedSampler", "REQUIRED_KEYS", "split_transitions", "evaluate", "prediction_grid",
           "train_dynamics", "model_label", "data_fingerprint"]

REQUIRED_KEYS = ("heightmap", "in_hand", "holding", "action", ("next", "heightmap"), ("next", "holding"))
log = logging.getLogger(__name__)


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

    Returns (see ``ldm_rl.metrics``): ``l1_m`` / ``l1_mm`` / ``l1_region_m`` / ``l1_region_mm`` (per-pixel
    means), ``sr`` / ``sr_pick`` / ``sr_place`` (fractions), ``sr_place_iouXX`` per
    ``settings.report_iou_thresholds``, and the floors of the same transitions: ``floor_sr`` /
    ``floor_sr_pick`` / ``floor_sr_place``, ``floor_pick_majority_success``, ``floor_l1_*``, ``n_pick`` / ``n_place``.
    """
    was_training = model.training
    model.eval()
    parts: dict[str, list[torch.Tensor]] = {}
    floor_parts: dict[str, list[torch.Tensor]] = {}
    for start in range(0, data.shape[0], batch_size):
        batch = data[start : start + batch_size]
        pred = model.predict(batch["heightmap"], batch["in_hand"], batch["holding"], batch["action"])
        for key, value in transition_metrics(pred.heightmap, pred.holding, batch, settings).items():
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


def _prefix_of(module: torch.nn.Module, parent: torch.nn.Module) -> str | None:
    """The state_dict prefix of ``module`` inside ``parent`` ("" if it is ``parent``), None if absent."""
    for name, child in parent.named_modules():
        if child is module:
            return f"{name}." if name else ""
    return None


CURVE_NAME = "curve.csv"
CURVE_FIELDS = ("iteration", "loss", "sr", "sr_pick", "sr_place", "sr_place_iou50", "sr_place_iou75", "sr_place_iou90",
                "l1_mm", "l1_region_mm", "floor_sr", "floor_sr_pick", "floor_sr_place", "elapsed_s")


def write_curve(rows: list[dict], path: Path) -> None:
    """``curve.csv``: one line per evaluation (:data:`CURVE_FIELDS`; SR as fractions, L1 in mm), rewritten atomically."""
    import csv

    from ldm_rl.runtime import atomic_path

    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CURVE_FIELDS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows({key: row.get(key, "") for key in CURVE_FIELDS} for row in rows)


def train_dynamics(
    model: DynamicsModel,
    loss_module,
    train: TensorDictBase,
    val: TensorDictBase,
    *,
    out_dir: str | Path,
    settings: MetricSettings,
    iterations: int,
    batch_size: int = 32,
    lr: float = 1e-3,
    lr_decay: float = 0.95,
    lr_decay_every: int = 2000,
    weight_decay: float = 0.0,
    eval_every: int = 100,
    eval_batch_size: int = 64,
    grid_samples: int = 6,
    logger=None,
    seed: int = 0,
    autocast: str | None = None,
    checkpoint_every: int = 0,
    checkpoint_meta: Mapping[str, Any] | None = None,
    resume: Checkpoint | Mapping[str, Any] | None = None,
    stop: StopSignals | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Train ``loss_module`` (an ``LDMLoss`` around ``model``) and write the run's artefacts to ``out_dir``.

    Minibatches are drawn with replacement by :class:`PrimitiveBalancedSampler` (half picks, half places).

    Every evaluation logs its row (``loss``, ``lr``, ``l1_mm``, ``sr``..., ``elapsed_s``; every number of
    :func:`evaluate`) as ``dynamics/<key>`` at step = iteration, plus ``dynamics/iterations_per_s``, to
    ``logger`` (a TorchRL logger, e.g. from ``ldm_rl.runtime.make_logger``; None: not logged) and one
    line to the ``logging`` module. ``progress``: a bar with ETA (plain lines off a terminal,
    ``ldm_rl.progress``). Artefacts: ``checkpoint.pt`` (see below),
    ``sr_vs_iteration.png`` and ``predictions.png`` (``ldm_rl.plots``; skipped with one line without
    matplotlib). Returns the final metrics.
    ``autocast="bf16"`` runs the loss forward under bf16 autocast (≈1.5× faster for the paper preset on
    an AVX-512-bf16 CPU, see benchmarks/bench_ldm.py).

    Checkpoints (``ldm_rl.checkpoint`` format, ``out_dir/checkpoint.pt``) are written every
    ``checkpoint_every`` iterations (0: never in between), at the end, and when ``stop`` (a
    :class:`~ldm_rl.checkpoint.StopSignals`) has caught a signal — then :class:`RunStopped` is raised.
    Their state holds the model, the loss' own buffers (class counts), the optimizer, the LR schedule,
    every RNG including the sampler's, the iteration, the metrics rows so far and the losses since the
    last evaluation; their meta is ``checkpoint_meta`` (``kind``, ``preset``, ``task``, ``config``...)
    plus ``iteration`` / ``iterations`` / ``complete``. ``resume`` (such a checkpoint) continues from
    it: with the same data, seed, threads and device, the final weights and metrics equal an
    uninterrupted run's bit for bit (the ``elapsed_s`` column is wall-clock time and does not).
    """
    if autocast not in (None, "bf16"):
        raise ValueError(f"autocast must be null or 'bf16', got {autocast!r}")
    if iterations < 1 or batch_size < 1 or eval_every < 1:
        raise ValueError(f"iterations, batch_size and eval_every must be >= 1, got {iterations}, {batch_size}, {eval_every}")
    if checkpoint_every < 0:
        raise ValueError(f"checkpoint_every must be >= 0, got {checkpoint_every}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    checkpoint_path = out_dir / "checkpoint.pt"
    optimizer = make_adam(loss_module.parameters(), lr=lr, weight_decay=weight_decay)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=lr_decay_every, gamma=lr_decay)
    sampler = PrimitiveBalancedSampler(train["holding"], batch_size, seed)
    prefix = _prefix_of(model, loss_module)
    rows: list[dict] = []
    running: list[float] = []
    done, elapsed_before = 0, 0.0

    def own_loss_state() -> dict:
        """The loss' own buffers (class counts), without the model's parameters."""
        state = loss_module.state_dict()
        return state if prefix is None else {k: v for k, v in state.items() if not k.startswith(prefix)}

    if resume is not None:
        state = resume.state if isinstance(resume, Checkpoint) else resume
        done = int(state["iteration"])
        if not 0 <= done <= iterations:
            raise ValueError(f"resume: the checkpoint is at iteration {done}, outside [0, iterations={iterations}]")
        model.load_state_dict(state["model"])
        if prefix:
            loss_module.load_state_dict({**{prefix + k: v for k, v in model.state_dict().items()}, **state["loss"]})
        elif prefix is None:
            loss_module.load_state_dict(state["loss"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        rows, running = [dict(r) for r in state["rows"]], [float(x) for x in state["running"]]
        elapsed_before = float(state["elapsed_s"])
        restore_rng_state(state["rng"], {"sampler": sampler.generator})

    start = time.perf_counter()

    def save(iteration: int) -> Path:
        state = {
            "model": model.state_dict(), "loss": own_loss_state(), "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(), "rng": capture_rng_state({"sampler": sampler.generator}),
            "iteration": iteration, "rows": rows, "running": running,
            "elapsed_s": elapsed_before + time.perf_counter() - start,
        }
        meta = {"kind": "dynamics", **dict(checkpoint_meta or {}), "iteration": iteration, "iterations": iterations,
                "complete": iteration == iterations, "metrics": rows[-1] if rows else None}
        with stop.saving() if stop is not None else contextlib.nullcontext():
            return save_checkpoint(checkpoint_path, state, meta=meta)

    loss_module.train()
    bar = progress_bar(total=iterations, initial=done, desc="train dynamics", unit="it", enabled=progress)
    for iteration in range(done + 1, iterations + 1):
        batch = train[sampler.sample()]
        with torch.autocast(batch.device.type if batch.device else "cpu", dtype=torch.bfloat16, enabled=autocast == "bf16"):
            loss = loss_module(batch)["loss_dynamics"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        running.append(loss.item())
        bar.update(1)
        if iteration % eval_every == 0 or iteration == iterations:
            metrics = evaluate(model, val, settings, eval_batch_size)
            row = {"iteration": iteration, "loss": float(np.mean(running)), "lr": scheduler.get_last_lr()[0],
                   **metrics, "elapsed_s": elapsed_before + time.perf_counter() - start}
            running = []
            rows.append(row)
            write_curve(rows, out_dir / CURVE_NAME)
            if logger is not None:
                scalars = {f"dynamics/{k}": v for k, v in row.items() if k != "iteration" and isinstance(v, (int, float))}
                scalars["dynamics/iterations_per_s"] = (iteration - done) / max(time.perf_counter() - start, 1e-9)
                logger.log_metrics(scalars, step=iteration)
            bar.set_postfix(loss=f"{row['loss']:.4f}", SR=f"{100 * row['sr']:.1f}%", refresh=False)
            log.info(
                f"[{iteration:>6}/{iterations}] loss {row['loss']:.4f}  L1 {row['l1_mm']:.2f} mm "
                f"(B_a {row['l1_region_mm']:.2f} mm)  SR {100 * row['sr']:.1f}% "
                f"(pick {100 * row['sr_pick']:.1f}%, place {100 * row['sr_place']:.1f}%)  {row['elapsed_s']:.0f}s"
            )
        saved = False
        if iteration == iterations or (checkpoint_every and iteration % checkpoint_every == 0):
            save(iteration)
            saved = True
        if stop is not None and stop.requested and iteration < iterations:
            if not saved:
                save(iteration)
            bar.close()
            raise RunStopped(stop.signal_name or "SIGTERM", iteration, iterations, checkpoint_path)
    bar.close()
    final = rows[-1]
    try:
        plot_success_rate(rows, out_dir / "sr_vs_iteration.png")
        prediction_grid(model, val, out_dir / "predictions.png", grid_samples, settings)
    except PlotDependencyError as err:
        log.warning(f"{err}: skipping sr_vs_iteration.png and predictions.png")
    return final
