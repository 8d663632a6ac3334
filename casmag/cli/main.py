"""Command line: thin wrappers over the library.

Exit codes: 0 success; 1 the solver failed (IPOPT's status is printed and recorded);
2 bad input (one line naming the file, the field and the reason; also an output path that
would lose files); 3 solved but not trusted (the verdict's reasons on stderr,
casmag.result.verdict); 130 / 143 interrupted by Ctrl-C / SIGTERM (the previous output kept).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from casmag.cli.sweep import sweep_command
from casmag.cli.tools import (
    EXIT_BAD_INPUT,
    EXIT_SOLVER_FAILED,
    INPUT_ERRORS,
    CasmagGroup,
    align_option,
    fail,
    fail_bad_input,
    fail_error,
    finish,
    output_options,
    print_progress,
    problem_kind,
    refuse_other_kind,
    with_evaluation,
)
from casmag.errors import CasmagError


@click.group(cls=CasmagGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="casmag")
def main() -> None:
    """casmag: magnetic-field SLAM with a Gaussian-process map (CasADi + IPOPT)."""


class LagParam(click.ParamType):
    """Seconds (a float) or ``auto``."""

    name = "lag"

    def convert(self, value: Any, param: Any, ctx: Any) -> float | str:
        if isinstance(value, float) or value == "auto":
            return value
        try:
            return float(value)
        except ValueError:
            self.fail(f"expected seconds or 'auto', got {value!r}", param, ctx)


def _solve_real(problem: Path, out_dir: Path, quiet: bool, align: str) -> None:
    """A real-data problem file (casmag.experiments.realbench): converted from
    ../shared/data, solved with ``casmag slam``'s defaults and the file's settings; exit 1
    when IPOPT failed."""
    from casmag.experiments.realbench import solve_problem

    try:
        rows = solve_problem(problem, out_dir, None if quiet else print_progress, align=align)
    except CasmagError as exc:
        fail_error(exc, problem)
    except INPUT_ERRORS as exc:
        fail_bad_input(problem, exc)
    failed = [r for r in rows if not r["success"]]
    if failed:
        fail(
            f"{problem}: IPOPT failed: status {failed[0]['status']} after "
            f"{failed[0]['iterations']} iterations (recorded in {out_dir / 'result.json'})",
            EXIT_SOLVER_FAILED,
        )
    if not quiet:
        for r in rows:
            before, after = (
                "-" if r.get(k) is None else f"{r[k]:.4f}" for k in ("rmse_before", "rmse_after")
            )
            click.echo(
                f"{r['name']}: {r['status']}, {r['iterations']} iterations; "
                f"RMSE {before} -> {after} m"
            )
        click.echo(f"wrote {out_dir}/")


def _problem_command(name: str, kind: str | None, help_text: str) -> click.Command:
    """``casmag NAME PROBLEM --out DIR``: solve a problem file of one ``kind`` (None: of any
    kind, as its keys say: casmag.problem.spec.document_kind); other kinds are refused naming
    their command."""

    @main.command(name, help=help_text)
    @click.argument("problem", type=click.Path(dir_okay=False, path_type=Path))
    @output_options
    def command(
        problem: Path,
        out_dir: Path,
        overrides: tuple[str, ...],
        no_figures: bool,
        quiet: bool,
        align: str,
    ) -> None:
        found = problem_kind(problem)
        if kind is not None:
            refuse_other_kind(problem, found, kind)
        if found in ("translational", "imu"):
            _solve_problem_file(problem, found, out_dir, overrides, no_figures, quiet, align)
        elif found == "recording":
            if overrides:
                fail(
                    f"--set: not taken by a real-data problem file ({problem}); edit its "
                    "model or solver section instead",
                    EXIT_BAD_INPUT,
                )
            _solve_real(problem, out_dir, quiet, align)
        else:
            refuse_other_kind(problem, found, "translational")

    return command


solve = _problem_command(
    "solve",
    None,
    "Solve PROBLEM, a problem file of any kind, and write its results to --out.\n\n"
    "The kind comes from the file's keys (casmag.problem.spec.document_kind): a translational "
    "problem (problems/paper, problems/bench) as casmag run, an IMU problem (problems/imu) "
    "as casmag imu, a real-data problem (problems/real: recording or sessions) as make "
    "bench-real solves one file. A table file (rows) is refused: it is run over seeds by "
    "casmag sweep.",
)
run = _problem_command(
    "run",
    "translational",
    "Solve PROBLEM (a translational problem file) and write result.json, trajectory.csv "
    "and figures (casmag solve takes every kind of problem file).",
)
imu = _problem_command(
    "imu",
    "imu",
    "Solve an IMU PROBLEM (problems/imu/*.yaml): strapdown, IMU-only adjustment, GP-SLAM. "
    "Writes result.json, biases.md, trajectory.csv, trajectory.png, cost.png and map.png "
    "(casmag solve takes every kind of problem file).",
)


def _solve_problem_file(
    problem: Path,
    kind: str,
    out_dir: Path,
    overrides: tuple[str, ...],
    no_figures: bool,
    quiet: bool,
    align: str,
) -> None:
    """Load a translational or IMU problem file, solve it (:func:`casmag.solver.api.solve`), print
    its plausibility warnings on stderr, save it, and end as every command does
    (:func:`casmag.cli.tools.finish`)."""
    from casmag.data.checks import warning_lines
    from casmag.problem.imu import load_imu_problem, refuse_unused_solver_keys
    from casmag.problem.spec import load_problem
    from casmag.solver.api import solve

    try:
        if kind == "imu":
            refuse_unused_solver_keys(overrides, "casmag imu")
            prob: Any = load_imu_problem(problem, overrides)
        else:
            prob = load_problem(problem, overrides)
        result = solve(prob, progress=None if quiet else print_progress)
        for line in warning_lines(problem, result.warnings):
            click.echo(line, err=True)
        with_evaluation(result, align).save(out_dir, figures=not no_figures)
    except CasmagError as exc:
        fail_error(exc, problem)
    except INPUT_ERRORS as exc:
        fail_bad_input(problem, exc)
    finish(result, problem, out_dir, quiet)


def _warn(line: str) -> None:
    click.echo(line, err=True)


@main.command()
@click.argument(
    "recordings", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path)
)
@output_options
@click.option(
    "--problem",
    "problem",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Problem file whose model and solver sections override the defaults.",
)
@click.option(
    "--anchor",
    type=click.Choice(["truth", "origin"]),
    default="truth",
    show_default=True,
    help="Where the estimate starts: the first true pose (when the recording has truth, "
    "else the origin) or the origin; compare with --align then.",
)
@click.option(
    "--no-field-check",
    is_flag=True,
    help="Solve even when the field shows no position information (default: odometry only).",
)
@click.option(
    "--mag-lag",
    type=LagParam(),
    default=None,
    metavar="SECONDS|auto",
    help="Remove this magnetometer lag behind the motion first; 'auto' removes the one "
    "casmag estimates when it is clear (translational recordings). Without it casmag "
    "estimates the lag and warns (result.json info.magnetometer_lag).",
)
@click.option(
    "--refit-noise",
    is_flag=True,
    help="Estimate sigma_m again where the path returns and solve again with it when it is "
    "clearly larger (translational recordings; casmag.solver.recslam.refit_sigma_m).",
)
def slam(
    recordings: tuple[Path, ...],
    out_dir: Path,
    problem: Path | None,
    overrides: tuple[str, ...],
    no_figures: bool,
    quiet: bool,
    align: str,
    anchor: str,
    no_field_check: bool,
    mag_lag: float | str | None,
    refit_noise: bool,
) -> None:
    """GP-SLAM on RECORDINGS (CSV: t, motion increments, mx,my,mz, optional truth).

    Defaults: reduced-rank map, hyperparameters from the data's marginal likelihood,
    odometry noise 2 % of the median step, one trajectory knot per second (per 5 s above
    20,000 samples), growing warm starts. Writes result.json, trajectory.csv,
    trajectory.png, cost.png and map.png. A planar recording (dfwd,dleft,dyaw) is solved
    with the planar heading model instead (--set model.KEY=VALUE, casmag.problem.imu).

    Several recordings of the same field (translational, each with its first position in
    the common frame) are solved together with one shared map, each with its own odometry
    bias (casmag.solver.multisession); result.json lists each session's errors and sessions.png
    shows them.
    """
    from casmag.data.recording import is_planar_recording
    from casmag.solver.recslam import slam as run_slam
    from casmag.solver.recslam import slam_sessions

    recording = recordings[0]
    progress = None if quiet else print_progress
    try:
        if len(recordings) == 1:  # translational or planar (casmag.solver.recslam.slam)
            result = run_slam(
                recording,
                problem,
                overrides,
                progress=progress,
                field_check=not no_field_check,
                on_warning=_warn,
                anchor=anchor,
                mag_lag=mag_lag,
                refit_noise=refit_noise,
            )
        else:
            for r in recordings:
                if is_planar_recording(r):
                    raise CasmagError(
                        f"{r}: planar recordings cannot be solved as several sessions"
                    )
            if mag_lag or refit_noise:
                raise CasmagError("--mag-lag, --refit-noise: one recording at a time")
            if anchor != "truth":
                raise CasmagError(
                    "--anchor origin: several sessions need each one's first position in the "
                    "common frame (their truth)"
                )
            result = slam_sessions(
                recordings,
                problem,
                overrides,
                progress=progress,
                field_check=not no_field_check,
                on_warning=_warn,
            )
        with_evaluation(result, align).save(out_dir, figures=not no_figures)
    except CasmagError as exc:
        fail_error(exc, recording)
    except INPUT_ERRORS as exc:
        fail_bad_input(recording, exc)
    finish(result, recording, out_dir, quiet)


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
@align_option(
    "Errors measured again after this alignment to the truth, from each result's "
    "arrays.npz (casmag.result.evaluation)."
)
def report(paths: tuple[Path, ...], out_file: Path | None, no_figures: bool, align: str) -> None:
    """Tabulate saved results (result.json files, or folders searched for them and for
    sweep.json) in the paper's layout; never re-solves."""
    from casmag.report import collect, markdown, write_report

    def warn(message: str) -> None:
        click.echo(f"casmag: warning: {message}", err=True)

    try:
        tables = collect(list(paths), warn=warn, align=align)
        if out_file is None:
            click.echo(markdown(tables), nl=False)
            return
        write_report(tables, out_file, figures=not no_figures)
    except CasmagError as exc:
        fail_error(exc)


