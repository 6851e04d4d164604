"""The ``liris`` command line: a thin click layer over the Python API.

Each subcommand lives in its own module in this package and is registered on
the :func:`cli` group below. Parsing and printing only; all work is done by the
library so that researchers can import it.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import threading
import warnings
from collections.abc import Callable
from typing import TypeVar

# Our kernels are numba-threaded or sized for one BLAS thread. OpenBLAS's own
# threads spin while waiting and, on a busy 2-core laptop, made Scan Context's
# all-pairs pass 8x slower (17.8 s -> 141.8 s measured), so the CLI defaults to
# one BLAS thread. Set OPENBLAS_NUM_THREADS yourself to override.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import click

from lidar_iris_eval import __version__
from lidar_iris_eval.cli.terminal import end_line, fresh_line, tracked_stderr
from lidar_iris_eval.errors import LirisError, LirisWarning, os_error, register_flags

EXIT_BAD_INPUT = 2
#: exit code of a run stopped by Ctrl-C (128 + SIGINT), as shells report it
EXIT_INTERRUPTED = 130

T = TypeVar("T")


def _interrupted_during_startup(signum, frame):  # pragma: no cover - timing dependent
    """Ctrl-C while the commands are being imported: nothing is written yet, so stop here."""
    sys.stderr.write("\nliris: interrupted\n")
    sys.stderr.flush()
    os._exit(EXIT_INTERRUPTED)


def _on_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


# Start-up (importing NumPy, numba and every command) takes a second or two; a
# Ctrl-C then printed a KeyboardInterrupt traceback. The handler is put back at
# the end of this module, so importing the package as a library changes nothing.
_STARTUP_SIGINT = (signal.signal(signal.SIGINT, _interrupted_during_startup)
                   if _on_main_thread() else None)


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Print every warning as one plain line instead of Python's source dump.

    A liris warning is its message; another library's (NumPy's RuntimeWarning,
    matplotlib's UserWarning) keeps its category name so it can be searched
    for, but loses the ``/site-packages/...py:218:`` prefix and the source line,
    which say nothing to a user and break ``grep warning`` on a log.
    """
    end_line()  # a bar keeps running; its next frame starts below the warning
    text = " ".join(str(message).split())
    if issubclass(category, LirisWarning):
        print(f"liris: warning: {text}", file=sys.stderr)
    else:
        print(f"liris: warning: {category.__name__}: {text}", file=sys.stderr)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="liris")
def cli() -> None:
    """Evaluate LiDAR loop-closure descriptors (LiDAR Iris, Scan Context, M2DP, ESF,
    GOSMatch, ESM, OverlapTransformer) under protocol 1 (best match) and protocol 2 (all pairs).

    Start with `liris simulate OUT` and `liris eval OUT -d lidar-iris`.
    """
    warnings.showwarning = _show_warning


def _register_commands() -> None:
    """Attach every subcommand module that exists; each defines ``command``."""
    import importlib

    for module_name in ("gt", "simulate", "extract", "eval", "plot", "bench", "show", "compare",
                        "report", "datasets", "segments"):
        try:
            module = importlib.import_module(f"lidar_iris_eval.cli.{module_name}_cmd")
        except ModuleNotFoundError as err:
            if err.name != f"lidar_iris_eval.cli.{module_name}_cmd":
                raise
            continue
        cli.add_command(module.command)


_register_commands()


class FiniteFloat(click.types.FloatParamType):
    """A float option that refuses ``nan`` and ``inf`` (Python's float() accepts both)."""

    def convert(self, value, param, ctx):
        number = super().convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return number


def _finite_floats() -> None:
    """Give every float option of every subcommand the finite check, in one place."""
    finite = FiniteFloat()
    for command in cli.commands.values():
        for param in command.params:
            if isinstance(param.type, click.types.FloatParamType) and not isinstance(
                    param.type, FiniteFloat):
                param.type = finite


def _register_reader_flags() -> None:
    """Let library errors name reader keywords by the flags that set them.

    ``open_sequence(lidar_frame=True)`` is ``--lidar-frame-poses`` here, so an
    error about it says so (see :func:`lidar_iris_eval.errors.option`).
    """
    from lidar_iris_eval.cli.sequence_options import _KEYWORDS

    keywords = {**_KEYWORDS, "poses_path": "poses", "calib_path": "calib"}
    flags: dict[str, str] = {}
    for command in cli.commands.values():
        for param in command.params:
            if isinstance(param, click.Option) and param.name in keywords:
                flags[keywords[param.name]] = max(param.opts, key=len)
    register_flags(flags)


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _check_workers(ctx, param, value):
    """``--workers``: at least 1; more than the usable CPUs is clamped, with a warning
    (1000 processes on 2 cores only thrash: load 118 measured)."""
    if value is None:
        return value
    if value < 1:
        raise click.BadParameter(f"must be at least 1, got {value}", ctx=ctx, param=param)
    cpus = usable_cpus()
    if value > cpus:
        from lidar_iris_eval.errors import warn

        warn(f"--workers {value}", f"more than the {cpus} usable CPU(s); using {cpus}")
        return cpus
    return value


