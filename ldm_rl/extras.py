"""Optional packages and the extras that install them; light (standard library only), so the command-line
pre-flight (``ldm_rl.config_schema``) and the loggers (``ldm_rl.run.outputs``) share one message."""

from __future__ import annotations

__all__ = ["MissingExtraError", "require_logger_backend", "require_equivariant_q"]

_LOGGER_MODULES = {"tensorboard": "tensorboard", "wandb": "wandb", "mlflow": "mlflow"}


class MissingExtraError(ImportError):
    """An optional backend's package is not installed; the one-line message names the extra to install."""


def require_logger_backend(backend: str) -> None:
    """Raise :class:`MissingExtraError` (one line naming the extra) if ``backend``'s package is missing."""
    import importlib.util

    module = _LOGGER_MODULES.get(backend)
    if module is None:
        return
    try:
        found = importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a broken install, or a module set to None in sys.modules
        found = False
    if not found:
        raise MissingExtraError(f"logger={backend} needs the {module!r} package, which is not installed: "
                                f"pip install 'ldm_rl[{backend}]' (from a clone: pip install -e '.[{backend}]')")


def _installed(module: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a broken install, or a module set to None in sys.modules
        return False


def require_equivariant_q() -> None:
    """Raise :class:`MissingExtraError` (one line naming the extra) if e2cnn, which
    ``agent.q_architecture=equivariant`` builds on, is missing."""
    if not _installed("e2cnn"):
        raise MissingExtraError("agent.q_architecture=equivariant needs the 'e2cnn' package, which is not installed: "
                                "pip install 'ldm_rl[equivariant]' (from a clone: pip install -e '.[equivariant]')")
