"""Supervised training of a dynamics model on demo transitions (used by ``recipes/train_dynamics.py``).

Pieces: :func:`split_transitions` (held-out split by episode), :func:`evaluate` (L1 / SR of
``ldm_rl.metrics`` over a dataset), :func:`prediction_grid` (PNG of predictions vs truth),
:func:`plot_success_rate`, and :func:`train_dynamics` (the loop: Adam, step decay, periodic eval,
TorchRL logger + ``metrics.csv``, periodic checkpoints in the ``ldm_rl.checkpoint`` format, exact
resume, a clean stop on SIGINT/SIGTERM).
"""

from __future__ import annotations

import csv
import io
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from tensordict import TensorDictBase

from ldm_rl.checkpoint import Checkpoint, RunStopped, StopSignals, capture_rng_state, restore_rng_state, save_checkpoint
from ldm_rl.metrics import MetricSettings, summarize, transition_metrics
from ldm_rl.runtime import atomic_path, atomic_write_text
from ldm_rl.world_model.core import DynamicsModel

__all__ = ["PrimitiveBalancedSampler", "REQUIRED_KEYS", "split_transitions", "evaluate", "prediction_grid", "plot_success_rate",
           "train_dynamics", "model_label", "data_fingerprint"]

REQUIRED_KEYS = ("heightmap", "in_hand", "holding", "action", ("next", "heightmap"), ("next", "holding"))
CSV_FIELDS = ("iteration", "loss", "lr", "l1_mm", "l1_region_mm", "sr", "sr_pick", "sr_place", "elapsed_s")


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
    """L1 (m, mm) and SR (overall / picks / places) of ``model`` on every transition of ``data``."""
    was_training = model.training
    model.eval()
    parts: dict[str, list[torch.Tensor]] = {}
    for start in range(0, data.shape[0], batch_size):
        batch = data[start : start + batch_size]
        pred = model.predict(batch["heightmap"], batch["in_hand"], batch["holding"], batch["action"])
        for key, value in transition_metrics(pred.heightmap, pred.holding, batch, settings).items():
            parts.setdefault(key, []).append(value)
    model.train(was_training)
    return summarize({k: torch.cat(v) for k, v in parts.items()})


def _colour(heights: torch.Tensor, max_height: float) -> np.ndarray:
    """[H, W] metres -> [H, W, 3] uint8 BGR (viridis, 0..max_height)."""
    import cv2

    scaled = (heights.clamp(0, max_height) / max_height * 255).round().to(torch.uint8).cpu().numpy()
    return cv2.applyColorMap(scaled, cv2.COLORMAP_VIRIDIS)


