"""Pieces shared by the command-line commands: exit codes, error lines, progress lines and
the output options every solving command takes."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn

import click

EXIT_SOLVER_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_UNTRUSTED = 3  # solved, but the result is flagged (e.g. a wrong optimum)


def fail(message: str, code: int) -> NoReturn:
    click.echo(f"casmag: error: {message}", err=True)
    sys.exit(code)


def fail_bad_input(source: Path, exc: Exception) -> NoReturn:
    """Exit 2 with the first line of an unexpected ValueError/RuntimeError, naming the file."""
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    fail(f"{source}: {text}", EXIT_BAD_INPUT)


def print_progress(k: int, cost: float, step: float, seconds: float) -> None:
    # Unconstrained NLPs: the constraint violation is always 0, so the step is shown instead.
    click.echo(f"  iter {k:4d}  cost {cost:.6e}  step {step:.2e}  {seconds:7.2f} s", err=True)


def output_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """--out DIR (required), --set KEY.PATH=VALUE (repeatable), --no-figures, --quiet."""
    options = [
        click.option(
            "--out",
            "out_dir",
            required=True,
            type=click.Path(file_okay=False, path_type=Path),
            help="Output folder (replaced atomically).",
        ),
        click.option(
            "--set",
            "overrides",
            multiple=True,
            metavar="KEY.PATH=VALUE",
            help="Override a problem-file value (YAML syntax); repeatable.",
        ),
        click.option("--no-figures", is_flag=True, help="Skip the PNG figures."),
        click.option("--quiet", "-q", is_flag=True, help="No progress lines, nothing on success."),
    ]
    for option in reversed(options):
        command = option(command)
    return command
