"""Where the CLI's own lines land on stderr: always at the start of a line.

tqdm redraws its bar with ``\\r`` and no newline, so a message printed while
(or just after) a bar was shown would share the bar's line, and ``tail -1``
of a log would not be the message. :func:`tracked_stderr` wraps
``sys.stderr`` for the duration of a command and remembers whether the last
character written was a newline; :func:`fresh_line` closes the open bars and
ends a started line, so the next ``liris: ...`` line stands on its own.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator


class _LineTracker:
    """A text stream that forwards to ``stream`` and knows if a line is open."""

    def __init__(self, stream):
        self._stream = stream
        self.line_open = False

    def write(self, text: str) -> int:
        if text:
            self.line_open = not text.endswith("\n")
        return self._stream.write(text)

    def writelines(self, lines) -> None:
        for line in lines:
            self.write(line)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


@contextlib.contextmanager
def tracked_stderr() -> Iterator[None]:
    """Track ``sys.stderr`` (as :func:`fresh_line` needs) while the block runs."""
    original = sys.stderr
    if isinstance(original, _LineTracker) or original is None:
        yield
        return
    sys.stderr = _LineTracker(original)
    try:
        yield
    finally:
        sys.stderr = original


def close_bars() -> None:
    """Close every tqdm bar still open (a loop left by an exception keeps its bar)."""
    tqdm = sys.modules.get("tqdm")
    cls = getattr(tqdm, "tqdm", None)
    for bar in list(getattr(cls, "_instances", ()) or ()):
        with contextlib.suppress(Exception):
            bar.close()


def end_line() -> None:
    """End stderr's current line if one was started (a bar's frame), so a line follows."""
    stream = sys.stderr
    if getattr(stream, "line_open", False):
        stream.write("\n")
        with contextlib.suppress(Exception):
            stream.flush()


def fresh_line() -> None:
    """Close open bars, then end stderr's current line: the last words of a command follow."""
    close_bars()
    end_line()