def _clamped_workers() -> None:
    """Give every ``--workers`` option the check above, in one place."""
    for command in cli.commands.values():
        for param in command.params:
            if isinstance(param, click.Option) and param.name == "workers":
                param.callback = _check_workers


_register_reader_flags()
_finite_floats()
_clamped_workers()
if _STARTUP_SIGINT is not None:
    signal.signal(signal.SIGINT, _STARTUP_SIGINT)


class _Interrupts:
    """SIGINT as a ``KeyboardInterrupt`` that is remembered once raised.

    Code interrupted inside a compiled kernel may turn the interrupt into
    another exception (numba reports a ``SystemError``); the flag lets
    :func:`main` still report it as an interrupt.
    """

    def __init__(self):
        self.seen = False
        self._previous = None

    def _handler(self, signum, frame):
        self.seen = True
        raise KeyboardInterrupt

    def __enter__(self):
        if _on_main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handler)
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
        return False


def _caused_by_interrupt(err: BaseException) -> bool:
    """True when ``err`` is, or was raised while handling, a ``KeyboardInterrupt``."""
    seen: set[int] = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt):
            return True
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return False


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point.

    Usage errors from click (an unknown option value, a missing argument) are
    folded into one line and exit code 2, like every other bad input. So are
    operating-system errors (a read-only or full disk, a path under a file):
    they name the path through :func:`lidar_iris_eval.errors.os_error`, and
    every writer is atomic, so nothing half-written is left behind. Ctrl-C
    prints ``liris: interrupted`` and exits 130, whatever was running. Every
    such line starts on a line of its own, after any progress bar.
    """
    run_guarded(lambda: cli.main(args=argv, prog_name="liris", standalone_mode=False))


def run_guarded(body: Callable[[], T]) -> T:
    """Run ``body`` and end it the way every ``liris`` command ends.

    The one place that words an ending: the CLI's entry point and the
    maintainer scripts (``scripts/*.py``, which parse with argparse or their
    own click command) both go through it, so a bad input there is the same
    single ``liris: error:`` line with exit code 2, an ``OSError`` names its
    path, and Ctrl-C is ``liris: interrupted`` with exit 130.

    Parameters
    ----------
    body : the work, called with no arguments.

    Returns
    -------
    What ``body`` returns when it ends normally.
    """
    with tracked_stderr(), _Interrupts() as interrupts:
        try:
            return body()
        except SystemExit:
            if interrupts.seen:
                _interrupted()
            raise
        except BaseException as err:  # noqa: BLE001 - every ending is worded below
            if interrupts.seen or _caused_by_interrupt(err):
                _interrupted()
            _handle(err)
            raise  # pragma: no cover - _handle exits or re-raises


def _handle(err: BaseException) -> None:
    """Word an exception that ended a command (re-raise one that is not the user's)."""
    if isinstance(err, click.exceptions.Abort):
        _stop("liris: aborted", EXIT_INTERRUPTED)
    if isinstance(err, click.ClickException):
        _stop(f"liris: error: {err.format_message()}", EXIT_BAD_INPUT)
    if isinstance(err, LirisError):
        _fail(err)
    if isinstance(err, BrokenPipeError):
        # stdout closed early (``liris ... | head``): not an error of the user's input.
        sys.stderr.close()
        sys.exit(141)
    if isinstance(err, OSError):
        _fail(os_error(err))
    if isinstance(err, UnicodeDecodeError):
        _fail(LirisError(None, f"a file is not UTF-8 text ({err.reason} at byte {err.start})"))
    raise err


def _stop(line: str, code: int) -> None:
    """``line`` on a line of its own on stderr (after closing progress bars), then exit."""
    fresh_line()
    click.echo(line, err=True)
    sys.exit(code)


def _interrupted() -> None:
    """``liris: interrupted``, exit 130 at once.

    The exception has unwound every ``with`` and ``finally`` by now (partial
    outputs removed, worker pools stopped), so nothing is left to clean up;
    what remains is the interpreter's own teardown of the compiled libraries,
    which took 1.2 s of the 1.6 s a Ctrl-C needed during registration
    (measured under load). ``os._exit`` skips it, as the start-up handler does.
    """
    fresh_line()
    click.echo("liris: interrupted", err=True)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(EXIT_INTERRUPTED)


def _fail(err: LirisError) -> None:
    """One line on stderr, exit code 2."""
    text = " ".join(str(err).split())  # one line, even if a message carries a newline
    _stop(f"liris: error: {text}", EXIT_BAD_INPUT)
