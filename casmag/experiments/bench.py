"""Benchmarks: ``python -m casmag.experiments.bench scale`` (``make bench-scale``) and
``... bench area`` (``make bench-area``).

Each configuration runs in its own process, so the peak memory reported is that run's
(``ru_maxrss``), and the results are collected into ``results/bench/scale.json`` (written to
a temporary name, then renamed) with a PNG of time per iteration and RMSE against N.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import click

from casmag.data.simulate import simulate_problem
from casmag.result.outdir import write_text_atomic

ROOT = Path(__file__).resolve().parents[2]
WALK = ROOT / "problems" / "bench" / "walk.yaml"
SCALE_SIZES = (1000, 4000, 16000, 64000)
KNOT_EVERY = {64000: 50}
"""Knot spacing by N where it differs from the problem file's 10 (one per second): at
64,000 samples one knot per second gives a 12,800 x 2,745 dense knot-weight Hessian border
(35 million entries; measured: 13 GB resident, killed after 9 minutes); one knot per 5 s
gives a fifth of it."""
EXACT_SIZES = (100, 150, 250, 500)


COMPARISON = [
    "simulation.trajectory.area=[2.0, 2.0]",
    "simulation.odometry.bias=[0.0, 0.0]",
    "model.odometry.estimate_bias=false",
    "solver.warm_start.strategy=none",
]
"""The exact-versus-reduced-rank comparison: a 2 m x 2 m room, so that a short walk crosses
itself, and an odometry without bias. (A few hundred samples of the 6 m room walk have no
loop closure, so a bias is unobservable; the exact GP then stretched the trajectory: at
N = 100 its RMSE went from 0.007 m to 18.8 m in 144 iterations.)"""


AREAS = ((6.0, 6.0), (20.0, 20.0), (50.0, 70.0))
AREA_SAMPLES = 10_000
AREA_FIELD = [
    "simulation.field.method=dipoles",
    "simulation.field.kernel=curl_free",
    "solver.uncertainty=false",
]
"""``make bench-area``: the walk's 10,000 samples (the file's l = 0.35 m, growing warm start)
over each area, in a field of dipoles under the floor (physics, not a GP draw;
casmag.data.simulate.dipole_floor_field), solved with the curl-free map as one box and as
tiles (:data:`AREA_MAPS`)."""

AREA_MAPS: dict[str, tuple[str, tuple[str, ...]]] = {
    "reduced_rank": ("reduced_rank", ()),
    "bumps": ("tiled", ("model.gp.tile_basis=bumps",)),
    "hilbert": ("tiled", ("model.gp.tile_basis=hilbert",)),
}
"""``make bench-area``'s maps, each a row's ``form``: the form and its overrides. One box;
the tiled map with the bumps (the default basis of every motion model) or with a
reduced-rank Hilbert basis per tile."""
AREA_DEFAULT_MAPS = "reduced_rank,bumps"
AREA_TILED_BEFORE = "hilbert"
"""Rows of area.json written before the tiled map's basis was a row of its own say
``tiled``: they were the Hilbert tiles, the translational default until 2026-12-06."""
AREA_STARTS = ("dead-reckoning", "truth")
"""``make bench-area``'s starts, each a row's ``start``: the walk's own warm start from the
dead reckoning, or one batch from the true positions (a diagnostic that needs the truth:
the time per iteration and the error of the model's optimum near the truth, apart from
whether a start finds it). Rows written before the starts were told apart say none: they
started from the dead reckoning."""

SCALE_SETS: dict[str, tuple[str, tuple[str, ...]]] = {
    "room": ("reduced_rank", ()),
    "building": ("tiled", ("simulation.trajectory.area=[50.0, 70.0]", *AREA_FIELD)),
}
"""``make bench-scale``'s settings, each run at every N: ``room``, the walk's own 6 m x 6 m
with its Fourier-feature field and one box (:data:`KNOT_EVERY`); ``building``, the same walk
over 50 m x 70 m in the area benchmark's dipole field with the tiled map (the box there would
need tens of thousands of functions for the same lengthscale), the file's knots."""


RUN_TIMEOUT = 3600.0
"""Seconds one run of ``make bench-area`` or ``make bench-scale`` may take before it is
stopped (its row says so, with what its progress lines said)."""


