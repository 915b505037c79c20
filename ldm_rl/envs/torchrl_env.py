"""TorchRL wrappers: ``make_env`` and ``make_env_from_config``."""

from __future__ import annotations

from typing import Any, Iterable, Mapping

__all__ = ["make_env", "make_env_from_config", "env_kwargs_from_config", "expert_policy", "unwrap", "EnvClosedError"]


class EnvClosedError(RuntimeError):
    """Raised when a closed env is reset, stepped or seeded. ``env.close()`` closes it, and so does a TorchRL
    collector given the env itself, when it reaches ``total_frames`` or on ``shutdown()``."""


def _pick_place_env_class():
    """``PickPlaceTorchEnv``, defined on first use so that importing this module does not import torchrl."""
    global PickPlaceTorchEnv
    if "PickPlaceTorchEnv" in globals():
        return PickPlaceTorchEnv
    from torchrl.envs import TransformedEnv

    class PickPlaceTorchEnv(TransformedEnv):
        """The ``TransformedEnv`` that :func:`make_env` returns: a TorchRL ``TransformedEnv`` that refuses,
        with :class:`EnvClosedError`, to reset, step or seed once closed (PyBullet would fail with a bare
        ``TypeError``).

        Being a subclass, wrapping it again (``TransformedEnv(env, t)``) nests quietly instead of
        TorchRL's auto-unwrap warning; ``env.append_transform(t)`` adds to its own chain.
        """

        def _check_open(self) -> None:
            if self.base_env.is_closed:
                env_id = getattr(self.base_env, "env_name", None) or type(self.base_env).__name__
                raise EnvClosedError(
                    f"the {env_id} environment is closed: env.close() or a collector closed it (a collector closes the "
                    "env it was given at total_frames and on shutdown()); make a new one with ldm_rl.make_env, e.g. "
                    "one per collector"
                )

        def _reset(self, tensordict=None, **kwargs):
            self._check_open()
            return super()._reset(tensordict, **kwargs)

        def _step(self, tensordict):
            self._check_open()
            return super()._step(tensordict)

        def set_seed(self, seed=None, static_seed=False):
            self._check_open()
            return super().set_seed(seed, static_seed=static_seed)

    PickPlaceTorchEnv.__qualname__ = "PickPlaceTorchEnv"  # a module-level name (``global``): picklable
    return PickPlaceTorchEnv


def __getattr__(name):
    if name == "PickPlaceTorchEnv":
        return _pick_place_env_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def make_env(env_id: str, *, transforms: Iterable = (), **kwargs):
    """A TorchRL env for ``env_id``: ``GymEnv(categorical_action_encoding=True)`` plus a cast of
    ``holding`` from int8 ``MultiBinary(1)`` to ``[1] bool`` (docs/conventions.md), then ``transforms``.

    The action is ``MultiCategorical([128, 128, R])`` int64 ``[3]``; ``kwargs`` go to the task's
    constructor (``num_objects``, ``max_steps``, ``num_rotations``, ``expert_noise``, ...).
    ``transforms``: TorchRL transforms appended in order to the env's own chain (no nested
    ``TransformedEnv``); later ones are added with ``env.append_transform(t)``. The result is a
    ``TransformedEnv`` (``PickPlaceTorchEnv``) that raises :class:`EnvClosedError` once closed.
    """
    import torch
    from torchrl.envs import DTypeCastTransform, GymEnv
    from torchrl.envs.transforms import Transform

    from ldm_rl.envs.registry import ENV_IDS, register_envs

    if env_id not in ENV_IDS:
        raise ValueError(f"env_id must be one of {sorted(ENV_IDS)}, got {env_id!r}")
    transforms = list(transforms) if not isinstance(transforms, Transform) else [transforms]
    for t in transforms:
        if not isinstance(t, Transform):
            raise ValueError(f"transforms must be torchrl Transform instances, got {type(t).__name__}")
    register_envs()
    base = GymEnv(env_id, categorical_action_encoding=True, **kwargs)
    env = _pick_place_env_class()(base, DTypeCastTransform(torch.int8, torch.bool, in_keys=["holding"]))
    for t in transforms:
        env.append_transform(t)
    return env


