"""Collection for the training loop: TorchRL collectors in this process, in N processes, or on N machines.

``recipes/train_policy.py`` collects through three calls (docs/scaling.md walks through each setting)::

    factory = TaskEnvFactory(cfg.env, reset_seed=training_scenes(seed))   # picklable: worker -> env
    collector = make_collector(cfg.collector, factory, agent.policy, seed=seed)
    episodes = EpisodeAssembler(TRANSITION_KEYS)
    for step in collected_steps(collector):        # one transition at a time; weights refreshed per batch
        episode = episodes.add(step)               # a finished episode [T] of one worker, or None
        ...                                        # replay, updates
    shutdown_collector(collector)

``cfg.collector`` (``conf/train_policy.yaml``):

=====================  ==============================================================================
``num_workers: 1``     TorchRL's ``Collector`` running ``policy`` in this process (exact resume)
``num_workers: N``     N worker processes: ``MultiSyncCollector`` (``sync: true``, reproducible) or
                       ``MultiAsyncCollector`` (``sync: false``), each worker with one torch thread,
                       its own scene stream and its own RNG seed
``backend: distributed``  TorchRL's ``DistributedCollector`` (torch.distributed, gloo): ``launcher: mp``
                       starts the N collectors as processes of this machine, ``launcher: submitit`` as
                       SLURM jobs on other machines (``slurm:`` holds submitit's executor options)
=====================  ==============================================================================

Worker copies of the policy get new weights through TorchRL's weight synchronisation
(``collector.update_policy_weights_()``, called by :func:`collected_steps` after each batch). A policy
with a schedule step (``policy.step`` / ``policy.set_step``, e.g. the LDM agent's planner) is wrapped
so that the step travels with the weights.
"""

from __future__ import annotations

import functools
import os
import signal
from typing import Any, Iterator, Mapping, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from ldm_rl.seeds import SEED_BLOCK

__all__ = ["BACKENDS", "LAUNCHERS", "DEFAULTS", "TaskEnvFactory", "make_collector", "collected_steps", "refresh_weights",
           "shutdown_collector", "EpisodeAssembler", "ScheduleSyncedPolicy", "worker_seed", "WORKER_KEY", "TRAJ_KEY"]

BACKENDS = ("process", "distributed")
LAUNCHERS = ("mp", "submitit")  # TorchRL's submitit_delayed needs a wrapped entry point, which the recipe is not
# per frame: the worker that collected it (index in the batch) and TorchRL's trajectory id
WORKER_KEY = ("collector", "worker")
TRAJ_KEY = ("collector", "traj_ids")
# DistributedCollector stops after total_frames even with -1 (torchrl 0.14.1): ask for "forever" instead
_FOREVER_BATCHES = 2**40
DEFAULTS = {"num_workers": 1, "sync": True, "frames_per_worker": 1, "backend": "process", "launcher": "mp",
            "tcp_port": None, "slurm": {}}