def run_one(
    samples: int,
    form: str,
    knot_every: int | None,
    comparison: bool = False,
    extra: tuple[str, ...] = (),
    start: str = "dead-reckoning",
) -> dict[str, Any]:
    """Simulate the walk with ``samples`` samples and solve it; figures measured here.
    ``extra``: more ``--set`` overrides (the area benchmark's area and field). ``start``
    (:data:`AREA_STARTS`): ``truth`` solves one batch from the true positions."""
    import numpy as np

    import casmag

    overrides = [f"simulation.trajectory.samples={samples}", f"model.gp.form={form}"]
    if knot_every is not None:
        overrides.append(f"model.trajectory.knot_every={knot_every}")
    if comparison:
        overrides += COMPARISON
    overrides += list(extra)
    problem = casmag.load_problem(WALK, overrides)
    t0 = time.perf_counter()
    data = simulate_problem(problem)
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    done = 0

    def progress(iteration: int, cost: float, step: float, seconds: float) -> None:
        # one line per IPOPT iteration on stderr: what a run stopped by --timeout leaves
        nonlocal done
        done += iteration > 0  # IPOPT's iteration 0 is the start of each stage
        line = {
            "iterations": done,
            "stage_iteration": iteration,
            "stage_seconds": seconds,
            "wall_seconds": time.perf_counter() - t0,
            "cost": cost,
            "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        }
        print(PROGRESS + json.dumps(line), file=sys.stderr, flush=True)

    initial = data.P_true if start == "truth" else None
    result = casmag.solve(problem, data, progress, initial_positions=initial)
    wall = time.perf_counter() - t0
    stages = result.stages  # the growing warm start's prefixes, the last the final solve
    iters = sum(s["iterations"] for s in stages[:-1]) + result.iterations
    solve_s = sum(s["solve_seconds"] for s in stages[:-1]) + result.solve_seconds
    err = None
    if result.success:
        err = float(np.abs(result.arrays["P_estimate"] - data.P_true).max())
    return {
        "samples": samples,
        "form": form,
        "start": start,
        "knot_every": problem.spec.model.trajectory.knot_every,
        "num_basis": result.info["num_basis"],
        "tiles": result.info.get("tiles"),
        "overrides": list(extra),
        "status": result.status,
        "success": result.success,
        "wall_seconds": wall,
        "simulate_seconds": t_sim,
        "build_seconds_last_stage": result.build_seconds,
        "iterations_total": iters,
        "iterations_last_stage": result.iterations,
        "solve_seconds_total": solve_s,
        "seconds_per_iteration": solve_s / max(1, iters),
        "seconds_per_iteration_last_stage": result.solve_seconds / max(1, result.iterations),
        "stages": stages,
        "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "rmse_before": result.rmse_before,
        "rmse_after": result.rmse_after,
        "max_before": result.max_before,
        "max_after": result.max_after,
        "max_error_check": err,
        "bias_estimate": result.odometry_bias,
        "bias_true": result.odometry_bias_true,
        "P_estimate": result.arrays["P_estimate"].tolist() if comparison else None,
    }


def _spawn(args: list[str], timeout: float | None = None) -> dict[str, Any]:
    """One configuration in its own process (``bench one ARGS``), its figures; a run that
    crashes, or that is still running after ``timeout`` seconds (then stopped), is a failed
    row that says so."""
    cmd = [sys.executable, "-m", "casmag.experiments.bench", "one", *args]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=timeout)
    except subprocess.TimeoutExpired as stopped:
        return {
            "args": args,
            "status": f"stopped: still running after {timeout:g} s (--timeout)",
            "success": False,
            "wall_seconds": timeout,
            **progress_so_far(stopped.stderr),
        }
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        said = [ln for ln in out.stderr.strip().splitlines() if not ln.startswith(PROGRESS)]
        tail = (said or [f"no output, exit code {out.returncode}"])[-1]
        return {
            "args": args,
            "status": f"crashed: {tail}",
            "success": False,
            **progress_so_far(out.stderr),
        }
    return json.loads(lines[-1])


#: The start of a progress line on a run's stderr (:func:`run_one`).
PROGRESS = "progress "


