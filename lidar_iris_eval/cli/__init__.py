"""The ``liris`` command line: a thin click layer over the Python API.

Each subcommand lives in its own module in this package and is registered on
the :func:`cli` group below. Parsing and printing only; all work is done by the
library so that researchers can import it.
"""

from __future__ import annotations

import math
import os
import sys
import warnings

# Our kernels are numba-threaded or sized for one BLAS thread. OpenBLAS's own
# threads spin while waiting and, on a busy 2-core laptop, made Scan Context's
# all-pairs pass 8x slower (17.8 s -> 141.8 s measured), so the CLI defaults to
# one BLAS thread. Set OPENBLAS_NUM_THREADS yourself to override.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import click

from lidar_iris_eval import __version__
from lidar_iris_eval.errors import LirisError, LirisWarning, os_error, register_flags

EXIT_BAD_INPUT = 2


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Print liris warnings as one plain line instead of Python's source dump."""
    if issubclass(category, LirisWarning):
        print(f"liris: warning: {message}", file=sys.stderr)
    else:
        _default_showwarning(message, category, filename, lineno, file, line)


_default_showwarning = warnings.showwarning


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="liris")
def cli() -> None:
    """Evaluate LiDAR loop-closure descriptors (LiDAR Iris, Scan Context, M2DP, ESF,
    GOSMatch, ESM) under protocol 1 (best match) and protocol 2 (all pairs).

    Start with `liris simulate OUT` and `liris eval OUT -d lidar-iris`.
    """
    warnings.showwarning = _show_warning


def _register_commands() -> None:
    """Attach every subcommand module that exists; each defines ``command``."""
    import importlib

    for module_name in ("gt", "simulate", "extract", "eval", "plot", "bench", "show", "compare",
                        "report", "datasets"):
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


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point.

    Usage errors from click (an unknown option value, a missing argument) are
    folded into one line and exit code 2, like every other bad input. So are
    operating-system errors (a read-only or full disk, a path under a file):
    they name the path through :func:`lidar_iris_eval.errors.os_error`, and
    every writer is atomic, so nothing half-written is left behind.
    """
    try:
        cli.main(args=argv, prog_name="liris", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("liris: aborted", err=True)
        sys.exit(130)
    except click.ClickException as err:
        click.echo(f"liris: error: {err.format_message()}", err=True)
        sys.exit(EXIT_BAD_INPUT)
    except LirisError as err:
        _fail(err)
    except BrokenPipeError:
        # stdout closed early (``liris ... | head``): not an error of the user's input.
        sys.stderr.close()
        sys.exit(141)
    except OSError as err:
        _fail(os_error(err))
    except UnicodeDecodeError as err:
        _fail(LirisError(None, f"a file is not UTF-8 text ({err.reason} at byte {err.start})"))


def _fail(err: LirisError) -> None:
    """One line on stderr, exit code 2."""
    text = " ".join(str(err).split())  # one line, even if a message carries a newline
    click.echo(f"liris: error: {text}", err=True)
    sys.exit(EXIT_BAD_INPUT)
