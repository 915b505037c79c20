"""The equivariant Q network (agent.q_architecture=equivariant, ldm_rl/models/equivariant_q.py): it commutes with
quarter turns of the scene (both heads, to float tolerance), a group step of π/R shifts the bins by one (up to
the pixel grid's interpolation error), QFCN's interface and masks, selection by config (default unchanged),
the one-line error without e2cnn, and a seeded smoke run of recipes/train_policy.py."""

from __future__ import annotations

import copy
import json
import math
import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from ldm_rl import geometry as g
from ldm_rl.config_schema import AgentConfig, ConfigError, TrainPolicyConfig, validate_config
from ldm_rl.extras import MissingExtraError
from ldm_rl.models.blocks import count_parameters
from ldm_rl.models.equivariant_q import EquivariantQFCN
from ldm_rl.models.q_fcn import Q_ARCHITECTURES, QFCN, build_q_network
from policy_helpers import q_states, quarter_turn_maps

ROOT = Path(__file__).resolve().parents[1]
MAX_HEIGHT = 0.15
TINY = 0.125  # width of the networks here


@pytest.fixture(autouse=True)
def one_torch_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def tiny_eq(num_rotations: int = 8, seed: int = 0, **kwargs) -> EquivariantQFCN:
    torch.manual_seed(seed)
    return build_q_network("lite", max_height=MAX_HEIGHT, num_rotations=num_rotations, width=TINY,
                           architecture="equivariant", **kwargs)


def states(n: int, seed: int = 0):
    return q_states(n, seed, max_layers=3)


def finite(t: torch.Tensor) -> torch.Tensor:
    return t.nan_to_num(neginf=-1e30)  # a finite sentinel that geometry.rotate carries exactly


# --------------------------------------------------------------------------------------------
# equivariance
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("num_rotations, grad", [(8, False), (8, True), (6, False)])
def test_q_maps_commute_with_quarter_turns_of_the_scene(num_rotations, grad):
    """Scene +90° <=> map +90° with the bin shifted by R/2 (and −90°), both heads, to float tolerance; the -inf
    pattern bit for bit. A plain CNN (or QFCN's weights without its rotations) fails this."""
    half = num_rotations // 2
    maps, plus, minus = quarter_turn_maps(tiny_eq(num_rotations), grad, max_layers=3)
    maps, plus, minus = (finite(t.detach()) for t in (maps, plus, minus))
    scale = maps[maps > -1e29].abs().max()
    for got, want in ((plus[:, :half], g.rotate(maps[:, half:], math.pi / 2)),
                      (plus[:, half:], g.rotate(maps[:, :half], math.pi / 2)),
                      (minus[:, half:], g.rotate(maps[:, :half], -math.pi / 2))):
        assert torch.equal(got <= -1e29, want <= -1e29)
        torch.testing.assert_close(got, want, rtol=0, atol=1e-5 * float(scale))
    # not vacuous: the bins differ, the pick (even rows) and place (odd rows) maps differ, a turn without the
    # bin shift is no match
    assert not torch.allclose(maps[:, 0], maps[:, 1], atol=1e-3 * float(scale))
    assert not torch.allclose(maps[0::2], maps[1::2], atol=1e-3 * float(scale))
    assert (plus[:, :half] - g.rotate(maps[:, :half], math.pi / 2)).abs().max() > 1e-2 * scale


def test_place_maps_read_the_in_hand_image_and_stay_equivariant_for_each_hand():
    q = tiny_eq()
    scene, in_hand, _ = states(2, seed=2)
    holding = torch.ones(2, dtype=torch.bool)
    with torch.no_grad():
        a = q(scene, in_hand, holding)
        b = q(scene, in_hand.flip(-1) * 0.5, holding)
        turned = q(g.rotate(scene, math.pi / 2), in_hand.flip(-1) * 0.5, holding)
    assert (finite(a) - finite(b)).abs().max() > 1e-4  # the hand changes the place map
    torch.testing.assert_close(finite(turned[:, :4]), g.rotate(finite(b[:, 4:]), math.pi / 2), rtol=0, atol=1e-5)
    pick = q(scene, in_hand, torch.zeros(2, dtype=torch.bool)).detach()
    with torch.no_grad():
        assert torch.equal(pick, q(scene, in_hand * 0.3, torch.zeros(2, dtype=torch.bool)))  # pick ignores the hand


