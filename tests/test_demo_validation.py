"""Demo folders are opened read-only and checked against demos.json before any work: each corruption is one
clear error naming the folder, the file and the problem, and leaves the files on disk exactly as they were."""

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from ldm_rl.data.demos import DemoDataError, load_demos, save_demos

REPO = Path(__file__).resolve().parents[1]


def synthetic_demos(n: int = 6):
    """A small demo set in the format of collect_demos (no physics: fast)."""
    from tensordict import TensorDict

    g = torch.Generator().manual_seed(0)
    heights = torch.rand(n, 1, 128, 128, generator=g) * 0.1
    td = TensorDict({
        "heightmap": heights, "in_hand": torch.rand(n, 1, 24, 24, generator=g) * 0.04,
        "holding": (torch.arange(n) % 2 == 1).unsqueeze(-1),
        "action": torch.stack((torch.randint(0, 128, (n,), generator=g), torch.randint(0, 128, (n,), generator=g),
                               torch.randint(0, 8, (n,), generator=g)), -1),
        "episode": torch.arange(n) // 2, "is_expert": torch.ones(n, 1, dtype=torch.bool),
        "next": {"heightmap": heights.roll(1, 0), "in_hand": torch.zeros(n, 1, 24, 24), "holding": (torch.arange(n) % 2 == 0).unsqueeze(-1),
                 "reward": torch.zeros(n, 1), "done": torch.zeros(n, 1, dtype=torch.bool),
                 "terminated": torch.zeros(n, 1, dtype=torch.bool), "truncated": torch.zeros(n, 1, dtype=torch.bool),
                 "primitive_success": torch.ones(n, 1, dtype=torch.bool)},
    }, batch_size=[n])
    td.set_non_tensor("metadata", {"env_id": "ldm_rl/BlockStacking-v0", "num_rotations": 8, "max_height": 0.25})
    return td


