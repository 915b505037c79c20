"""Runs that stop cleanly: SIGINT/SIGTERM set a flag, the loop saves a checkpoint and raises :class:`RunStopped`.

Nothing here imports torch.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any

__all__ = ["StopSignals", "RunStopped"]


class RunStopped(Exception):
    """Raised by a training loop after it saved a checkpoint on SIGINT/SIGTERM.

    ``str()`` is the one line to show, e.g. ``stopped by SIGTERM at iteration 30/400; checkpoint saved
    to outputs/.../checkpoint.pt`` (``position`` replaces ``iteration 30/400`` where another unit bounds the
    run, e.g. ``episode 24, 12.3 of 36.0 min``); ``exit_code`` is the shell's 128 + signal number.
    """

    def __init__(self, signal_name: str, iteration: int, total: int, checkpoint: str | os.PathLike, *,
                 unit: str = "iteration", position: str | None = None) -> None:
        self.signal_name, self.iteration, self.total, self.checkpoint = signal_name, iteration, total, Path(checkpoint)
        where = position if position is not None else f"{unit} {iteration}/{total}"
        super().__init__(f"stopped by {signal_name} at {where}; checkpoint saved to {self.checkpoint}")

    @property
    def exit_code(self) -> int:
        return 128 + int(getattr(signal.Signals, self.signal_name, signal.SIGTERM))


class StopSignals:
    """While active, SIGINT / SIGTERM ask the loop to stop instead of killing the process.

    ``with StopSignals("the end of this episode") as stop: ... if stop.requested: with stop.saving(): save;
    raise RunStopped(stop.signal_name, ...)``. The first signal sets ``requested`` and ``signal_name`` and
    says on stderr what the loop finishes first (``waiting_for``); a second one aborts at once (one line on
    stderr, exit code 128 + signal number) without a new checkpoint — the last one on disk stays whole: a
    second signal that arrives inside ``saving()`` aborts only once that save is complete. The previous
    handlers come back on exit. Signals the process ignores (SIGINT of a background job) stay ignored;
    outside the main thread (where Python cannot install handlers) it does nothing.
    """

    def __init__(self, waiting_for: str = "the current step",
                 signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> None:
        self.waiting_for = str(waiting_for)
        self.signals = tuple(signals)
        self.requested = False
        self.signal_name: str | None = None
        self._previous: dict[int, Any] = {}
        self._saving = False
        self._abort_after_save: int | None = None

    def __enter__(self) -> "StopSignals":
        if threading.current_thread() is threading.main_thread():
            for signum in self.signals:
                previous = signal.getsignal(signum)
                if previous is signal.SIG_IGN:  # e.g. SIGINT of a background job: stays ignored
                    continue
                self._previous[signum] = previous
                signal.signal(signum, self._handle)
        return self

    def _handle(self, signum: int, frame) -> None:
        name = signal.Signals(signum).name
        if self.requested:
            if self._saving:  # never abort half-way through a checkpoint
                self._abort_after_save = signum
                print(f"second {name}: aborting once the checkpoint being written is complete", file=sys.stderr, flush=True)
                return
            self._abort(signum)
        self.requested, self.signal_name = True, name
        print(f"{name}: stopping after {self.waiting_for}, then saving a checkpoint; "
              f"{name} again aborts at once (the last checkpoint on disk is kept)", file=sys.stderr, flush=True)

    def _abort(self, signum: int) -> None:
        self._restore()
        print(f"second {signal.Signals(signum).name}: aborted without a new checkpoint", file=sys.stderr, flush=True)
        raise SystemExit(128 + signum)

    @contextlib.contextmanager
    def saving(self):
        """A block a second signal does not interrupt (a checkpoint being written); it aborts right after."""
        self._saving = True
        try:
            yield
        finally:
            self._saving = False
            pending, self._abort_after_save = self._abort_after_save, None
            if pending is not None:
                self._abort(pending)

    def _restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)
        self._previous.clear()

    def __exit__(self, *exc) -> None:
        self._restore()
