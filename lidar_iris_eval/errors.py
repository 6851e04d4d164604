"""User-facing error types and the one place that words them.

Every problem caused by the user's input or environment (a missing file, a
truncated scan, a bad option, a read-only or full disk) is raised as
:class:`LirisError`. The CLI turns it into one line on stderr and exit code 2,
without a traceback. Library users can catch it like any ``ValueError``.

Three helpers keep the wording the same everywhere:

* :func:`os_error` turns an :class:`OSError` (``EACCES``, ``EROFS``,
  ``ENOSPC``, ``ENOTDIR``...) into a :class:`LirisError` naming the path and
  the cause in plain words; the CLI applies it to any ``OSError`` that reaches
  it, so a new write site needs no code of its own.
* :func:`read_text` reads a text file the user named and reports a binary or
  wrongly encoded file as one error naming the file, not a ``UnicodeDecodeError``.
* :func:`option` / :func:`options` name a library keyword the way the user
  gave it: ``--lidar-frame-poses`` on the command line (the CLI registers its
  flags with :func:`register_flags`), ``lidar_frame=True`` in Python.
"""

from __future__ import annotations

import errno
import os
import shutil
import warnings
from collections.abc import Iterable, Mapping
from pathlib import Path


class LirisError(ValueError):
    """A problem with the user's input, reported as one line naming its source."""

    def __init__(self, source: str | os.PathLike | None, problem: str):
        self.source = None if source is None else str(source)
        self.problem = problem
        text = problem if self.source is None else f"{self.source}: {problem}"
        super().__init__(text)

    def __reduce__(self):
        # The two-argument constructor does not survive default pickling, which
        # replays ``args`` (one string); rebuild from the two parts instead.
        return (type(self), (self.source, self.problem))


class LirisWarning(UserWarning):
    """A recoverable input problem, such as NaN points that were dropped."""


def warn(source: str | os.PathLike | None, message: str) -> None:
    """Emit a :class:`LirisWarning` naming its source (a file or option)."""
    text = message if source is None else f"{source}: {message}"
    warnings.warn(text, LirisWarning, stacklevel=2)


# --- operating-system errors -------------------------------------------------

#: errno -> the cause in plain words (the rest fall back to ``strerror``)
_OS_CAUSES = {
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EROFS: "read-only file system",
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "disk quota exceeded",
    errno.ENOENT: "no such file or folder",
    errno.EISDIR: "is a folder, not a file",
    errno.EEXIST: "already exists",
    errno.ENAMETOOLONG: "file name too long",
    errno.EIO: "input/output error",
    errno.EMFILE: "too many open files",
}


def os_error(err: OSError, path: str | os.PathLike | None = None, action: str = "") -> LirisError:
    """The :class:`LirisError` for ``err``: the path it concerns and the cause in plain words.

    Parameters
    ----------
    err : the operating-system error.
    path : the path to name when ``err`` carries none (or a clearer one).
    action : what was being done, e.g. ``"cannot write the run folder"``.
    """
    target = path if path is not None else (err.filename if err.filename is not None else None)
    if isinstance(target, bytes):
        target = os.fsdecode(target)
    if err.errno == errno.ENOTDIR and target is not None:
        blocker = file_in_the_way(Path(target))
        cause = (f"{blocker} is a file, so it cannot hold a folder" if blocker is not None
                 else "a part of this path is a file, not a folder")
    elif err.errno is None and target is not None and _nearly_full(Path(target)):
        cause = _OS_CAUSES[errno.ENOSPC]  # NumPy's short-write OSError carries no errno
    else:
        cause = (_OS_CAUSES.get(err.errno) or err.strerror or str(err)
                 or type(err).__name__).lower()
    if err.filename2 is not None and path is None:
        cause += f" (with {os.fsdecode(err.filename2)})"
    return LirisError(target, f"{action}: {cause}" if action else cause)


def _nearly_full(path: Path) -> bool:
    """True when the file system holding ``path`` has less than 1 MiB free."""
    existing = next((p for p in [path, *path.parents] if p.exists()), None)
    try:
        return existing is not None and shutil.disk_usage(existing).free < 2**20
    except OSError:
        return False


def file_in_the_way(path: Path) -> Path | None:
    """The first ancestor of ``path`` (or itself) that exists and is not a folder."""
    for candidate in reversed([path, *path.parents]):
        if candidate.exists() and not candidate.is_dir():
            return candidate
    return None


def check_writable_dir(folder: str | os.PathLike, what: str) -> Path:
    """Raise a :class:`LirisError` now if ``folder`` cannot be created or written.

    Called before long work so that a read-only, missing-parent or
    file-in-the-way output location fails at once, not after an hour. Creates
    nothing that stays: the nearest existing ancestor is probed with a
    temporary file (``os.access`` is wrong for root, ACLs and read-only
    mounts). Full disks cannot be predicted; writes stay atomic for those.
    """
    folder = Path(folder)
    blocker = file_in_the_way(folder)
    if blocker is not None:
        problem = ("is a file, not a folder" if blocker == folder
                   else f"cannot be created: {blocker} is a file")
        raise LirisError(folder, f"{what} {problem}")
    existing = next(p for p in [folder, *folder.parents] if p.exists() or p == Path(p.anchor))
    probe = existing / f".liris-write-test-{os.getpid()}"
    try:
        fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
        os.close(fd)
        os.unlink(probe)
    except FileExistsError:
        pass
    except OSError as err:
        where = "" if existing == folder else f" (creating it inside {existing})"
        raise os_error(err, folder, f"cannot write the {what}{where}") from None
    return folder


# --- text files ----------------------------------------------------------------


def read_text(path: str | os.PathLike, what: str) -> str:
    """The text of a file the user named, or one :class:`LirisError` naming it.

    A binary file, a UTF-16 file or any file that is not UTF-8 is reported
    with the offset of the first bad byte; OS errors go through :func:`os_error`.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise os_error(err, path, f"cannot read the {what}") from None
    if data[:2] in (b"\xff\xfe", b"\xfe\xff") or b"\x00" in data[:4096]:
        kind = "UTF-16" if data[:2] in (b"\xff\xfe", b"\xfe\xff") else "binary"
        raise LirisError(path, f"{what} is a {kind} file, not UTF-8 text")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise LirisError(path, f"{what} is not UTF-8 text (byte 0x{data[err.start]:02x} at "
                               f"offset {err.start})") from None


# --- naming options as the user gave them -----------------------------------------

_FLAGS: dict[str, str] = {}


def register_flags(mapping: Mapping[str, str]) -> None:
    """Tell :func:`option` how the CLI spells library keywords (``lidar_frame`` -> flag)."""
    _FLAGS.update(mapping)


def option(keyword: str, value: object = ...) -> str:
    """``keyword`` (with ``value``) as the user wrote it: a CLI flag or a Python keyword."""
    flag = _FLAGS.get(keyword)
    if flag is not None:
        if value is ... or isinstance(value, bool):
            return flag
        return f"{flag} {value}"
    return keyword if value is ... else f"{keyword}={value!r}"


def options(keywords: Iterable[str]) -> str:
    """Several keywords as the user wrote them, comma-separated."""
    return ", ".join(option(k) for k in sorted(keywords))
