"""The ``liris`` command line: a thin click layer over the Python API.

Each subcommand lives in its own module in this package and is registered on
the :func:`cli` group below. Parsing and printing only; all work is done by the
library so that researchers can import it.
"""

from __future__ import annotations

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
from lidar_iris_eval.errors import LirisError, LirisWarning

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
    """Evaluate LiDAR loop-closure descriptors (LiDAR Iris, Scan Context, M2DP, ESF)."""
    warnings.showwarning = _show_warning


def _register_commands() -> None:
    """Attach every subcommand module that exists; each defines ``command``."""
    import importlib

    for module_name in ("gt", "simulate", "extract", "eval", "plot", "bench"):
        try:
            module = importlib.import_module(f"lidar_iris_eval.cli.{module_name}_cmd")
        except ModuleNotFoundError as err:
            if err.name != f"lidar_iris_eval.cli.{module_name}_cmd":
                raise
            continue
        cli.add_command(module.command)


_register_commands()


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point.

    Usage errors from click (an unknown option value, a missing argument) are
    folded into one line and exit code 2, like every other bad input.
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
        click.echo(f"liris: error: {err}", err=True)
        sys.exit(EXIT_BAD_INPUT)
