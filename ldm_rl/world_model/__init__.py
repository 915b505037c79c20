"""The Local Dynamics Model as a world model: the plain core and its TorchRL wrappers.

``DynamicsModel``/``HandStateRule`` import without torchrl; the TorchRL pieces
(``make_dynamics_module``, ``ForesightTransform``, ``LDMImaginedEnv``) are imported on first use.
"""

from ldm_rl.world_model.core import DynamicsModel, DynamicsPrediction, HandStateRule, validate_state_action
from ldm_rl.world_model.factory import PRESET_WIDTHS, build_dynamics_model, count_parameters

_LAZY = {
    "make_dynamics_module": "ldm_rl.world_model.modules",
    "DynamicsPredictor": "ldm_rl.world_model.modules",
    "ForesightTransform": "ldm_rl.world_model.transform",
    "LDMImaginedEnv": "ldm_rl.world_model.imagined_env",
}

__all__ = ["DynamicsModel", "DynamicsPrediction", "HandStateRule", "validate_state_action", "build_dynamics_model",
           "count_parameters", "PRESET_WIDTHS", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
