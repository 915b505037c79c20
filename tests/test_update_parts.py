"""benchmarks/update_parts.py: the split times the terms the agent's options switch on, and trains nothing."""

from __future__ import annotations

from collections import defaultdict

import pytest
import torch

from benchmark_loader import load_benchmark

pytestmark = pytest.mark.filterwarnings("ignore:No target network updater has been associated:UserWarning")

BASE = {"LDM loss: forward", "LDM loss: backward", "targets (target networks)", "Q TD term: forward", "Q TD term: backward"}
OPTIONS = {"Q on its proposals: forward", "Q on its proposals: backward", "Q expert margin: forward",
           "Q expert margin: backward", "V expert margin: forward", "V expert margin: backward"}


@pytest.mark.parametrize("overrides, terms", [
    ((), BASE),
    (("agent.q_proposal_fit=1", "agent.expert_margin_weight=0.5", "agent.value_margin_weight=0.5"), BASE | OPTIONS),
])
def test_the_split_times_each_term_the_agent_has_and_leaves_its_weights_as_they_were(overrides, terms):
    from test_baselines import batch, make_agent

    bench = load_benchmark("update_parts")
    agent = make_agent("ldm", *overrides)
    data = batch(4)
    data["is_expert"] = torch.tensor([True, False, True, False])
    before = {name: p.detach().clone() for name, p in agent.loss.named_parameters()}
    spent: dict[str, float] = defaultdict(float)
    bench.split_update(agent, data, spent)
    assert set(spent) == terms and all(seconds > 0 for seconds in spent.values())
    for name, p in agent.loss.named_parameters():
        assert torch.equal(p, before[name]), name  # timed, not trained
        assert p.grad is None, name  # each term's gradients cleared
