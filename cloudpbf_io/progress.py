"""Progress reports that work in a terminal and in a log.

On a terminal (stderr is a TTY) :func:`progress_bar` gives a tqdm bar; otherwise (CI logs, ``| tee``,
``nohup``, a notebook's captured stderr) it prints plain lines such as::

    growing (cpu): 40/200 step (20%), 12.3 s elapsed, ~49 s left

at most every ``CLOUDPBF_PROGRESS_INTERVAL`` seconds (default 10) and once at the end, where tqdm
would print nothing at all.  ``CLOUDPBF_PROGRESS=bar|lines|off`` forces one style.
"""
from __future__ import annotations

import os
import sys
import time

__all__ = ["Progress", "PlainProgress", "progress_bar", "progress_style"]


def progress_style(stream=None) -> str:
    """'bar', 'lines' or 'off': CLOUDPBF_PROGRESS if set, else 'bar' on a terminal, 'lines' elsewhere."""
    forced = os.environ.get("CLOUDPBF_PROGRESS", "").strip().lower()
    if forced in ("bar", "lines", "off"):
        return forced
    stream = stream or sys.stderr
    try:
        return "bar" if stream.isatty() else "lines"
    except (AttributeError, ValueError):
        return "lines"


def _interval() -> float:
    try:
        return max(0.0, float(os.environ.get("CLOUDPBF_PROGRESS_INTERVAL", "10")))
    except ValueError:
        return 10.0


class PlainProgress:
    """A tqdm-like object that prints a plain line at most every `interval` seconds and at the end."""

    def __init__(self, total=None, initial: int = 0, desc: str = "", unit: str = "it", interval: float | None = None,
                 file=None, disable: bool = False, **_ignored):
        self.total = total
        self.n = int(initial)
        self.initial = int(initial)
        self.desc = desc
        self.unit = unit
        self.interval = _interval() if interval is None else float(interval)
        self.file = file
        self.disable = bool(disable)
        self.start = time.perf_counter()
        self._last = self.start
        self._printed_n = None
        self.closed = False

    def _line(self) -> str:
        elapsed = time.perf_counter() - self.start
        head = f"{self.desc}: " if self.desc else ""
        if self.total:
            pct = 100.0 * self.n / self.total
            done = self.n - self.initial
            left = ""
            if 0 < done and self.n < self.total:
                left = f", ~{elapsed / done * (self.total - self.n):.0f} s left"
            return f"{head}{self.n}/{self.total} {self.unit} ({pct:.0f}%), {elapsed:.1f} s elapsed{left}"
        return f"{head}{self.n} {self.unit}, {elapsed:.1f} s elapsed"

    def _emit(self) -> None:
        if self.disable:
            return
        print(self._line(), file=self.file or sys.stderr, flush=True)
        self._printed_n = self.n
        self._last = time.perf_counter()

    def update(self, n: int = 1) -> None:
        self.n += int(n)
        if time.perf_counter() - self._last >= self.interval:
            self._emit()

    def update_to(self, n: int) -> None:
        self.update(int(n) - self.n)

    def set_postfix(self, *args, **kwargs) -> None:   # tqdm compatibility
        pass

    def refresh(self) -> None:
        pass

    def close(self) -> None:
        if not self.closed and self._printed_n != self.n and self.n > self.initial:
            self._emit()
        self.closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @staticmethod
    def write(message: str, file=None) -> None:
        print(message, file=file or sys.stderr, flush=True)


def progress_bar(total=None, initial: int = 0, desc: str = "", unit: str = "it", disable=None, **kwargs):
    """A tqdm bar on a terminal, a :class:`PlainProgress` otherwise (see the module docstring).

    Takes tqdm's keyword arguments; ``disable=True`` silences both."""
    style = progress_style(kwargs.get("file"))
    if disable is True or style == "off":
        return PlainProgress(total=total, initial=initial, desc=desc, unit=unit, disable=True)
    if style == "bar":
        try:
            from tqdm.auto import tqdm
        except ImportError:
            pass
        else:
            return tqdm(total=total, initial=initial, desc=desc, unit=unit, disable=False, **kwargs)
    return PlainProgress(total=total, initial=initial, desc=desc, unit=unit, file=kwargs.get("file"))


def _write(message: str, file=None) -> None:
    try:
        from tqdm.auto import tqdm
    except ImportError:
        PlainProgress.write(message, file)
    else:
        tqdm.write(message, file=file or sys.stderr)


progress_bar.write = _write   # tqdm.write stand-in: prints a line without breaking a bar


class Progress:
    """``Simulation.step(n, progress=True)``'s reporter: :func:`progress_bar` with ``update_to``."""

    def __init__(self, total: int, desc: str = "", unit: str = "step"):
        self.bar = progress_bar(total=total, desc=desc, unit=unit, leave=False)

    def update_to(self, n: int) -> None:
        self.bar.update(int(n) - self.bar.n)

    def close(self) -> None:
        self.bar.close()
