"""The checkpoint format (ldm_rl.run.checkpoint, ldm_rl.run.signals): verification, atomic writes, RNG states, stale temporaries and
stop signals (the dynamics recipe's exact resume: tests/test_dyn_recipe.py)."""

import os
import random
import signal
import subprocess
import sys

import numpy as np
import pytest
import torch

from ldm_rl.run import checkpoint as ck
from ldm_rl.run import signals
from ldm_rl.run.checkpoint import CheckpointError, load_checkpoint, save_checkpoint

META = {"kind": "dynamics", "preset": "lite", "task": "ldm_rl/BlockStacking-v0", "config": {"env": {"num_rotations": 8}}}


def snapshot(folder):
    """{relative path: (bytes, mtime_ns)} of every file under ``folder``."""
    return {p.relative_to(folder).as_posix(): (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def saved(tmp_path):
    state = {"weights": torch.arange(4096, dtype=torch.float32), "step": 7, "rows": [{"sr": 0.5}]}
    return save_checkpoint(tmp_path / "checkpoint.pt", state, meta=META), state


def test_round_trip_returns_state_and_meta(saved):
    path, state = saved
    loaded = load_checkpoint(path, expect={"kind": "dynamics", "preset": "lite", "config.env.num_rotations": 8})
    assert torch.equal(loaded.state["weights"], state["weights"]) and loaded.state["step"] == 7
    assert loaded.meta == META and loaded.format_version == ck.FORMAT_VERSION and loaded.path == path
    assert load_checkpoint(path.parent).path == path  # a run folder works too
    assert ck.read_checkpoint_meta(path) == META == ck.read_checkpoint_meta(path, verify=True)


@pytest.mark.parametrize("expect, field, held, wanted", [
    ({"preset": "paper"}, "preset", "'lite'", "'paper'"),
    ({"task": "ldm_rl/HouseBuilding-v0"}, "task", "'ldm_rl/BlockStacking-v0'", "'ldm_rl/HouseBuilding-v0'"),
    ({"kind": "agent"}, "kind", "'dynamics'", "'agent'"),
])
def test_each_expect_mismatch_is_one_clear_line(saved, expect, field, held, wanted):
    path, _ = saved
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(path, expect=expect)
    message = str(err.value)
    assert "\n" not in message and str(path) in message
    assert f"{field} is {held}, expected {wanted}" in message


def test_a_missing_meta_field_is_named(saved):
    with pytest.raises(CheckpointError, match=r"has no 'seed' field, expected seed=3"):
        load_checkpoint(saved[0], expect={"seed": 3})


@pytest.mark.parametrize("where", ["header", "meta", "state_start", "state_middle", "end"])
def test_4_kib_of_flipped_bytes_anywhere_is_caught_and_the_file_left_alone(saved, where):
    path, _ = saved
    data = bytearray(path.read_bytes())
    offset = {"header": len(ck.MAGIC) + 5, "meta": data.index(b'"kind"'), "state_start": len(data) - 16500,
              "state_middle": len(data) // 2 + 4000, "end": len(data) - 4096}[where]
    size = 4096 if where not in ("header", "meta") else 8
    for i in range(offset, min(offset + size, len(data))):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))
    before = snapshot(path.parent)
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)
    assert any(word in str(err.value) for word in ("corrupted", "format version", "truncated", "extra bytes"))
    assert snapshot(path.parent) == before


def test_truncated_padded_foreign_old_newer_and_missing_files(saved, tmp_path):
    path, _ = saved
    data = path.read_bytes()
    cases = {
        "short.pt": (data[:-100], "truncated"),
        "long.pt": (data + b"\0" * 10, "extra bytes"),
        "text.pt": (b"hello", "not an ldm_rl checkpoint"),
        "newer.pt": (data.replace(b'"format_version": 1', b'"format_version": 9', 1), "format version 9"),
    }
    for name, (content, expected) in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(CheckpointError, match=expected):
            load_checkpoint(tmp_path / name)
    torch.save({"model_state": {}}, tmp_path / "old.pt")
    with pytest.raises(CheckpointError, match="plain torch.save file"):
        load_checkpoint(tmp_path / "old.pt")
    with pytest.raises(CheckpointError, match="no such file"):
        load_checkpoint(tmp_path / "absent.pt")


