"""``casmag imu PROBLEM.yaml --out DIR``: solve an IMU problem (a thin wrapper over
:func:`casmag.imuslam.solve_imu`).

Exit codes: 0 success; 1 IPOPT failed in either stage (its status is printed and recorded in
result.json with ``success: false``); 2 bad input (one line naming the file, the key and the
reason; nothing is written).
"""

from __future__ import annotations

from pathlib import Path

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


@click.command("imu")
@click.argument("problem", type=click.Path(dir_okay=False, path_type=Path))
@output_options
def imu_command(
    problem: Path, out_dir: Path, overrides: tuple[str, ...], no_figures: bool, quiet: bool
) -> None:
    """Solve an IMU PROBLEM (problems/imu/*.yaml): strapdown, IMU-only adjustment, GP-SLAM.
    Writes result.json, biases.md, trajectory.csv, trajectory.png and cost.png."""
    from casmag.imuconfig import load_imu_problem
    from casmag.imuslam import solve_imu

    try:
        prob = load_imu_problem(problem, overrides)
        result = solve_imu(prob, progress=None if quiet else print_progress)
        result.save(out_dir, figures=not no_figures)
    except CasmagError as exc:
        fail(str(exc), EXIT_BAD_INPUT)
    except (ValueError, RuntimeError) as exc:
        fail_bad_input(problem, exc)
    if not result.success:
        stage = "IMU-only adjustment" if result.failed_stage == "imu_only" else "GP-SLAM"
        fail(
            f"{problem}: IPOPT failed in the {stage}: status {result.status} after "
            f"{result.iterations} iterations (recorded in {out_dir / 'result.json'})",
            EXIT_SOLVER_FAILED,
        )
    if not quiet:
        e = result.errors
        its = " + ".join(str(p["iterations"]) for p in result.gp_slam_passes) or "0"
        line = (
            f"{result.info['name']}: {result.status}, {result.iterations_imu_only} (IMU only) + "
            f"{its} (GP-SLAM) iterations, {result.solve_seconds_imu_only:.1f} + "
            f"{result.solve_seconds:.1f} s solve ({result.build_seconds:.1f} s build)"
        )
        if e["gp_slam"]["rmse"] is not None:
            line += (
                f"; position RMSE strapdown {e['strapdown']['rmse']:.4g} m, IMU only "
                f"{e['imu_only']['rmse']:.4g} m, GP-SLAM {e['gp_slam']['rmse']:.4g} m; "
                f"orientation RMS {e['gp_slam']['orientation_rms_deg']:.3f} deg"
            )
        click.echo(line)
        click.echo(result.bias_table(), nl=False)
        click.echo(f"wrote {out_dir}/")