@main.command()
@click.argument("source", type=click.Path(path_type=Path))
@click.option("--out", "out_file", required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--drift", type=float, help="Final odometry drift [m] (default 0.5).")
@click.option("--seed", type=int, help="Seed of the odometry noise and bias (default 0).")
@click.option("--rate", type=float, help="Output rate [Hz] (default 10).")
@click.option("--noise", type=float, help="Odometry noise per step, fraction of the median step.")
@click.option("--motion", type=click.Choice(["translational", "planar"]))
@click.option("--field", type=click.Choice(["recorded", "constant"]))
@click.option("--no-align", is_flag=True, help="Keep the recorded magnetometer timing.")
def convert(
    source: Path,
    out_file: Path,
    drift: float | None,
    seed: int | None,
    rate: float | None,
    noise: float | None,
    motion: str | None,
    field: str | None,
    no_align: bool,
) -> None:
    """Turn a recorded sequence into a recording CSV (casmag.data.realdata's protocol).

    SOURCE is a sequence prefix (DIR/N for DIR/N-time.csv, N-loc.csv, N-mag.csv), a
    handheld recording with the device's pose (a .mat file: t, dPos, quat, m; planar
    odometry with the publishing paper's noise and a 0.005 rad/s heading-rate bias by
    default) or a real-data problem file (problems/real/*.yaml) whose ``recording`` section
    gives the settings; options override either. Writes OUT and OUT's stem + .json (the protocol
    record: clock shift, bias, measured drift).
    """
    import json

    from casmag.data.realdata import Protocol, arkit_protocol, load_arkit, load_sequence
    from casmag.data.realdata import convert as convert_sequence
    from casmag.data.recording import write_recording
    from casmag.experiments.realbench import load_real_problem, sequence_path

    given = {
        "drift": drift,
        "seed": seed,
        "rate": rate,
        "noise": noise,
        "motion": motion,
        "field": field,
    }
    given = {k: v for k, v in given.items() if v is not None}
    if no_align:
        given["align"] = False
    try:
        if source.suffix == ".mat":
            conv = convert_sequence(load_arkit(source), arkit_protocol(**given))
        else:
            if source.suffix in (".yaml", ".yml"):
                spec = load_real_problem(source)
                settings = spec.recording.model_dump()
                prefix = sequence_path(spec, source)
                settings.pop("sequence")
            else:
                settings, prefix = {}, source
            settings.update(given)
            conv = convert_sequence(load_sequence(prefix), Protocol(**settings))
        record = out_file.with_suffix(".json")
        write_recording(out_file, **conv.arrays)
        tmp = record.with_name(f".{record.name}.tmp")
        tmp.write_text(json.dumps(conv.record, indent=2) + "\n")
        tmp.replace(record)
    except CasmagError as exc:
        fail_error(exc, source)
    except (ValueError, TypeError) as exc:
        fail_bad_input(source, exc)
    od = conv.record["odometry"]
    click.echo(
        f"wrote {out_file}: {conv.record['samples']} samples at {conv.record['rate']:.3g} Hz, "
        f"odometry drift {od['final_drift']:.3f} m (RMSE {od['rmse']:.3f} m)"
    )


main.add_command(sweep_command)

if __name__ == "__main__":  # pragma: no cover
    main(prog_name="casmag")
