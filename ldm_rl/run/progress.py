"""Progress reporting for every long loop (demos, training, evaluation): one helper, two renderings.

* stderr is a terminal: a tqdm bar with rate and ETA. While it is shown, console logging is routed
  through ``tqdm.write`` so log lines print above the bar instead of breaking it (log files unaffected).
* stderr is not a terminal (a pipe, a file, a cluster job): no carriage returns. Plain lines go through
  ``logging`` (logger ``ldm_rl.run.progress``, level INFO), so they land on the console *and* in the Hydra
  run's ``<job>.log``::

      train LDM(64): 150/300 it (50%) [elapsed 02:31, ETA 02:31, 0.99 it/s, loss=0.412]

  A line is written when the loop starts, each time another ``every_percent`` of it is done, when
  ``every_s`` seconds passed since the last line, and when it ends. A bar made with ``leave=False``
  (a nested, transient loop such as the periodic evaluation inside training) writes only the
  ``every_s`` lines, so short nested loops stay quiet.

Use it like ``tqdm``::

    from ldm_rl.run.progress import progress_bar

    for episode in progress_bar(range(100), desc="evaluate", unit="episode"):
        ...
    bar = progress_bar(total=300, initial=done, desc="train", unit="it")
    bar.update(1); bar.set_postfix(loss=0.41); bar.close()

``LDM_RL_PROGRESS=bar|lines|off`` overrides the terminal check (e.g. ``lines`` under a terminal
multiplexer whose log you keep, ``off`` to silence every loop).
"""

from __future__ import annotations

import logging
import math
import os
import sys
from typing import IO, Any, Iterable

from tqdm.std import tqdm

__all__ = ["progress_bar", "progress_mode", "LOGGER_NAME"]

LOGGER_NAME = "ldm_rl.run.progress"
_MODES = ("bar", "lines", "off")
_SECONDS_PER_UNIT = {"s": 1.0, "min": 60.0, "h": 3600.0}  # bars whose total is a time budget


def progress_mode(stream: IO | None = None) -> str:
    """``"bar"`` if ``stream`` (default: stderr) is a terminal, else ``"lines"``; ``LDM_RL_PROGRESS``
    (bar | lines | off) overrides the check. Raises ValueError for another value of the variable."""
    forced = os.environ.get("LDM_RL_PROGRESS", "").strip().lower()
    if forced:
        if forced not in _MODES:
            raise ValueError(f"LDM_RL_PROGRESS must be one of {', '.join(_MODES)}, got {forced!r}")
        return forced
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    try:
        return "bar" if callable(isatty) and isatty() else "lines"
    except ValueError:  # a closed stream
        return "lines"


def progress_bar(
    iterable: Iterable | None = None,
    *,
    total: float | None = None,
    desc: str | None = None,
    unit: str = "it",
    enabled: bool = True,
    initial: float = 0,
    leave: bool = True,
    every_s: float = 30.0,
    every_percent: float = 10.0,
    stream: IO | None = None,
    **tqdm_kwargs: Any,
) -> tqdm:
    """A ``tqdm`` over ``iterable`` (or a manual one with ``total``) rendered for where it is shown.

    Args:
        iterable / total / desc / unit / initial / leave: as for ``tqdm`` (``initial``: items already
            done, e.g. the iteration a resumed run starts from; rates and ETA count only new items).
        enabled: False gives a disabled bar (same API, prints nothing).
        every_s: seconds between plain lines when stderr is not a terminal (> 0).
        every_percent: percent of ``total`` between plain lines (> 0; ignored without a total).
        stream: the stream whose terminal-ness decides the rendering and that carries the bar
            (default: stderr).
        tqdm_kwargs: any other ``tqdm`` option (``postfix``, ``smoothing``, ...).
    """
    if every_s <= 0 or every_percent <= 0:
        raise ValueError(f"every_s and every_percent must be > 0, got {every_s!r} and {every_percent!r}")
    mode = progress_mode(stream) if enabled else "off"
    common = dict(total=total, desc=desc, unit=unit, initial=initial, leave=leave, **tqdm_kwargs)
    if mode == "off":
        return tqdm(iterable, disable=True, **common)
    if mode == "bar":
        return _TerminalBar(iterable, file=sys.stderr if stream is None else stream, dynamic_ncols=True, **common)
    return _LoggedProgress(iterable, every_s=every_s, every_percent=every_percent, **common)


