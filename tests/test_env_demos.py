"""Demo collection, compact storage and the generate_demos recipe."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from ldm_rl.data.demos import collect_demos, load_demos, save_demos

REPO = Path(__file__).resolve().parents[1]
STACKING = {"id": "ldm_rl/BlockStacking-v0", "num_objects": 3, "max_steps": None, "num_rotations": 8,
            "max_height": 0.25}


@pytest.fixture(scope="module")
def demos():
    return collect_demos(STACKING, num_steps=10, seed=0, procedure="deconstruct",
                         noise={"position": 0.005, "random_action_prob": 0.1}, progress=False)


def test_collected_demos_follow_the_contract(demos):
    td = demos
    assert td.batch_size == (10,)
    expected = {
        "heightmap": ((10, 1, 128, 128), torch.float32), "in_hand": ((10, 1, 24, 24), torch.float32),
        "holding": ((10, 1), torch.bool), "action": ((10, 3), torch.int64), "episode": ((10,), torch.int64),
        "is_expert": ((10, 1), torch.bool), ("next", "heightmap"): ((10, 1, 128, 128), torch.float32),
        ("next", "in_hand"): ((10, 1, 24, 24), torch.float32), ("next", "holding"): ((10, 1), torch.bool),
        ("next", "reward"): ((10, 1), torch.float32), ("next", "done"): ((10, 1), torch.bool),
        ("next", "terminated"): ((10, 1), torch.bool), ("next", "truncated"): ((10, 1), torch.bool),
        ("next", "primitive_success"): ((10, 1), torch.bool),
    }
    for key, (shape, dtype) in expected.items():
        assert td[key].shape == shape and td[key].dtype == dtype, key
    # transitions chain within an episode: next obs of step t is the obs of step t+1
    same_episode = td["episode"][1:] == td["episode"][:-1]
    assert same_episode.any()
    assert torch.equal(td["next", "heightmap"][:-1][same_episode], td["heightmap"][1:][same_episode])
    assert torch.equal(td["next", "holding"][:-1][same_episode], td["holding"][1:][same_episode])
    # the hand alternates: a successful pick ends holding
    picks = ~td["holding"][:, 0] & td["next", "primitive_success"][:, 0]
    assert td["next", "holding"][picks].all()
    meta = td.get_non_tensor("metadata")
    assert meta["env_id"] == STACKING["id"] and meta["procedure"] == "deconstruct" and meta["max_height"] == 0.25


def test_saved_then_loaded_demos_equal_the_in_process_ones_bit_for_bit(demos, tmp_path):
    """Training on a saved demo folder gives the same inputs (and so the same result) as training on the
    demos collected in the same process: every key comes back with the same dtype and the same bits."""
    path = save_demos(demos, tmp_path / "demos")
    loaded = load_demos(path)
    assert loaded.batch_size == demos.batch_size
    keys = [k for k in demos.keys(True, True) if k != "metadata"]
    assert sorted(map(str, keys)) == sorted(map(str, (k for k in loaded.keys(True, True) if k != "metadata")))
    for key in keys:
        a, b = demos[key], loaded[key]
        assert b.dtype == a.dtype and b.shape == a.shape, key
        assert torch.equal(a.view(torch.uint8) if a.is_floating_point() else a, b.view(torch.uint8) if b.is_floating_point() else b), key
    assert loaded.get_non_tensor("metadata") == demos.get_non_tensor("metadata")
    manifest = json.loads((path / "demos.json").read_text())
    assert manifest["num_transitions"] == 10 and manifest["metadata"]["env_id"] == STACKING["id"]
    # float32 heightmaps (exact), uint8 actions (exact for pixels < 128 and bins < 8)
    assert (path / "heightmap.memmap").stat().st_size == 10 * 128 * 128 * 4
    assert (path / "action.memmap").stat().st_size == 10 * 3
    # the folder stays a TensorDict memmap directory (TorchRL's LazyMemmapStorage layout)
    from tensordict import TensorDict

    assert torch.equal(TensorDict.load_memmap(path)["heightmap"], demos["heightmap"])


def test_bad_requests_raise(tmp_path):
    with pytest.raises(ValueError, match="exactly one"):
        collect_demos(STACKING, num_steps=3, num_episodes=2)
    with pytest.raises(ValueError, match="procedure"):
        collect_demos(STACKING, num_steps=3, procedure="teleop")
    with pytest.raises(ValueError, match="demos.json is missing"):
        load_demos(tmp_path)
    with pytest.raises(ValueError, match="no such folder"):
        load_demos(tmp_path / "absent")


def test_generate_demos_recipe_smoke(tmp_path):
    run_dir = tmp_path / "run"
    cmd = [sys.executable, str(REPO / "recipes" / "generate_demos.py"), "env=house_building", "demos.num_steps=4",
           "demos.progress=false", f"hydra.run.dir={run_dir}"]
    subprocess.run(cmd, check=True, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    td = load_demos(run_dir / "demos")
    assert td.batch_size == (4,)
    assert td.get_non_tensor("metadata")["env_id"] == "ldm_rl/HouseBuilding-v0"
