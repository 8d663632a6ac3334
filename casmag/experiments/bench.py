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
tiles."""


def run_one(
    samples: int,
    form: str,
    knot_every: int | None,
    comparison: bool = False,
    extra: tuple[str, ...] = (),
) -> dict[str, Any]:
    """Simulate the walk with ``samples`` samples and solve it; figures measured here.
    ``extra``: more ``--set`` overrides (the area benchmark's area and field)."""
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
    result = casmag.solve(problem, data)
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


def _spawn(args: list[str]) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "casmag.experiments.bench", "one", *args]
    out = subprocess.run(cmd, capture_output=True, text=True, check=False)
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        tail = (out.stderr.strip().splitlines() or ["no output"])[-1]
        return {"args": args, "status": f"crashed: {tail}", "success": False}
    return json.loads(lines[-1])


def _write_json(path: Path, data: Any) -> None:
    write_text_atomic(path, json.dumps(data, indent=2) + "\n")


def _figure(runs: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    rr = [r for r in runs if r.get("form") == "reduced_rank" and r.get("success")]
    fig = Figure(figsize=(10, 4))
    ax1, ax2 = fig.subplots(1, 2)
    n = [r["samples"] for r in rr]
    ax1.loglog(n, [r["seconds_per_iteration_last_stage"] for r in rr], "o-", label="s / iteration")
    ax1.loglog(n, [r["wall_seconds"] for r in rr], "s-", label="wall s (all stages)")
    if rr:
        ref = rr[0]["seconds_per_iteration_last_stage"] / n[0]
        ax1.loglog(n, [ref * k for k in n], "k:", label="linear in N")
    ax1.set_xlabel("samples N")
    ax1.set_ylabel("seconds")
    ax1.legend()
    ax1.grid(True, which="both", alpha=0.3)
    ax2.loglog(n, [r["rmse_before"] for r in rr], "o--", label="odometry only")
    ax2.loglog(n, [r["rmse_after"] for r in rr], "o-", label="GP-SLAM")
    ax2.set_xlabel("samples N")
    ax2.set_ylabel("position RMSE [m]")
    ax2.legend()
    ax2.grid(True, which="both", alpha=0.3)
    fig.suptitle("Reduced-rank GP-SLAM on a looping 6 m x 6 m walk (10 Hz)")
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}.png")
    fig.savefig(tmp, dpi=110)
    os.replace(tmp, path)


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
def one(
    samples: int, form: str, knot_every: int | None, comparison: bool, extra: tuple[str, ...]
) -> None:
    """Run one configuration and print its figures as one JSON line."""
    click.echo(json.dumps(run_one(samples, form, knot_every, comparison, extra)))


@main.command()
@click.option("--out", "out_dir", default=str(ROOT / "results" / "bench"), type=click.Path())
@click.option("--samples", default=AREA_SAMPLES, type=int)
@click.option("--forms", default="reduced_rank,tiled", help="Comma-separated map forms.")
def area(out_dir: str, samples: int, forms: str) -> None:
    """The same walk length over each area of :data:`AREAS` (:data:`AREA_FIELD`), each map
    form in its own process: wall time, time per iteration, peak memory, RMSE before and
    after. Writes OUT/area.json and OUT/area.png."""
    runs = []
    for w, h in AREAS:
        for form in forms.split(","):
            click.echo(f"{w:g} x {h:g} m, {form} ...", err=True)
            sets = [f"simulation.trajectory.area=[{w}, {h}]", *AREA_FIELD]
            args = [str(samples), "--form", form] + [a for s in sets for a in ("--set", s)]
            runs.append({"area": [w, h], **_spawn(args)})
            runs[-1].pop("P_estimate", None)
            click.echo(f"  {_summary(runs[-1])}", err=True)
    out = Path(out_dir)
    _write_json(out / "area.json", {"meta": _meta(), "runs": runs})
    _area_figure(runs, out / "area.png")
    click.echo(f"wrote {out / 'area.json'} and {out / 'area.png'}", err=True)


