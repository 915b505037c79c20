"""Target networks equal their source after every copy, BatchNorm statistics included, for every agent."""

from __future__ import annotations

import pytest
import torch
from torchrl.objectives import HardUpdate

from ldm_rl.agents.base import is_target_entry
from ldm_rl.objectives import LookaheadLoss, TargetSync
from ldm_rl.torch_utils import eval_mode, swapped_parameters
from policy_helpers import tiny_networks, transitions
from test_baselines import batch, make_agent

AGENT_NAMES = ("ldm", "fcdqn", "rs", "dynaq")


def _outputs(module: torch.nn.Module, probe) -> list[torch.Tensor]:
    """Eval-mode outputs of a Q network, a V network or an LDM on fixed states (and actions)."""
    with torch.no_grad(), eval_mode(module):
        if hasattr(module, "predict"):  # the LDM: next heightmap, in-hand image and hand state
            pred = module.predict(probe["heightmap"], probe["in_hand"], probe["holding"], probe["action"])
            return [pred.heightmap, pred.in_hand, pred.holding]
        if hasattr(module, "action_values"):
            return [module(probe["heightmap"], probe["in_hand"], probe["holding"])]
        return [module(probe["heightmap"], probe["in_hand"])]


def _online_and_target(loss) -> dict[str, tuple[list[torch.Tensor], list[torch.Tensor]]]:
    """network name -> (online outputs, target outputs) for every target network of ``loss``."""
    probe = transitions(6, seed=7)
    out = {}
    for name, _ in loss.named_children():
        if not (name.startswith("target_") and name.endswith("_params")):
            continue
        network = name[len("target_"):-len("_params")]
        module = getattr(loss, network)
        online = _outputs(module, probe)
        with swapped_parameters(module, getattr(loss, name)):
            target = _outputs(module, probe)
        out[network] = (online, target)
    return out


def _assert_targets_equal(loss) -> None:
    pairs = _online_and_target(loss)
    assert pairs
    for network, (online, target) in pairs.items():
        for a, b in zip(online, target):
            assert torch.equal(a, b), f"target {network} differs from its source"


@pytest.mark.parametrize("name", AGENT_NAMES)
def test_targets_equal_their_source_after_pretraining_and_a_sync(name):
    agent = make_agent(name)
    for seed in range(3):  # model-only updates move the LDM's weights and BatchNorm statistics
        agent.pretrain_update(batch(4, seed))
    agent.sync_targets()
    _assert_targets_equal(agent.loss)


@pytest.mark.parametrize("name", AGENT_NAMES)
def test_targets_equal_their_source_after_every_periodic_copy(name):
    agent = make_agent(name, "agent.target_update_interval=2")
    agent.update(batch(4, 0))
    if name != "fcdqn":  # the first update moved the LDM's BatchNorm statistics (FC-DQN has no LDM)
        with pytest.raises(AssertionError, match="differs"):
            _assert_targets_equal(agent.loss)
    agent.update(batch(4, 1))  # the second update ends with a copy
    _assert_targets_equal(agent.loss)


def test_the_ldm_agent_target_model_carries_the_batchnorm_statistics():
    agent = make_agent("ldm")
    for seed in range(3):
        agent.pretrain_update(batch(4, seed))
    stale = _online_and_target(agent.loss)["dynamics"]
    assert not torch.equal(stale[0][0], stale[1][0])  # without a copy the target predicts differently
    agent.sync_targets()
    loss = agent.loss
    for key, value in loss.dynamics_params.items(True, True):
        if "running" in "".join(map(str, key)):
            assert torch.equal(loss.target_dynamics_params.get(key), value)


def test_torchrl_hard_update_alone_leaves_the_batchnorm_statistics_behind():
    """Why TargetSync exists: TorchRL's HardUpdate copies only what requires grad."""
    q, dynamics, value = tiny_networks()
    loss = LookaheadLoss(q, dynamics, value)
    updater = HardUpdate(loss, value_network_update_interval=0)  # copies at every step()
    with torch.no_grad():  # what a train-mode pass does to the running statistics
        for m in dynamics.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.add_(0.5)
    updater.step()
    with pytest.raises(AssertionError, match="differs"):
        _assert_targets_equal(loss)
    TargetSync(loss, interval=1).sync()
    _assert_targets_equal(loss)


