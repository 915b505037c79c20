"""Run-time helpers: atomic files, devices, seeding, loggers, and the light package import."""

import subprocess
import sys

import pytest
import torch

from ldm_rl import runtime


def test_atomic_path_leaves_nothing_behind_on_failure(tmp_path):
    target = tmp_path / "ckpt.pt"
    with pytest.raises(RuntimeError, match="boom"):
        with runtime.atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_atomic_torch_save_replaces_whole_files(tmp_path):
    target = tmp_path / "sub" / "ckpt.pt"
    runtime.atomic_torch_save({"a": torch.ones(2)}, target)
    runtime.atomic_torch_save({"a": torch.zeros(3)}, target)
    assert torch.equal(torch.load(target)["a"], torch.zeros(3))
    assert sorted(p.name for p in target.parent.iterdir()) == ["ckpt.pt"]


def test_atomic_path_replaces_directories(tmp_path):
    target = tmp_path / "demos"
    for payload in ("old", "new"):
        with runtime.atomic_path(target) as tmp:
            tmp.mkdir()
            (tmp / "x.txt").write_text(payload)
    assert (target / "x.txt").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demos"]


def test_resolve_device():
    assert runtime.resolve_device("cpu") == torch.device("cpu")
    assert runtime.resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="device must be"):
        runtime.resolve_device("gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA"):
            runtime.resolve_device("cuda")


def test_seed_everything_is_reproducible_and_validated():
    runtime.seed_everything(7)
    a = torch.rand(3)
    gen = runtime.seed_everything(7)
    assert torch.equal(a, torch.rand(3))
    assert torch.equal(torch.rand(2, generator=gen), torch.rand(2, generator=torch.Generator().manual_seed(7)))
    with pytest.raises(ValueError, match="seed"):
        runtime.seed_everything(-1)
    with pytest.raises(ValueError, match="threads"):
        runtime.set_threads(0)


def test_csv_logger_writes_scalars(tmp_path):
    logger = runtime.make_logger({"backend": "csv", "exp_name": "run"}, tmp_path)
    logger.log_scalar("l1_mm", 1.5, step=3)
    files = list(tmp_path.rglob("l1_mm.csv"))
    assert len(files) == 1 and "1.5" in files[0].read_text()
    assert runtime.make_logger({"backend": "none"}, tmp_path) is None
    with pytest.raises(ValueError, match="logger.backend"):
        runtime.make_logger({"backend": "wandb2"}, tmp_path)


def test_importing_ldm_rl_stays_light():
    code = (
        "import sys, ldm_rl, ldm_rl.geometry, ldm_rl.runtime; "
        "heavy = [m for m in ('torchrl', 'pybullet', 'tensordict', 'hydra', 'cv2') if m in sys.modules]; "
        "assert not heavy, heavy"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
