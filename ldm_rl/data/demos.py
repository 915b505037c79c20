"""Expert demonstrations: collect them from the envs, save them compactly, load them back.

A demo set is one TensorDict of transitions, batch ``[N]`` (the data contract of DESIGN / the
dynamics model), in working dtypes:

==========================================  ==========================  =====================
key                                         shape / dtype               on disk
==========================================  ==========================  =====================
``heightmap``, ``("next", "heightmap")``    ``[N,1,128,128] float32`` m  float16 (≤0.1 mm error
``in_hand``, ``("next", "in_hand")``        ``[N,1,24,24] float32`` m    below 0.25 m)
``holding``, ``("next", "holding")``        ``[N,1] bool``               bool
``action``                                  ``[N,3] int64`` (row,col,rot) uint8
``("next", "reward")``                      ``[N,1] float32``            float32
``("next", done|terminated|truncated)``     ``[N,1] bool``               bool
``("next", "primitive_success")``           ``[N,1] bool``               bool
``episode``                                 ``[N] int64``                int32
``is_expert``                               ``[N,1] bool``               bool
==========================================  ==========================  =====================

plus the non-tensor ``metadata`` dict (``td.get_non_tensor("metadata")``: task id, env kwargs,
num_rotations, max_height, procedure, noise, seed). On disk a demo set is a TensorDict memmap
directory (what TorchRL's ``LazyMemmapStorage`` uses) with a readable ``demos.json`` beside the data.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from tensordict import TensorDict

from ldm_rl.runtime import atomic_path

__all__ = ["collect_demos", "save_demos", "load_demos", "episodes_to_tensordict"]

PROCEDURES = ("direct", "deconstruct")
_FLOAT_KEYS = ("heightmap", "in_hand")
_DISK_DTYPES = {"heightmap": torch.float16, "in_hand": torch.float16, "action": torch.uint8, "episode": torch.int32}
_WORK_DTYPES = {"heightmap": torch.float32, "in_hand": torch.float32, "action": torch.int64, "episode": torch.int64}


def _make_gym_env(env_cfg: Mapping[str, Any], noise):
    import gymnasium as gym

    from ldm_rl.envs import register_envs
    from ldm_rl.envs.torchrl_env import env_kwargs_from_config

    register_envs()
    env_id, kwargs = env_kwargs_from_config(env_cfg)
    return gym.make(env_id, expert_noise=noise, **kwargs).unwrapped, env_id, kwargs


def collect_demos(
    env_cfg: Mapping[str, Any],
    *,
    num_steps: int | None = None,
    num_episodes: int | None = None,
    seed: int = 0,
    procedure: str = "direct",
    noise: Mapping[str, float] | None = None,
    progress: bool = True,
) -> TensorDict:
    """Run the scripted expert and return its transitions (format in the module docstring).

    Args:
        env_cfg: a ``cfg.env`` node (``id``, ``num_objects``, ``max_steps``, ``num_rotations``, ...).
        num_steps / num_episodes: exactly one; with ``num_steps`` the last episode is cut to fit.
        seed: episode ``i`` is reset with a seed drawn from ``numpy.random.default_rng(seed)``.
        procedure: ``"direct"`` (the direct planner) or ``"deconstruct"`` (build, deconstruct, replay
            reversed; block stacking and house building only; failed deconstructions are skipped).
        noise: ``{"position": metres, "random_action_prob": p}`` (default: noiseless).
        progress: show a tqdm bar.

    The metadata's ``num_episodes`` / ``success_rate`` describe the episodes collected (before a
    ``num_steps`` cut); ``success_rate`` counts episodes ending terminated with a positive reward.
    """
    from ldm_rl.envs.base import ExpertNoise
    from ldm_rl.envs.episodes import run_deconstruct_episode, run_expert_episode

    if (num_steps is None) == (num_episodes is None):
        raise ValueError(f"give exactly one of num_steps / num_episodes, got {num_steps!r} / {num_episodes!r}")
    budget = num_steps if num_steps is not None else num_episodes
    if not isinstance(budget, int) or isinstance(budget, bool) or budget < 1:
        raise ValueError(f"num_steps / num_episodes must be a positive int, got {budget!r}")
    if procedure not in PROCEDURES:
        raise ValueError(f"procedure must be one of {PROCEDURES}, got {procedure!r}")
    noise = ExpertNoise(**dict(noise or {}))
    env, env_id, kwargs = _make_gym_env(env_cfg, noise)
    run = run_expert_episode if procedure == "direct" else run_deconstruct_episode
    rng = np.random.default_rng(seed)
    episodes, steps = [], 0
    from tqdm.auto import tqdm

    bar = tqdm(total=budget, unit="step" if num_steps else "episode", disable=not progress, desc=f"demos {env_id}")
    try:
        while (steps if num_steps else len(episodes)) < budget:
            episode = run(env, int(rng.integers(2**31)), noise)
            if not episode:
                continue
            episodes.append(episode)
            steps += len(episode)
            bar.update(min(len(episode), budget - bar.n) if num_steps else 1)
    finally:
        bar.close()
        env.close()
    td = episodes_to_tensordict(episodes)
    if num_steps is not None:
        td = td[:num_steps]
    metadata = {
        "env_id": env_id,
        "env_kwargs": kwargs,
        "num_rotations": int(kwargs.get("num_rotations", 8)),
        "max_height": float(env_cfg.get("max_height", type(env).max_height)),
        "procedure": procedure,
        "noise": {"position": noise.position, "random_action_prob": noise.random_action_prob},
        "seed": seed,
        "num_episodes": len(episodes),
        "success_rate": float(np.mean([ep[-1].terminated and ep[-1].reward > 0 for ep in episodes])),
    }
    td.set_non_tensor("metadata", metadata)
    return td


def episodes_to_tensordict(episodes) -> TensorDict:
    """Stack a list of episodes (lists of ``ldm_rl.envs.episodes.Transition``) into the demo format."""
    flat = [(i, t) for i, ep in enumerate(episodes) for t in ep]
    if not flat:
        raise ValueError("episodes must contain at least one transition")

    def stack(key, which):
        return torch.from_numpy(np.stack([getattr(t, which)[key] for _, t in flat]))

    def column(values, dtype):
        return torch.tensor(values, dtype=dtype).reshape(len(flat), 1)

    terminated = column([t.terminated for _, t in flat], torch.bool)
    truncated = column([t.truncated for _, t in flat], torch.bool)
    td = TensorDict(
        {
            "heightmap": stack("heightmap", "obs"),
            "in_hand": stack("in_hand", "obs"),
            "holding": stack("holding", "obs").bool(),
            "action": torch.from_numpy(np.stack([t.action for _, t in flat])).long(),
            "episode": torch.tensor([i for i, _ in flat], dtype=torch.int64),
            "is_expert": column([t.is_expert for _, t in flat], torch.bool),
            "next": {
                "heightmap": stack("heightmap", "next_obs"),
                "in_hand": stack("in_hand", "next_obs"),
                "holding": stack("holding", "next_obs").bool(),
                "reward": column([t.reward for _, t in flat], torch.float32),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
                "primitive_success": column([t.primitive_success for _, t in flat], torch.bool),
            },
        },
        batch_size=[len(flat)],
    )
    return td


def _cast(td: TensorDict, dtypes: Mapping[str, torch.dtype]) -> TensorDict:
    out = td.clone(False)
    for key, value in td.items(include_nested=True, leaves_only=True, is_leaf=_is_tensor_leaf):
        name = key[-1] if isinstance(key, tuple) else key
        if name in dtypes and isinstance(value, torch.Tensor):
            out.set(key, value.to(dtypes[name]))
    return out


def _is_tensor_leaf(cls) -> bool:
    return not issubclass(cls, TensorDict)


def save_demos(td: TensorDict, path: str | os.PathLike) -> Path:
    """Write ``td`` (the demo format) atomically to the directory ``path`` in compact dtypes."""
    missing = [k for k in ("heightmap", "in_hand", "holding", "action", ("next", "reward")) if k not in td.keys(True)]
    if missing:
        raise ValueError(f"td is not a demo set: missing keys {missing}")
    path = Path(path)
    compact = _cast(td, _DISK_DTYPES)
    with atomic_path(path) as tmp:
        compact.memmap(tmp)
        metadata = td.get_non_tensor("metadata") if "metadata" in td.keys() else {}
        (tmp / "demos.json").write_text(json.dumps({"num_transitions": td.batch_size[0], **metadata}, indent=2))
    return path


def load_demos(path: str | os.PathLike) -> TensorDict:
    """Read a directory written by ``save_demos``; tensors in working dtypes, in memory."""
    path = Path(path)
    if not (path / "demos.json").is_file():
        raise ValueError(f"path must be a demo directory written by save_demos, got {str(path)!r}")
    td = TensorDict.load_memmap(path)
    metadata = td.get_non_tensor("metadata") if "metadata" in td.keys() else None
    td = _cast(td.exclude("metadata").to_tensordict(), _WORK_DTYPES)
    if metadata is not None:
        td.set_non_tensor("metadata", metadata)
    return td
