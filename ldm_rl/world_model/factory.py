"""``build_dynamics_model(cfg.model, max_height)``: the one place that turns a model config into a model."""

from __future__ import annotations

from typing import Any, Mapping

from ldm_rl.models.blocks import count_parameters
from ldm_rl.world_model.core import DynamicsModel, HandStateRule

__all__ = ["PRESET_WIDTHS", "build_dynamics_model", "count_parameters", "load_dynamics_checkpoint"]

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


def load_dynamics_checkpoint(path, expect: Mapping[str, Any] | None = None, *, map_location="cpu"):
    """Rebuild the dynamics model saved by ``recipes/train_dynamics.py``; returns ``(model, checkpoint)``.

    ``path``: a ``checkpoint.pt`` or the run folder holding it. The file is verified by
    :func:`ldm_rl.checkpoint.load_checkpoint` (checksum, format version, ``kind == "dynamics"`` and every
    ``expect`` key, e.g. ``{"preset": "lite", "task": "ldm_rl/BlockStacking-v0"}``); the model is built
    from the config stored in it (``config.model``, ``config.env.max_height``), given its weights, moved
    to ``map_location`` and returned in eval mode. Every problem is one ``CheckpointError``.
    """
    from ldm_rl.checkpoint import CheckpointError, load_checkpoint

    checkpoint = load_checkpoint(path, expect={"kind": "dynamics", **dict(expect or {})}, map_location=map_location)
    cfg = checkpoint.meta.get("config") or {}
    try:
        model_cfg, max_height = cfg["model"], float(cfg["env"]["max_height"])
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"checkpoint {checkpoint.path}: its meta has no config.model / config.env.max_height to "
                              "rebuild the model from") from err
    model = build_dynamics_model(model_cfg, max_height)
    try:
        model.load_state_dict(checkpoint.state["model"])
    except (KeyError, RuntimeError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CheckpointError(f"checkpoint {checkpoint.path}: its weights do not fit the model its config describes ({first})") from err
    return model.to(map_location).eval(), checkpoint
