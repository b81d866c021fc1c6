"""Progress of long runs (the camera loop, sweeps): a bar with elapsed and remaining time.

On a terminal a ``rich`` progress bar (on stderr) shows what runs, how much of it is done and the
time left; written to a log (not a terminal) the same news comes as one plain line each time the
description changes (a swing, a chunk), so a log holds a readable history and no control
characters. The estimate of the time left counts from the first unit done, so a compilation
before it (reported on its own line with :meth:`ProgressBar.log`) does not inflate it.
"""

from __future__ import annotations

import sys
import time

__all__ = ["ProgressBar", "format_seconds", "restore_terminal"]

_clock = time.perf_counter  # [s] (a module attribute: tests replace it)


def format_seconds(seconds: float | None) -> str:
    """``"1:02:03"``, ``"2:03"`` (minutes:seconds), or ``"?"`` for None."""
    if seconds is None:
        return "?"
    s = int(round(seconds))
    h, rest = divmod(s, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def restore_terminal() -> None:
    """Shows the cursor again on a terminal (a bar hides it; a process ended by a signal
    through ``os._exit`` never stops its bar).
    """
    if sys.stderr.isatty():
        sys.stderr.write("\x1b[?25h\n")
        sys.stderr.flush()


class ProgressBar:
    """A context manager: a bar over ``total`` units of work, with elapsed and remaining time.

    Args:
        total: units of work (e.g. frames x seeds, runs); at least 1.
        unit: what a unit is, for the display ("frames", "runs").
        enabled: False: nothing is shown (calls still work).
        terminal: force the terminal (True) or the log (False) display; None: the terminal one
            when stderr is a terminal.

    Attributes:
        done: units done so far.
    """

    def __init__(self, total: int, unit: str, enabled: bool = True, terminal: bool | None = None):
        if not (isinstance(total, int) and total >= 1):
            raise ValueError(f"total must be an integer >= 1, got {total!r}")
        self.total, self.unit, self.enabled = total, unit, enabled
        self.terminal = sys.stderr.isatty() if terminal is None else terminal
        self.done = 0
        self._description = ""
        self._t_start = self._t_first = None
        self._done_first = 0
        self._rich = self._task = None

    def __enter__(self) -> ProgressBar:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def start(self) -> ProgressBar:
        """Shows the bar (the clock starts); returns it."""
        self._t_start = _clock()
        if self.enabled and self.terminal:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self._rich = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn(self.unit),
                TimeElapsedColumn(),
                TextColumn("elapsed,"),
                TimeRemainingColumn(),
                TextColumn("left"),
                console=Console(stderr=True),
            )
            self._rich.start()
            self._task = self._rich.add_task(self._description, total=self.total)
        return self

    def stop(self) -> None:
        """Ends the display (on a terminal the bar stays, complete or not)."""
        if self._rich is not None:
            self._rich.stop()
            self._rich = None

    def elapsed(self) -> float:
        """Seconds since the bar started."""
        return 0.0 if self._t_start is None else _clock() - self._t_start

    def remaining(self) -> float | None:
        """Estimated seconds left, from the rate since the first unit was done (None before)."""
        if self._t_first is None or self.done <= self._done_first:
            return None
        rate = (self.done - self._done_first) / (_clock() - self._t_first)
        return (self.total - self.done) / rate if rate > 0 else None

    def update(self, advance: int = 0, description: str | None = None) -> None:
        """Counts ``advance`` more units done and, if given, sets what is running now (on a log,
        a new description prints the line of what is done so far).
        """
        if advance and self._t_first is None:
            self._t_first, self._done_first = _clock(), self.done + advance
        self.done = min(self.done + advance, self.total)
        changed = description is not None and description != self._description
        if description is not None:
            self._description = description
        if not self.enabled:
            return
        if self._rich is not None:
            self._rich.update(self._task, completed=self.done, description=self._description)
        elif changed or self.done == self.total:
            self._print_line()

    def log(self, text: str) -> None:
        """Prints ``text`` on its own line (above the bar on a terminal)."""
        if not self.enabled:
            return
        if self._rich is not None:
            self._rich.console.print(text, highlight=False, markup=False)
        else:
            print(text, file=sys.stderr, flush=True)

    def _print_line(self) -> None:
        pct = 100.0 * self.done / self.total
        left = self.remaining()
        tail = "" if self.done == self.total else f", about {format_seconds(left)} left"
        print(
            f"{self._description}: {self.done}/{self.total} {self.unit} ({pct:.0f}%),"
            f" {format_seconds(self.elapsed())} elapsed{tail}",
            file=sys.stderr,
            flush=True,
        )
