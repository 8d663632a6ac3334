"""Command line: thin wrappers over the library.

Exit codes: 0 success; 1 the solver failed (IPOPT's status is printed and recorded);
2 bad input (one line naming the file, the field and the reason).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from casmag.clitools import (
    EXIT_BAD_INPUT,
    EXIT_SOLVER_FAILED,
    fail,
    fail_bad_input,
    output_options,
    print_progress,
)
from casmag.errors import CasmagError
from casmag.imucli import imu_command
from casmag.sweep import sweep_command

if TYPE_CHECKING:
    from casmag.result import Result


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="casmag")
def main() -> None:
    """casmag: magnetic-field SLAM with a Gaussian-process map (CasADi + IPOPT)."""


@main.command()
@click.argument("problem", type=click.Path(dir_okay=False, path_type=Path))
@output_options
def run(
    problem: Path, out_dir: Path, overrides: tuple[str, ...], no_figures: bool, quiet: bool
) -> None:
    """Solve PROBLEM (a YAML problem file) and write result.json, trajectory.csv and figures."""
    from casmag.api import solve
    from casmag.config import load_problem

    try:
        prob = load_problem(problem, overrides)
        result = solve(prob, progress=None if quiet else print_progress)
        result.save(out_dir, figures=not no_figures)
    except CasmagError as exc:
        fail(str(exc), EXIT_BAD_INPUT)
    except (ValueError, RuntimeError) as exc:
        fail_bad_input(problem, exc)
    _finish(result, problem, out_dir, quiet)


def _finish(result: Result, source: Path, out_dir: Path, quiet: bool) -> None:
    """Exit 1 with IPOPT's status when the solve failed, else print the summary."""
    if not result.success:
        fail(
            f"{source}: IPOPT failed: status {result.status} after {result.iterations} iterations "
            f"(recorded in {out_dir / 'result.json'})",
            EXIT_SOLVER_FAILED,
        )
    if not quiet:
        line = (
            f"{result.info['name']}: {result.status}, {result.iterations} iterations, "
            f"{result.solve_seconds:.2f} s solve ({result.build_seconds:.1f} s build)"
        )
        if result.rmse_before is not None:
            line += (
                f"; RMSE {result.rmse_before:.4f} -> {result.rmse_after:.4f} m, "
                f"max {result.max_before:.4f} -> {result.max_after:.4f} m"
            )
        click.echo(line)
        click.echo(f"wrote {out_dir}/")


@main.command()
@click.argument("recording", type=click.Path(dir_okay=False, path_type=Path))
@output_options
@click.option(
    "--problem",
    "problem",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Problem file whose model and solver sections override the defaults.",
)
def slam(
    recording: Path,
    out_dir: Path,
    problem: Path | None,
    overrides: tuple[str, ...],
    no_figures: bool,
    quiet: bool,
) -> None:
    """GP-SLAM on RECORDING (CSV: t, motion increments, mx,my,mz, optional truth).

    Defaults: reduced-rank map, hyperparameters from the data's marginal likelihood,
    odometry noise 2 % of the median step, one trajectory knot per second (per 5 s above
    20,000 samples), growing warm starts. Writes result.json, trajectory.csv,
    trajectory.png, cost.png and map.png.
    """
    from casmag.api import slam as run_slam

    try:
        result = run_slam(recording, problem, overrides, progress=None if quiet else print_progress)
        result.save(out_dir, figures=not no_figures)
    except CasmagError as exc:
        fail(str(exc), EXIT_BAD_INPUT)
    except (ValueError, RuntimeError) as exc:
        fail_bad_input(recording, exc)
    _finish(result, recording, out_dir, quiet)


@main.command()
@click.argument("paths", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option(
    "--out",
    "out_file",
    type=click.Path(dir_okay=False, path_type=Path),
    help=(
        "Markdown file to write; the same stem .csv and .tex and figures/*.png are written "
        "beside it (all atomically). Markdown on standard output if omitted."
    ),
)
@click.option("--no-figures", is_flag=True, help="Tables only.")
def report(paths: tuple[Path, ...], out_file: Path | None, no_figures: bool) -> None:
    """Tabulate saved results (result.json files, or folders searched for them and for
    sweep.json) in the paper's layout; never re-solves."""
    from casmag.report import collect, markdown, write_report

    try:
        tables = collect(list(paths))
        if out_file is None:
            click.echo(markdown(tables), nl=False)
            return
        write_report(tables, out_file, figures=not no_figures)
    except CasmagError as exc:
        fail(str(exc), EXIT_BAD_INPUT)


main.add_command(sweep_command)
main.add_command(imu_command)

if __name__ == "__main__":  # pragma: no cover
    main()
