"""Pieces shared by the command-line commands: exit codes, error lines, progress lines and
the output options every solving command takes."""

from __future__ import annotations

import functools
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn

import click

from casmag import interrupt, memory
from casmag.errors import CasmagError, MemoryBudgetError
from casmag.interrupt import Interrupted
from casmag.nlp import MEMORY_STATUS
from casmag.problem.spec import document_kind, read_yaml
from casmag.result import Result, bias_table, evaluation_of
from casmag.result.evaluation import ALIGNMENTS, evaluate_result
from casmag.result.outdir import OutputError, check_output_dir

EXIT_SOLVER_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_UNTRUSTED = 3  # solved, but the verdict does not trust it (casmag.result.verdict)
# Interrupted by a signal: 128 + its number (130 SIGINT / Ctrl-C, 143 SIGTERM).
EXIT_INTERRUPTED = 130


def fail(message: str, code: int) -> NoReturn:
    click.echo(f"casmag: error: {message}", err=True)
    sys.exit(code)


def fail_error(exc: CasmagError, source: Path | None = None) -> NoReturn:
    """Exit with a casmag error's line: 1 for a solve refused by the memory budget (naming
    ``source``, the file solved), 2 (bad input) for every other."""
    if isinstance(exc, MemoryBudgetError):
        fail(f"{source}: {exc}" if source is not None else str(exc), EXIT_SOLVER_FAILED)
    fail(str(exc), EXIT_BAD_INPUT)


#: What a value the numerics cannot carry raises past validation (casmag.problem.spec refuses inf
#: and nan; huge values overflow, huge sizes exhaust memory): exit 2 naming the file.
INPUT_ERRORS = (ValueError, RuntimeError, ArithmeticError, MemoryError)


def fail_bad_input(source: Path, exc: BaseException) -> NoReturn:
    """Exit 2 with the first line of an unexpected error of INPUT_ERRORS, naming the file."""
    if isinstance(exc, MemoryError):
        text = f"needs more memory than this machine has ({type(exc).__name__}: {exc})"
    elif isinstance(exc, ArithmeticError):
        text = f"a value is too large for the numerics ({type(exc).__name__}: {exc})"
    else:
        text = str(exc) or type(exc).__name__
    fail(f"{source}: {text.splitlines()[0]}", EXIT_BAD_INPUT)


def print_progress(k: int, cost: float, step: float, seconds: float) -> None:
    # Unconstrained NLPs: the constraint violation is always 0, so the step is shown instead.
    click.echo(f"  iter {k:4d}  cost {cost:.6e}  step {step:.2e}  {seconds:7.2f} s", err=True)


def distinct_set_keys(ctx: click.Context, param: click.Parameter, value: Any) -> Any:
    """Callback of ``--set``: a key given twice is refused (the later would silently win,
    as a key given twice in a YAML file would)."""
    seen: set[str] = set()
    for text in value or ():
        key = text.partition("=")[0].strip()
        if key in seen:
            raise click.BadParameter(f"{key} is given twice", ctx=ctx, param=param)
        seen.add(key)
    return value


def align_option(help_text: str) -> Callable[..., Any]:
    """--align {none,start,se} (casmag.result.evaluation)."""
    return click.option(
        "--align", type=click.Choice(ALIGNMENTS), default="none", show_default=True, help=help_text
    )


def output_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """--out DIR (required), --set KEY.PATH=VALUE (repeatable), --no-figures, --quiet,
    --align {none,start,se}."""
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
            callback=distinct_set_keys,
            help="Override a problem-file value (YAML syntax); repeatable.",
        ),
        click.option("--no-figures", is_flag=True, help="Skip the PNG figures."),
        click.option("--quiet", "-q", is_flag=True, help="No progress lines, nothing on success."),
        align_option(
            "Errors against the truth also after this alignment (result.json 'evaluation'): "
            "start = first positions matched, se = rigid least squares."
        ),
    ]

    @functools.wraps(command)
    def checked(*args: Any, **kwargs: Any) -> Any:
        # Before anything is read or solved: an output path that would lose files, or that
        # cannot be written, is refused with one line (casmag.result.outdir).
        try:
            check_output_dir(kwargs["out_dir"])
        except OutputError as exc:
            fail(str(exc), EXIT_BAD_INPUT)
        return command(*args, **kwargs)

    for option in reversed(options):
        checked = option(checked)
    return checked


class CasmagGroup(click.Group):
    """The command group: Ctrl-C and SIGTERM stop any command cleanly (casmag.interrupt):
    one line, the previous output kept, exit 130 or 143."""

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        """Click's main; a usage error (unknown option, a value out of its range, a missing
        argument) is one line naming the option and the command's help, exit 2, like
        every other bad input."""
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            rv = super().main(*args, standalone_mode=False, **kwargs)
        except click.UsageError as exc:
            where = f" (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
            fail(" ".join(exc.format_message().split()) + where, exc.exit_code)
        except click.ClickException as exc:
            fail(" ".join(exc.format_message().split()), exc.exit_code)
        except click.Abort:
            fail("aborted", EXIT_INTERRUPTED)
        sys.exit(rv if isinstance(rv, int) else 0)

    def invoke(self, ctx: click.Context) -> Any:
        interrupt.install()
        try:
            return super().invoke(ctx)
        except Interrupted as exc:
            fail(f"interrupted ({exc.name}); no output was replaced", exc.exit_code)


#: The command that solves each kind of problem file (casmag.problem.spec.document_kind).
COMMAND_OF_KIND = {
    "translational": "casmag run",
    "imu": "casmag imu",
    "oriented": "casmag solve",
    "recording": "casmag solve",
    "table": "casmag sweep",
}
_KIND_NAMES = {
    "translational": "a translational problem file",
    "imu": "an IMU problem file",
    "oriented": "a planar or pose problem file",
    "recording": "a real-data problem file",
    "table": "a table file (rows of overrides of a problem file)",
}