def _has_console_handler(logger: logging.Logger) -> bool:
    return any(isinstance(h, logging.StreamHandler) and h.stream in (sys.stdout, sys.stderr) for h in logger.handlers)


class _TerminalBar(tqdm):
    """A tqdm bar that routes the root logger's console handlers through ``tqdm.write`` while open."""

    def __init__(self, *args, **kwargs) -> None:
        from tqdm.contrib.logging import logging_redirect_tqdm

        self._redirect = logging_redirect_tqdm(tqdm_class=tqdm) if _has_console_handler(logging.root) else None
        if self._redirect is not None:
            self._redirect.__enter__()
        super().__init__(*args, **kwargs)

    def close(self) -> None:
        try:
            super().close()
        finally:
            redirect, self._redirect = getattr(self, "_redirect", None), None
            if redirect is not None:
                redirect.__exit__(None, None, None)


class _NullStream:
    """Where tqdm's own status printer writes in lines mode (every line goes through logging instead)."""

    def write(self, _text: str) -> int:
        return 0

    def flush(self) -> None:
        pass


class _LoggedProgress(tqdm):
    """tqdm bookkeeping (rate, ETA, postfix) with plain periodic ``logging`` lines instead of a bar."""

    def __init__(self, *args, every_s: float, every_percent: float, **kwargs) -> None:
        self._every_s, self._every_fraction = float(every_s), float(every_percent) / 100.0
        self._last_line_t: float | None = None
        self._last_line_n: float | None = None
        self._last_bucket = -1
        self._closing = False
        self._log = logging.getLogger(LOGGER_NAME)
        kwargs.update(file=_NullStream(), mininterval=0.0, miniters=1, ascii=True)
        super().__init__(*args, **kwargs)

    def _bucket(self) -> int:
        if not self.total:
            return -1
        return math.floor(min(self.n / self.total, 1.0) / self._every_fraction + 1e-9)

    def line(self) -> str:
        """The plain line: ``desc: n/total unit (pct%) [elapsed, ETA, rate, postfix]``."""
        d = self.format_dict
        elapsed, n, total, unit = d["elapsed"], d["n"], d["total"], d["unit"]
        new = n - d.get("initial", 0)
        rate = d["rate"] if d["rate"] else (new / elapsed if elapsed > 0 and new > 0 else None)
        parts = [f"elapsed {self.format_interval(elapsed)}"]
        if total and unit in _SECONDS_PER_UNIT:  # a time budget: what is left of it, not an extrapolation
            remaining = (total - n) * _SECONDS_PER_UNIT[unit]
            parts.append(f"ETA {self.format_interval(remaining)}")
        elif total:
            remaining = (total - n) / rate if rate else None
            parts.append(f"ETA {self.format_interval(remaining) if remaining is not None else '?'}")
        if rate and unit not in _SECONDS_PER_UNIT:  # a time budget's "60 s/min" says nothing
            parts.append(f"{1 / rate:.3g} s/{unit}" if rate < 1 else f"{rate:.3g} {unit}/s" if rate < 1000 else f"{rate:,.0f} {unit}/s")
        if d.get("postfix"):
            parts.append(str(d["postfix"]))
        count = f"{self.format_num(n) if isinstance(n, float) else n}"
        done = f"{count}/{total} {unit} ({100 * n / total:.0f}%)" if total else f"{count} {unit}"
        prefix = f"{d['prefix']}: " if d.get("prefix") else ""
        return f"{prefix}{done} [{', '.join(parts)}]"

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        if msg == "":  # tqdm clearing a transient bar: nothing to clear in a log
            return True
        now, bucket = self._time(), self._bucket()
        # tqdm's first call comes from __init__, before start_t exists
        since = now - (self._last_line_t if self._last_line_t is not None else getattr(self, "start_t", now))
        due = (since >= self._every_s
               or (self.leave and (self._last_line_t is None or bucket > self._last_bucket
                                   or (self._closing and self.n != self._last_line_n))))
        if due:
            self._log.info(self.line())
            self._last_line_t, self._last_line_n, self._last_bucket = now, self.n, bucket
        return True

    def close(self) -> None:
        self._closing = True
        super().close()
