"""``casmag imu PROBLEM.yaml --out DIR``: solve an IMU problem (a thin wrapper over
:func:`casmag.imuslam.solve_imu`); and ``casmag slam`` on a planar recording
(``dfwd,dleft,dyaw``), dispatched here from ``casmag.cli``.

Exit codes: 0 success; 1 IPOPT failed in either stage (its status is printed and recorded in
result.json with ``success: false``); 2 bad input (one line naming the file, the key and the
reason; nothing is written); 3 solved, but not trusted (``verdict`` in result.json, e.g. a
``wrong_basin`` flag; each reason is printed on stderr).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click
import numpy as np

from casmag.clitools import (
    EXIT_BAD_INPUT,
    EXIT_SOLVER_FAILED,
    INPUT_ERRORS,
    exit_untrusted,
    fail,
    fail_bad_input,
    output_options,
    print_progress,
    problem_kind,
    refuse_other_kind,
    with_evaluation,
)
from casmag.errors import CasmagError
from casmag.result import bias_table

if TYPE_CHECKING:
    pass


@click.command("imu")
@click.argument("problem", type=click.Path(dir_okay=False, path_type=Path))
@output_options
def imu_command(
    problem: Path,
    out_dir: Path,
    overrides: tuple[str, ...],
    no_figures: bool,
    quiet: bool,
    align: str,
) -> None:
    """Solve an IMU PROBLEM (problems/imu/*.yaml): strapdown, IMU-only adjustment, GP-SLAM.
    Writes result.json, biases.md, trajectory.csv, trajectory.png and cost.png."""
    from casmag.checks import warning_lines
    from casmag.imuconfig import load_imu_problem, refuse_unused_solver_keys
    from casmag.imuslam import solve_imu

    refuse_other_kind(problem, problem_kind(problem), "imu")
    try:
        refuse_unused_solver_keys(overrides, "casmag imu")
        prob = load_imu_problem(problem, overrides)
        result = solve_imu(prob, progress=None if quiet else print_progress)
        for line in warning_lines(problem, result.warnings):
            click.echo(line, err=True)
        with_evaluation(result, align).save(out_dir, figures=not no_figures)
    except CasmagError as exc:
        fail(str(exc), EXIT_BAD_INPUT)
    except INPUT_ERRORS as exc:
        fail_bad_input(problem, exc)
    if not result.success:
        failed = result.details["failed_stage"]
        stage = "IMU-only adjustment" if failed == "imu_only" else "GP-SLAM"
        passes = result.stages_named("gp_slam")
        grow = passes[-1].get("grow") if passes else None
        if failed == "gp_slam" and grow:
            stage += f" (prefix of {grow[-1]['keyframes']} of {result.info['keyframes']} keyframes)"
        fail(
            f"{problem}: IPOPT failed in the {stage}: status {result.status} after "
            f"{result.iterations} iterations (recorded in {out_dir / 'result.json'})",
            EXIT_SOLVER_FAILED,
        )
    if not quiet:
        e = result.details["errors"]
        imu_only = result.stage("imu_only") or {}
        passes = result.stages_named("gp_slam")
        its = " + ".join(_pass_iterations(p) for p in passes) or "0"
        line = (
            f"{result.info['name']}: {result.status}, {imu_only['iterations']} (IMU only) + "
            f"{its} (GP-SLAM) iterations, {imu_only['solve_seconds']:.1f} + "
            f"{result.solve_seconds:.1f} s solve ({result.build_seconds:.1f} s build)"
        )
        if e["gp_slam"]["rmse"] is not None:
            line += (
                f"; position RMSE strapdown {e['strapdown']['rmse']:.4g} m, IMU only "
                f"{e['imu_only']['rmse']:.4g} m, GP-SLAM {e['gp_slam']['rmse']:.4g} m; "
                f"orientation RMS {e['gp_slam']['orientation_rms_deg']:.3f} deg"
            )
        if result.details["map_decision"].startswith("homogeneous"):
            evidence = result.details["field_evidence"]
            line += (
                f"; field homogeneous (log Bayes factor "
                f"{evidence['log_bayes_factor']:.2f}): IMU-only adjustment kept"
            )
        click.echo(line)
        click.echo(bias_table(result.details, result.stages), nl=False)
        click.echo(f"wrote {out_dir}/")
    exit_untrusted(result, problem)


# --------------------------------------------------------------------------- planar recordings
def is_planar_recording(path: Path) -> bool:
    """Whether a recording's header names the planar motion columns ``dfwd,dleft,dyaw``
    (read from the first line only; the full reader checks everything else). False when the
    file cannot be read, so the translational path reports the error."""
    from casmag.recording import MOTION_COLUMNS

    try:
        with open(path) as fh:
            header = fh.readline()
    except (OSError, UnicodeDecodeError):
        return False
    names = {name.strip() for name in header.split(",")}
    return set(MOTION_COLUMNS["planar"]) <= names


def planar_slam(
    recording: Path,
    out_dir: Path,
    problem: Path | None,
    overrides: tuple[str, ...],
    no_figures: bool,
    quiet: bool,
    field_check: bool = True,
    align: str = "none",
    anchor: str = "truth",
    mag_lag: float | None = None,
) -> None:
    """``casmag slam`` on a planar recording (``dfwd,dleft,dyaw``): the library's
    :func:`casmag.recslam.slam` (the planar model with a heading-rate bias,
    :func:`casmag.recslam.slam_planar`), saved with its figures; exits as every command
    does (0, 1 with IPOPT's status, 2; a constant magnetometer with ``field_check`` off:
    2)."""
    from casmag.recslam import slam as run_slam

    try:
        result = run_slam(
            recording,
            problem,
            overrides,
            progress=None if quiet else print_progress,
            field_check=field_check,
            on_warning=lambda line: click.echo(line, err=True),
            anchor=anchor,
            mag_lag=mag_lag,
        )
        with_evaluation(result, align).save(out_dir, figures=not no_figures)
    except CasmagError as exc:
        fail(str(exc), EXIT_BAD_INPUT)
    except INPUT_ERRORS as exc:
        fail_bad_input(recording, exc)
    if not result.success:
        fail(
            f"{recording}: IPOPT failed: status {result.status} after {result.iterations} "
            f"iterations (recorded in {out_dir / 'result.json'})",
            EXIT_SOLVER_FAILED,
        )
    if not quiet:
        line = (
            f"{result.info['name']}: planar model, {result.status}, {result.iterations} "
            f"iterations, {result.solve_seconds:.2f} s solve ({result.build_seconds:.1f} s build)"
        )
        if result.rmse_before is not None:
            line += f"; RMSE {result.rmse_before:.4f} -> {result.rmse_after:.4f} m"
        bias = result.odometry_bias
        if bias is not None and len(bias) == 1:
            line += f"; heading-rate bias {np.degrees(bias[0]):.4f} deg/s"
        click.echo(line)
        click.echo(f"wrote {out_dir}/")
    exit_untrusted(result, recording)


def _pass_iterations(p: dict) -> str:
    """A GP-SLAM pass's iterations; a grown pass (model.gp.grow): its last solve's and the
    total over its solves."""
    grow = p.get("grow")
    if not grow:
        return str(p["iterations"])
    return f"{p['iterations']} (grown: {p['iterations_total']} over {len(grow)} solves)"