def problem_kind(problem: Path) -> str:
    """The kind of a problem file (exit 2 with one line when it cannot be read)."""
    try:
        return document_kind(read_yaml(problem))
    except CasmagError as exc:
        fail_error(exc)


def refuse_other_kind(problem: Path, kind: str, expected: str) -> None:
    """Exit 2 naming the command for a problem file of another kind than ``expected``."""
    if kind == expected:
        return
    command = f"'{COMMAND_OF_KIND[kind]} {problem} --out DIR'"
    if COMMAND_OF_KIND[kind] not in ("casmag solve", "casmag sweep"):
        command += f" or 'casmag solve {problem} --out DIR'"
    fail(f"{problem}: {_KIND_NAMES[kind]}, solved by {command}", EXIT_BAD_INPUT)


def with_evaluation(result: Any, align: str) -> Any:
    """The result with its ``evaluation`` after ``--align`` (casmag.result.evaluation)."""
    result.evaluation = evaluate_result(result, align)
    return result


def finish(result: Result, source: Path, out_dir: Path, quiet: bool) -> None:
    """How every solving command ends, for a result of any motion model: exit 1 with
    IPOPT's status (and, for IMU problems, the stage that failed) when the solve failed;
    else the summary (:func:`summary_lines`) unless ``quiet``; then exit 3 when the verdict
    does not trust the estimate (:func:`exit_untrusted`), else return (exit 0)."""
    if result.status == MEMORY_STATUS:
        fail(
            f"{source}: stopped{_failed_where(result)}: status {MEMORY_STATUS}: the solve "
            "needs more memory than solver.memory_budget allows (default 80 % of the "
            f"machine's): {memory.REMEDY}; recorded in {out_dir / 'result.json'}",
            EXIT_SOLVER_FAILED,
        )
    if not result.success:
        fail(
            f"{source}: IPOPT failed{_failed_where(result)}: status {result.status} after "
            f"{result.iterations} iterations (recorded in {out_dir / 'result.json'})",
            EXIT_SOLVER_FAILED,
        )
    if not quiet:
        for line in summary_lines(result):
            click.echo(line)
        click.echo(f"wrote {out_dir}/")
    exit_untrusted(result, source)


def _failed_where(result: Result) -> str:
    """`` in the STAGE`` for an IMU result (the IMU-only adjustment, GP-SLAM, a grown
    prefix), else nothing."""
    if result.motion != "imu":
        return ""
    failed = result.details.get("failed_stage")
    stage = "IMU-only adjustment" if failed == "imu_only" else "GP-SLAM"
    passes = result.stages_named("gp_slam")
    grow = passes[-1].get("grow") if passes else None
    if failed == "gp_slam" and grow:
        stage += f" (prefix of {grow[-1]['keyframes']} of {result.info['keyframes']} keyframes)"
    return f" in the {stage}"


def summary_lines(result: Result) -> list[str]:
    """What a command prints after a successful solve: one line with the status, iterations,
    seconds and errors (for IMU problems per stage, for planar ones the heading-rate bias),
    then the IMU biases table or each session's errors."""
    name = result.info.get("name", "")
    if result.motion == "imu":
        return _imu_summary(result)
    model = "planar model, " if result.motion == "planar" else ""
    line = (
        f"{name}: {model}{result.status}, {result.iterations} iterations, "
        f"{result.solve_seconds:.2f} s solve ({result.build_seconds:.1f} s build)"
    )
    if result.rmse_before is not None and result.rmse_after is not None:
        line += f"; RMSE {result.rmse_before:.4f} -> {result.rmse_after:.4f} m"
        if result.motion == "translational":
            line += f", max {result.max_before:.4f} -> {result.max_after:.4f} m"
        rigid = evaluation_of(result).get("rigid", {}).get("after", {}) if result.arrays else {}
        if rigid.get("rmse") is not None:
            line += f" ({rigid['rmse']:.4f} m after a rigid fit, {rigid['rotation_deg']:.1f} deg)"
    bias = result.odometry_bias
    if result.motion == "planar" and bias is not None and len(bias) == 1:
        line += f"; heading-rate bias {math.degrees(bias[0]):.4f} deg/s"
    lines = [line]
    for row in result.info.get("sessions", []):
        if row.get("rmse_after") is not None:
            lines.append(
                f"  {row['name']}: RMSE {row['rmse_before']:.4f} -> {row['rmse_after']:.4f} m"
            )
    return lines


def _imu_summary(result: Result) -> list[str]:
    e = result.details["errors"]
    imu_only = result.stage("imu_only") or {}
    its = " + ".join(_pass_iterations(p) for p in result.stages_named("gp_slam")) or "0"
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
    return [line, bias_table(result.details, result.stages).rstrip("\n")]


def _pass_iterations(p: dict[str, Any]) -> str:
    """A GP-SLAM pass's iterations; a grown pass (model.gp.grow): its last solve's and the
    total over its solves."""
    grow = p.get("grow")
    if not grow:
        return str(p["iterations"])
    return f"{p['iterations']} (grown: {p['iterations_total']} over {len(grow)} solves)"


def exit_untrusted(result: Any, source: Any) -> None:
    """A solved result the verdict does not trust (casmag.result.verdict): each reason on stderr
    (``casmag: not trusted: SOURCE: reason``), then exit 3. Nothing for a trusted one."""
    v = result.verdict or {}
    if not result.success or v.get("trusted", True):
        return
    for reason in v.get("reasons", []):
        click.echo(f"casmag: not trusted: {source}: {reason}", err=True)
    raise SystemExit(EXIT_UNTRUSTED)
