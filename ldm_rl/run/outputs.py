"""A run's outputs: atomic files, the run folder, the resolved config, loggers and their scalars.

Nothing here imports torchrl or pybullet at module import time, so config-only code stays fast.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator, Mapping

import torch

from ldm_rl.extras import MissingExtraError, require_logger_backend  # the pre-flight checks them too

__all__ = [
    "atomic_path",
    "atomic_torch_save",
    "atomic_write_text",
    "hydra_output_dir",
    "make_logger",
    "close_logger",
    "read_scalars",
    "save_resolved_config",
    "require_logger_backend",
    "MissingExtraError",
    "LOGGER_BACKENDS",
]


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


LOGGER_BACKENDS = ("csv", "tensorboard", "wandb", "mlflow", "none")
# backend -> the module it imports (the pip extra of ldm_rl that installs it has the backend's name)
# wandb.init modes: online (needs `wandb login`), offline (no account; `wandb sync` later), disabled
WANDB_MODES = ("online", "offline", "disabled")


def _flat_hparams(config: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested config -> {"env.id": ..., ...} with values TensorBoard and MLflow accept (numbers, bools, str)."""
    flat: dict[str, Any] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(_flat_hparams(value, f"{name}."))
        elif isinstance(value, (bool, int, float, str)):
            flat[name] = value
        else:
            flat[name] = "null" if value is None else str(value)
    return flat


def make_logger(cfg: Mapping[str, Any] | None, log_dir: str | os.PathLike, *, config: Mapping[str, Any] | None = None):
    """The TorchRL logger named by ``cfg.backend``, built with ``torchrl.record.loggers.get_logger``.

    ``cfg`` is a ``conf/logger/*.yaml`` node: ``backend`` (csv | tensorboard | wandb | mlflow | none),
    ``exp_name``, and per backend ``project`` / ``group`` / ``mode`` (wandb) or ``tracking_uri`` (mlflow).
    ``log_dir`` is the run's output folder. ``config`` (the resolved run config, a plain dict) is
    recorded, flattened (``env.id``), as the run's hyperparameters by tensorboard / mlflow and as the
    W&B run's config; a CSV run keeps it in ``config_resolved.yaml`` instead.

    Where each backend writes:
      * csv: ``<log_dir>/<exp_name>/scalars/<name>.csv`` (``step,value`` lines; see :func:`read_scalars`);
        videos as ``.pt`` tensors unless torchcodec is installed (then ``.mp4``, TorchRL's choice);
      * tensorboard: ``<log_dir>/<exp_name>/events.out.tfevents.*``;
      * wandb: ``<log_dir>/wandb/`` (``mode: offline`` needs no account; ``wandb sync`` uploads later);
      * mlflow: the store at ``tracking_uri`` (a folder, default ``mlruns`` in the working directory, or
        a server/database URI), experiment ``exp_name``, one MLflow run per recipe run.

    Returns None for ``backend: none``. Raises ValueError for an unknown backend or wandb mode, and
    :class:`MissingExtraError` if the backend's package is not installed. Close it with :func:`close_logger`.
    """
    cfg = dict(cfg or {})
    backend = cfg.get("backend") or "none"
    if backend not in LOGGER_BACKENDS:
        raise ValueError(f"logger.backend must be one of {', '.join(LOGGER_BACKENDS)}; got {backend!r}")
    if backend == "none":
        return None
    require_logger_backend(backend)
    from torchrl.record.loggers import get_logger

    exp_name = str(cfg.get("exp_name") or "ldm_rl")
    log_dir = Path(log_dir).resolve()
    hparams = _flat_hparams(config) if config is not None else None
    if backend == "csv":
        import importlib.util

        logger = get_logger("csv", str(log_dir), exp_name)
        if importlib.util.find_spec("torchcodec") is None:  # get_logger's CSV logger writes mp4 videos with torchcodec
            logger.video_format = logger.experiment.video_format = "pt"
        return logger
    if backend == "tensorboard":
        logger = get_logger("tensorboard", str(log_dir), exp_name)
    elif backend == "wandb":
        mode = cfg.get("mode") or os.environ.get("WANDB_MODE") or "online"
        if mode not in WANDB_MODES:
            raise ValueError(f"logger.mode must be one of {', '.join(WANDB_MODES)} for wandb; got {mode!r}")
        # flat keys (env.id): TorchRL's WandbLogger puts its package metadata under the top-level "env" key
        kwargs = {"project": cfg.get("project") or "ldm_rl", "group": cfg.get("group"), "mode": mode, "config": hparams}
        return get_logger("wandb", str(log_dir), exp_name, wandb_kwargs={k: v for k, v in kwargs.items() if v is not None})
    else:  # mlflow
        uri = str(cfg.get("tracking_uri") or "mlruns")
        if "://" in uri and not uri.startswith("file:"):  # a tracking server or database: TorchRL's logger as is
            from torchrl.record.loggers import MLFlowLogger

            logger = MLFlowLogger(exp_name, tracking_uri=uri)
        else:  # a folder: get_logger's file store (MLflow >= 3.7 asks for this opt-in to keep writing it)
            os.environ.setdefault("MLFLOW_ALLOW_FILE_STORE", "true")
            folder = Path(uri.removeprefix("file://").removeprefix("file:")).expanduser()
            logger = get_logger("mlflow", str(folder.resolve()), exp_name)
    if hparams:
        logger.log_hparams(hparams)
    return logger


def close_logger(logger) -> None:
    """Flush and close ``logger`` (None is fine): finishes a W&B run, ends an MLflow run, closes TensorBoard
    files. Call it when the run ends, so the next job of an in-process sweep starts a fresh run."""
    if logger is None:
        return
    logger.shutdown()
    if type(logger).__name__ == "MLFlowLogger":  # TorchRL's shutdown leaves the MLflow run active
        import mlflow

        mlflow.end_run()


def read_scalars(folder: str | os.PathLike) -> dict[str, list[tuple[int, float]]]:
    """The scalars a CSV logger wrote: ``{"dynamics/sr": [(step, value), ...], ...}`` sorted by step.

    ``folder`` is a run folder (``<run>/<exp_name>/scalars/`` is found below it) or the ``scalars``
    folder itself. A step written twice (a resumed run redoes the steps between its last checkpoint
    and the kill) keeps its last value. Raises FileNotFoundError without exactly one scalars folder.
    """
    folder = Path(folder)
    found = [folder] if folder.name == "scalars" else sorted(folder.glob("scalars")) + sorted(folder.glob("*/scalars"))
    if len(found) != 1:
        raise FileNotFoundError(f"expected one CSV logger 'scalars' folder in {folder} (logger=csv), found "
                                f"{[str(p) for p in found] or 'none'}")
    scalars: dict[str, list[tuple[int, float]]] = {}
    for path in sorted(found[0].rglob("*.csv")):
        by_step: dict[int, float] = {}
        for line in path.read_text().splitlines():
            if line.strip():
                step, value = line.rsplit(",", 1)
                by_step[int(float(step))] = float(value)
        scalars[path.relative_to(found[0]).with_suffix("").as_posix()] = sorted(by_step.items())
    return scalars


def save_resolved_config(cfg, out_dir: str | os.PathLike) -> Path:
    """Write ``config_resolved.yaml`` (every interpolation resolved) to ``out_dir``; returns its path.

    Hydra's own ``.hydra/config.yaml`` keeps interpolations such as ``${env.demo_procedure}``
    unresolved; this file holds the values the run used.
    """
    from omegaconf import OmegaConf

    return atomic_write_text(Path(out_dir) / "config_resolved.yaml", OmegaConf.to_yaml(cfg, resolve=True))
