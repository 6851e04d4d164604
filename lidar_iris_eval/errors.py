"""User-facing error types.

Every problem caused by the user's input (a missing file, a truncated scan, a
bad option) is raised as :class:`LirisError`. The CLI turns it into one line on
stderr and exit code 2, without a traceback. Library users can catch it like any
``ValueError``.
"""

from __future__ import annotations

import os
import warnings


class LirisError(ValueError):
    """A problem with the user's input, reported as one line naming its source."""

    def __init__(self, source: str | os.PathLike | None, problem: str):
        self.source = None if source is None else str(source)
        self.problem = problem
        text = problem if self.source is None else f"{self.source}: {problem}"
        super().__init__(text)


class LirisWarning(UserWarning):
    """A recoverable input problem, such as NaN points that were dropped."""


def warn(source: str | os.PathLike | None, message: str) -> None:
    """Emit a :class:`LirisWarning` naming its source (a file or option)."""
    text = message if source is None else f"{source}: {message}"
    warnings.warn(text, LirisWarning, stacklevel=2)
