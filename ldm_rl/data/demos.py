"""Expert demonstrations: collect them from the envs, save them exactly, load them back verified.

A demo set is one TensorDict of transitions, batch ``[N]`` (the data contract of docs/conventions.md / the
dynamics model), in working dtypes:

==========================================  ==========================  =====================
key                                         shape / dtype               on disk
==========================================  ==========================  =====================
``heightmap``, ``("next", "heightmap")``    ``[N,1,128,128] float32`` m  float32
``in_hand``, ``("next", "in_hand")``        ``[N,1,24,24] float32`` m    float32
``holding``, ``("next", "holding")``        ``[N,1] bool``               bool
``action``                                  ``[N,3] int64`` (row,col,rot) uint8
``("next", "reward")``                      ``[N,1] float32``            float32
``("next", done|terminated|truncated)``     ``[N,1] bool``               bool
``("next", "primitive_success")``           ``[N,1] bool``               bool
``episode``                                 ``[N] int64``                int32
``is_expert``                               ``[N,1] bool``               bool
==========================================  ==========================  =====================

plus the non-tensor ``metadata`` dict (``td.get_non_tensor("metadata")``: task id, env kwargs,
num_rotations, max_height, procedure, noise, seed). Heights are stored as float32, so a saved and
reloaded set equals the in-process one bit for bit (every conversion above is exact): training on
saved data gives the same result as training on data collected in the same process.

On disk a demo set is a TensorDict memmap directory (``TensorDict.load_memmap`` reads it; what
TorchRL's ``LazyMemmapStorage`` uses) plus ``demos.json``: the format version, ``num_transitions``,
the metadata, each tensor's file, dtype and shape, and each file's size and SHA-256.
:func:`load_demos` opens every file read-only and checks all of it (files present, sizes, checksums,
dtypes and shapes, finite values in range) before returning anything; a problem is one
:class:`DemoDataError` naming the folder, the file and what is wrong, and the folder is never modified.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from tensordict import TensorDict

from ldm_rl.geometry import NUM_ROTATIONS
from ldm_rl.run.outputs import atomic_path

__all__ = ["collect_demos", "save_demos", "load_demos", "episodes_to_tensordict", "DemoDataError", "FORMAT_VERSION"]

PROCEDURES = ("direct", "deconstruct")
FORMAT = "ldm_rl.demos"
FORMAT_VERSION = 2  # 1 (no version field): float16 heights, no manifest
MANIFEST = "demos.json"
# key -> (dtype on disk, shape after the batch dim, dtype in memory); every key of collect_demos
SPEC: dict[str, tuple[str, tuple[int, ...], torch.dtype]] = {
    "heightmap": ("float32", (1, 128, 128), torch.float32),
    "in_hand": ("float32", (1, 24, 24), torch.float32),
    "holding": ("bool", (1,), torch.bool),
    "action": ("uint8", (3,), torch.int64),
    "episode": ("int32", (), torch.int64),
    "is_expert": ("bool", (1,), torch.bool),
    "next/heightmap": ("float32", (1, 128, 128), torch.float32),
    "next/in_hand": ("float32", (1, 24, 24), torch.float32),
    "next/holding": ("bool", (1,), torch.bool),
    "next/reward": ("float32", (1,), torch.float32),
    "next/done": ("bool", (1,), torch.bool),
    "next/terminated": ("bool", (1,), torch.bool),
    "next/truncated": ("bool", (1,), torch.bool),
    "next/primitive_success": ("bool", (1,), torch.bool),
}
REQUIRED = ("heightmap", "in_hand", "holding", "action", "next/heightmap", "next/holding", "next/reward")
_HEIGHT_KEYS = ("heightmap", "in_hand", "next/heightmap", "next/in_hand")
MAX_HEIGHT_M = 1.0  # the camera clips heights to [0, 1] m (ldm_rl.envs.camera)
_TORCH_DTYPES = {"float32": torch.float32, "float64": torch.float64, "float16": torch.float16, "bool": torch.bool,
                 "uint8": torch.uint8, "int8": torch.int8, "int16": torch.int16, "int32": torch.int32, "int64": torch.int64}


class DemoDataError(ValueError):
    """A demo folder (or set) that is missing, damaged or does not match its metadata."""


def _make_gym_env(env_cfg: Mapping[str, Any], noise):
    import gymnasium as gym

    from ldm_rl.envs import register_envs
    from ldm_rl.envs.torchrl_env import env_kwargs_from_config

    register_envs()
    env_id, kwargs = env_kwargs_from_config(env_cfg, training=True)
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
        noise: ``{"position": metres, "random_action_prob": p, "rotation_prob": p}`` (default: noiseless).
        progress: show progress (``ldm_rl.run.progress``: a bar with ETA on a terminal, else periodic log lines).

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
    from ldm_rl.run.progress import progress_bar

    bar = progress_bar(total=budget, unit="step" if num_steps else "episode", enabled=progress, desc=f"demos {env_id}")
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
        "num_rotations": int(kwargs.get("num_rotations", NUM_ROTATIONS)),
        "max_height": float(env_cfg.get("max_height", type(env).max_height)),
        "procedure": procedure,
        "noise": {"position": noise.position, "random_action_prob": noise.random_action_prob,
                  "rotation_prob": noise.rotation_prob},
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


def _key_name(key) -> str:
    return "/".join(key) if isinstance(key, tuple) else key


def _tensor_leaves(td: TensorDict) -> dict[str, torch.Tensor]:
    return {_key_name(k): v for k, v in td.items(include_nested=True, leaves_only=True) if isinstance(v, torch.Tensor)}


def _check_values(name: str, values: torch.Tensor, num_rotations: int | None, where: str) -> None:
    """Raise DemoDataError if ``values`` (key ``name``, working dtype) are outside what the format allows;
    ``where`` starts the message (the folder and file, or ``td``)."""
    if values.is_floating_point():
        bad = (~torch.isfinite(values)).sum().item()
        if bad:
            raise DemoDataError(f"{where} holds {bad:,} NaN/inf values")
        if name in _HEIGHT_KEYS and values.numel():
            low, high = values.min().item(), values.max().item()
            if low < 0.0 or high > MAX_HEIGHT_M:
                raise DemoDataError(f"{where} holds heights outside [0, {MAX_HEIGHT_M:g}] m "
                                    f"(min {low:.4g}, max {high:.4g})")
    elif name == "action" and values.numel():
        rc, rot = values[..., :2], values[..., 2]
        if rc.min().item() < 0 or rc.max().item() >= 128:
            raise DemoDataError(f"{where} holds action pixels outside [0, 128) (min {rc.min().item()}, max {rc.max().item()})")
        if rot.min().item() < 0 or (num_rotations is not None and rot.max().item() >= num_rotations):
            raise DemoDataError(f"{where} holds rotation bins outside [0, {num_rotations}) (max {rot.max().item()})")
    elif name == "episode" and values.numel() and values.min().item() < 0:
        raise DemoDataError(f"{where} holds negative episode ids")


def _validate_td(td: TensorDict) -> tuple[dict[str, torch.Tensor], dict]:
    """The tensor leaves and metadata of a demo TensorDict, checked against :data:`SPEC`."""
    if not isinstance(td, TensorDict) or len(td.batch_size) != 1:
        raise DemoDataError(f"a demo set is a TensorDict with batch [N], got {type(td).__name__} {getattr(td, 'batch_size', '')}")
    leaves = _tensor_leaves(td)
    missing = [k for k in REQUIRED if k not in leaves]
    if missing:
        raise DemoDataError(f"td is not a demo set: missing keys {missing}")
    metadata = td.get_non_tensor("metadata") if "metadata" in td.keys() else {}
    metadata = dict(metadata or {})
    num_rotations = metadata.get("num_rotations")
    for name, value in leaves.items():
        if name in SPEC:
            _, shape, dtype = SPEC[name]
            if tuple(value.shape[1:]) != shape or value.dtype != dtype:
                raise DemoDataError(f"td[{name!r}] must be [N, {', '.join(map(str, shape))}] {dtype}, got "
                                    f"{list(value.shape)} {value.dtype}")
        _check_values(name, value, num_rotations, f"td[{name!r}]")
    return leaves, metadata


def save_demos(td: TensorDict, path: str | os.PathLike) -> Path:
    """Write ``td`` (the demo format) atomically to the directory ``path``; return the path.

    Values are checked first (keys, dtypes, shapes, finite heights in range). Conversions to the disk
    dtypes are exact (float32 stays float32), so ``load_demos(save_demos(td, p))`` equals ``td``.
    """
    leaves, metadata = _validate_td(td)
    path = Path(path)
    n = int(td.batch_size[0])
    disk = td.exclude("metadata").clone(False)
    tensors = {}
    for name, value in leaves.items():
        dtype = SPEC[name][0] if name in SPEC else str(value.dtype).removeprefix("torch.")
        if dtype not in _TORCH_DTYPES:
            raise DemoDataError(f"td[{name!r}] has dtype {value.dtype}, which demo folders do not store")
        converted = value.to(_TORCH_DTYPES[dtype])
        if not torch.equal(converted.to(value.dtype), value):
            raise DemoDataError(f"td[{name!r}] does not fit {dtype} exactly (values out of its range)")
        disk.set(tuple(name.split("/")), converted)
        tensors[name] = {"file": f"{name}.memmap", "dtype": dtype, "shape": [n, *value.shape[1:]]}
    if metadata:
        disk.set_non_tensor("metadata", metadata)
    with atomic_path(path) as tmp:
        disk.memmap(tmp)
        files = {}
        for file in sorted(p for p in tmp.rglob("*") if p.is_file()):
            data = file.read_bytes()
            files[file.relative_to(tmp).as_posix()] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
        for name, entry in tensors.items():
            expected = math.prod(entry["shape"]) * np.dtype(entry["dtype"]).itemsize
            if files.get(entry["file"], {}).get("bytes") != expected:  # the memmap layout we read back
                raise RuntimeError(f"save_demos: {entry['file']} was written with an unexpected layout")
        manifest = {"format": FORMAT, "format_version": FORMAT_VERSION, "num_transitions": n, "metadata": metadata,
                    "tensors": tensors, "files": files}
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2))
    return path


def _read_manifest(path: Path) -> dict:
    where = f"demo folder {path}"
    if not path.exists():
        raise DemoDataError(f"{where}: no such folder")
    if not path.is_dir():
        raise DemoDataError(f"{where}: not a folder (a demo set is a folder written by save_demos / recipes/generate_demos.py)")
    file = path / MANIFEST
    if not file.is_file():
        raise DemoDataError(f"{where}: {MANIFEST} is missing (not a folder written by save_demos, or damaged)")
    try:
        manifest = json.loads(file.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as err:
        raise DemoDataError(f"{where}: {MANIFEST} is not UTF-8 text (damaged)") from err
    except json.JSONDecodeError as err:
        raise DemoDataError(f"{where}: {MANIFEST} is not valid JSON (line {err.lineno} column {err.colno}: {err.msg})") from err
    if not isinstance(manifest, dict):
        raise DemoDataError(f"{where}: {MANIFEST} is not a JSON object")
    version = manifest.get("format_version")
    if version is None:
        raise DemoDataError(f"{where}: saved by an older ldm_rl (float16 heights, no checksums); regenerate it with "
                            "recipes/generate_demos.py")
    if manifest.get("format") != FORMAT or version != FORMAT_VERSION:
        raise DemoDataError(f"{where}: {MANIFEST} says format {manifest.get('format')!r} version {version!r}; this ldm_rl "
                            f"reads {FORMAT!r} version {FORMAT_VERSION}")
    n = manifest.get("num_transitions")
    tensors, files, metadata = manifest.get("tensors"), manifest.get("files"), manifest.get("metadata")
    if not (isinstance(n, int) and n >= 1 and isinstance(tensors, dict) and isinstance(files, dict) and isinstance(metadata, dict)):
        raise DemoDataError(f"{where}: {MANIFEST} lacks a valid num_transitions / tensors / files / metadata")
    missing = [k for k in REQUIRED if k not in tensors]
    if missing:
        raise DemoDataError(f"{where}: {MANIFEST} lists no {missing} (a demo set needs {list(REQUIRED)})")
    for name, entry in tensors.items():
        ok = isinstance(entry, dict) and isinstance(entry.get("shape"), list) and entry.get("dtype") in _TORCH_DTYPES \
            and entry.get("file") in files and all(isinstance(d, int) and d >= 0 for d in entry["shape"])
        if not ok:
            raise DemoDataError(f"{where}: {MANIFEST} has a malformed entry for {name!r}: {entry!r}")
        if entry["shape"][:1] != [n]:
            raise DemoDataError(f"{where}: {MANIFEST} gives {name} {entry['shape'][:1]} rows, num_transitions is {n}")
        if name in SPEC and (entry["dtype"], tuple(entry["shape"][1:])) != SPEC[name][:2]:
            raise DemoDataError(f"{where}: {MANIFEST} gives {name} as {entry['dtype']} {entry['shape']}; the format says "
                                f"{SPEC[name][0]} [N, {', '.join(map(str, SPEC[name][1]))}]")
    for rel, entry in files.items():
        if not (isinstance(entry, dict) and isinstance(entry.get("bytes"), int) and isinstance(entry.get("sha256"), str)):
            raise DemoDataError(f"{where}: {MANIFEST} has a malformed entry for the file {rel!r}")
        if Path(rel).is_absolute() or ".." in Path(rel).parts:
            raise DemoDataError(f"{where}: {MANIFEST} names a file outside the folder: {rel!r}")
    return manifest


def _read_verified(path: Path, rel: str, entry: Mapping[str, Any]) -> bytearray:
    """The bytes of ``path/rel``, read-only, after checking size and SHA-256 against ``entry``."""
    file = path / rel
    where = f"demo folder {path}"
    if not file.is_file():
        raise DemoDataError(f"{where}: {rel} is missing (listed in {MANIFEST})")
    size = file.stat().st_size
    if size != entry["bytes"]:
        what = "truncated" if size < entry["bytes"] else "has extra bytes"
        raise DemoDataError(f"{where}: {rel} {what}: {size:,} bytes, {MANIFEST} says {entry['bytes']:,}")
    data = bytearray(size)
    with open(file, "rb") as f:
        if f.readinto(data) != size:
            raise DemoDataError(f"{where}: {rel} changed size while being read")
    if hashlib.sha256(data).hexdigest() != entry["sha256"]:
        raise DemoDataError(f"{where}: {rel} does not match its SHA-256 in {MANIFEST} (the bytes were changed: corrupted)")
    return data


def load_demos(path: str | os.PathLike) -> TensorDict:
    """Read and verify a directory written by :func:`save_demos`; tensors in working dtypes, in memory.

    Every file is opened read-only. Checked before anything is returned: ``demos.json`` (present, valid,
    this format version, every required key, dtypes and shapes as the format says), every listed file
    (present, exact size: no truncation or extra bytes, SHA-256), then the values (finite heights in
    [0, 1] m, actions inside the image and the rotation bins, flags 0/1). Raises
    :class:`DemoDataError` (a ``ValueError``) naming the folder, the file and the problem.
    """
    path = Path(path)
    manifest = _read_manifest(path)
    where = f"demo folder {path}"
    metadata = manifest["metadata"]
    num_rotations = metadata.get("num_rotations")
    buffers = {rel: _read_verified(path, rel, entry) for rel, entry in manifest["files"].items()}
    td = TensorDict({}, batch_size=[manifest["num_transitions"]])
    for name, entry in manifest["tensors"].items():
        data, dtype = buffers[entry["file"]], np.dtype(entry["dtype"])
        expected = math.prod(entry["shape"]) * dtype.itemsize
        if len(data) != expected:
            raise DemoDataError(f"{where}: {entry['file']} holds {len(data):,} bytes; {entry['dtype']} {entry['shape']} "
                                f"needs {expected:,}")
        if dtype == np.bool_:
            raw = np.frombuffer(data, dtype=np.uint8)
            if raw.size and raw.max() > 1:
                raise DemoDataError(f"{where}: {entry['file']} holds bytes other than 0/1 for a bool key")
        array = np.frombuffer(data, dtype=dtype).reshape(entry["shape"])
        value = torch.from_numpy(array)
        if name in SPEC:
            value = value.to(SPEC[name][2])
        _check_values(name, value, num_rotations, f"{where}: {entry['file']}")
        td.set(tuple(name.split("/")), value)
    if metadata:
        td.set_non_tensor("metadata", metadata)
    return td
