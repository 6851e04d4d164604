"""Worker processes that die with their parent.

A SIGKILL (or an out-of-memory kill) of ``liris`` gives its pool no chance to
shut down; without help the workers keep computing for nobody (57 s measured).
:func:`die_with_parent`, called first in every pool worker, closes that gap
twice over:

* on Linux, ``prctl(PR_SET_PDEATHSIG, SIGKILL)`` asks the kernel to kill the
  worker the moment its parent dies;
* everywhere, a daemon thread polls the parent pid once a second and exits
  the worker when it has changed (the parent is gone, the worker re-parented).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import re
import shutil
import signal
import socket
import sys
import threading
from pathlib import Path

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
POLL_SECONDS = 1.0


def die_with_parent(parent_pid: int, poll_seconds: float = POLL_SECONDS) -> None:
    """Make this process exit when ``parent_pid`` (the process that made the pool) dies.

    The direct parent may differ from ``parent_pid`` (a fork server); the
    worker then watches both.
    """
    direct = os.getppid()
    # Ctrl-C reaches the whole process group: the parent reports it once and
    # shuts the pool down; a worker's own KeyboardInterrupt traceback is noise.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):
            pass  # the watchdog below still applies

    def orphaned() -> bool:
        return os.getppid() != direct or not _alive(parent_pid)

    if orphaned():  # the parent died before the kernel was told to watch it
        os._exit(1)

    def watch() -> None:
        while not orphaned():
            threading.Event().wait(poll_seconds)
        os._exit(1)

    threading.Thread(target=watch, name="liris-parent-watchdog", daemon=True).start()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# --- temporary files and folders that outlive a killed process -----------------------

#: this host, as it appears in temporary names (only its own leftovers are removed)
HOST = "".join(c if c.isalnum() else "_" for c in socket.gethostname()) or "host"
_TEMP = re.compile(r"^\..+\.tmp-(?P<host>[A-Za-z0-9_]+)-(?P<pid>\d+)-[A-Za-z0-9_]+(\.\w+)?$")


def temp_prefix(name: str) -> str:
    """``.<name>.tmp-<host>-<pid>-``: a temporary name that says who owns it."""
    return f".{name}.tmp-{HOST}-{os.getpid()}-"


def remove_stale_temps(folder: str | os.PathLike) -> list[Path]:
    """Delete temporary files and folders (:func:`temp_prefix`) whose process is gone.

    Only entries made on this host by a process that no longer exists are
    removed (a live process, or one on another host sharing the disk, is left
    alone). Returns what was removed.
    """
    removed: list[Path] = []
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return removed
    for entry in entries:
        match = _TEMP.match(entry.name)
        if match is None or match["host"] != HOST or _alive(int(match["pid"])):
            continue
        if entry.is_dir():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
        removed.append(entry)
    return removed