class TaskEnvFactory:
    """A picklable ``(worker, num_workers) -> env`` factory for one task (``make_env_from_config``).

    Scene seeds: worker ``w`` of ``N`` plays its k-th episode on the scene of seed
    ``reset_seed + w * (seed_block // N) + start_episode + k``; with one worker this is the
    uninterrupted stream ``reset_seed + k`` of a single env. ``start_episode`` moves every stream on
    (a resumed run sets it to the episodes already played, so no finished scene repeats).

    Args:
        env_cfg: a ``cfg.env`` node (conf/env/*.yaml) or dict.
        reset_seed: first scene seed (None: unseeded scenes).
        start_episode: episode index every worker starts from.
        seed_block: scene seeds reserved for one run (``reset_seed`` of consecutive run seeds is this far apart).
    """

    def __init__(self, env_cfg: Mapping[str, Any], *, reset_seed: int | None = None, start_episode: int = 0,
                 seed_block: int = SEED_BLOCK) -> None:
        from omegaconf import OmegaConf

        if OmegaConf.is_config(env_cfg):
            env_cfg = OmegaConf.to_container(env_cfg, resolve=True)
        if "id" not in env_cfg:
            raise ValueError(f"env_cfg needs an 'id' (a cfg.env node), got keys {sorted(env_cfg)}")
        if not isinstance(start_episode, int) or start_episode < 0:
            raise ValueError(f"start_episode must be a non-negative int, got {start_episode!r}")
        self.env_cfg, self.reset_seed, self.start_episode, self.seed_block = dict(env_cfg), reset_seed, start_episode, seed_block

    def __call__(self, worker: int = 0, num_workers: int = 1):
        from ldm_rl.envs import make_env_from_config
        from ldm_rl.envs.torchrl_env import unwrap

        if not 0 <= worker < num_workers:
            raise ValueError(f"worker must be in [0, {num_workers}), got {worker}")
        reset_seed = None if self.reset_seed is None else self.reset_seed + worker * (self.seed_block // num_workers)
        env = make_env_from_config(self.env_cfg, training=True, reset_seed=reset_seed)
        unwrap(env).episode_index = self.start_episode
        return env

    def __repr__(self) -> str:
        return (f"TaskEnvFactory({self.env_cfg.get('id')!r}, reset_seed={self.reset_seed}, "
                f"start_episode={self.start_episode})")


def worker_seed(seed: int, worker: int) -> int:
    """An independent 63-bit seed for worker ``worker`` of a run seeded ``seed`` (numpy's SeedSequence)."""
    import numpy as np

    return int(np.random.SeedSequence([int(seed), int(worker)]).generate_state(2, np.uint64)[0] >> np.uint64(1))


def _worker_env(env_factory, worker: int, num_workers: int, seed: int, parent_pid: int):
    """Worker ``worker``'s env. In a worker process, first: one torch thread, the worker's seeds, and
    SIGINT/SIGTERM left to the training process (which stops the workers after its checkpoint). In the
    training process itself (TorchRL's DistributedCollector builds one env there to learn the batch
    layout) only the env is built."""
    if os.getpid() != parent_pid:
        from ldm_rl.torch_utils import seed_everything

        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        torch.set_num_threads(1)
        seed_everything(worker_seed(seed, worker))
    return env_factory(worker, num_workers)


class ScheduleSyncedPolicy(TensorDictModuleBase):
    """``policy`` plus its schedule step as a buffer, so that weight synchronisation carries the step.

    Planners evaluate their schedules (temperatures, inhibition) at ``policy.step``, a Python int that
    TorchRL's weight sync (parameters and buffers) would not send to worker copies. :meth:`publish`
    (called by :func:`collected_steps` before each weight refresh) copies it into ``schedule_step``;
    ``forward`` in a worker applies it with ``policy.set_step``.
    """

    def __init__(self, policy: TensorDictModuleBase) -> None:
        super().__init__()
        self.policy = policy
        self.in_keys, self.out_keys = list(policy.in_keys), list(policy.out_keys)
        self.register_buffer("schedule_step", torch.tensor(int(policy.step), dtype=torch.int64))

    def publish(self) -> None:
        self.schedule_step.fill_(int(self.policy.step))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        step = int(self.schedule_step)
        if self.policy.step != step:
            self.policy.set_step(step)
        return self.policy(tensordict)


def _settings(cfg: Mapping[str, Any] | None) -> dict[str, Any]:
    from omegaconf import OmegaConf

    if cfg is not None and OmegaConf.is_config(cfg):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    unknown = sorted(set(cfg or {}) - set(DEFAULTS))
    if unknown:
        raise ValueError(f"collector settings {unknown} are unknown: expected some of {sorted(DEFAULTS)}")
    s = {**DEFAULTS, **dict(cfg or {})}
    for key in ("num_workers", "frames_per_worker"):
        if not isinstance(s[key], int) or isinstance(s[key], bool) or s[key] < 1:
            raise ValueError(f"collector.{key} must be a positive int, got {s[key]!r}")
    if s["backend"] not in BACKENDS:
        raise ValueError(f"collector.backend must be one of {BACKENDS}, got {s['backend']!r}")
    if s["launcher"] not in LAUNCHERS:
        raise ValueError(f"collector.launcher must be one of {LAUNCHERS}, got {s['launcher']!r}")
    if not isinstance(s["sync"], bool):
        raise ValueError(f"collector.sync must be true or false, got {s['sync']!r}")
    if s["backend"] == "distributed" and not s["sync"]:
        raise ValueError("collector.sync=false needs collector.backend=process: the distributed collector's async "
                         "batches do not say which worker sent them")
    return s


def make_collector(cfg: Mapping[str, Any] | None, env_factory, policy: TensorDictModuleBase, *,
                   device: torch.device | str | None = None, seed: int = 0):
    """The TorchRL collector that ``cfg`` (a ``collector`` node, keys of :data:`DEFAULTS`) asks for.

    Args:
        cfg: ``num_workers``, ``sync``, ``frames_per_worker``, ``backend``, ``launcher``, ``tcp_port``, ``slurm``.
        env_factory: ``(worker, num_workers) -> env`` (e.g. :class:`TaskEnvFactory`); picklable when
            ``num_workers > 1`` or ``backend=distributed`` (it runs in the workers).
        policy: a TensorDict module writing ``"action"``; runs in this process with one worker, as
            worker copies otherwise.
        device: the collector's device (policy and env).
        seed: the run's seed; worker ``w`` seeds python/numpy/torch with ``worker_seed(seed, w)``.

    Returns an endless collector: ``Collector`` (one worker, in this process),
    ``MultiSyncCollector`` / ``MultiAsyncCollector`` (``backend=process``) or ``DistributedCollector``.
    Each batch holds ``frames_per_worker`` frames of every worker (``[N, F]`` when synchronous, ``[F]``
    of one worker when not); iterate it with :func:`collected_steps`.
    """
    from torchrl.collectors import Collector

    s = _settings(cfg)
    n, frames = s["num_workers"], s["frames_per_worker"]
    if n == 1 and s["backend"] == "process":
        return Collector(env_factory(0, 1), policy, frames_per_batch=frames, total_frames=-1, device=device,
                         auto_register_policy_transforms=False)
    worker_policy = ScheduleSyncedPolicy(policy) if hasattr(policy, "set_step") and hasattr(policy, "step") else policy
    env_fns = [functools.partial(_worker_env, env_factory, w, n, int(seed), os.getpid()) for w in range(n)]
    if s["backend"] == "process":
        # num_threads: keep the training process's thread count (TorchRL's default lowers it)
        return Collector(env_fns, worker_policy, backend="process", num_collectors=n, sync=s["sync"],
                         frames_per_batch=n * frames, total_frames=-1, device=device, num_threads=torch.get_num_threads(),
                         num_sub_threads=1, auto_register_policy_transforms=False)
    options = {"launcher": s["launcher"], "collector_kwargs": {"auto_register_policy_transforms": False}}
    if s["tcp_port"] is not None:
        options["tcp_port"] = int(s["tcp_port"])
    if s["slurm"]:
        options["slurm_kwargs"] = dict(s["slurm"])
    return Collector(env_fns, worker_policy, backend="distributed", num_collectors=n, sync=True,
                     frames_per_batch=n * frames, total_frames=n * frames * _FOREVER_BATCHES, device=device,
                     backend_options=options)


def _is_in_process(collector) -> bool:
    from torchrl.collectors import Collector, MultiCollector

    return isinstance(collector, Collector) and not isinstance(collector, MultiCollector)


def refresh_weights(collector) -> None:
    """Send the training process's policy weights (and schedule step) to the collector's workers; nothing
    to do for the in-process ``Collector``, which runs the policy object itself."""
    if _is_in_process(collector):
        return
    policy = getattr(collector, "policy", None)
    if isinstance(policy, ScheduleSyncedPolicy):
        policy.publish()
    collector.update_policy_weights_()


def collected_steps(collector) -> Iterator[TensorDictBase]:
    """Single transitions (batch size ``[]``) from an endless collector, worker by worker, each in time
    order, with ``("collector", "worker")`` (the worker's index in a synchronous batch, else 0) beside
    TorchRL's ``("collector", "traj_ids")``. After the last transition of a batch has been handled by
    the caller's loop body (its updates), the workers get the new weights (:func:`refresh_weights`)."""
    for batch in collector:
        if batch.batch_dims > 2:
            raise ValueError(f"expected collector batches [F] or [workers, F], got batch size {tuple(batch.batch_size)}")
        if batch.batch_dims == 2:
            workers = torch.arange(batch.shape[0]).view(-1, 1).expand(batch.shape).clone()
        else:
            workers = torch.zeros(batch.shape, dtype=torch.int64)
        batch.set(WORKER_KEY, workers)
        frames = batch.reshape(-1)
        for i in range(frames.shape[0]):
            yield frames[i]
        refresh_weights(collector)


def shutdown_collector(collector) -> None:
    """Stop the collector's workers, keeping this process's torch thread count (TorchRL raises it on shutdown)."""
    threads = torch.get_num_threads()
    collector.shutdown()
    torch.set_num_threads(threads)


class EpisodeAssembler:
    """Builds whole episodes from transitions that arrive interleaved from several workers.

    :meth:`add` files each transition under its (worker, trajectory id) and returns the episode, stacked
    ``[T]``, when the transition ends it (``("next", "done")``); ``keys`` (default: all but
    ``"collector"``) are the entries kept.
    """

    def __init__(self, keys: Sequence | None = None) -> None:
        self.keys = None if keys is None else list(keys)
        self._open: dict[tuple[int, int], list[TensorDictBase]] = {}

    def add(self, step: TensorDictBase) -> TensorDictBase | None:
        if step.batch_dims != 0:
            raise ValueError(f"add takes one transition (batch size []), got batch size {tuple(step.batch_size)}")
        if ("next", "done") not in step.keys(include_nested=True):
            raise KeyError("a transition needs ('next', 'done') to tell where its episode ends")
        worker = int(step.get(WORKER_KEY)) if WORKER_KEY in step.keys(include_nested=True) else 0
        traj = int(step.get(TRAJ_KEY)) if TRAJ_KEY in step.keys(include_nested=True) else 0
        kept = step.select(*self.keys) if self.keys is not None else step.exclude("collector")
        frames = self._open.setdefault((worker, traj), [])
        frames.append(kept)
        if not bool(step.get(("next", "done"))):
            return None
        del self._open[(worker, traj)]
        return torch.stack(frames)

    @property
    def open_frames(self) -> int:
        """Transitions of episodes still running (dropped if the run stops now)."""
        return sum(len(frames) for frames in self._open.values())