def progress_so_far(stderr: bytes | str | None) -> dict[str, Any]:
    """What the progress lines of a run stopped part-way say: IPOPT iterations done, the
    solve's seconds to the last one, and the seconds per iteration of the stage it was in
    (``seconds_per_iteration_last_stage``, as a finished run's: its last stage so far),
    the peak resident memory to then. Empty without progress lines (stopped before the
    first iteration ended)."""
    text = stderr.decode(errors="replace") if isinstance(stderr, bytes) else stderr or ""
    lines = []
    for ln in text.splitlines():
        if ln.startswith(PROGRESS):
            try:
                lines.append(json.loads(ln[len(PROGRESS) :]))
            except json.JSONDecodeError:  # cut off by the stop
                pass
    if not lines:
        return {}
    last = lines[-1]
    return {
        "iterations_done": last["iterations"],
        "solve_seconds_done": last["wall_seconds"],
        "stage_iterations_done": last["stage_iteration"],
        "seconds_per_iteration_last_stage": last["stage_seconds"] / max(1, last["stage_iteration"]),
        "cost_last": last["cost"],
        "peak_rss_gib": max(ln.get("peak_rss_gib", 0.0) for ln in lines),
    }


def _previous_runs(path: Path) -> list[dict[str, Any]]:
    """The rows of an earlier benchmark file (none when it does not exist)."""
    return json.loads(path.read_text()).get("runs", []) if path.exists() else []


def _write_json(path: Path, data: Any) -> None:
    write_text_atomic(path, json.dumps(data, indent=2) + "\n")


SET_LABELS = {"room": "6 x 6 m, one box", "building": "50 x 70 m, tiles"}


