"""``build_dynamics_model(cfg.model, max_height)``: the one place that turns a model config into a model."""

from __future__ import annotations

from typing import Any, Mapping

from ldm_rl.models.blocks import count_parameters
from ldm_rl.world_model.core import DynamicsModel, HandStateRule

__all__ = ["PRESET_WIDTHS", "build_dynamics_model", "count_parameters"]

# channel multiplier of each preset; ``lite`` reads ``cfg.width`` (default below)
PRESET_WIDTHS = {"paper": 1.0, "lite": 0.25}
MODEL_NAMES = ("ldm", "naive")


def build_dynamics_model(cfg: Mapping[str, Any], max_height: float):
    """Build a :class:`ldm_rl.world_model.DynamicsModel` from a ``conf/model/*.yaml`` node.

    Keys: ``name`` (ldm | naive), ``preset`` (paper | lite), ``width`` (lite multiplier),
    ``crop_size`` (ldm), ``num_depth_classes``, ``num_rotations``, optional ``hand_rule``
    (center_size, before_threshold, after_threshold), ``hand_crop_mode``, ``action_sigma`` (naive).
    ``max_height``: metres of the top depth class (``cfg.env.max_height``).
    """
    from ldm_rl.models.dynamics_net import TwoHeadDynamicsNet

    name = cfg.get("name", "ldm")
    if name not in MODEL_NAMES:
        raise ValueError(f"model.name must be one of {MODEL_NAMES}, got {name!r}")
    preset = cfg.get("preset", "lite")
    if preset not in PRESET_WIDTHS:
        raise ValueError(f"model.preset must be one of {tuple(PRESET_WIDTHS)}, got {preset!r}")
    width = float(cfg.get("width", PRESET_WIDTHS["lite"])) if preset == "lite" else PRESET_WIDTHS[preset]
    num_classes = int(cfg.get("num_depth_classes", 21))
    net = TwoHeadDynamicsNet(num_classes, width=width, extra_channels=3 if name == "naive" else 0)
    rule = HandStateRule(**dict(cfg.get("hand_rule") or {}))
    return DynamicsModel(
        net,
        frame="global" if name == "naive" else "local",
        crop_size=int(cfg.get("crop_size", 64)),
        max_height=float(max_height),
        num_rotations=int(cfg.get("num_rotations", 8)),
        hand_rule=rule,
        hand_crop_mode=cfg.get("hand_crop_mode", "bilinear"),
        action_sigma=float(cfg.get("action_sigma", 2.0)),
    )


