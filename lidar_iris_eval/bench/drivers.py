"""Reference implementations built by the user, timed in the same run: ``liris bench --cpp DIR``.

A C++ ratio is only printed when both sides were timed in the same run, on
the same scans and the same CPU. The reference side is a small *driver*
program per descriptor that the user builds from the authors' code; liris
never builds, downloads or ships one.

Driver contract
---------------
* ``DIR/<descriptor>`` is an executable, named after the liris descriptor
  (``lidar-iris``, ``scan-context``, ``esf``, ``m2dp``). Descriptors without a
  driver in ``DIR`` get no ratio.
* It is run as ``DIR/<descriptor> LIST``, where ``LIST`` is a text file with
  one KITTI ``.bin`` path per line (float32 x, y, z, intensity).
* For every scan, in list order, it prints one line to stdout::

      extract <path> <milliseconds>

  the CPU time of computing that scan's descriptor once the points are in
  memory (file reading excluded), single-threaded, in milliseconds.
* Optionally, for pairs it compares, one line each::

      pair <path_a> <path_b> <microseconds>

  the CPU time of one comparison of the two descriptors.
* Other lines, and lines starting with ``#``, are ignored. Exit status 0.

liris runs the driver with one thread per library (``OMP_NUM_THREADS=1`` and
the like), pinned to the CPU that times liris's own code, alternating with it
round by round; the ratio is the median of ours / theirs over scans, each a
median over rounds.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError

#: descriptors a driver may be given for
DRIVER_NAMES = ("lidar-iris", "scan-context", "esf", "m2dp")
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                "NUMBA_NUM_THREADS")


def find_drivers(folder: str | os.PathLike) -> dict[str, Path]:
    """The executable drivers of ``folder`` by descriptor name (see the module docstring)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise LirisError(str(folder), "no such folder (--cpp)")
    found = {name: folder / name for name in DRIVER_NAMES
             if (folder / name).is_file() and os.access(folder / name, os.X_OK)}
    if not found:
        raise LirisError(str(folder), "no driver: expected an executable named one of "
                         + ", ".join(DRIVER_NAMES) + " (--cpp)")
    return found


def parse_output(text: str, paths: Sequence[str], source: str) -> dict:
    """``{"extract_ms": [...] in list order, "pair_us": [...]}`` from a driver's stdout.

    Every scan of ``paths`` must have exactly one ``extract`` line with a
    finite, non-negative time; anything else is an error naming the driver.
    """
    extract: dict[str, float] = {}
    pairs: list[float] = []
    for number, line in enumerate(text.splitlines(), 1):
        fields = line.split()
        if not fields or fields[0].startswith("#") or fields[0] not in ("extract", "pair"):
            continue
        want = 3 if fields[0] == "extract" else 4
        try:
            if len(fields) != want:
                raise ValueError
            value = float(fields[-1])
        except ValueError:
            raise LirisError(source, f"output line {number}: expected '{fields[0]} "
                             + ("<path> <ms>" if want == 3 else "<path_a> <path_b> <us>")
                             + f"', got {line.strip()!r}") from None
        if not np.isfinite(value) or value < 0:
            raise LirisError(source, f"output line {number}: time {fields[-1]} is not a "
                             "finite non-negative number")
        if fields[0] == "pair":
            pairs.append(value)
        elif fields[1] in extract:
            raise LirisError(source, f"output line {number}: second time for {fields[1]}")
        else:
            extract[fields[1]] = value
    missing = [p for p in paths if p not in extract]
    if missing:
        raise LirisError(source, f"printed no 'extract' line for {len(missing)} of "
                         f"{len(paths)} scans (first: {missing[0]})")
    return {"extract_ms": [extract[p] for p in paths], "pair_us": pairs}


def run_driver(driver: Path, paths: Sequence[str], timeout_s: float = 600.0) -> dict:
    """Run one driver on ``paths`` (one thread per library); its parsed per-scan times."""
    env = dict(os.environ)
    env.update({var: "1" for var in _THREAD_VARS})
    with tempfile.TemporaryDirectory(prefix="liris-cpp-") as tmp:
        listing = Path(tmp) / "scans.txt"
        listing.write_text("".join(f"{p}\n" for p in paths))
        try:
            done = subprocess.run([str(driver), str(listing)], capture_output=True, text=True,
                                  env=env, timeout=timeout_s, check=False)
        except subprocess.TimeoutExpired:
            raise LirisError(str(driver), f"driver did not finish in {timeout_s:.0f} s") from None
        except OSError as err:
            raise LirisError(str(driver), f"cannot run the driver: {err.strerror}") from None
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise LirisError(str(driver), f"driver failed (exit {done.returncode}): {tail}")
    return parse_output(done.stdout, list(paths), str(driver))
