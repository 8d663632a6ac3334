"""``casmag sweep FILES --out DIR``: a problem or table file over seeds (and grids), in
parallel and resumable (casmag.experiments.sweep)."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from casmag.cli.tools import (
    EXIT_SOLVER_FAILED,
    distinct_set_keys,
    fail,
    fail_error,
)
from casmag.errors import CasmagError, ProblemError
from casmag.experiments.sweep import SweepAborted, load_sweep, run_sweeps
from casmag.interrupt import Interrupted
from casmag.result.outdir import check_output_dir


@click.command("sweep")
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--out",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=Path),
    help="Output folder; with several FILES, one subfolder per file (its table name).",
)
@click.option(
    "--seeds", default=20, show_default=True, type=click.IntRange(1), help="Seeds per row."
)
@click.option("--first-seed", type=int, default=None, help="First seed [default: the problem's].")
@click.option(
    "--grid",
    multiple=True,
    metavar="KEY.PATH=V1,V2,...",
    help="Solve every value (YAML syntax); repeatable, every combination is a row.",
)
@click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="KEY.PATH=VALUE",
    callback=distinct_set_keys,
    help="Override a problem-file value for every run; repeatable.",
)
@click.option(
    "--jobs",
    "-j",
    type=click.IntRange(1),
    default=None,
    help="Local worker processes [default: cores].",
)
@click.option(
    "--scheduler",
    metavar="ADDRESS",
    default=None,
    help="Run on a Dask distributed cluster (e.g. tcp://10.0.0.2:8786) instead of locally.",
)
@click.option(
    "--figures",
    type=click.Choice(["first", "all", "none"]),
    default="first",
    show_default=True,
    help="PNG figures for the first seed of each row, every run, or none.",
)
@click.option("--rerun", is_flag=True, help="Solve finished runs again.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or summary.")
def sweep_command(
    files: tuple[Path, ...],
    out_dir: Path,
    seeds: int,
    first_seed: int | None,
    grid: tuple[str, ...],
    overrides: tuple[str, ...],
    jobs: int | None,
    scheduler: str | None,
    figures: str,
    rerun: bool,
    quiet: bool,
) -> None:
    """Solve problem or table FILES over seeds (and a --grid) in parallel; resumable.

    Each run is saved in OUT/<row>/seed-<seed>/ (as casmag run does), OUT/sweep.json lists the
    rows; `casmag report OUT` tabulates them. Runs already saved are skipped. Exit codes: 0
    every run saved (IPOPT failures are results, counted in the summary); 1 some runs raised
    an error (error.json in their folders; they are retried next time); 2 bad input.
    """
    try:
        check_output_dir(out_dir, kind="tree")
        plans = []
        for f in files:
            plans.append(load_sweep(f, out_dir, seeds, first_seed, grid, overrides))
        if len(plans) > 1:
            names = [p.name for p in plans]
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise ProblemError(str(files[names.index(dup[0], 1)]), "name", "is used twice")
            for p in plans:
                p.out_dir = out_dir / p.name
        summary = run_sweeps(plans, jobs, scheduler, figures, rerun, progress=not quiet)
    except SweepAborted as exc:
        fail(f"{exc}; rerun the same command to resume", EXIT_SOLVER_FAILED)
    except CasmagError as exc:
        fail_error(exc)
    except KeyboardInterrupt:
        fail("interrupted; saved runs are kept, rerun the same command to resume", 130)
    except Interrupted as exc:
        fail(
            f"interrupted ({exc.name}); saved runs are kept, rerun the same command to resume",
            exc.exit_code,
        )
    if not quiet:
        line = (
            f"{summary.planned} runs: {summary.skipped} already saved, {summary.solved} solved, "
            f"{summary.failed} failed, {summary.errors} errors in {summary.seconds:.1f} s"
        )
        if summary.statuses:
            line += " (" + ", ".join(f"{s} x{n}" for s, n in sorted(summary.statuses.items())) + ")"
        click.echo(line)
    for msg in summary.error_messages[:10]:
        click.echo(f"casmag: error: {msg}", err=True)
    if summary.errors:
        sys.exit(1)
