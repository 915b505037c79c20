"""Run-time helpers: atomic files, devices, seeding, loggers, and the light package import."""

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from ldm_rl import torch_utils
from ldm_rl.run import outputs


def test_atomic_path_leaves_nothing_behind_on_failure(tmp_path):
    target = tmp_path / "ckpt.pt"
    with pytest.raises(RuntimeError, match="boom"):
        with outputs.atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_atomic_torch_save_replaces_whole_files(tmp_path):
    target = tmp_path / "sub" / "ckpt.pt"
    outputs.atomic_torch_save({"a": torch.ones(2)}, target)
    outputs.atomic_torch_save({"a": torch.zeros(3)}, target)
    assert torch.equal(torch.load(target)["a"], torch.zeros(3))
    assert sorted(p.name for p in target.parent.iterdir()) == ["ckpt.pt"]


def test_atomic_path_replaces_directories(tmp_path):
    target = tmp_path / "demos"
    for payload in ("old", "new"):
        with outputs.atomic_path(target) as tmp:
            tmp.mkdir()
            (tmp / "x.txt").write_text(payload)
    assert (target / "x.txt").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demos"]


def test_resolve_device():
    assert torch_utils.resolve_device("cpu") == torch.device("cpu")
    assert torch_utils.resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="device must be"):
        torch_utils.resolve_device("gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA"):
            torch_utils.resolve_device("cuda")


def test_seed_everything_is_reproducible_and_validated():
    torch_utils.seed_everything(7)
    a = torch.rand(3)
    gen = torch_utils.seed_everything(7)
    assert torch.equal(a, torch.rand(3))
    assert torch.equal(torch.rand(2, generator=gen), torch.rand(2, generator=torch.Generator().manual_seed(7)))
    with pytest.raises(ValueError, match="seed"):
        torch_utils.seed_everything(-1)
    with pytest.raises(ValueError, match="threads"):
        torch_utils.set_threads(0)


def test_csv_logger_writes_scalars(tmp_path):
    logger = outputs.make_logger({"backend": "csv", "exp_name": "run"}, tmp_path)
    logger.log_scalar("l1_mm", 1.5, step=3)
    files = list(tmp_path.rglob("l1_mm.csv"))
    assert len(files) == 1 and "1.5" in files[0].read_text()
    assert outputs.make_logger({"backend": "none"}, tmp_path) is None
    with pytest.raises(ValueError, match="logger.backend"):
        outputs.make_logger({"backend": "wandb2"}, tmp_path)


def test_importing_ldm_rl_stays_light():
    code = (
        "import sys, ldm_rl, ldm_rl.geometry, ldm_rl.torch_utils, ldm_rl.run.outputs; "
        "heavy = [m for m in ('torchrl', 'pybullet', 'tensordict', 'hydra', 'cv2') if m in sys.modules]; "
        "assert not heavy, heavy"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_make_adam_is_fused_adam_with_the_same_update_rule_and_every_agent_uses_it():
    from hydra import compose, initialize_config_dir

    from ldm_rl.agents import build_agent

    torch.manual_seed(0)
    params = [torch.randn(5, 3, requires_grad=True), torch.randn(7, requires_grad=True)]
    twins = [p.detach().clone().requires_grad_(True) for p in params]
    fused = torch_utils.make_adam(params, lr=1e-2, weight_decay=1e-3)
    plain = torch.optim.Adam(twins, lr=1e-2, weight_decay=1e-3)
    assert fused.defaults["fused"] is True and fused.defaults["lr"] == 1e-2
    for step in range(3):
        for group in (params, twins):
            for p in group:
                p.grad = torch.full_like(p, 0.1 * (step + 1)) + p.detach()
        fused.step()
        plain.step()
    for a, b in zip(params, twins):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)  # the same rule; only the last bits may differ
    with pytest.raises(ValueError, match="learning rate"):
        torch_utils.make_adam(params, lr=-1.0)
    conf = str(Path(__file__).resolve().parents[1] / "conf")
    for name in ("ldm", "fcdqn", "rs", "dynaq"):
        with initialize_config_dir(version_base="1.3", config_dir=conf):
            cfg = compose(config_name="train_policy", overrides=["experiment=smoke", f"agent={name}"])
        agent = build_agent(cfg, 0.25)
        assert agent.optimizers and all(opt.defaults["fused"] is True for opt in agent.optimizers.values()), name


@pytest.mark.parametrize("raised", [ValueError("bad batch"), SystemExit(143)])
def test_swapped_parameters_gives_the_module_its_weights_back_however_the_block_ends(raised):
    from tensordict import TensorDict

    net = torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.BatchNorm1d(2))
    own = net[0].weight
    other = TensorDict.from_module(net).data.clone()
    other["0", "weight"].fill_(3.0)
    x = torch.ones(1, 2)
    with torch_utils.swapped_parameters(net, other):
        assert torch.equal(net[0](x), torch.full((1, 2), 6.0) + net[0].bias)  # the other weights are in use
    assert net[0].weight is own
    with pytest.raises(type(raised)):
        with torch_utils.swapped_parameters(net, other):
            raise raised
    assert net[0].weight is own and isinstance(net[0].weight, torch.nn.Parameter)
    assert net[1].running_var is not other["1", "running_var"]