def smooth_scenes(n: int, seed: int = 0) -> torch.Tensor:
    """[n, 1, 128, 128] m: four Gaussian mounds (σ 6 px, 6 cm) near the centre: few pixel-scale edges."""
    gen = torch.Generator().manual_seed(seed)
    rows, cols = torch.meshgrid(torch.arange(128.0), torch.arange(128.0), indexing="ij")
    centres = torch.rand(n, 4, 2, generator=gen) * 60 + 34
    d2 = (rows - centres[..., 0, None, None]) ** 2 + (cols - centres[..., 1, None, None]) ** 2  # [n, 4, H, W]
    return (0.06 * torch.exp(-d2 / (2 * 6.0**2))).sum(1, keepdim=True)


def test_one_group_step_shifts_the_bins_by_one_up_to_the_grids_interpolation_error():
    """C_2R also holds at θ = π/R (R = 8: 22.5°), but no pixel grid rotates exactly by it: the scene and the maps
    are resampled, and each 3×3 layer and 2×2 pooling adds interpolation error. On smooth mounds (256 depth
    classes, bilinear) the turned scene's bin k matches bin k + 1 within ~20 % (relative to the maps'
    spread, in a central disk) while the other shifts miss by ~100 %: the direction of the bin convention
    (θ_k = k·π/R, geometry.rotate) is the one QFCN and the LDM use. Untrained, on 21-class block scenes the
    error is ~60 %: a tight bound at non-quarter angles is not feasible on a pixel grid."""
    torch.manual_seed(0)
    q = EquivariantQFCN(MAX_HEIGHT, 256, 8, TINY)
    scene = smooth_scenes(4, seed=3)
    in_hand, holding = states(4)[1:]
    with torch.no_grad():
        maps = q(scene, in_hand, holding)
        turned = q(g.rotate(scene, math.pi / 8, mode="bilinear"), in_hand, holding)
    rows, cols = torch.meshgrid(torch.arange(128), torch.arange(128), indexing="ij")
    disk = (rows - 63.5) ** 2 + (cols - 63.5) ** 2 < 40**2
    spread = (turned[..., disk] - turned[..., disk].mean(-1, keepdim=True)).norm()

    def error(shift: int) -> float:
        want = g.rotate(maps.roll(-shift, 1).nan_to_num(neginf=0.0), math.pi / 8, mode="bilinear")
        return float((turned[..., disk] - want[..., disk]).norm() / spread)

    assert torch.isfinite(turned[..., disk]).all()
    assert error(1) < 0.35
    assert error(0) > 0.7 and error(-1) > 0.7 and error(2) > 0.7


# --------------------------------------------------------------------------------------------
# QFCN's interface
# --------------------------------------------------------------------------------------------
def test_pick_min_height_masks_the_same_picks_as_qfcn_and_survives_pickling():
    """With pick_min_height the pick maps are -inf on the same pixels as QFCN's, elsewhere the unmasked net's
    values; place maps untouched; a pickled copy keeps the setting."""
    q, plain = tiny_eq(pick_min_height=0.015), tiny_eq()
    fcn = QFCN(MAX_HEIGHT, 21, 8, TINY, pick_min_height=0.015)
    scene, in_hand, holding = states(4, seed=2)
    holding = torch.tensor([False, False, True, False])
    with torch.no_grad():
        maps, reference, fcn_maps = q(scene, in_hand, holding), plain(scene, in_hand, holding), fcn(scene, in_hand, holding)
    masked = torch.isneginf(maps) & torch.isfinite(reference)
    assert masked[~holding].any() and not masked[holding].any()
    assert torch.equal(torch.isneginf(maps), torch.isneginf(fcn_maps))
    assert torch.equal(maps[~masked], reference[~masked])
    assert pickle.loads(pickle.dumps(q)).pick_min_height == 0.015


