"""Run-time plumbing shared by every recipe: seeding, devices, threads, atomic files, loggers.

Nothing here imports torchrl or pybullet at module import time, so config-only code stays fast.
"""

from __future__ import annotations

import contextlib
import os
import random
import tempfile
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np
import torch

__all__ = [
    "seed_everything",
    "resolve_device",
    "set_threads",
    "atomic_path",
    "atomic_torch_save",
    "atomic_write_text",
    "hydra_output_dir",
    "make_logger",
    "eval_mode",
]


def seed_everything(seed: int) -> torch.Generator:
    """Seed python, numpy and torch (CPU and CUDA); return a torch.Generator seeded the same way."""
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}")
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)


def resolve_device(spec: str | torch.device | None = "auto") -> torch.device:
    """``"auto"``/None -> cuda if available else cpu; anything else is parsed by ``torch.device``.

    Raises ValueError for an unknown device string or a CUDA device on a machine without CUDA.
    """
    if spec is None or spec == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(spec)
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"device must be 'auto', 'cpu', 'cuda' or 'cuda:N', got {spec!r}") from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={spec!r} asked for CUDA, but torch.cuda.is_available() is False")
    return device


def set_threads(threads: int | None) -> None:
    """Set torch's intra-op thread count; None leaves torch's default."""
    if threads is None:
        return
    if not isinstance(threads, int) or isinstance(threads, bool) or threads < 1:
        raise ValueError(f"threads must be a positive int or null, got {threads!r}")
    torch.set_num_threads(threads)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; move it onto ``path`` only if the block succeeds.

    Works for files and directories. A failure (or interrupt) leaves ``path`` as it was and removes
    the temporary, so readers never see a half-written checkpoint or dataset.
    """
    import shutil

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)) / path.name
    try:
        yield tmp
        if path.is_dir() and not path.is_symlink():
            old = path.with_name(f".{path.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    finally:
        shutil.rmtree(tmp.parent, ignore_errors=True)


def atomic_torch_save(obj: Any, path: str | os.PathLike) -> Path:
    """``torch.save`` that never leaves a truncated file at ``path``."""
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def hydra_output_dir(default: str | os.PathLike = ".") -> Path:
    """The current Hydra run's output directory, or ``default`` outside a Hydra app."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return Path(HydraConfig.get().runtime.output_dir)
    except (ImportError, ValueError):
        return Path(default)


def make_logger(cfg: Mapping[str, Any] | None, log_dir: str | os.PathLike):
    """Build the TorchRL logger named by ``cfg.backend`` (csv | tensorboard | none) under ``log_dir``.

    Returns a ``torchrl.record.loggers.Logger`` or None for ``backend: none``. The CSV logger keeps
    videos as ``.pt`` tensors (TorchRL's mp4 path needs torchcodec, which is not a dependency).
    """
    backend = (cfg or {}).get("backend", "csv")
    exp_name = (cfg or {}).get("exp_name") or "ldm_rl"
    if backend in (None, "none"):
        return None
    if backend == "csv":
        from torchrl.record.loggers import CSVLogger

        return CSVLogger(exp_name=exp_name, log_dir=str(log_dir), video_format="pt")
    if backend == "tensorboard":
        try:
            from torchrl.record.loggers import TensorboardLogger

            return TensorboardLogger(exp_name=exp_name, log_dir=str(log_dir))
        except ImportError as err:  # pragma: no cover - depends on the optional extra
            raise ImportError("logger=tensorboard needs: pip install 'ldm_rl[tensorboard]'") from err
    raise ValueError(f"logger.backend must be one of csv, tensorboard, none; got {backend!r}")


@contextlib.contextmanager
def eval_mode(*modules: torch.nn.Module) -> Iterator[None]:
    """Run the block with every module (and submodule) in eval mode and without gradients, then give
    each submodule back the train/eval flag it had (BatchNorm statistics stay untouched).

    Used by every prediction made for acting, planning, targets, foresight and imagination.
    """
    flags = [(m, m.training) for module in modules for m in module.modules()]
    try:
        for module in modules:
            module.eval()
        with torch.no_grad():
            yield
    finally:
        for m, training in flags:
            m.training = training