def _area_figure(runs: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 4))
    axes = fig.subplots(1, 3)
    for form in sorted({r.get("form") for r in runs if r.get("form")}):
        ok = [r for r in runs if r.get("form") == form and r.get("success")]
        a = [r["area"][0] * r["area"][1] for r in ok]
        axes[0].loglog(a, [r["seconds_per_iteration_last_stage"] for r in ok], "o-", label=form)
        axes[1].loglog(a, [r["peak_rss_gib"] for r in ok], "o-", label=form)
        axes[2].loglog(a, [r["rmse_after"] for r in ok], "o-", label=f"{form} after")
        axes[2].loglog(a, [r["rmse_before"] for r in ok], "x:", label=f"{form} before")
    for ax, ylabel in zip(
        axes, ("s / iteration (last stage)", "peak RSS [GiB]", "position RMSE [m]"), strict=True
    ):
        ax.set_xlabel("area [m^2]")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle("10,000-sample walk over growing areas, dipole field: one box against tiles")
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}.png")
    fig.savefig(tmp, dpi=110)
    os.replace(tmp, path)


@main.command()
@click.option("--out", "out_dir", default=str(ROOT / "results" / "bench"), type=click.Path())
@click.option("--sizes", default=",".join(map(str, SCALE_SIZES)), help="Comma-separated N.")
@click.option("--exact-sizes", default=",".join(map(str, EXACT_SIZES)), help="N for exact GP.")
def scale(out_dir: str, sizes: str, exact_sizes: str) -> None:
    """Reduced-rank GP-SLAM on the walk at each N, and exact against reduced rank at small N
    (one knot per sample for both, :data:`COMPARISON`). Writes OUT/scale.json and
    OUT/scale.png."""
    runs = _comparisons([int(v) for v in exact_sizes.split(",") if v])
    for n in [int(v) for v in sizes.split(",") if v]:
        click.echo(f"N = {n} reduced_rank ...", err=True)
        knots = ["--knot-every", str(KNOT_EVERY[n])] if n in KNOT_EVERY else []
        runs.append({"comparison": "scale", **_spawn([str(n), *knots])})
        runs[-1].pop("P_estimate", None)
        click.echo(f"  {_summary(runs[-1])}", err=True)
    _save(Path(out_dir), runs)


@main.command()
@click.option("--out", "out_dir", default=str(ROOT / "results" / "bench"), type=click.Path())
@click.option("--sizes", default=",".join(map(str, EXACT_SIZES)), help="Comma-separated N.")
def exact(out_dir: str, sizes: str) -> None:
    """Exact against reduced rank at each N (:data:`COMPARISON`), replacing those rows of
    OUT/scale.json and keeping its scale rows."""
    out = Path(out_dir)
    old = json.loads((out / "scale.json").read_text()) if (out / "scale.json").exists() else {}
    kept = [r for r in old.get("runs", []) if r.get("comparison") != "exact_vs_reduced_rank"]
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

    return {
        "problem": str(WALK.relative_to(ROOT)),
        "machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0]},
        "casadi": casadi.__version__,
    }


def _save(out: Path, runs: list[dict[str, Any]]) -> None:
    _write_json(out / "scale.json", {"meta": _meta(), "runs": runs})
    _figure([r for r in runs if r["comparison"] == "scale"], out / "scale.png")
    click.echo(f"wrote {out / 'scale.json'} and {out / 'scale.png'}", err=True)


def _summary(r: dict[str, Any]) -> str:
    if not r.get("success"):
        return f"FAILED: {r.get('status')}"
    return (
        f"{r['status']}: {r['iterations_total']} it, {r['wall_seconds']:.1f} s wall, "
        f"{r['seconds_per_iteration_last_stage']:.2f} s/it, {r['peak_rss_gib']:.2f} GiB, "
        f"RMSE {r['rmse_before']:.4f} -> {r['rmse_after']:.4f} m"
    )


if __name__ == "__main__":
    main()
