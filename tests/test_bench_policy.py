"""benchmarks/bench_policy.py --training-step: each agent's env step split into the phases that agent has."""

from __future__ import annotations

import pytest

from benchmark_loader import load_benchmark

TINY = ["model.width=0.0625", "agent.q_width=0.125", "agent.value_width=0.125", "agent.num_target_candidates=2",
        "planner.num_candidates=3", "replay.capacity=400", "replay.batch_size=4", "schedule.expert_episodes=2",
        "schedule.pretrain_updates=1"]


@pytest.mark.filterwarnings("ignore:Seems like `optimizer.step")  # the phase timers wrap each optimiser's step
@pytest.mark.parametrize("agent", ["ldm", "fcdqn", "rs", "dynaq"])
def test_training_steps_times_the_phases_each_agent_has(agent):
    bench = load_benchmark("bench_policy")
    result = bench.training_steps([f"agent={agent}", *TINY], steps=2, warmup=1)
    assert result["total"] > 0 and set(bench.PHASES) <= set(result)
    assert (result["imagine"] > 0) == (agent == "dynaq")  # only Dyna-Q imagines transitions
    assert (result["ldm loss"] > 0) == (agent != "fcdqn")  # FC-DQN trains no world model
    assert result["targets"] > 0 and result["backward"] > 0 and result["act"] > 0