def _figure(runs: list[dict[str, Any]], path: Path) -> None:
    """Seconds per iteration, wall time and RMSE against N, one line per setting."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4))
    ax1, ax2 = fig.subplots(1, 2)
    for name in SCALE_SETS:
        ok = [r for r in runs if r.get("set", "room") == name and r.get("success")]
        if not ok:
            continue
        label = SET_LABELS.get(name, name)
        n = [r["samples"] for r in ok]
        per_it = [r["seconds_per_iteration_last_stage"] for r in ok]
        line = ax1.loglog(n, per_it, "o-", label=f"{label}: s / iteration")[0]
        ax1.loglog(n, [r["wall_seconds"] for r in ok], "s--", color=line.get_color(),
                   label=f"{label}: wall s (all stages)")  # fmt: skip
        ax1.loglog(n, [per_it[0] / n[0] * k for k in n], ":", color=line.get_color(), lw=0.8)
        ax2.loglog(n, [r["rmse_before"] for r in ok], "x:", color=line.get_color(),
                   label=f"{label}: odometry only")  # fmt: skip
        ax2.loglog(n, [r["rmse_after"] for r in ok], "o-", color=line.get_color(),
                   label=f"{label}: GP-SLAM")  # fmt: skip
    ax1.set_xlabel("samples N (dotted: linear in N)")
    ax1.set_ylabel("seconds")
    ax2.set_xlabel("samples N")
    ax2.set_ylabel("position RMSE [m]")
    for ax in (ax1, ax2):
        ax.grid(True, which="both", alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=7)
    fig.suptitle("GP-SLAM on a looping walk (10 Hz): a room with one box, a building with tiles")
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}.png")
    fig.savefig(tmp, dpi=110)
    os.replace(tmp, path)


TIMEOUT_OPTION = click.option(
    "--timeout",
    default=RUN_TIMEOUT,
    type=float,
    show_default=True,
    help="Seconds one run may take; a run still going then is stopped and its row says so.",
)


@click.group()
def main() -> None:
    """casmag benchmarks."""


@main.command()
@click.argument("samples", type=int)
@click.option(
    "--form", default="reduced_rank", type=click.Choice(["reduced_rank", "exact", "tiled"])
)
@click.option("--knot-every", type=int, default=None)
@click.option("--comparison", is_flag=True, help="The exact-versus-reduced-rank set-up.")
@click.option("--set", "extra", multiple=True, help="More overrides (key.path=value).")
@click.option("--start", default=AREA_STARTS[0], type=click.Choice(AREA_STARTS))
def one(
    samples: int,
    form: str,
    knot_every: int | None,
    comparison: bool,
    extra: tuple[str, ...],
    start: str,
) -> None:
    """Run one configuration and print its figures as one JSON line."""
    click.echo(json.dumps(run_one(samples, form, knot_every, comparison, extra, start)))


@main.command()
@click.option("--out", "out_dir", default=str(ROOT / "results" / "bench"), type=click.Path())
@click.option("--samples", default=AREA_SAMPLES, type=int)
@click.option(
    "--forms",
    default=AREA_DEFAULT_MAPS,
    show_default=True,
    help=f"Comma-separated maps of AREA_MAPS ({', '.join(AREA_MAPS)}).",
)
@TIMEOUT_OPTION
@click.option(
    "--areas",
    default=",".join(f"{w:g}x{h:g}" for w, h in AREAS),
    show_default=True,
    help="Comma-separated areas WxH [m] to run; rows of other areas in OUT/area.json are kept.",
)
@click.option(
    "--starts",
    default=AREA_STARTS[0],
    show_default=True,
    help=f"Comma-separated starts of AREA_STARTS ({', '.join(AREA_STARTS)}).",
)
def area(out_dir: str, samples: int, forms: str, timeout: float, areas: str, starts: str) -> None:
    """The same walk length over each area of :data:`AREAS` (:data:`AREA_FIELD`), each map
    form in its own process: wall time, time per iteration, peak memory, RMSE before and
    after. Writes OUT/area.json (again after every run, so a stopped benchmark keeps the
    rows it finished; rows of areas, forms and starts not run this time are kept) and
    OUT/area.png."""
    chosen = [_area(a, areas) for a in areas.split(",") if a]
    form_list = [f for f in forms.split(",") if f]
    unknown = [f for f in form_list if f not in AREA_MAPS]
    if unknown:
        raise click.BadParameter(
            f"{', '.join(unknown)}: not one of {', '.join(AREA_MAPS)}", param_hint="--forms"
        )
    start_list = [s for s in starts.split(",") if s]
    odd = [s for s in start_list if s not in AREA_STARTS]
    if odd or not start_list:
        raise click.BadParameter(
            f"{', '.join(odd) or starts!r}: not one of {', '.join(AREA_STARTS)}",
            param_hint="--starts",
        )
    out = Path(out_dir)
    earlier = [
        {
            **r,
            "form": AREA_TILED_BEFORE if r.get("form") == "tiled" else r.get("form"),
            "start": r.get("start", AREA_STARTS[0]),
        }
        for r in _previous_runs(out / "area.json")
    ]
    kept = [
        r
        for r in earlier
        if not (
            tuple(r.get("area", ())) in chosen
            and r.get("form") in form_list
            and r["start"] in start_list
        )
    ]
    runs: list[dict[str, Any]] = []
    both = kept
    order = lambda r: (r["area"][0] * r["area"][1], r["form"], r["start"])  # noqa: E731
    for w, h in chosen:
        for form in form_list:
            kind, extra = AREA_MAPS[form]
            sets = [f"simulation.trajectory.area=[{w}, {h}]", *AREA_FIELD, *extra]
            for start in start_list:
                where = start.replace("-", " ")
                click.echo(f"{w:g} x {h:g} m, {form}, from the {where} ...", err=True)
                args = [str(samples), "--form", kind, "--start", start]
                args += [a for s in sets for a in ("--set", s)]
                row = _spawn(args, timeout)
                runs.append({"area": [w, h], **row, "form": form, "start": start})
                runs[-1].pop("P_estimate", None)
                click.echo(f"  {_summary(runs[-1])}", err=True)
                both = sorted(kept + runs, key=order)
                _write_json(out / "area.json", {"meta": _meta(), "runs": both})
    _area_figure(both, out / "area.png")
    click.echo(f"wrote {out / 'area.json'} and {out / 'area.png'}", err=True)


def _area_series(axes: Any, runs: list[dict[str, Any]], color: str, label: str, mk: str) -> None:
    """One map and start's rows on the three panels of :func:`_area_figure` (``mk``: the
    marker and line style of its finished runs; a stopped run is the marker, open)."""
    ok = [r for r in runs if r.get("success")]
    a = [r["area"][0] * r["area"][1] for r in ok]
    if ok:
        axes[0].loglog(a, [r["seconds_per_iteration_last_stage"] for r in ok], mk,
                       color=color, label=label)  # fmt: skip
        axes[1].loglog(a, [r["peak_rss_gib"] for r in ok], mk, color=color, label=label)
        axes[2].loglog(a, [r["rmse_after"] for r in ok], mk, color=color,
                       label=f"{label} after")  # fmt: skip
        axes[2].loglog(a, [r["rmse_before"] for r in ok], "x:", color=color,
                       label=f"{label} before")  # fmt: skip
    part = [r for r in runs if not r.get("success")]
    for ax, key in ((axes[0], "seconds_per_iteration_last_stage"), (axes[1], "peak_rss_gib")):
        shown = [r for r in part if r.get(key)]
        if shown:
            a_s = [r["area"][0] * r["area"][1] for r in shown]
            ax.loglog(a_s, [r[key] for r in shown], mk[0], mfc="none", color=color,
                      label=f"{label}, stopped: so far")  # fmt: skip


def _area(text: str, option: str) -> tuple[float, float]:
    """One WxH of ``--areas`` as (W, H) metres; BadParameter naming the option's value."""
    try:
        w, h = (float(v) for v in text.split("x"))
    except ValueError:
        raise click.BadParameter(
            f"{option!r}: expected WxH[,WxH...] in metres", param_hint="--areas"
        ) from None
    return w, h