def env_kwargs_from_config(cfg: Mapping[str, Any], *, training: bool = False) -> tuple[str, dict]:
    """(env id, constructor kwargs) from a ``cfg.env`` node (see conf/env/*.yaml). ``training``: the
    env that collects training episodes and expert demos, which draws its object count per episode
    from ``train_object_counts`` when that is set (evaluation envs keep ``num_objects``)."""
    cfg = dict(cfg)
    if "id" not in cfg:
        raise ValueError("cfg.env needs an 'id' (e.g. ldm_rl/BlockStacking-v0)")
    counts = cfg.get("train_object_counts") if training else None
    kwargs = {
        "num_objects": cfg.get("num_objects"),
        "max_steps": cfg.get("max_steps"),
        "num_rotations": cfg.get("num_rotations"),  # absent: the env's default
        "object_counts": list(counts) if counts is not None else None,
    }
    kwargs = {k: v for k, v in kwargs.items() if v is not None}
    # the finger pads' torsional friction (conf/env/*.yaml: 0.1, the anchor's); a config stored before the key
    # existed (runs before 2026-11-27) gets 0, the physics it ran on, so old runs resume and re-score as they were
    spin = cfg.get("finger_spinning_friction", 0.0)
    if isinstance(spin, bool) or not isinstance(spin, (int, float)) or not spin >= 0:
        raise ValueError(f"env.finger_spinning_friction must be a number >= 0, got {spin!r}")
    kwargs["gripper"] = {"finger_spinning_friction": float(spin)}
    # bin packing's optional progress term (conf/env/bin_packing.yaml); absent or 0: the task's sparse reward
    if cfg.get("progress_reward"):
        kwargs["progress_reward"] = cfg["progress_reward"]
    return cfg["id"], kwargs


def make_env_from_config(cfg: Mapping[str, Any], *, training: bool = False, **overrides):
    """``make_env`` from a Hydra ``cfg.env`` node (``training``: see ``env_kwargs_from_config``);
    ``overrides`` win over the config. ``failed_pick_memory`` > 0 appends
    :class:`~ldm_rl.envs.memory.FailedPickMemory` of that size, ``scene_memory`` > 0
    :class:`~ldm_rl.envs.memory.SceneMemory`."""
    from ldm_rl.envs.memory import FailedPickMemory, SceneMemory

    env_id, kwargs = env_kwargs_from_config(cfg, training=training)
    kwargs.update(overrides)
    picks, scenes = int(cfg.get("failed_pick_memory") or 0), int(cfg.get("scene_memory") or 0)
    transforms = [FailedPickMemory(picks)] if picks else []
    transforms += [SceneMemory(scenes)] if scenes else []
    return make_env(env_id, transforms=transforms, **kwargs)


def unwrap(env):
    """The ``PickPlaceEnv`` (gymnasium) inside a TorchRL env built by ``make_env``, however many
    ``TransformedEnv`` layers wrap it (unbatched envs only): ``unwrap(env).expert_action()``, its poses."""
    from torchrl.envs import TransformedEnv

    from ldm_rl.envs.base import PickPlaceEnv

    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    inner = getattr(base, "__dict__", {}).get("_env")  # GymEnv keeps the gymnasium env there
    if inner is None or not isinstance(getattr(inner, "unwrapped", None), PickPlaceEnv):
        raise ValueError(f"env must be a single (unbatched) env from make_env, got {type(env).__name__}")
    return inner.unwrapped


def expert_policy(env, noise=None):
    """A TorchRL policy (``td -> td`` writing ``"action"`` ``[3] int64``) that plays the scripted
    expert of ``env`` (a single env from ``make_env``), e.g. ``env.rollout(10, expert_policy(env))``."""
    import torch

    task = unwrap(env)

    def policy(td):
        if getattr(env, "is_closed", False):
            raise EnvClosedError("expert_policy: its environment is closed; make a new env and a new expert_policy(env)")
        td.set("action", torch.as_tensor(task.expert_action(noise), dtype=torch.int64))
        return td

    return policy
