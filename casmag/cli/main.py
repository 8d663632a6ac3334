"""Command line: thin wrappers over the library.

Exit codes: 0 success; 1 the solver failed (IPOPT's status is printed and recorded);
2 bad input (one line naming the file, the field and the reason; also an output path that
would lose files); 3 solved but not trusted (the verdict's reasons on stderr,
casmag.result.verdict); 130 / 143 interrupted by Ctrl-C / SIGTERM (the previous output kept).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NoReturn

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
        if found in ("translational", "imu", "oriented"):
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
    "as casmag imu, a planar or pose problem (problems/planar, problems/pose: a simulated "
    "recording, solved as casmag slam solves one), a real-data problem (problems/real: "
    "recording or sessions) as make bench-real solves one file. A table file (rows) is "
    "refused: it is run over seeds by casmag sweep.",
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
    """Load a translational, IMU, planar or pose problem file, solve it
    (:func:`casmag.solver.api.solve`), print
    its plausibility warnings on stderr, save it, and end as every command does
    (:func:`casmag.cli.tools.finish`)."""
    from casmag.data.checks import warning_lines
    from casmag.problem.imu import IMU_SOLVER_KEYS, load_imu_problem, refuse_unused_solver_keys
    from casmag.problem.oriented import load_oriented_problem
    from casmag.problem.spec import load_problem
    from casmag.solver.api import solve

    try:
        if kind == "imu":
            refuse_unused_solver_keys(overrides, "casmag imu", IMU_SOLVER_KEYS)
            prob: Any = load_imu_problem(problem, overrides)
        elif kind == "oriented":
            prob = load_oriented_problem(problem, overrides)
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
    help="Remove this magnetometer lag behind the motion first (0 keeps the magnetometer "
    "as recorded); 'auto' removes the one casmag estimates when it is clear (every kind of "
    "recording; the default for IMU recordings). Otherwise casmag estimates the lag "
    "and warns (result.json info.magnetometer_lag).",
)
@click.option(
    "--refit-noise",
    is_flag=True,
    help="Estimate sigma_m again where the path returns and solve again with it when it is "
    "clearly larger (translational recordings; casmag.solver.recslam.refit_sigma_m).",
)
@click.option(
    "--map",
    "map_file",
    type=click.Path(path_type=Path),
    default=None,
    help="Locate the recording against this saved map (map.npz, or the result folder of an "
    "earlier run) instead of mapping from scratch, with the map's kernel and "
    "hyperparameters, and write the map updated by the recording (its posterior as the "
    "prior; translational recordings: casmag.solver.localize, with --method ekf the filter "
    "does the same; planar and pose recordings: the model's warm start against the map; "
    "IMU recordings: a box map, the anneal schedule against the map held, then updated).",
)
@click.option(
    "--hold-map",
    is_flag=True,
    help="With --map and the MAP estimate: locate against the map held at its mean, without "
    "the update (faster, less accurate where the map is weak; no map.npz is written).",
)
@click.option(
    "--method",
    type=click.Choice(["map", "ekf", "both"]),
    default="map",
    show_default=True,
    help="map: the MAP estimate (GP-SLAM); ekf: the filter baseline, an EKF with the same "
    "map, hyperparameters and noise in its state (casmag.solver.ekf), for comparison; "
    "both: each into OUT/map and OUT/ekf, with methods.md, methods.json and methods.png "
    "side by side (the exit code is the MAP's).",
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
    map_file: Path | None,
    hold_map: bool,
    method: str,
) -> None:
    """GP-SLAM on RECORDINGS (CSV: t, motion increments, mx,my,mz, optional truth).

    Defaults: a reduced-rank map on one box around the path, or on tiles with the
    curl-free kernel where that box would be capped or too costly (model.gp.form: auto,
    casmag.model.mapchoice; IMU recordings: the box), hyperparameters from the data's
    marginal likelihood, odometry noise 2 % of the median step, one trajectory knot per
    second (per 5 s above 20,000 samples), growing warm starts. Writes result.json,
    trajectory.csv, trajectory.png, cost.png and map.png. A planar recording
    (dfwd,dleft,dyaw) is solved with the planar heading model instead (--set
    model.KEY=VALUE, casmag.problem.imu), a pose recording (dpx..dqz) with the pose model,
    and an IMU recording (dqw..dqz, dvx..dvz; at rest for its first 0.5 s) with the IMU
    model, the sensors' noise taken from that rest (casmag.solver.imurec).

    Several recordings of the same field (translational, planar or pose, one kind, each with
    its first position, and a planar or pose one's heading or orientation, in the common
    frame: truth columns) are solved together with one shared map, each with its own
    odometry bias (casmag.solver.multisession; casmag.solver.staged.solve_sessions for planar
    and pose); result.json lists each session's errors and sessions.png shows them.

    Every translational, planar and pose run writes map.npz (a box or tiles, up to 6,000 map
    unknowns; an IMU run a box), the map with its posterior; --map MAP locates a later
    recording of any of those kinds (its first position in the map's frame) against it and
    writes the map updated by it (the filter, --method ekf, and IMU recordings need a box
    map), and casmag map MAP draws it.
    """
    from casmag.solver.recslam import slam as run_slam
    from casmag.solver.recslam import slam_sessions

    recording = recordings[0]
    progress = None if quiet else print_progress
    try:
        if len(recordings) == 1 and method == "both":
            if refit_noise:
                raise CasmagError("--refit-noise: for the MAP alone, not with --method both")
            result = _both_methods(
                recording, problem, overrides, progress, not no_field_check, anchor, mag_lag,
                map_file, hold_map, out_dir, align, no_figures, quiet,
            )  # fmt: skip
        elif len(recordings) == 1:  # any motion input (casmag.solver.recslam.slam)
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
                map_file=map_file,
                hold_map=hold_map,
                method=method,
            )
        else:
            if map_file is not None or hold_map or method != "map":
                raise CasmagError("--map, --hold-map, --method: one recording at a time")
            if refit_noise:
                raise CasmagError("--refit-noise: one recording at a time")
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
                mag_lag=mag_lag,
            )
        if method != "both":
            with_evaluation(result, align).save(out_dir, figures=not no_figures)
    except CasmagError as exc:
        fail_error(exc, recording)
    except INPUT_ERRORS as exc:
        fail_bad_input(recording, exc)
    finish(result, recording, out_dir / "map" if method == "both" else out_dir, quiet)


def _both_methods(
    recording: Path,
    problem: Path | None,
    overrides: tuple[str, ...],
    progress: Any,
    field_check: bool,
    anchor: str,
    mag_lag: float | str | None,
    map_file: Path | None,
    hold_map: bool,
    out_dir: Path,
    align: str,
    no_figures: bool,
    quiet: bool,
) -> Any:
    """``casmag slam REC --method both``: the MAP and the filter on the recording, each timed
    whole, saved side by side (casmag.report.methods); returns the MAP's result."""
    import time

    import numpy as np

    from casmag.data.recording import read_recording
    from casmag.report.methods import BOTH, markdown, rows, save_methods
    from casmag.solver.recslam import slam as run_slam

    results, walls = {}, {}
    for m in BOTH:
        t0 = time.perf_counter()
        results[m] = run_slam(
            recording,
            problem,
            overrides,
            progress=progress if m == "map" else None,
            field_check=field_check,
            on_warning=_warn if m == "map" else None,
            anchor=anchor,
            mag_lag=mag_lag,
            map_file=map_file,
            hold_map=hold_map and m == "map",
            method=m,
        )
        walls[m] = time.perf_counter() - t0
        with_evaluation(results[m], align)
    duration = float(np.ptp(read_recording(recording).t))
    save_methods(out_dir, results, walls, duration, str(recording), figures=not no_figures)
    if not quiet:
        click.echo(markdown(rows(results, walls, duration), str(recording)))
    return results["map"]


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
@click.option(
    "--out",
    "out_file",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Recording CSV to write (required; a bag's topics are listed without it).",
)
@click.option("--drift", type=float, help="Final odometry drift [m] (default 0.5).")
@click.option("--seed", type=int, help="Seed of the odometry noise and bias (default 0).")
@click.option("--rate", type=float, help="Output rate [Hz] (default 10).")
@click.option("--noise", type=float, help="Odometry noise per step, fraction of the median step.")
@click.option(
    "--motion",
    type=click.Choice(["translational", "planar", "translational3", "pose"]),
    help="Motion input written: dx,dy | dfwd,dleft,dyaw | dx,dy,dz | dpx,dpy,dpz,dqw..dqz "
    "(translational3: bags only; pose: sequences and .mat files, 6-DoF odometry of the "
    "true 3-D pose, level at z = 0 along the heading of motion without a recorded "
    "orientation). A bag's default is translational; with --imu it gets the IMU increments.",
)
@click.option("--field", type=click.Choice(["recorded", "constant"]))
@click.option("--no-align", is_flag=True, help="Keep the recorded magnetometer timing.")
@click.option(
    "--magnetometer",
    metavar="TOPIC",
    help="Bag: sensor_msgs/msg/MagneticField topic (tesla, written in microtesla).",
)
@click.option(
    "--odometry",
    metavar="TOPIC",
    help="Bag: nav_msgs/msg/Odometry or geometry_msgs/msg/PoseStamped topic, written as "
    "increments of --motion.",
)
@click.option(
    "--imu",
    metavar="TOPIC",
    help="Bag: sensor_msgs/msg/Imu topic (rad/s, m/s^2), written as strapdown increments "
    "(instead of --odometry).",
)
@click.option(
    "--truth",
    metavar="TOPIC",
    help="Bag: nav_msgs/msg/Odometry or geometry_msgs/msg/PoseStamped topic of the true pose.",
)
def convert(
    source: Path,
    out_file: Path | None,
    drift: float | None,
    seed: int | None,
    rate: float | None,
    noise: float | None,
    motion: str | None,
    field: str | None,
    no_align: bool,
    magnetometer: str | None,
    odometry: str | None,
    imu: str | None,
    truth: str | None,
) -> None:
    """Turn a recorded sequence or a ROS bag into a recording CSV.

    SOURCE is a sequence prefix (DIR/N for DIR/N-time.csv, N-loc.csv, N-mag.csv), a
    handheld recording with the device's pose (a .mat file: t, dPos, quat, m; planar
    odometry with the publishing paper's noise and a 0.005 rad/s heading-rate bias by
    default, --motion pose: 6-DoF odometry of the recorded pose with the same noise and
    bias about the body z axis) or a real-data problem file (problems/real/*.yaml) whose
    ``recording`` section gives the settings (casmag.data.realdata's protocol); options
    override either. Writes OUT and OUT's stem + .json (the protocol record: clock shift,
    bias, measured drift).

    SOURCE may also be a ROS 1 .bag file or a ROS 2 bag folder (with metadata.yaml),
    read with the rosbags package (pip install casmag[bags]; casmag.data.rosbag): give
    --magnetometer (tesla in the bag, microtesla in OUT) and --odometry (with --motion) or
    --imu, optionally --truth. Times are the messages' header stamps, from the earliest
    one written. Without these topics the bag's topics are listed (exit 2). OUT's stem +
    .json records the topics, message counts and the first stamp.
    """
    bag_options = {
        "--magnetometer": magnetometer,
        "--odometry": odometry,
        "--imu": imu,
        "--truth": truth,
    }
    sequence_options = {
        "--drift": drift,
        "--seed": seed,
        "--rate": rate,
        "--noise": noise,
        "--field": field,
        "--no-align": no_align or None,
    }
    from casmag.data.rosbag import is_bag

    if is_bag(source):
        given = [name for name, value in sequence_options.items() if value is not None]
        if given:
            fail(f"{given[0]}: not taken by a ROS bag ({source})", EXIT_BAD_INPUT)
        _convert_bag(source, out_file, motion, magnetometer, odometry, imu, truth)
        return
    given = [name for name, value in bag_options.items() if value is not None]
    if given:
        fail(
            f"{given[0]}: for ROS bags only ({source} is not a .bag file or a folder with "
            "metadata.yaml)",
            EXIT_BAD_INPUT,
        )
    if motion == "translational3":
        fail(f"--motion translational3: for ROS bags only ({source})", EXIT_BAD_INPUT)
    if out_file is None:
        _missing_out()
    _convert_sequence(source, out_file, drift, seed, rate, noise, motion, field, no_align)


def _missing_out() -> NoReturn:
    """The usage error click gives for a missing required --out (exit 2)."""
    ctx = click.get_current_context()
    param = next(p for p in ctx.command.params if p.name == "out_file")
    raise click.MissingParameter(ctx=ctx, param=param)


def _convert_sequence(
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
    """``casmag convert`` of a sequence, a .mat recording or a real-data problem file."""
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


def _convert_bag(
    source: Path,
    out_file: Path | None,
    motion: str | None,
    magnetometer: str | None,
    odometry: str | None,
    imu: str | None,
    truth: str | None,
) -> None:
    """``casmag convert BAG``: the bag's topics as a recording (casmag.data.rosbag.read_bag);
    without the magnetometer or a motion topic, the bag's topics listed and exit 2."""
    import json

    from casmag.data.rosbag import list_topics, read_bag

    missing = None
    if magnetometer is None:
        missing = "--magnetometer TOPIC is missing (a sensor_msgs/msg/MagneticField topic)"
    elif odometry is None and imu is None:
        missing = (
            "--odometry TOPIC or --imu TOPIC is missing (a nav_msgs/msg/Odometry or "
            "geometry_msgs/msg/PoseStamped topic, or a sensor_msgs/msg/Imu topic)"
        )
    elif odometry is not None and imu is not None:
        fail(f"{source}: --odometry and --imu: give one motion topic", EXIT_BAD_INPUT)
    elif imu is not None and motion is not None:
        fail(
            f"--motion {motion}: not taken with --imu (the IMU topic gives the IMU increments)",
            EXIT_BAD_INPUT,
        )
    if missing is not None:
        try:
            topics = list_topics(source)
        except CasmagError as exc:
            fail_error(exc, source)
        _echo_topics(source, topics)
        fail(f"{source}: {missing}; the bag's topics are listed above", EXIT_BAD_INPUT)
    if out_file is None:
        _missing_out()
    try:
        rec = read_bag(source, magnetometer, odometry, imu, truth, motion)
        rec.write(out_file)
        record = out_file.with_suffix(".json")
        tmp = record.with_name(f".{record.name}.tmp")
        tmp.write_text(json.dumps(rec.record, indent=2) + "\n")
        tmp.replace(record)
    except CasmagError as exc:
        fail_error(exc, source)
    except INPUT_ERRORS as exc:
        fail_bad_input(source, exc)
    for note in rec.notes:
        click.echo(f"casmag: note: {source}: {note}", err=True)
    used = ", ".join(f"{info['used']} {role}" for role, info in rec.record["topics"].items())
    click.echo(
        f"wrote {out_file}: {rec.rows.shape[0]} rows ({rec.record['motion']}) from {used} "
        f"messages, t = 0 at stamp {rec.record['t0_stamp']} s"
    )


def _echo_topics(source: Path, topics: list[tuple[str, str, int]]) -> None:
    """The bag's topics, one a line: topic, message type, message count."""
    click.echo(f"{source}: {len(topics)} topics")
    if not topics:
        return
    wide = max(len(t) for t, _, _ in topics)
    kind = max(len(k) for _, k, _ in topics)
    for topic, msgtype, count in topics:
        click.echo(f"  {topic:<{wide}}  {msgtype:<{kind}}  {count:>8d}")


@main.command(name="map")
@click.argument("map_file", type=click.Path(path_type=Path))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--points", type=click.IntRange(2, 1000), default=90, show_default=True)
@click.option("--z", type=float, default=None, help="Height of the grid of a 3-D map [m].")
def map_command(map_file: Path, out_dir: Path, points: int, z: float | None) -> None:
    """Draw a saved map (MAP_FILE: map.npz, or a result folder) and export its grid.

    Writes OUT/map.png (field magnitude, blank where the posterior standard deviation is
    above half the prior's, and the posterior standard deviation) and OUT/map_grid.csv (x, y
    [, z] [m], the field mx, my, mz, its posterior and prior standard deviations per
    component, in the map's field units) on a POINTS x POINTS grid over the map's box (a
    tiled map's: over its tile centres, NaN where a point lacks one of its tiles). A map
    saved as its mean alone (too many unknowns for a dense precision) is drawn without its
    posterior standard deviation, NaN in the CSV.
    """
    from types import SimpleNamespace

    from casmag.gp.savedmap import load_map, write_grid_csv
    from casmag.result.outdir import save_atomic
    from casmag.result.plotting import map_figure

    try:
        saved = load_map(map_file)
        grid = saved.grid(points, z)
        drawn = grid if saved.has_posterior else {k: v for k, v in grid.items() if k != "map_std"}
        status = "saved map" if saved.has_posterior else "saved map, its mean alone"
        drawable = SimpleNamespace(
            arrays=drawn, info={"name": map_file.stem}, status=status, success=True
        )

        def write(tmp: Path) -> None:
            write_grid_csv(grid, tmp / "map_grid.csv")
            map_figure(drawable, tmp / "map.png")

        save_atomic(out_dir, write)
    except CasmagError as exc:
        fail_error(exc, map_file)
    except INPUT_ERRORS as exc:
        fail_bad_input(map_file, exc)
    click.echo(f"wrote {out_dir / 'map.png'} and {out_dir / 'map_grid.csv'} ({saved.frame})")


main.add_command(sweep_command)

if __name__ == "__main__":  # pragma: no cover
    main(prog_name="casmag")