def _area_figure(runs: list[dict[str, Any]], path: Path) -> None:
    """Seconds per iteration, peak memory and RMSE against the area, a line per map form
    and start (one colour per map, dashed from the truth); a run stopped or crashed
    part-way is an open marker at what it had reached (seconds per iteration of its stage
    then, memory to then: lower bounds of the finished run's)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 4))
    axes = fig.subplots(1, 3)
    own = AREA_STARTS[0]  # rows written before the starts were told apart started there
    for k, form in enumerate(sorted({r.get("form") for r in runs if r.get("form")})):
        for start in AREA_STARTS:
            of = [r for r in runs if r.get("form") == form and r.get("start", own) == start]
            label, mk = (form, "o-") if start == own else (f"{form} from the {start}", "s--")
            _area_series(axes, of, f"C{k}", label, mk)
    every = [r["area"][0] * r["area"][1] for r in runs if r.get("area")]
    for ax, ylabel in zip(
        axes, ("s / iteration (last stage)", "peak RSS [GiB]", "position RMSE [m]"), strict=True
    ):
        if every:  # the same area axis on every panel, whatever each one holds
            ax.set_xscale("log")
            ax.set_xlim(min(every) / 1.5, max(every) * 1.5)
        ax.set_xlabel("area [m^2]")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        if ax.lines:
            ax.legend(fontsize=7)
    fig.suptitle(
        "10,000-sample walk over growing areas, dipole field: one box against tiles"
        " (squares, dashed: from the true positions)"
    )
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}.png")
    fig.savefig(tmp, dpi=110)
    os.replace(tmp, path)


@main.command()
@click.option("--out", "out_dir", default=str(ROOT / "results" / "bench"), type=click.Path())
@click.option("--sizes", default=",".join(map(str, SCALE_SIZES)), help="Comma-separated N.")
@click.option("--exact-sizes", default=",".join(map(str, EXACT_SIZES)), help="N for exact GP.")
@click.option(
    "--sets",
    "names",
    default=",".join(SCALE_SETS),
    show_default=True,
    help="Comma-separated settings of SCALE_SETS to run at each N.",
)
@TIMEOUT_OPTION
def scale(out_dir: str, sizes: str, exact_sizes: str, names: str, timeout: float) -> None:
    """GP-SLAM on the walk at each N in each setting of :data:`SCALE_SETS` (the 6 m x 6 m
    room with one box, the 50 m x 70 m building with tiles), and exact against reduced rank
    at small N (one knot per sample for both, :data:`COMPARISON`). Writes OUT/scale.json
    (again after every run; rows of settings not run this time are kept) and
    OUT/scale.png."""
    chosen = [v for v in names.split(",") if v]
    unknown = sorted(set(chosen) - set(SCALE_SETS))
    if unknown:
        raise click.BadParameter(
            f"{', '.join(unknown)} (known: {', '.join(SCALE_SETS)})", param_hint="--sets"
        )
    out = Path(out_dir)
    exact_n = [int(v) for v in exact_sizes.split(",") if v]
    kept = [
        r
        for r in _previous_runs(out / "scale.json")
        if not (r.get("comparison") == "exact_vs_reduced_rank" and exact_n)
        and not (r.get("comparison") == "scale" and r.get("set", "room") in chosen)
    ]
    runs = _comparisons(exact_n)
    for name in chosen:
        form, extra = SCALE_SETS[name]
        for n in [int(v) for v in sizes.split(",") if v]:
            click.echo(f"{name}: N = {n} {form} ...", err=True)
            knots = (
                ["--knot-every", str(KNOT_EVERY[n])] if name == "room" and n in KNOT_EVERY else []
            )
            sets = [a for v in extra for a in ("--set", v)]
            row = _spawn([str(n), "--form", form, *knots, *sets], timeout)
            runs.append({"comparison": "scale", "set": name, "samples": n, "form": form, **row})
            runs[-1].pop("P_estimate", None)
            click.echo(f"  {_summary(runs[-1])}", err=True)
            _save(out, runs + kept, figure=False)
    _save(out, runs + kept)


@main.command()
@click.option("--out", "out_dir", default=str(ROOT / "results" / "bench"), type=click.Path())
@click.option("--sizes", default=",".join(map(str, EXACT_SIZES)), help="Comma-separated N.")
def exact(out_dir: str, sizes: str) -> None:
    """Exact against reduced rank at each N (:data:`COMPARISON`), replacing those rows of
    OUT/scale.json and keeping its scale rows."""
    out = Path(out_dir)
    previous = _previous_runs(out / "scale.json")
    kept = [r for r in previous if r.get("comparison") != "exact_vs_reduced_rank"]
    _save(out, _comparisons([int(v) for v in sizes.split(",") if v]) + kept)


def _comparisons(sizes: list[int]) -> list[dict[str, Any]]:
    """The exact GP and the reduced-rank map on the same data at each N, one knot per
    sample, with the largest position difference between the two."""
    runs: list[dict[str, Any]] = []
    for n in sizes:
        pair = []
        for form in ("exact", "reduced_rank"):
            click.echo(f"N = {n} {form} (one knot per sample) ...", err=True)
            pair.append(
                {
                    "comparison": "exact_vs_reduced_rank",
                    **_spawn([str(n), "--form", form, "--knot-every", "1", "--comparison"]),
                }
            )
            click.echo(f"  {_summary(pair[-1])}", err=True)
        P = [r.pop("P_estimate", None) for r in pair]
        if all(p is not None for p in P) and all(r.get("success") for r in pair):
            import numpy as np

            diff = float(np.abs(np.asarray(P[0]) - np.asarray(P[1])).max())
            pair[1]["max_position_difference_to_exact"] = diff
            click.echo(f"  max |P_exact - P_reduced_rank| = {diff:.2e} m", err=True)
        runs += pair
    return runs


def _meta() -> dict[str, Any]:
    import casadi

    from casmag.versions import versions

    return {
        "problem": str(WALK.relative_to(ROOT)),
        "machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0]},
        "casadi": casadi.__version__,
        "versions": versions(),
    }


def _save(out: Path, runs: list[dict[str, Any]], figure: bool = True) -> None:
    _write_json(out / "scale.json", {"meta": _meta(), "runs": runs})
    if figure:
        _figure([r for r in runs if r["comparison"] == "scale"], out / "scale.png")
        click.echo(f"wrote {out / 'scale.json'} and {out / 'scale.png'}", err=True)


def _summary(r: dict[str, Any]) -> str:
    if not r.get("success"):
        done = ""
        if "iterations_done" in r:
            done = (
                f" ({r['iterations_done']} it in {r['solve_seconds_done']:.0f} s, "
                f"{r['seconds_per_iteration_last_stage']:.2f} s/it in its last stage)"
            )
        return f"FAILED: {r.get('status')}{done}"
    return (
        f"{r['status']}: {r['iterations_total']} it, {r['wall_seconds']:.1f} s wall, "
        f"{r['seconds_per_iteration_last_stage']:.2f} s/it, {r['peak_rss_gib']:.2f} GiB, "
        f"RMSE {r['rmse_before']:.4f} -> {r['rmse_after']:.4f} m"
    )


if __name__ == "__main__":
    main()
