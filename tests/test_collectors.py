"""ldm_rl.collectors: TorchRL's in-process, multi-process and distributed collectors on the real tasks.

The worker tests start real processes (each imports torchrl and builds a PyBullet env), so they take
seconds each; the distributed ones run TorchRL's DistributedCollector (torch.distributed, gloo) on this
machine, with ``launcher=mp`` and with submitit (which runs its jobs locally where there is no SLURM).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torch import nn

from ldm_rl.collectors import (EpisodeAssembler, TaskEnvFactory, collected_steps, make_collector, shutdown_collector,
                               worker_seed)

ROOT = Path(__file__).resolve().parents[1]
ENV_CFG = {"id": "ldm_rl/BlockStacking-v0", "num_objects": 3, "max_steps": 3, "num_rotations": 8, "max_height": 0.25}
SEED_BLOCK = 1_000_000


class StepProbe(TensorDictModuleBase):
    """A tiny real policy reporting what a worker's copy sees: its weight, its schedule step, torch's
    thread count and one draw of the worker's torch RNG. Acts a pick at the centre."""

    in_keys = ["heightmap"]
    out_keys = ["action", "probe_weight", "probe_step", "probe_threads", "probe_draw"]

    def __init__(self) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.zeros(1))
        self.step = 0

    def set_step(self, step: int) -> None:
        self.step = step

    def forward(self, td):
        td.set("action", torch.tensor([64, 64, 0]))
        td.set("probe_weight", self.weight.detach().clone())
        td.set("probe_step", torch.tensor([self.step]))
        td.set("probe_threads", torch.tensor([torch.get_num_threads()]))
        td.set("probe_draw", torch.rand(1))
        return td


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def first_scene(factory: TaskEnvFactory, worker: int, num_workers: int) -> torch.Tensor:
    env = factory(worker, num_workers)
    try:
        return env.reset()["heightmap"]
    finally:
        env.close()


def smoke_planner():
    """The LDM agent's planner with the tiny networks of experiment=smoke (random weights, seeded)."""
    from hydra import compose, initialize_config_dir

    from ldm_rl.agents import build_agent

    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose(config_name="train_policy", overrides=["experiment=smoke"])
    torch.manual_seed(0)
    return build_agent(cfg, float(cfg.env.max_height)).policy


# ------------------------------------------------------------------------------------------ fast


@pytest.mark.parametrize("cfg, message", [
    ({"num_workers": 0}, "collector.num_workers must be a positive int, got 0"),
    ({"frames_per_worker": 1.5}, "collector.frames_per_worker must be a positive int, got 1.5"),
    ({"backend": "ray"}, "collector.backend must be one of ('process', 'distributed'), got 'ray'"),
    ({"launcher": "k8s"}, "collector.launcher must be one of ('mp', 'submitit'), got 'k8s'"),
    ({"workers": 2}, "collector settings ['workers'] are unknown"),
    ({"backend": "distributed", "sync": False}, "collector.sync=false needs collector.backend=process"),
])
def test_bad_settings_are_one_clear_error_before_anything_starts(cfg, message):
    def factory(worker, num_workers):  # never called: the settings are checked first
        raise AssertionError("the env factory ran")

    with pytest.raises(ValueError) as err:
        make_collector(cfg, factory, StepProbe())
    assert message in str(err.value) and "\n" not in str(err.value)


def test_episode_assembler_keeps_interleaved_workers_apart():
    def step(worker, traj, t, done):
        return TensorDict({"obs": torch.tensor([10.0 * worker + t]), "collector": {"worker": torch.tensor(worker),
                           "traj_ids": torch.tensor(traj)}, "next": {"done": torch.tensor([done])}}, batch_size=[])

    assembler = EpisodeAssembler(["obs", ("next", "done")])
    stream = [step(0, 0, 0, False), step(1, 0, 0, False), step(0, 0, 1, False), step(1, 0, 1, True),
              step(0, 0, 2, True), step(1, 1, 0, False)]  # the distributed collector may give two workers traj 0
    finished = [ep for ep in map(assembler.add, stream) if ep is not None]
    assert [ep["obs"].view(-1).tolist() for ep in finished] == [[10.0, 11.0], [0.0, 1.0, 2.0]]
    assert all(ep.batch_size == (len(ep["obs"]),) and set(ep.keys()) == {"obs", "next"} for ep in finished)
    assert [ep["next", "done"].view(-1).tolist() for ep in finished][1] == [False, False, True]
    assert assembler.open_frames == 1
    with pytest.raises(ValueError, match=r"one transition \(batch size \[\]\)"):
        assembler.add(torch.stack([stream[0], stream[1]]))