def test_shapes_masks_and_action_values_match_qfcn():
    """[*B, R, 128, 128] maps, -inf exactly where QFCN's are (frame margin included), action_values = the map's
    entry (0 where -inf), a mixed batch = each sample alone; the same input errors."""
    q, fcn = tiny_eq(frame_margin=6), QFCN(MAX_HEIGHT, 21, 8, TINY, frame_margin=6)
    scene, in_hand, holding = states(6, seed=4)
    batch = (2, 3)
    scene, in_hand, holding = scene.view(*batch, 1, 128, 128), in_hand.view(*batch, 1, 24, 24), holding.view(*batch, 1)
    with torch.no_grad():
        maps, reference = q(scene, in_hand, holding), fcn(scene, in_hand, holding)
        alone = torch.cat([q(scene[i, j:j + 1], in_hand[i, j:j + 1], holding[i, j:j + 1]) for i in range(2) for j in range(3)])
    assert maps.shape == reference.shape == (*batch, 8, 128, 128) and q.num_rotations == 8
    assert torch.equal(torch.isneginf(maps), torch.isneginf(reference))
    torch.testing.assert_close(finite(maps).flatten(0, 1), finite(alone), rtol=1e-5, atol=1e-5)
    gen = torch.Generator().manual_seed(0)
    action = torch.stack([torch.randint(0, 128, batch, generator=gen), torch.randint(0, 128, batch, generator=gen),
                          torch.randint(0, 8, batch, generator=gen)], -1)
    action[0, 0] = torch.tensor([0, 0, 1])  # a corner at a non-quarter bin: -inf in the map
    values = q.action_values(scene, in_hand, holding, action)
    entries = maps[torch.arange(2)[:, None], torch.arange(3)[None], action[..., 2], action[..., 0], action[..., 1]]
    assert values.shape == batch and torch.isneginf(entries[0, 0]) and values[0, 0] == 0
    torch.testing.assert_close(values[entries > -math.inf], entries[entries > -math.inf], rtol=1e-5, atol=1e-5)
    values.sum().backward()
    grads = {name: p.grad is not None and bool(p.grad.abs().sum() > 0) for name, p in q.named_parameters()}
    assert all(grads.values()), [name for name, ok in grads.items() if not ok]  # both heads and the hand encoder
    with pytest.raises(ValueError, match=r"action must have row, col in \[0, 128\) and rot in \[0, 8\)"):
        q.action_values(scene, in_hand, holding, action + 200)
    with pytest.raises(ValueError, match="holding must be bool"):
        q(scene, in_hand, holding.float())
    with pytest.raises(ValueError, match="num_rotations must be a positive int, got 0"):
        EquivariantQFCN(MAX_HEIGHT, num_rotations=0)
    empty = q(scene[:0, 0], in_hand[:0, 0], holding[:0, 0])
    assert empty.shape == (0, 8, 128, 128)


def test_weights_pickle_and_target_swaps_act_on_every_call():
    """The state dict holds only the basis coefficients; pickling (e2cnn's groups cannot) rebuilds the same
    network (meta weights stay meta: TorchRL's multi-process collectors ship those), deep copies copy it; a
    target-weight swap (TorchRL's ``to_module``) in eval mode takes effect (e2cnn's own eval-mode filter cache
    would keep the old weights)."""
    from tensordict import TensorDict

    q = tiny_eq().eval()
    assert sum(v.numel() for v in q.state_dict().values()) == count_parameters(q)
    scene, in_hand, holding = states(2, seed=5)
    with torch.no_grad():
        before = q(scene, in_hand, holding)
        rng = torch.random.get_rng_state()
        assert torch.equal(pickle.loads(pickle.dumps(q))(scene, in_hand, holding), before)
        assert torch.equal(torch.random.get_rng_state(), rng)  # unpickling draws no initial weights
        assert torch.equal(copy.deepcopy(q)(scene, in_hand, holding), before)
        with TensorDict.from_module(q).data.to("meta").to_module(q):  # what TorchRL's worker processes receive
            worker = pickle.loads(pickle.dumps(q))
        assert all(p.is_meta for p in worker.parameters())
        TensorDict.from_module(q).data.to_module(worker)  # then the weight sync
        assert torch.equal(worker(scene, in_hand, holding), before)
        target = TensorDict.from_module(q).data.clone()
        for p in q.parameters():
            p.add_(0.05)
        after = q(scene, in_hand, holding)
        with target.to_module(q):
            assert torch.equal(q(scene, in_hand, holding), before)
    assert not torch.equal(after, before)


