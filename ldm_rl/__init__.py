"""ldm_rl: visual foresight with a Local Dynamics Model (Kohler & Platt), TorchRL-native.

The public API at the root (docs/api.md):

* the TensorDict key names of :mod:`ldm_rl.keys` (``HEIGHTMAP``, ``ACTION``, ``PRED_HEIGHTMAP``,
  ``FORESIGHT_KEYS``, ...), and ``keys`` itself;
* ``make_dynamics_model("ldm64", task="block_stacking", preset="lite")``: a dynamics model by name;
* ``make_env(env_id, transforms=[...])``, ``expert_policy(env)``, ``unwrap(env)`` (the gymnasium task
  inside a TorchRL env) and ``EnvClosedError``.

Importing the package is cheap on purpose: torchrl, pybullet and friends are imported by the
submodules that need them (``ldm_rl.envs``, ``ldm_rl.models``...) on first use, never here.
"""

from ldm_rl import keys
from ldm_rl.keys import *  # noqa: F401,F403  (pure names, no imports)

__version__ = "0.1.0"

_LAZY = {
    "make_dynamics_model": "ldm_rl.world_model.factory",
    "make_env": "ldm_rl.envs.torchrl_env",
    "expert_policy": "ldm_rl.envs.torchrl_env",
    "unwrap": "ldm_rl.envs.torchrl_env",
    "EnvClosedError": "ldm_rl.envs.torchrl_env",
}

__all__ = ["__version__", "keys", *keys.__all__, *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