def test_saving_is_atomic_and_refuses_what_would_not_load(saved, monkeypatch):
    path, _ = saved
    before = path.read_bytes()
    with pytest.raises(TypeError, match=r"state\['bad'\] is a numpy.ndarray"):
        save_checkpoint(path, {"bad": np.zeros(3)}, meta=META)

    def crash(*args):
        raise OSError("disk full")

    monkeypatch.setattr(ck.os, "replace", crash)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, {"weights": torch.zeros(2)}, meta=META)
    assert path.read_bytes() == before and sorted(p.name for p in path.parent.iterdir()) == ["checkpoint.pt"]
    monkeypatch.undo()
    save_checkpoint(path, {"x": np.float64(1.5), "n": np.int64(3), "flag": np.bool_(True)}, meta=META)
    state = load_checkpoint(path).state
    assert state == {"x": 1.5, "n": 3, "flag": True} and type(state["x"]) is float


def test_clean_stale_temporaries_removes_only_leftovers(tmp_path):
    (tmp_path / ".hydra").mkdir()
    (tmp_path / "checkpoint.pt").write_bytes(b"keep")
    (tmp_path / ".checkpoint.pt.k3x9_a0q.tmp").write_bytes(b"half a checkpoint")
    (tmp_path / ".metrics.csv.abcdefgh.tmp").mkdir()
    (tmp_path / ".metrics.csv.abcdefgh.tmp" / "metrics.csv").write_text("half")
    (tmp_path / "demos").mkdir()
    (tmp_path / ".demos.old").mkdir()
    (tmp_path / ".data.old").mkdir()  # "data" itself is gone: the previous copy comes back
    (tmp_path / ".data.old" / "x").write_text("previous")
    removed = ck.clean_stale_temporaries(tmp_path)
    assert sorted(p.name for p in removed) == [".checkpoint.pt.k3x9_a0q.tmp", ".data.old", ".demos.old", ".metrics.csv.abcdefgh.tmp"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [".hydra", "checkpoint.pt", "data", "demos"]
    assert (tmp_path / "data" / "x").read_text() == "previous"
    assert ck.clean_stale_temporaries(tmp_path) == []


def test_rng_states_round_trip_through_a_checkpoint(tmp_path):
    gens = {"sampler": torch.Generator().manual_seed(1), "env": np.random.default_rng(2),
            "mt": np.random.Generator(np.random.MT19937(3)), "legacy": np.random.RandomState(4), "py": random.Random(5)}

    def draw():
        return (torch.rand(3).tolist(), np.random.rand(2).tolist(), random.random(), torch.rand(2, generator=gens["sampler"]).tolist(),
                gens["env"].random(), gens["mt"].integers(1 << 30), gens["legacy"].rand(), gens["py"].random())

    path = save_checkpoint(tmp_path / "rng.pt", {"rng": ck.capture_rng_state(gens)}, meta={"kind": "test"})
    first = draw()
    ck.restore_rng_state(load_checkpoint(path).state["rng"], gens)
    assert draw() == first
    with pytest.raises(ValueError, match="no generator 'other'"):
        ck.restore_rng_state(ck.capture_rng_state(), {"other": torch.Generator()})


def test_stop_signals_set_a_flag_then_a_second_signal_aborts():
    # SIGTERM both times: a suite started in the background (`pytest &`) inherits an ignored SIGINT, which
    # StopSignals leaves ignored on purpose
    previous = signal.getsignal(signal.SIGTERM)
    with signals.StopSignals() as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.requested and stop.signal_name == "SIGTERM"
        with pytest.raises(SystemExit) as exited:
            os.kill(os.getpid(), signal.SIGTERM)
        assert exited.value.code == 128 + signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is previous
    stopped = signals.RunStopped("SIGTERM", 30, 400, "run/checkpoint.pt")
    assert str(stopped) == "stopped by SIGTERM at iteration 30/400; checkpoint saved to run/checkpoint.pt"
    assert stopped.exit_code == 143
    budget = signals.RunStopped("SIGINT", 24, 100000, "c.pt", unit="episode", position="episode 24, 12.0 of 36.0 min")
    assert str(budget) == "stopped by SIGINT at episode 24, 12.0 of 36.0 min; checkpoint saved to c.pt"


def test_the_first_signal_says_what_it_waits_for_and_a_second_never_cuts_a_save(capsys):
    with signals.StopSignals("the current episode") as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        assert capsys.readouterr().err.startswith("SIGTERM: stopping after the current episode, then saving a checkpoint")
        written = []
        with pytest.raises(SystemExit) as exited:
            with stop.saving():
                os.kill(os.getpid(), signal.SIGTERM)  # arrives half-way through the save
                written.append("the rest of the checkpoint")
        assert written == ["the rest of the checkpoint"] and exited.value.code == 128 + signal.SIGTERM
        err = capsys.readouterr().err
        assert "aborting once the checkpoint being written is complete" in err and "aborted without a new checkpoint" in err


def test_importing_the_checkpoint_module_stays_light():
    code = "import sys, ldm_rl.run.checkpoint, ldm_rl.run.signals; assert 'torch' not in sys.modules and 'hydra' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
