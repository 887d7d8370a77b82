"""Progress on stderr: a tqdm bar on a terminal, a plain line every few seconds elsewhere.

A bar redrawn with carriage returns is unreadable in a log file, a CI job or
``make`` output, so when stderr is not a terminal :func:`progress` writes one
line at most every :data:`INTERVAL` seconds and a final line when the loop
ends, e.g. ``relight synth-capture: 12/40 frames (30%)``.  ``quiet`` silences
both.  Standard library only (tqdm is imported for a terminal only); the engine
may use it, so it never imports click.
"""

from __future__ import annotations

import sys
import time

#: Seconds between two plain progress lines.
INTERVAL = 5.0

# The running command's name for the plain lines ("relight synth-capture"); the CLI
# sets it (relight_cli.cli.tools.quiet_option), library use keeps "relight".
_COMMAND = ["relight"]


def set_command(name: str) -> None:
    _COMMAND[0] = name


# Called once, before the first progress bar or line is shown (then forgotten): the CLI
# holds a command's log lines until its work shows progress, and says them here, so that
# they keep their place before it (relight_cli.cli.tools.held_log_lines).  None: nothing.
_BEFORE_SHOWN = [None]


def before_shown(callback) -> None:
    """Run ``callback`` (or nothing: None) before the next progress is first shown."""
    _BEFORE_SHOWN[0] = callback


def _shown() -> None:
    callback, _BEFORE_SHOWN[0] = _BEFORE_SHOWN[0], None
    if callback is not None:
        callback()


def progress(iterable=None, total=None, desc: str = "", quiet: bool = False, initial: int = 0,
             unit: str = "", stream=None, clock=time.monotonic, interval: float | None = None):
    """An iterable/updatable progress object on ``stream`` (stderr).

    Used like tqdm: iterate over it, or ``update(n)`` / ``set_postfix(dict)`` /
    ``close()`` (also as a context manager).  ``clock`` and ``interval`` are for tests.
    """
    stream = sys.stderr if stream is None else stream
    if total is None and iterable is not None and hasattr(iterable, "__len__"):
        total = len(iterable)
    if quiet:
        return PlainProgress(iterable, total, desc, initial, unit, None, clock, interval)
    if _is_terminal(stream):
        _shown()
        from tqdm import tqdm
        return tqdm(iterable, total=total, desc=desc, initial=initial, file=stream, leave=False,
                    dynamic_ncols=True, **({"unit": unit} if unit else {}))
    return PlainProgress(iterable, total, desc, initial, unit, stream, clock, interval)


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


class PlainProgress:
    """tqdm's small API (iterate, update, set_postfix, close) as plain lines.

    A line is written when at least ``interval`` seconds passed since the last
    one (or the start), and once at the end (exhausted iteration, ``close()``, or
    a ``with`` block left without an exception; not twice when the last update
    said the same line); an error leaves no final line,
    so a failing command still prints its one error line last.  ``stream=None``
    writes nothing (``--quiet``).
    """

    def __init__(self, iterable=None, total=None, desc="", initial=0, unit="", stream=None,
                 clock=time.monotonic, interval=None):
        self.iterable = iterable
        self.total = total
        self.desc = desc
        self.n = int(initial)
        self.unit = unit
        self.stream = stream
        self.clock = clock
        self.interval = INTERVAL if interval is None else float(interval)
        self.postfix = ""
        self._last = clock()
        self._closed = False

    def __iter__(self):
        for item in self.iterable:
            yield item
            self.update(1)
        self.close()

    def __len__(self):
        return self.total if self.total is not None else len(self.iterable)

    def __enter__(self):
        return self

    def __exit__(self, kind, value, traceback):
        if kind is None:
            self.close()
        else:
            self._closed = True

    def update(self, n: int = 1) -> None:
        self.n += n
        now = self.clock()
        if now - self._last >= self.interval:
            self._write()
            self._last = now

    def set_postfix(self, values=None, refresh: bool = True, **kwargs) -> None:
        values = dict(values or {}, **kwargs)
        self.postfix = ", ".join(f"{k}={v}" for k, v in values.items())

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._write()

    def line(self) -> str:
        """``relight CMD: N/TOTAL DESC (P%)``, with the postfix after a semicolon."""
        what = {"it": "iterations"}.get(self.unit, self.unit) or self.desc or "steps"
        if self.total:
            text = f"{self.n}/{self.total} {what} ({100 * self.n // self.total}%)"
        else:
            text = f"{self.n} {what}"
        if self.postfix:
            text += f"; {self.postfix}"
        return f"{_COMMAND[0]}: {text}"

    def _write(self) -> None:
        if self.stream is None:
            return
        line = self.line()
        if line == getattr(self, "_said", None):
            return          # the final line of a bar whose last update said it already
        _shown()
        self._said = line
        self.stream.write(line + "\n")
        self.stream.flush()


class LateProgress:
    """Progress over ``total`` units of work shown only once the work looks long: after
    ``seconds`` / 5 have passed, if the units done so far project a total of at least
    ``seconds`` (elapsed × total / done), :func:`progress` opens at the units done; short
    work stays silent.  ``update(n)`` / ``close()`` as :func:`progress`'s object."""

    def __init__(self, total: int, desc: str = "", unit: str = "", quiet: bool = False,
                 seconds: float = 5.0, clock=time.monotonic):
        self.total, self.desc, self.unit, self.quiet = total, desc, unit, quiet
        self.seconds, self.clock, self.done, self.bar = float(seconds), clock, 0, None
        self.start = clock()

    def update(self, n: int = 1) -> None:
        self.done += n
        if self.bar is not None:
            self.bar.update(n)
        elif not self.quiet and self.done > 0:
            elapsed = self.clock() - self.start
            if elapsed >= self.seconds / 5 and elapsed * self.total >= self.seconds * self.done:
                self.bar = progress(total=self.total, initial=self.done, desc=self.desc,
                                    unit=self.unit)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