def test_task_env_factory_gives_each_worker_its_own_scene_stream():
    factory = TaskEnvFactory(ENV_CFG, reset_seed=7 * SEED_BLOCK)
    single, w0, w1 = first_scene(factory, 0, 1), first_scene(factory, 0, 2), first_scene(factory, 1, 2)
    assert torch.equal(single, w0) and not torch.equal(w0, w1)
    # worker 1 of 2 starts half a seed block further: the scene of a single env seeded there
    assert torch.equal(w1, first_scene(TaskEnvFactory(ENV_CFG, reset_seed=7 * SEED_BLOCK + SEED_BLOCK // 2), 0, 1))
    resumed = TaskEnvFactory(ENV_CFG, reset_seed=7 * SEED_BLOCK, start_episode=5)
    assert torch.equal(first_scene(resumed, 0, 1), first_scene(TaskEnvFactory(ENV_CFG, reset_seed=7 * SEED_BLOCK + 5), 0, 1))
    with pytest.raises(ValueError, match=r"worker must be in \[0, 2\), got 2"):
        factory(2, 2)
    assert worker_seed(0, 0) != worker_seed(0, 1) != worker_seed(1, 0) and worker_seed(3, 1) == worker_seed(3, 1)


def test_one_worker_is_the_in_process_collector_running_the_policy_itself():
    from torchrl.collectors import Collector, MultiCollector

    probe = StepProbe()
    collector = make_collector({"num_workers": 1}, TaskEnvFactory(ENV_CFG, reset_seed=0), probe)
    try:
        assert isinstance(collector, Collector) and not isinstance(collector, MultiCollector)
        steps = collected_steps(collector)
        first = next(steps)
        with torch.no_grad():
            probe.weight.fill_(5.0)
        probe.step = 4
        second = next(steps)  # same object: no refresh needed
        assert first["probe_weight"].item() == 0.0 and second["probe_weight"].item() == 5.0
        assert second["probe_step"].item() == 4 and second["collector", "worker"].item() == 0
    finally:
        shutdown_collector(collector)


# ------------------------------------------------------------------------------- worker processes


@pytest.mark.slow
def test_two_workers_get_new_weights_and_step_one_thread_and_own_seeds():
    threads = torch.get_num_threads()
    probe = StepProbe()
    factory = TaskEnvFactory(ENV_CFG, reset_seed=3 * SEED_BLOCK)
    collector = make_collector({"num_workers": 2}, factory, probe, seed=3)
    try:
        assert torch.get_num_threads() == threads  # the training process keeps its threads
        steps = collected_steps(collector)
        first = [next(steps), next(steps)]  # one batch: one step of each worker
        with torch.no_grad():
            probe.weight.fill_(2.0)
        probe.step = 9
        second = [next(steps), next(steps)]  # after the refresh between the batches
    finally:
        shutdown_collector(collector)
    assert torch.get_num_threads() == threads
    assert [s["collector", "worker"].item() for s in first + second] == [0, 1, 0, 1]
    assert [s["probe_weight"].item() for s in first] == [0.0, 0.0] and [s["probe_weight"].item() for s in second] == [2.0, 2.0]
    assert [s["probe_step"].item() for s in first] == [0, 0] and [s["probe_step"].item() for s in second] == [9, 9]
    assert all(s["probe_threads"].item() == 1 for s in first + second)
    assert first[0]["probe_draw"].item() != first[1]["probe_draw"].item()  # each worker its own torch seed
    for w in (0, 1):  # each worker its own scene stream
        assert torch.equal(first[w]["heightmap"], first_scene(factory, w, 2))


@pytest.mark.slow
def test_two_worker_train_policy_runs_are_seeded_and_reproducible(tmp_path):
    """recipes/train_policy.py with collector.num_workers=2, twice: the same weights; episodes of both
    workers reach the replay whole."""
    from ldm_rl.run.checkpoint import load_checkpoint

    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg", "RL_WARNINGS": "0"}
    tiny = ["experiment=smoke", "collector.num_workers=2", "env.max_steps=4", "schedule.total_episodes=4",
            "schedule.expert_episodes=1", "schedule.eval_every=100", "schedule.final_eval_episodes=1", "logger=none"]
    states = []
    for name in ("a", "b"):
        proc = subprocess.run([sys.executable, str(ROOT / "recipes" / "train_policy.py"), *tiny,
                               f"hydra.run.dir={tmp_path / name}"], capture_output=True, text=True, env=env,
                              cwd=tmp_path, timeout=900)
        assert proc.returncode == 0, proc.stderr[-3000:]
        states.append(load_checkpoint(tmp_path / name / "checkpoint.pt").state)
    a, b = states
    assert a["counters"] == b["counters"] and a["counters"]["episodes"] >= 4
    assert all(torch.equal(a["agent"][k], b["agent"][k]) for k in a["agent"])
    final = json.loads((tmp_path / "a" / "final_metrics.json").read_text())
    assert final["episodes"] == a["counters"]["episodes"] and final["env_steps"] == a["counters"]["env_steps"]
    assert final["env_steps"] <= 4 * final["episodes"] + 2 * 4  # whole episodes, plus at most one open per worker


# ------------------------------------------------------------------------------------ distributed


@pytest.mark.slow
def test_distributed_collector_on_localhost_refreshes_worker_weights():
    """TorchRL's DistributedCollector (torch.distributed, gloo) with two collectors started as local
    processes (launcher=mp): batches [2, 1], and new weights and schedule step reach both workers."""
    probe = StepProbe()
    factory = TaskEnvFactory(ENV_CFG, reset_seed=5 * SEED_BLOCK)
    cfg = {"num_workers": 2, "backend": "distributed", "launcher": "mp", "tcp_port": free_port()}
    collector = make_collector(cfg, factory, probe, seed=5)
    try:
        assert type(collector).__name__ == "DistributedCollector"
        steps = collected_steps(collector)
        first = [next(steps), next(steps)]
        with torch.no_grad():
            probe.weight.fill_(3.0)
        probe.step = 7
        second = [next(steps), next(steps)]
    finally:
        shutdown_collector(collector)
    assert [s["collector", "worker"].item() for s in first + second] == [0, 1, 0, 1]
    assert [s["probe_weight"].item() for s in second] == [3.0, 3.0] and [s["probe_step"].item() for s in second] == [7, 7]
    assert all(s["probe_threads"].item() == 1 for s in first + second)
    for w in (0, 1):
        assert torch.equal(first[w]["heightmap"], first_scene(factory, w, 2))


@pytest.mark.slow
def test_distributed_collector_through_submitit_runs_the_ldm_planner(tmp_path, monkeypatch):
    """The multi-machine path: DistributedCollector with launcher=submitit (a SLURM job per worker on a
    cluster; submitit runs the job locally here, where there is no SLURM), one worker, a few frames."""
    pytest.importorskip("submitit", reason="submitit is not installed (pip install 'ldm_rl[sweep]')")
    monkeypatch.chdir(tmp_path)  # TorchRL writes submitit's logs to ./log_test
    planner = smoke_planner()
    cfg = {"num_workers": 1, "backend": "distributed", "launcher": "submitit", "tcp_port": free_port(),
           "slurm": {"timeout_min": 10}}
    collector = make_collector(cfg, TaskEnvFactory(ENV_CFG, reset_seed=0), planner, seed=0)
    try:
        steps = collected_steps(collector)
        frames = [next(steps) for _ in range(3)]
    finally:
        shutdown_collector(collector)
    actions = torch.stack([f["action"] for f in frames])
    assert actions.shape == (3, 3) and (actions[:, :2] >= 0).all() and (actions[:, :2] < 128).all()
    assert (actions[:, 2] < 8).all() and all(f["candidate_values"].shape == (3,) for f in frames)
    assert any((tmp_path / "log_test").glob("*_log.out"))  # submitit ran the worker as a job
