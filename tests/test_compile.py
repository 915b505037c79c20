"""Compiled inference (``compile=true``, ldm_rl/models/compile.py): the same targets and decisions as eager
passes, training passes never compiled, nothing compiled in a module's pickled or copied state."""

import copy
import pickle
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from torchrl.envs.utils import ExplorationType, set_exploration_type

from ldm_rl.agents import build_agent
from ldm_rl.data.replay import FrameReplay
from ldm_rl.models import DepthUNet
from ldm_rl.models.compile import compile_inference
from ldm_rl.torch_utils import seed_everything

ROOT = Path(__file__).resolve().parents[1]


def _unet():
    torch.manual_seed(0)
    return compile_inference(DepthUNet(in_channels=6, num_classes=3, width=0.125))


def test_training_passes_and_passes_with_gradients_stay_eager():
    net = _unet()
    x = torch.randn(2, 6, 16, 16)
    net.train()
    with torch.no_grad():
        net(x)
    net.eval()
    net(x).sum().backward()  # eval mode but with gradients: eager
    assert "_compiled_fn" not in net.__dict__


def test_the_compiled_function_is_never_pickled_or_copied():
    net = _unet()
    net.__dict__["_compiled_fn"] = lambda x: x  # stands for torch.compile's (unpicklable) callable
    for clone in (copy.deepcopy(net), pickle.loads(pickle.dumps(net))):
        assert "_compiled_fn" not in clone.__dict__ and clone._compile_inference
    compile_inference(net, False)
    assert "_compiled_fn" not in net.__dict__ and not net._compile_inference
    with pytest.raises(ValueError, match="enabled must be a bool"):
        compile_inference(net, "yes")
    with pytest.raises(ValueError, match="module must be a torch.nn.Module, got dict"):
        compile_inference({"q": net})


@pytest.mark.slow
def test_compiled_targets_and_decisions_equal_the_eager_ones(monkeypatch):
    """stacking_lite's LDM agent: the lookahead targets (target networks swapped in by TorchRL's to_module,
    here different from the online ones) and a greedy decision, eager then compiled. Compiled here with the
    ``aot_eager`` backend: TorchDynamo's graph capture (parameters as graph inputs, so the swap reuses a graph,
    and its guards) and AOTAutograd, what this code relies on, without inductor's C++ code generation, which
    took 6 min of a 2-core CI machine's suite for these two networks (and 4.5 min for one tiny U-Net)."""
    import functools

    monkeypatch.setattr(torch, "compile", functools.partial(torch.compile, backend="aot_eager"))
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="train_policy", overrides=["experiment=stacking_lite", "agent.bootstrap_cache=0"])
    seed_everything(0)
    max_height = float(cfg.env.max_height)
    agent = build_agent(cfg, max_height)
    generator = torch.Generator().manual_seed(0)
    replay = FrameReplay(64, max_height=max_height, batch_size=8, return_gamma=float(cfg.agent.gamma))
    steps = 6
    heights = torch.rand(steps + 1, 1, 128, 128, generator=generator) * 0.05
    heights[:, :, 40:60, 40:60] += 0.03  # a block to pick
    hands = torch.rand(steps + 1, 1, 24, 24, generator=generator) * 0.03
    from tensordict import TensorDict

    episode = TensorDict({
        "heightmap": heights[:-1], "in_hand": hands[:-1], "holding": torch.arange(steps).remainder(2).bool().view(-1, 1),
        "action": torch.randint(0, 128, (steps, 3), generator=generator).remainder(torch.tensor([128, 128, 8])),
        "next": {"heightmap": heights[1:], "in_hand": hands[1:],
                 "holding": torch.arange(1, steps + 1).remainder(2).bool().view(-1, 1),
                 "reward": torch.zeros(steps, 1), "terminated": torch.zeros(steps, 1, dtype=torch.bool),
                 "truncated": torch.zeros(steps, 1, dtype=torch.bool), "done": torch.zeros(steps, 1, dtype=torch.bool)},
    }, batch_size=[steps])
    episode["next", "done"][-1] = True
    episode["next", "truncated"][-1] = True
    replay.extend_episode(episode, expert=True)
    batch = replay.sample()
    agent.sync_targets()
    with torch.no_grad():  # online != target from here on
        for p in agent.planner.q_network.parameters():
            p.mul_(1.1)
        for p in agent.planner.dynamics.parameters():
            p.mul_(0.9)
    state = batch[:1].select("heightmap", "in_hand", "holding")
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        eager = agent.loss.targets(batch), agent.policy(state.clone())["action"]
        compile_inference(agent)
        compiled = agent.loss.targets(batch), agent.policy(state.clone())["action"]
    assert {type(m).__name__ for m in agent.modules() if "_compiled_fn" in m.__dict__} == {"QFCN", "DepthUNet"}
    for e, c in zip(eager[0], compiled[0]):
        torch.testing.assert_close(c, e, rtol=1e-5, atol=1e-5)
    assert torch.equal(compiled[1], eager[1])

