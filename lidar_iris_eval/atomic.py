"""The one atomic writer: a temporary file beside the target, then :func:`os.replace`.

Every file liris writes for the user (figures, reports, simulated scans,
exported descriptors and loops) goes through :func:`atomic_write`, so

* a reader sees either the old file or the complete new one, never half;
* a full disk, a read-only folder or a kill leaves no temporary file behind
  (the temporary name says which host and process owns it, see
  :func:`lidar_iris_eval.lifetime.temp_prefix`, so a killed writer's leftovers
  are recognised);
* the error names the *target* path and the cause in plain words
  (``liris: error: out/pr.png: cannot write the figure: no space left on the
  device``), not the temporary name;
* the file gets the permissions the umask allows (``mkstemp`` alone makes
  0600 files, which a group-shared results folder must not get).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from lidar_iris_eval.errors import LirisError, os_error
from lidar_iris_eval.lifetime import temp_prefix

Writer = Callable[[IO[bytes]], Any]


def umask() -> int:
    """The process umask (read by setting it and putting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write(path: str | os.PathLike, data: bytes | str | Writer, what: str = "file",
                 fsync: bool = False) -> Path:
    """Write ``data`` (bytes, text, or a callable given the open binary handle) to ``path``.

    Parameters
    ----------
    path : the target; its folder is created when missing.
    data : the content, or ``write(handle)``.
    what : what the file is, for the error (``"cannot write the <what>"``).
    fsync : flush to the device before the rename (cache files; slower).

    Raises
    ------
    LirisError
        Naming ``path`` when the write fails for an operating-system reason
        (``ENOSPC``, ``EACCES``, ``EROFS``...); no temporary file is left.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=temp_prefix(path.name),
                                   suffix=path.suffix)
    except OSError as err:
        raise os_error(err, path, f"cannot write the {what}") from None
    try:
        os.fchmod(fd, 0o666 & ~umask())
        with os.fdopen(fd, "wb") as handle:
            if isinstance(data, str):
                handle.write(data.encode("utf-8"))
            elif isinstance(data, (bytes, bytearray, memoryview)):
                handle.write(data)
            else:
                data(handle)
            handle.flush()
            if fsync:
                os.fsync(handle.fileno())
        os.replace(tmp, path)
    except OSError as err:
        Path(tmp).unlink(missing_ok=True)
        raise os_error(err, path, f"cannot write the {what}") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def figure_format(path: str | os.PathLike, flag: str) -> str:
    """The image format of ``path``'s suffix, or a LirisError naming ``flag`` and the path."""
    from matplotlib.figure import Figure

    path = Path(path)
    supported = Figure().canvas.get_supported_filetypes()
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in supported:
        shown = fmt and f"'.{fmt}'" or "no suffix"
        raise LirisError(f"{flag} {path}", f"unknown image format ({shown}); use one of "
                                           f"{', '.join('.' + s for s in sorted(supported))}")
    return fmt


def atomic_save_figure(fig: Any, path: str | os.PathLike, flag: str = "figure",
                       **savefig: Any) -> Path:
    """``fig.savefig`` through :func:`atomic_write`; the format comes from the suffix."""
    fmt = figure_format(path, flag)
    return atomic_write(path, lambda handle: fig.savefig(handle, format=fmt, **savefig),
                        what="figure")
