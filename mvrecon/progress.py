"""One progress bar style for every long stage (stderr, hidden with -q or when logging is quiet).

A bar of our own rather than tqdm's: importing tqdm cost 45-55 ms of every command's start-up (its version
lookup imports importlib.metadata and the email package), 1% of a whole `reconstruct` of the temples. A log
record clears the bar's line first (`clear_line`, installed as a logging filter by the CLI), so that messages
do not run on after the bar's text.
"""

import logging
import shutil
import sys
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import TextIO

_enabled = True
_shown = None  # the bar currently drawn on stderr's last line, if any


def set_enabled(enabled: bool) -> None:
    global _enabled
    _enabled = enabled


@contextmanager
def hidden() -> Iterator[None]:
    """No bar drawn inside the block (work run as one item of a stage that shows its own bar)."""
    global _enabled
    was, _enabled = _enabled, False
    try:
        yield
    finally:
        _enabled = was


def clear_line(record: logging.LogRecord | None = None) -> bool:
    """Erase the drawn bar (it is redrawn at its next update); usable as a logging filter, hence `record`."""
    global _shown
    if _shown is not None:
        _shown._erase()
        _shown = None
    return True


class Bar:
    """`update(n)`, `set_postfix_str(text)`, `close()`, and iteration over a wrapped iterable."""

    def __init__(self, iterable: Iterable | None = None, total: int | None = None, desc: str = "", unit: str = "it",
                 disable: bool = False, stream: TextIO | None = None, min_interval: float = 0.1):
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.iterable, self.total, self.desc, self.unit = iterable, total, desc, unit
        self.disable, self.stream, self.min_interval = disable, stream or sys.stderr, min_interval
        self.n, self.postfix, self.start, self._drawn_at, self._width = 0, "", time.monotonic(), -1.0, 0

    def __iter__(self):
        try:
            for item in self.iterable:
                yield item
                self.update(1)
        finally:  # finished, broken out of, or failed: the line is left clean (as tqdm's leave=False)
            self.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.monotonic()
        if not self.disable and (now - self._drawn_at >= self.min_interval or self.n == self.total):
            self._draw(now)

    def set_postfix_str(self, text: str) -> None:
        self.postfix = text
        if not self.disable:
            self._draw(time.monotonic())

    def close(self) -> None:
        global _shown
        if _shown is self:
            _shown = None
        self._erase()

    def text(self, now: float) -> str:
        elapsed = now - self.start
        rate = self.n / elapsed if elapsed > 0 else 0.0
        head = f"{self.desc}: " if self.desc else ""
        tail = f"{rate:.1f} {self.unit}/s" + (f", {self.postfix}" if self.postfix else "")
        if not self.total:
            return f"{head}{self.n} {self.unit} [{_clock(elapsed)}, {tail}]"
        frac = min(self.n / self.total, 1.0)
        eta = (self.total - self.n) / rate if rate > 0 else 0.0
        bar = "#" * round(20 * frac)
        return f"{head}{100 * frac:3.0f}% |{bar:<20}| {self.n}/{self.total} [{_clock(elapsed)}<{_clock(eta)}, {tail}]"

    def _draw(self, now: float) -> None:
        global _shown
        if _shown is not None and _shown is not self:
            _shown._erase()
        columns = shutil.get_terminal_size((100, 20)).columns - 1
        line = self.text(now)[:columns]
        self.stream.write("\r" + line + " " * max(self._width - len(line), 0))
        self.stream.flush()
        self._width, self._drawn_at, _shown = len(line), now, self

    def _erase(self) -> None:
        if self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()
            self._width = 0


def _clock(seconds: float) -> str:
    m, s = divmod(int(seconds), 60)
    return f"{m // 60}:{m % 60:02d}:{s:02d}" if m >= 60 else f"{m:02d}:{s:02d}"


def progress(iterable: Iterable | None = None, *, total: int | None = None, desc: str = "",
             unit: str = "it") -> Bar:
    """Wrap an iterable (or make a bar to `update()` by hand) with the project's progress bar."""
    disable = not _enabled or logging.getLogger("mvrecon").getEffectiveLevel() > logging.INFO
    return Bar(iterable, total=total, desc=desc, unit=unit, disable=disable)
