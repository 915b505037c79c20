"""Loggers (TorchRL's get_logger behind ``ldm_rl.run.outputs.make_logger``) and progress reporting.

Each backend writes the scalars it is given where docs/logging.md says; tensorboard / wandb / mlflow
are skipped when their package is not installed. A recipe's log file holding the console's lines is
checked in tests/test_dyn_recipe.py (it reuses that smoke run).
"""

from __future__ import annotations

import importlib.util
import io
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ldm_rl.run import outputs
from ldm_rl.run.progress import LOGGER_NAME, progress_bar, progress_mode

ROOT = Path(__file__).resolve().parents[1]
CONFIG = {"env": {"id": "ldm_rl/BlockStacking-v0", "num_objects": 3}, "seed": 0, "model": {"crop_size": 64, "width": None}}


def _log_two_evaluations(logger) -> None:
    logger.log_metrics({"dynamics/sr": 0.25, "dynamics/l1_mm": 3.5}, step=50)
    logger.log_metrics({"dynamics/sr": 0.5, "dynamics/l1_mm": 2.0}, step=100)


def test_csv_backend_writes_one_file_per_scalar_and_read_scalars_keeps_the_last_value(tmp_path):
    logger = outputs.make_logger({"backend": "csv", "exp_name": "train_dynamics"}, tmp_path, config=CONFIG)
    _log_two_evaluations(logger)
    logger.log_scalar("dynamics/sr", 0.75, step=100)  # a resumed run redoing step 100
    outputs.close_logger(logger)
    assert (tmp_path / "train_dynamics" / "scalars" / "dynamics" / "sr.csv").read_text() == "50,0.25\n100,0.5\n100,0.75\n"
    scalars = outputs.read_scalars(tmp_path)
    assert scalars == {"dynamics/l1_mm": [(50, 3.5), (100, 2.0)], "dynamics/sr": [(50, 0.25), (100, 0.75)]}
    assert outputs.read_scalars(tmp_path / "train_dynamics" / "scalars") == scalars
    if importlib.util.find_spec("torchcodec") is None:
        assert logger.experiment.video_format == "pt"  # get_logger's mp4 needs torchcodec
    with pytest.raises(FileNotFoundError, match="logger=csv"):
        outputs.read_scalars(tmp_path / "train_dynamics" / "videos")