def test_the_lite_network_is_smaller_than_qfcn_lite():
    torch.manual_seed(0)
    eq, fcn = (build_q_network("lite", max_height=MAX_HEIGHT, architecture=a) for a in ("equivariant", "fcn"))
    assert isinstance(eq, EquivariantQFCN) and isinstance(fcn, QFCN)
    assert count_parameters(eq) < count_parameters(fcn) / 5
    assert eq.feature_channels == 16  # one regular C16 field at 128²


# --------------------------------------------------------------------------------------------
# selection by config
# --------------------------------------------------------------------------------------------
def test_the_default_is_qfcn_and_the_choices_are_the_builders():
    field = AgentConfig.__dataclass_fields__["q_architecture"]
    assert field.default == "fcn" and field.metadata["rule"].choices == Q_ARCHITECTURES
    assert isinstance(build_q_network("lite", max_height=MAX_HEIGHT, width=TINY), QFCN)
    with pytest.raises(ValueError, match=r"unknown Q architecture 'steerable'; expected one of \['fcn', 'equivariant'\]"):
        build_q_network("lite", max_height=MAX_HEIGHT, architecture="steerable")
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        for agent in ("ldm", "fcdqn", "dynaq"):
            assert compose("train_policy", overrides=[f"agent={agent}"]).agent.q_architecture == "fcn"
        cfg = compose("train_policy", overrides=["experiment=smoke", "agent=fcdqn", "agent.q_architecture=equivariant"])
        rs = compose("train_policy", overrides=["agent=rs", "agent.q_architecture=equivariant"])
    from ldm_rl.agents import build_agent

    torch.manual_seed(0)
    assert isinstance(build_agent(cfg, MAX_HEIGHT).policy.q_network, EquivariantQFCN)
    with pytest.raises(ConfigError, match="agent.q_architecture=equivariant is set but agent=rs builds no Q network"):
        validate_config(rs, TrainPolicyConfig)


def test_without_e2cnn_selecting_it_is_one_line_naming_the_extra(monkeypatch):
    from ldm_rl.run.cli import machine_problems

    monkeypatch.setitem(sys.modules, "e2cnn", None)  # as if not installed
    monkeypatch.delitem(sys.modules, "ldm_rl.models.equivariant_q")
    message = r"agent.q_architecture=equivariant needs the 'e2cnn' package, which is not installed: .*pip install -e '.\[equivariant\]'"
    with pytest.raises(MissingExtraError, match=message) as caught:
        build_q_network("lite", max_height=MAX_HEIGHT, architecture="equivariant")
    assert "\n" not in str(caught.value)
    problems = machine_problems(OmegaConf.create({"agent": {"q_architecture": "equivariant"}}))
    assert len(problems) == 1 and "pip install -e '.[equivariant]'" in problems[0]
    assert machine_problems(OmegaConf.create({"agent": {"q_architecture": "fcn"}})) == []


@pytest.mark.slow
def test_smoke_run_with_the_equivariant_q(tmp_path):
    """recipes/train_policy.py experiment=smoke agent.q_architecture=equivariant (agent=ldm): a seeded run ends,
    and its checkpoint loads back with the equivariant Q."""
    from ldm_rl.agents import load_agent

    env = {**os.environ, "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    command = [sys.executable, str(ROOT / "recipes" / "train_policy.py"), "experiment=smoke", "agent.q_architecture=equivariant",
               "seed=3", f"hydra.run.dir={tmp_path}"]
    proc = subprocess.run(command, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    final = json.loads((tmp_path / "final_metrics.json").read_text())
    assert final["agent"] == "ldm" and final["updates"] > 0 and final["episodes_final_eval"] == 2
    agent, cfg = load_agent(tmp_path / "checkpoint.pt")
    assert cfg["agent"]["q_architecture"] == "equivariant" and isinstance(agent.policy.q_network, EquivariantQFCN)