@torch.inference_mode()
def prediction_grid(model: DynamicsModel, data: TensorDictBase, path: str | Path, num_samples: int = 6) -> Path:
    """Write a PNG: one row per transition, columns = before | predicted next | true next | |error|.

    The action pixel is marked with a red cross. Written atomically.
    """
    import cv2

    batch = data[: min(num_samples, data.shape[0])]
    was_training = model.training
    model.eval()
    pred = model.predict(batch["heightmap"], batch["in_hand"], batch["holding"], batch["action"])
    model.train(was_training)
    h = model.max_height
    rows = []
    for i in range(batch.shape[0]):
        error = (pred.heightmap[i, 0] - batch["next", "heightmap"][i, 0]).abs()
        tiles = [_colour(x, h) for x in (batch["heightmap"][i, 0], pred.heightmap[i, 0], batch["next", "heightmap"][i, 0], error)]
        r, c = (int(v) for v in batch["action"][i, :2])
        for tile in tiles:
            cv2.drawMarker(tile, (c, r), (0, 0, 255), cv2.MARKER_CROSS, 9, 1)
        rows.append(np.concatenate([np.pad(t, ((2, 2), (2, 2), (0, 0)), constant_values=255) for t in tiles], axis=1))
    image = np.concatenate(rows, axis=0)
    image = cv2.resize(image, None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    path = Path(path)
    with atomic_path(path) as tmp:
        ok, encoded = cv2.imencode(".png", image)
        if not ok:
            raise RuntimeError("cv2 could not encode the prediction grid")
        tmp.write_bytes(encoded.tobytes())
    return path


def plot_success_rate(rows: list[dict], path: str | Path) -> Path | None:
    """Plot SR (overall, picks, places) vs iteration to ``path``; returns None (with a message) without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: skipping the SR plot")
        return None
    fig, ax = plt.subplots(figsize=(5, 3.5))
    it = [r["iteration"] for r in rows]
    for key, label in (("sr", "all"), ("sr_pick", "picks"), ("sr_place", "places")):
        ax.plot(it, [100 * r[key] for r in rows], marker="o", ms=3, label=label)
    ax.set_xlabel("iteration")
    ax.set_ylabel("held-out action success rate (%)")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=120)
    plt.close(fig)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buffer.getvalue())
    return path


def _write_csv(rows: list[dict], path: Path) -> None:
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=CSV_FIELDS, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(path, text.getvalue())


def _prefix_of(module: torch.nn.Module, parent: torch.nn.Module) -> str | None:
    """The state_dict prefix of ``module`` inside ``parent`` ("" if it is ``parent``), None if absent."""
    for name, child in parent.named_modules():
        if child is module:
            return f"{name}." if name else ""
    return None


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
) -> dict[str, Any]:
    """Train ``loss_module`` (an ``LDMLoss`` around ``model``) and write the run's artefacts to ``out_dir``.

    Minibatches are drawn with replacement by :class:`PrimitiveBalancedSampler` (half picks, half places).

    Artefacts: ``metrics.csv`` (one row per evaluation), ``checkpoint.pt`` (see below),
    ``sr_vs_iteration.png`` (if matplotlib), ``predictions.png``. Returns the final metrics.
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
    optimizer = torch.optim.Adam(loss_module.parameters(), lr=lr, weight_decay=weight_decay)
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
        return save_checkpoint(checkpoint_path, state, meta=meta)

    loss_module.train()
    for iteration in range(done + 1, iterations + 1):
        batch = train[sampler.sample()]
        with torch.autocast(batch.device.type if batch.device else "cpu", dtype=torch.bfloat16, enabled=autocast == "bf16"):
            loss = loss_module(batch)["loss_dynamics"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        running.append(loss.item())
        if iteration % eval_every == 0 or iteration == iterations:
            metrics = evaluate(model, val, settings, eval_batch_size)
            row = {"iteration": iteration, "loss": float(np.mean(running)), "lr": scheduler.get_last_lr()[0],
                   **metrics, "elapsed_s": elapsed_before + time.perf_counter() - start}
            running = []
            rows.append(row)
            _write_csv(rows, out_dir / "metrics.csv")
            if logger is not None:
                for key in ("loss", "lr", "l1_mm", "l1_region_mm", "sr", "sr_pick", "sr_place"):
                    logger.log_scalar(f"dynamics/{key}", row[key], step=iteration)
            print(
                f"[{iteration:>6}/{iterations}] loss {row['loss']:.4f}  L1 {row['l1_mm']:.2f} mm "
                f"(B_a {row['l1_region_mm']:.2f} mm)  SR {100 * row['sr']:.1f}% "
                f"(pick {100 * row['sr_pick']:.1f}%, place {100 * row['sr_place']:.1f}%)  {row['elapsed_s']:.0f}s",
                flush=True,
            )
        saved = False
        if iteration == iterations or (checkpoint_every and iteration % checkpoint_every == 0):
            save(iteration)
            saved = True
        if stop is not None and stop.requested and iteration < iterations:
            if not saved:
                save(iteration)
            raise RunStopped(stop.signal_name or "SIGTERM", iteration, iterations, checkpoint_path)
    if done == iterations:  # resumed a finished run: artefacts again, checkpoint as it was
        _write_csv(rows, out_dir / "metrics.csv")
    final = rows[-1]
    plot_success_rate(rows, out_dir / "sr_vs_iteration.png")
    prediction_grid(model, val, out_dir / "predictions.png", grid_samples)
    return final
