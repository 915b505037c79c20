"""The Local Dynamics Model as a world model: the plain core and its TorchRL wrappers.

``make_dynamics_model("ldm64", task="block_stacking")`` builds one by name (``build_dynamics_model`` from
a composed config node). ``DynamicsModel``/``HandStateRule`` import without torchrl; the TorchRL pieces
(``make_dynamics_module``, ``ForesightTransform``, ``LDMImaginedEnv``) are imported on first use.
"""

from ldm_rl.world_model.core import DynamicsModel, DynamicsPrediction, HandStateRule, HeldOutcome, pixel_entropy, validate_state_action
from ldm_rl.world_model.factory import PRESET_WIDTHS, build_dynamics_model, count_parameters, make_dynamics_model

_LAZY = {
    "make_dynamics_module": "ldm_rl.world_model.modules",
    "DynamicsPredictor": "ldm_rl.world_model.modules",
    "ForesightTransform": "ldm_rl.world_model.transform",
    "LDMImaginedEnv": "ldm_rl.world_model.imagined_env",
    "ImaginedReward": "ldm_rl.world_model.imagined_env",
}

__all__ = ["DynamicsModel", "DynamicsPrediction", "HandStateRule", "HeldOutcome", "pixel_entropy", "validate_state_action", "make_dynamics_model",
           "build_dynamics_model", "count_parameters", "PRESET_WIDTHS", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