def test_none_unknown_backend_and_missing_package(tmp_path, monkeypatch):
    assert outputs.make_logger({"backend": "none", "exp_name": "x"}, tmp_path) is None
    outputs.close_logger(None)
    with pytest.raises(ValueError, match=r"logger.backend must be one of csv, tensorboard, wandb, mlflow, none; got 'neptune'"):
        outputs.make_logger({"backend": "neptune"}, tmp_path)
    for backend in ("tensorboard", "wandb", "mlflow"):
        monkeypatch.setitem(sys.modules, backend, None)  # as if not installed
        with pytest.raises(outputs.MissingExtraError) as err:
            outputs.make_logger({"backend": backend, "exp_name": "x"}, tmp_path)
        message = str(err.value)
        assert "\n" not in message and f"logger={backend} needs the '{backend}' package" in message
        assert f"pip install 'ldm_rl[{backend}]'" in message
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(importlib.util.find_spec("wandb") is not None, reason="wandb is installed")
def test_a_recipe_with_a_missing_backend_stops_with_one_line(tmp_path):
    done = subprocess.run([sys.executable, str(ROOT / "recipes" / "train_dynamics.py"), "logger=wandb", "threads=1",
                           f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    lines = [ln for ln in done.stderr.splitlines() if ln.strip() and not ln.startswith("pybullet build time")]
    assert done.returncode == 2 and len(lines) == 1, done.stderr
    assert lines[0].startswith("error: logger=wandb needs the 'wandb' package") and "ldm_rl[wandb]" in lines[0]


def test_tensorboard_backend_writes_events(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    logger = outputs.make_logger({"backend": "tensorboard", "exp_name": "train_dynamics"}, tmp_path, config=CONFIG)
    _log_two_evaluations(logger)
    outputs.close_logger(logger)
    events = EventAccumulator(str(tmp_path / "train_dynamics"))
    events.Reload()
    assert [(e.step, e.value) for e in events.Scalars("dynamics/sr")] == [(50, 0.25), (100, 0.5)]


def test_wandb_offline_needs_no_account(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    for name in ("WANDB_API_KEY", "WANDB_MODE", "WANDB_DIR"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("WANDB_CONFIG_DIR", str(tmp_path / "wandb_config"))  # no ~/.config/wandb, no netrc login
    monkeypatch.setenv("WANDB_SILENT", "true")
    logger = outputs.make_logger({"backend": "wandb", "exp_name": "train_dynamics", "mode": "offline", "project": "tests"},
                                 tmp_path / "run", config=CONFIG)
    _log_two_evaluations(logger)
    run = logger.experiment
    assert run.settings.mode == "offline" and run.config["env.id"] == "ldm_rl/BlockStacking-v0"
    assert run.summary["dynamics/sr"] == 0.5 and run.summary["dynamics/l1_mm"] == 2.0
    outputs.close_logger(logger)
    # the offline record that `wandb sync` uploads later (its encoding is wandb's: checked above through the run)
    (record,) = (tmp_path / "run" / "wandb").glob("offline-run-*/run-*.wandb")
    assert record.stat().st_size > 0
    with pytest.raises(ValueError, match="logger.mode must be one of online, offline, disabled"):
        outputs.make_logger({"backend": "wandb", "mode": "sometimes"}, tmp_path / "other")


def test_mlflow_backend_records_metrics_and_the_config(tmp_path):
    pytest.importorskip("mlflow")
    from mlflow.tracking import MlflowClient

    store = tmp_path / "mlruns"
    logger = outputs.make_logger({"backend": "mlflow", "exp_name": "train_dynamics", "tracking_uri": str(store)},
                                 tmp_path / "run", config=CONFIG)
    _log_two_evaluations(logger)
    outputs.close_logger(logger)
    client = MlflowClient(store.as_uri())
    (run,) = client.search_runs([client.get_experiment_by_name("train_dynamics").experiment_id])
    assert [(m.step, m.value) for m in client.get_metric_history(run.info.run_id, "dynamics/sr")] == [(50, 0.25), (100, 0.5)]
    assert run.data.params["env.id"] == "ldm_rl/BlockStacking-v0" and run.data.params["model.width"] == "null"
    assert run.info.status == "FINISHED"


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == LOGGER_NAME]


def test_progress_off_a_terminal_is_plain_lines_every_10_percent(caplog, monkeypatch):
    monkeypatch.delenv("LDM_RL_PROGRESS", raising=False)
    caplog.set_level(logging.INFO, logger=LOGGER_NAME)
    stream = io.StringIO()
    assert progress_mode(stream) == "lines"
    for _ in progress_bar(range(40), desc="evaluate", unit="episode", stream=stream, every_s=1e9):
        pass
    lines = _lines(caplog)
    assert stream.getvalue() == ""  # nothing written to the stream itself: every line went through logging
    assert lines[0] == "evaluate: 0/40 episode (0%) [elapsed 00:00, ETA ?]"
    assert [line.split(" [")[0] for line in lines[1:]] == [f"evaluate: {4 * k}/40 episode ({10 * k}%)" for k in range(1, 11)]
    assert all("ETA 00:00" in line and "episode/s" in line and "\r" not in line for line in lines[1:])


def test_progress_lines_every_interval_with_resume_offset_and_postfix(caplog, monkeypatch):
    monkeypatch.delenv("LDM_RL_PROGRESS", raising=False)
    caplog.set_level(logging.INFO, logger=LOGGER_NAME)
    now = [0.0]  # tqdm's clock driven by hand: 20 s per iteration, so a line whenever 30 s passed since the last one
    monkeypatch.setattr("tqdm.std.time", lambda: now[0])
    bar = progress_bar(total=300, initial=150, desc="train dynamics", stream=io.StringIO(), every_s=30, every_percent=100)
    for i in range(4):
        if i == 3:
            bar.set_postfix(loss="0.4100", refresh=False)
        now[0] += 20.0
        bar.update(1)
    bar.close()  # no new line: the last one already showed 154/300
    lines = _lines(caplog)
    assert [line.split(" [")[0] for line in lines] == ["train dynamics: 150/300 it (50%)", "train dynamics: 152/300 it (51%)",
                                                       "train dynamics: 154/300 it (51%)"]
    assert lines[1].endswith("[elapsed 00:40, ETA 49:20, 20 s/it]")  # 148 left at 20 s: only new iterations count
    assert lines[-1].endswith("loss=0.4100]")
    caplog.clear()
    nested = progress_bar(total=10, desc="evaluate", leave=False, stream=io.StringIO(), every_s=1e9)
    for _ in range(10):
        nested.update(1)
    nested.close()
    assert _lines(caplog) == []  # a transient (leave=False) loop only reports when it is slow...
    slow = progress_bar(total=10, desc="evaluate", leave=False, stream=io.StringIO(), every_s=30)
    for _ in range(3):
        now[0] += 20.0
        slow.update(1)
    slow.close()
    assert [line.split(" [")[0] for line in _lines(caplog)] == ["evaluate: 2/10 it (20%)"]  # ...every 30 s


def test_progress_on_a_terminal_is_a_tqdm_bar_and_logging_prints_above_it(monkeypatch, capsys):
    monkeypatch.delenv("LDM_RL_PROGRESS", raising=False)
    terminal = _Terminal()
    console = logging.StreamHandler(sys.stdout)
    monkeypatch.setattr(logging.root, "handlers", [console])
    monkeypatch.setattr(logging.root, "level", logging.INFO)
    bar = progress_bar(total=5, desc="train", unit="it", stream=terminal)
    assert logging.root.handlers != [console]  # console logging goes through tqdm.write while the bar is up
    logging.getLogger("train_dynamics").info("an evaluation line")
    bar.update(5)
    bar.close()
    assert logging.root.handlers == [console]
    assert "an evaluation line" in capsys.readouterr().out
    shown = terminal.getvalue()
    assert "\r" in shown and "train: 100%" in shown and "5/5" in shown
    monkeypatch.setenv("LDM_RL_PROGRESS", "off")
    assert progress_mode(terminal) == "off" and progress_bar(total=3, stream=terminal).disable
    monkeypatch.setenv("LDM_RL_PROGRESS", "sometimes")
    with pytest.raises(ValueError, match="LDM_RL_PROGRESS must be one of bar, lines, off, got 'sometimes'"):
        progress_bar(total=3)
    monkeypatch.setenv("LDM_RL_PROGRESS", "lines")
    assert progress_mode(terminal) == "lines"
    assert os.environ["LDM_RL_PROGRESS"] == "lines"