def snapshot(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): (p.read_bytes(), p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def folder(tmp_path):
    return save_demos(synthetic_demos(), tmp_path / "demos")


def corrupt_and_load(folder: Path, change) -> str:
    """Apply ``change`` to the folder, load it (must fail), check nothing changed on disk; the message."""
    change(folder)
    before = snapshot(folder)
    with pytest.raises(DemoDataError) as err:
        load_demos(folder)
    assert snapshot(folder) == before, "loading changed the files on disk"
    message = str(err.value)
    assert "\n" not in message and str(folder) in message
    return message


def _truncate(folder):
    with open(folder / "heightmap.memmap", "r+b") as f:
        f.truncate(1000)


def _random_bytes(folder):
    file = folder / "next" / "heightmap.memmap"
    data = bytearray(file.read_bytes())
    data[5000:9096] = torch.randint(0, 256, (4096,), generator=torch.Generator().manual_seed(1), dtype=torch.uint8).numpy().tobytes()
    file.write_bytes(bytes(data))


def _extra_bytes(folder):
    with open(folder / "action.memmap", "ab") as f:
        f.write(b"\0" * 3)


def test_a_clean_folder_loads_and_equals_what_was_saved(folder):
    loaded, original = load_demos(folder), synthetic_demos()
    for key in original.keys(True, True):
        if key != "metadata":
            assert loaded[key].dtype == original[key].dtype and torch.equal(loaded[key], original[key]), key


def test_truncated_file(folder):
    message = corrupt_and_load(folder, _truncate)
    assert "heightmap.memmap truncated: 1,000 bytes" in message


def test_random_bytes_inside_a_file(folder):
    message = corrupt_and_load(folder, _random_bytes)
    assert "next/heightmap.memmap does not match its SHA-256" in message


def test_deleted_file(folder):
    message = corrupt_and_load(folder, lambda f: (f / "action.memmap").unlink())
    assert "action.memmap is missing" in message


def test_extra_bytes(folder):
    message = corrupt_and_load(folder, _extra_bytes)
    assert "action.memmap has extra bytes: 21 bytes" in message


def test_missing_metadata(folder):
    message = corrupt_and_load(folder, lambda f: (f / "demos.json").unlink())
    assert "demos.json is missing" in message


def test_malformed_metadata(folder):
    message = corrupt_and_load(folder, lambda f: (f / "demos.json").write_text('{"format": "ldm_rl.demos", "format_version": '))
    assert "demos.json is not valid JSON (line 1" in message


def test_metadata_that_contradicts_the_format(folder):
    def claim_float16(f):
        manifest = json.loads((f / "demos.json").read_text())
        manifest["tensors"]["heightmap"]["dtype"] = "float16"
        (f / "demos.json").write_text(json.dumps(manifest))

    message = corrupt_and_load(folder, claim_float16)
    assert "gives heightmap as float16" in message and "the format says float32" in message


def test_metadata_of_an_older_format(folder):
    def legacy(f):
        manifest = json.loads((f / "demos.json").read_text())
        (f / "demos.json").write_text(json.dumps({"num_transitions": manifest["num_transitions"], **manifest["metadata"]}))

    assert "older ldm_rl" in corrupt_and_load(folder, legacy)


def test_a_missing_tensordict_meta_json(folder):
    message = corrupt_and_load(folder, lambda f: (f / "next" / "meta.json").unlink())
    assert "next/meta.json is missing" in message


def _rewrite_with_checksum(folder: Path, rel: str, data: bytes) -> None:
    """Replace a file and fix its checksum in demos.json (a folder consistent with itself, with bad values)."""
    (folder / rel).write_bytes(data)
    manifest = json.loads((folder / "demos.json").read_text())
    manifest["files"][rel] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    (folder / "demos.json").write_text(json.dumps(manifest))


def _nan_heights():
    heights = torch.zeros(6, 1, 128, 128)
    heights[2, 0, 5, 5] = float("nan")
    return heights.numpy().tobytes()


@pytest.mark.parametrize("rel, data, expected", [
    ("heightmap.memmap", _nan_heights(), "heightmap.memmap holds 1 NaN/inf values"),
    ("next/in_hand.memmap", torch.full((6, 1, 24, 24), 2.5).numpy().tobytes(), "heights outside [0, 1] m (min 2.5, max 2.5)"),
    ("action.memmap", torch.tensor([[1, 2, 3]] * 5 + [[200, 2, 3]], dtype=torch.uint8).numpy().tobytes(),
     "action pixels outside [0, 128)"),
    ("holding.memmap", bytes([0, 1, 7, 0, 0, 1]), "holding.memmap holds bytes other than 0/1"),
], ids=["nan", "height_range", "action_range", "bool_bytes"])
def test_bad_values_are_caught_even_with_matching_checksums(folder, rel, data, expected):
    assert expected in corrupt_and_load(folder, lambda f: _rewrite_with_checksum(f, rel, data))


def test_save_refuses_bad_values_and_keeps_the_previous_folder(folder):
    before = snapshot(folder)
    td = synthetic_demos()
    td["heightmap"][0, 0, 0, 0] = float("nan")
    with pytest.raises(DemoDataError, match=r"td\['heightmap'\] holds 1 NaN/inf values"):
        save_demos(td, folder)
    td = synthetic_demos()
    td["action"][0, 2] = 9
    with pytest.raises(DemoDataError, match=r"rotation bins outside \[0, 8\)"):
        save_demos(td, folder)
    assert snapshot(folder) == before


def test_the_recipe_stops_on_a_corrupt_folder_with_one_line(folder, tmp_path):
    _truncate(folder)
    before = snapshot(folder)
    run_dir = tmp_path / "run"
    proc = subprocess.run([sys.executable, str(REPO / "recipes" / "train_dynamics.py"), f"dynamics.data={folder}", "logger=none",
                           f"hydra.run.dir={run_dir}"], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip() and not ln.startswith("pybullet build time")]
    assert lines == [f"error: demo folder {folder}: heightmap.memmap truncated: 1,000 bytes, demos.json says 393,216"]
    assert snapshot(folder) == before and not (run_dir / "checkpoint.pt").exists()
