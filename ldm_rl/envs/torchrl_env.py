"""TorchRL wrappers: ``make_env`` and ``make_env_from_config``."""

from __future__ import annotations

from typing import Any, Mapping

__all__ = ["make_env", "make_env_from_config", "env_kwargs_from_config", "expert_policy", "unwrap"]


def make_env(env_id: str, **kwargs):
    """A TorchRL env for ``env_id``: ``GymEnv(categorical_action_encoding=True)`` plus a cast of
    ``holding`` from int8 ``MultiBinary(1)`` to ``[1] bool`` (docs/conventions.md).

    The action is ``MultiCategorical([128, 128, R])`` int64 ``[3]``; ``kwargs`` go to the task's
    constructor (``num_objects``, ``max_steps``, ``num_rotations``, ``expert_noise``, ...).
    """
    import torch
    from torchrl.envs import DTypeCastTransform, GymEnv, TransformedEnv

    from ldm_rl.envs import ENV_IDS, register_envs

    if env_id not in ENV_IDS:
        raise ValueError(f"env_id must be one of {sorted(ENV_IDS)}, got {env_id!r}")
    register_envs()
    base = GymEnv(env_id, categorical_action_encoding=True, **kwargs)
    cast = DTypeCastTransform(torch.int8, torch.bool, in_keys=["holding"])
    return TransformedEnv(base, cast)


def env_kwargs_from_config(cfg: Mapping[str, Any]) -> tuple[str, dict]:
    """(env id, constructor kwargs) from a ``cfg.env`` node (see conf/env/*.yaml)."""
    cfg = dict(cfg)
    if "id" not in cfg:
        raise ValueError("cfg.env needs an 'id' (e.g. ldm_rl/BlockStacking-v0)")
    kwargs = {
        "num_objects": cfg.get("num_objects"),
        "max_steps": cfg.get("max_steps"),
        "num_rotations": cfg.get("num_rotations", 8),
    }
    return cfg["id"], {k: v for k, v in kwargs.items() if v is not None}


def make_env_from_config(cfg: Mapping[str, Any], **overrides):
    """``make_env`` from a Hydra ``cfg.env`` node; ``overrides`` win over the config."""
    env_id, kwargs = env_kwargs_from_config(cfg)
    kwargs.update(overrides)
    return make_env(env_id, **kwargs)


def unwrap(env):
    """The ``PickPlaceEnv`` inside a TorchRL env built by ``make_env`` (unbatched envs only)."""
    base = getattr(env, "base_env", env)
    inner = getattr(base, "_env", None)
    if inner is None:
        raise ValueError(f"env must be a single (unbatched) env from make_env, got {type(env).__name__}")
    return inner.unwrapped


def expert_policy(env, noise=None):
    """A TorchRL policy (``td -> td`` writing ``"action"`` ``[3] int64``) that plays the scripted
    expert of ``env`` (a single env from ``make_env``), e.g. ``env.rollout(10, expert_policy(env))``."""
    import torch

    task = unwrap(env)

    def policy(td):
        td.set("action", torch.as_tensor(task.expert_action(noise), dtype=torch.int64))
        return td

    return policy
