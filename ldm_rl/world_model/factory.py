"""Dynamics models from configs: ``make_dynamics_model("ldm64", task="block_stacking")`` (by name, for
users) and ``build_dynamics_model(cfg.model, max_height)`` (from a composed config node, for recipes): the
one place that turns a model config into a model."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Sequence

from ldm_rl.geometry import NUM_ROTATIONS
from ldm_rl.models.blocks import count_parameters
from ldm_rl.world_model.core import DynamicsModel, HandStateRule

__all__ = ["PRESET_WIDTHS", "CONF_DIR", "make_dynamics_model", "build_dynamics_model", "count_parameters",
           "load_dynamics_checkpoint"]

# the repository's Hydra configs (conf/ beside the package)
CONF_DIR = Path(__file__).resolve().parents[2] / "conf"

# channel multiplier of each preset; ``lite`` reads ``cfg.width`` (default below)
PRESET_WIDTHS = {"paper": 1.0, "lite": 0.25}
MODEL_NAMES = ("ldm", "naive")


def build_dynamics_model(cfg: Mapping[str, Any], max_height: float):
    """Build a :class:`ldm_rl.world_model.DynamicsModel` from a ``conf/model/*.yaml`` node.

    Keys: ``name`` (ldm | naive), ``preset`` (paper | lite), ``width`` (lite multiplier),
    ``crop_size`` (ldm), ``num_depth_classes``, ``num_rotations``, optional ``hand_rule``
    (center_size, before_threshold, after_threshold), ``hand_crop_mode``, ``action_sigma`` (naive), ``height_anchor``
    (ldm; metres or null).
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
        num_rotations=int(cfg.get("num_rotations", NUM_ROTATIONS)),
        hand_rule=rule,
        hand_crop_mode=cfg.get("hand_crop_mode", "bilinear"),
        action_sigma=float(cfg.get("action_sigma", 2.0)),
        height_anchor=None if cfg.get("height_anchor") is None else float(cfg["height_anchor"]),
    )


def make_dynamics_model(
    model: str = "ldm64",
    *,
    task: str = "block_stacking",
    preset: str = "lite",
    overrides: Sequence[str] = (),
    config_dir: str | os.PathLike | None = None,
) -> DynamicsModel:
    """A new (randomly initialised, train-mode) dynamics model for ``task``, configured as the recipes do.

    Composes ``conf/train_dynamics.yaml`` with ``model=<model> env=<task> model.preset=<preset>`` plus
    ``overrides`` (Hydra override strings over the whole config, e.g. ``"model.width=0.125"``), checks it
    like a recipe's command line, and builds ``build_dynamics_model(cfg.model, cfg.env.max_height)``: the
    task's ``max_height`` (metres of the top depth class) and ``num_rotations`` come from
    ``conf/env/<task>.yaml``, the network and ``num_depth_classes`` from ``conf/model/<model>.yaml``.

    Args:
        model: ``"ldm64"`` (LDM on 64 px crops), ``"ldm128"`` or ``"naive"`` (a ``conf/model`` option).
        task: a ``conf/env`` option (``"block_stacking"``, ``"house_building"``, ``"bottle_arrangement"``,
            ``"bin_packing"``) or its gymnasium id (``"ldm_rl/BlockStacking-v0"``).
        preset: ``"lite"`` (channels × ``model.width``, CPU-sized; the configs' default) or ``"paper"``.
        overrides: more Hydra overrides, e.g. ``["model.width=0.125", "model.hand_rule.center_size=24"]``.
        config_dir: a folder with the same layout as the repository's ``conf/`` (default: that one).

    The model exposes ``max_height``, ``num_classes`` and ``num_rotations`` for the networks built beside
    it (``build_q_network(..., max_height=model.max_height, num_classes=model.num_classes)``). Any bad
    name, override or value raises one ``ValueError``.
    """
    cfg = _compose(model, task, preset, overrides, Path(config_dir) if config_dir is not None else CONF_DIR)
    return build_dynamics_model(cfg.model, float(cfg.env.max_height))


def _options(conf: Path, group: str) -> list[str]:
    return sorted(f.stem for f in (conf / group).glob("*.yaml"))


def _env_option(conf: Path, task: str) -> str:
    """A ``conf/env`` option name from an option name or a gymnasium id."""
    from omegaconf import OmegaConf

    options = _options(conf, "env")
    if task in options:
        return task
    ids = {str(OmegaConf.load(conf / "env" / f"{name}.yaml").get("id")): name for name in options}
    if task in ids:
        return ids[task]
    raise ValueError(f"task must be one of {options} or their ids {sorted(ids)}, got {task!r}")


def _compose(model: str, task: str, preset: str, overrides: Sequence[str], conf: Path):
    """The composed, checked ``conf/train_dynamics.yaml`` (no ``hydra`` node) for :func:`make_dynamics_model`."""
    if not (conf / "train_dynamics.yaml").is_file():
        raise ValueError(f"no Hydra configs at {conf} (train_dynamics.yaml missing): make_dynamics_model reads the repository's "
                         "conf/; install ldm_rl from its repository (pip install -e .) or pass config_dir=")
    models = _options(conf, "model")
    if model not in models:
        raise ValueError(f"model must be one of {models}, got {model!r}")
    if preset not in PRESET_WIDTHS:
        raise ValueError(f"preset must be one of {tuple(PRESET_WIDTHS)}, got {preset!r}")
    if isinstance(overrides, str) or not all(isinstance(o, str) for o in overrides):
        raise ValueError(f"overrides must be a list of Hydra override strings like 'model.width=0.125', got {overrides!r}")
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from ldm_rl.config_schema import ConfigError, TrainDynamicsConfig, _omegaconf_line, validate_config  # registers the configs' schema

    composed = [f"model={model}", f"env={_env_option(conf, task)}", f"model.preset={preset}", *overrides]
    # called inside a Hydra app: put its state back afterwards (initialize_config_dir replaces the singleton)
    outer = GlobalHydra.instance().hydra if GlobalHydra.instance().is_initialized() else None
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(conf.resolve()), version_base="1.3", job_name="make_dynamics_model"):
            cfg = compose(config_name="train_dynamics", overrides=composed)
        validate_config(cfg, TrainDynamicsConfig)
    except ConfigError as err:
        raise ValueError(f"make_dynamics_model: {err}") from None
    except Exception as err:  # Hydra / OmegaConf composition errors, in one line naming the override
        raise ValueError(f"make_dynamics_model: {_omegaconf_line(err)}") from None
    finally:
        GlobalHydra.instance().clear()
        if outer is not None:
            GlobalHydra.instance().initialize(outer)
    return cfg


def load_dynamics_checkpoint(path, expect: Mapping[str, Any] | None = None, *, map_location="cpu"):
    """Rebuild the dynamics model saved by ``recipes/train_dynamics.py``; returns ``(model, checkpoint)``.

    ``path``: a ``checkpoint.pt`` or the run folder holding it. The file is verified by
    :func:`ldm_rl.run.checkpoint.load_checkpoint` (checksum, format version, ``kind == "dynamics"`` and every
    ``expect`` key, e.g. ``{"preset": "lite", "task": "ldm_rl/BlockStacking-v0"}``); the model is built
    from the config stored in it (``config.model``, ``config.env.max_height``), given its weights, moved
    to ``map_location`` and returned in eval mode. Every problem is one ``CheckpointError``.
    """
    from ldm_rl.run.checkpoint import CheckpointError, load_checkpoint

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