def test_sync_tells_the_loss_and_step_copies_every_interval():
    q, dynamics, value = tiny_networks()

    class Loss(LookaheadLoss):
        changes = 0

        def targets_changed(self):
            type(self).changes += 1

    loss = Loss(q, dynamics, value)
    updater = TargetSync(loss, interval=3)
    for _ in range(7):
        updater.step()
    assert Loss.changes == 2  # at the 3rd and 6th step
    updater.sync()
    assert Loss.changes == 3 and updater.counter == 1


@pytest.mark.parametrize("interval", [0, -1, 1.5, True, None])
def test_bad_interval(interval):
    q, dynamics, value = tiny_networks()
    with pytest.raises(ValueError, match="interval must be a positive int"):
        TargetSync(LookaheadLoss(q, dynamics, value), interval=interval)


def test_the_ldm_agent_caches_bootstraps_until_a_copy_or_a_checkpoint():
    agent = make_agent("ldm", "agent.target_update_interval=2")
    data = batch(4, 0)
    data["index"] = torch.arange(4)
    agent.loss.targets(data)
    assert len(agent.loss.bootstrap_cache) > 0
    agent.drop_caches()  # what the recipe does at each checkpoint
    assert len(agent.loss.bootstrap_cache) == 0
    agent.update(data.clone())
    assert len(agent.loss.bootstrap_cache) > 0
    agent.update(data.clone())  # ends with a target copy
    assert len(agent.loss.bootstrap_cache) == 0


@pytest.mark.parametrize("name", AGENT_NAMES)
def test_policy_state_holds_no_target_copies_and_loads_with_synced_targets(name):
    trained = make_agent(name)
    for seed in range(2):
        trained.pretrain_update(batch(4, seed))
    policy_state = trained.policy_state_dict()
    assert not any(is_target_entry(key) for key in policy_state)
    assert len(policy_state) < len(trained.state_dict())
    fresh = make_agent(name)
    fresh.load_policy_state_dict(policy_state)
    for key, value in trained.policy_state_dict().items():  # the online networks, buffers included
        assert torch.equal(fresh.state_dict()[key], value), key
    _assert_targets_equal(fresh.loss)  # the targets re-created from the loaded online networks


def test_full_state_dicts_still_load_and_a_foreign_key_is_refused():
    trained, fresh = make_agent("ldm"), make_agent("ldm")
    trained.pretrain_update(batch(4, 0))
    fresh.load_policy_state_dict(trained.state_dict())  # checkpoints written before policy_state_dict existed
    assert all(torch.equal(fresh.state_dict()[k], v) for k, v in trained.state_dict().items())
    with pytest.raises(RuntimeError, match="unexpected"):
        fresh.load_policy_state_dict({**trained.policy_state_dict(), "planner.bogus": torch.zeros(1)})


@pytest.mark.parametrize("name", AGENT_NAMES)
def test_a_second_signal_inside_the_targets_exits_with_its_code_and_the_online_weights_back(name, monkeypatch):
    """A SystemExit raised while the target weights are swapped in (the second SIGTERM of a stopping run) leaves
    as itself, not as tensordict's "Converting a tensordict to boolean value", and the online weights return."""
    loss = make_agent(name).loss
    # the first network each target computation runs: RS predicts with the LDM, the others start with Q
    network_name, method = ("dynamics", "predict") if name == "rs" else ("q_network", "forward")
    network, target_params = getattr(loss, network_name), getattr(loss, f"target_{network_name}_params")
    first_name = next(iter(dict(network.named_parameters())))
    online_first = network.get_parameter(first_name)
    target_first = target_params.get(tuple(first_name.split(".")))
    seen = []

    def stopped(*args, **kwargs):
        current = network
        for part in first_name.split("."):
            current = getattr(current, part)
        seen.append(current.data_ptr() == target_first.data_ptr())
        raise SystemExit(143)

    monkeypatch.setattr(network, method, stopped)
    with pytest.raises(SystemExit) as stop:
        loss.targets(batch(4, 0))
    assert stop.value.code == 143
    assert seen == [True]  # it was raised with the target weights in the network
    assert network.get_parameter(first_name) is online_first
    assert target_params.get(tuple(first_name.split("."))) is target_first
