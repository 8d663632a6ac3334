"""Figures (PNG, matplotlib's Agg canvas; no global pyplot state).

The figures read a result and never the other way round: they take any object with the
attributes of :class:`Drawable` or :class:`DrawableErrors` (casmag.result.Result of every
motion model), so this module imports nothing of casmag's. Each figure function
writes its PNG and returns the matplotlib Figure (the tests read its titles and artists).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator


class Drawable(Protocol):
    """What the figures read of a result: ``info["name"]`` (and ``info["sessions"]``), the
    arrays (``P_odometry``, ``P_estimate``, ``P_true``, ``P_cov``, ``map_x``, ``map_y``,
    ``map_field``, ``map_std``, ``map_prior_std``), the IPOPT status and success, iterations,
    and the convergence record of every solve (casmag.nlp.Solution.trace)."""

    info: dict[str, Any]
    arrays: dict[str, Any]
    status: str
    success: bool
    iterations: int
    cost_per_iteration: list[float]
    convergence: list[dict[str, Any]]


class DrawableErrors(Drawable, Protocol):
    """A :class:`Drawable` with its errors before and after [m] (None when unknown)."""

    rmse_before: float | None
    max_before: float | None
    rmse_after: float | None
    max_after: float | None


def result_figures(result: Any, folder: Path) -> None:
    """Every figure a result has the data for, into folder: trajectory.png (the IMU
    layout for ``motion`` imu), sessions.png (several sessions), cost.png (a cost per
    iteration), map.png (a map grid)."""
    folder = Path(folder)
    if getattr(result, "motion", "translational") == "imu":
        imu_trajectory_figure(result, folder / "trajectory.png")
    else:
        trajectory_figure(result, folder / "trajectory.png")
    if result.info.get("sessions"):
        sessions_figure(result, folder / "sessions.png")
    if result.cost_per_iteration:
        cost_figure(result, folder / "cost.png")
    if result.arrays.get("map_field") is not None:
        map_figure(result, folder / "map.png")


def _save(fig: Figure, path: Path) -> None:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=120)


def trajectory_figure(result: DrawableErrors, path: Path) -> Figure:
    """Odometry-only (dashed), estimate (solid) and truth (triangles), as in the paper's
    Figures 1-4, start and end marked, the solver status and the errors in the title. A
    failed solve's last iterate is drawn dotted and labelled as such, never as an estimate.
    With position covariances: 3-sigma ellipses at about 40 points along the estimate,
    labelled by the covariance drawn, and a panel of the position error against the
    3-sigma radius along the path (the ellipses can be too small to see at the map's
    scale)."""
    a = result.arrays
    cov = a.get("P_cov")
    fig = Figure(figsize=(6.0, 7.4 if cov is not None else 5.6))
    if cov is not None:
        ax, ax_err = fig.subplots(2, 1, height_ratios=[3.2, 1.0])
    else:
        ax, ax_err = fig.add_subplot(), None
    label = _covariance_label(result)
    _trajectories(ax, a, _pieces(result), result.success, label, estimate=estimate_label(result))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=7)
    ax.set_title(_title(result), fontsize=9, color="black" if trusted(result) else "tab:red")
    if ax_err is not None:
        _error_panel(ax_err, a, label)
    fig.tight_layout()
    _save(fig, path)
    return fig


def _title(result: DrawableErrors) -> str:
    """Name and status, then the errors (or why there are none)."""
    title = f"{result.info.get('name', '')}: {result.status}"
    if not result.success:
        return title + "\nIPOPT failed: no estimate (the last iterate is drawn dotted)"
    if result.rmse_before is not None and result.rmse_after is not None:
        title += (
            f"\nRMSE {result.rmse_before:.4f} m -> {result.rmse_after:.4f} m, "
            f"max {result.max_before:.4f} m -> {result.max_after:.4f} m"
        )
    return title + untrusted_line(result)


def trusted(result: Any) -> bool:
    """Solved and trusted by its verdict (a result without one: solved)."""
    verdict = getattr(result, "verdict", None) or {}
    return bool(result.success) and bool(verdict.get("trusted", True))


def untrusted_line(result: Any, width: int = 70) -> str:
    """A title line saying a solved result is not trusted, with its first reason (cut to
    ``width`` characters); empty for a trusted or failed one."""
    verdict = getattr(result, "verdict", None) or {}
    if not result.success or verdict.get("trusted", True):
        return ""
    reasons = verdict.get("reasons") or ["see result.json"]
    first = reasons[0] if len(reasons[0]) <= width else reasons[0][: width - 3] + "..."
    more = f" (+{len(reasons) - 1} more)" if len(reasons) > 1 else ""
    return f"\nNOT TRUSTED: {first}{more}"


def estimate_label(result: Drawable) -> str:
    """What the estimate is called in a legend: ``GP-SLAM`` (the MAP) or the method that made
    it (``info.method``, e.g. ``EKF``)."""
    method = result.info.get("method")
    return "GP-SLAM" if method in (None, "map") else str(method).upper()


def _covariance_label(result: Drawable) -> str:
    """What the drawn covariance is: the Laplace covariance, inflated for correlated
    magnetometer residuals when that was applied (casmag.solver.uncertainty), or a filter's
    own covariance."""
    u = getattr(result, "uncertainty", None) or {}
    inflation = u.get("inflation") or {}
    label = "Laplace, inflated for correlated residuals" if inflation.get("active") else "Laplace"
    if result.info.get("method") not in (None, "map"):
        label = f"{estimate_label(result)}'s own"
        if inflation.get("active"):
            label += ", inflated for correlated residuals"
    return label if trusted(result) or not result.success else label + ", NOT TRUSTED"


def _error_panel(ax: Any, a: dict[str, Any], label: str) -> None:
    """Position error and 3-sigma radius (3 sqrt of the covariance's trace) per sample."""
    import numpy as np

    cov = a["P_cov"]
    k = np.arange(cov.shape[0])
    radius = 3.0 * np.sqrt(np.trace(cov, axis1=1, axis2=2))
    ax.plot(k, radius, "-", color="tab:purple", lw=1.0, label=f"3-sigma radius ({label})")
    if a.get("P_true") is not None:
        err = np.linalg.norm(a["P_estimate"] - a["P_true"], axis=1)
        ax.plot(k, err, "-", color="tab:blue", lw=0.8, label="position error")
    ax.set_xlabel("sample")
    ax.set_ylabel("[m]")
    ax.set_ylim(bottom=0.0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=7)


def _pieces(result: Drawable) -> list[slice]:
    """The ranges of the result's arrays drawn as separate lines: one per session
    (casmag.solver.multisession; the IMU model's arrays are per keyframe, its session rows
    count keyframes)."""
    sessions = result.info.get("sessions")
    if not sessions:
        return [slice(None)]
    if "first_keyframe" in sessions[0]:
        return [slice(s["first_keyframe"], s["first_keyframe"] + s["keyframes"]) for s in sessions]
    return [slice(s["first_sample"], s["first_sample"] + s["n_samples"]) for s in sessions]


def _trajectories(
    ax: Any,
    a: dict,
    pieces: list[slice],
    success: bool = True,
    covariance: str = "Laplace",
    ellipses: bool = True,
    estimate: str = "GP-SLAM",
    before: str = "odometry only",
) -> None:
    for i, sl in enumerate(pieces):
        first = i == 0
        ax.plot(
            *a["P_odometry"][sl, :2].T,
            "--",
            color="tab:cyan",
            lw=1.4,
            label=before if first else None,
        )
        if a.get("P_true") is not None:
            ax.plot(
                *a["P_true"][sl, :2].T,
                "^",
                color="tab:red",
                ms=4,
                mfc="none",
                label="truth" if first else None,
            )
        if success:
            ax.plot(
                *a["P_estimate"][sl, :2].T,
                "-",
                color="tab:blue",
                lw=1.4,
                label=estimate if first else None,
            )
        else:
            ax.plot(
                *a["P_estimate"][sl, :2].T,
                ":",
                color="tab:red",
                lw=1.2,
                label="last iterate (failed)" if first else None,
            )
        start, end = a["P_estimate"][sl][0, :2], a["P_estimate"][sl][-1, :2]
        ax.plot(*start, "o", color="black", ms=6, label="start" if first else None)
        ax.plot(*end, "s", color="black", ms=5, mfc="none", label="end" if first else None)
    if ellipses and success and a.get("P_cov") is not None and a["P_cov"].shape[1] == 2:
        _ellipses(ax, a["P_estimate"], a["P_cov"], covariance)


def sessions_figure(result: Drawable, path: Path) -> Figure:
    """One panel per session of a multi-session solve (casmag.solver.multisession): odometry-only
    (IMU: the IMU-only adjustment), estimate and truth, with the session's errors in its
    title."""
    import math

    sessions = result.info["sessions"]
    imu = result.arrays.get("P_odometry") is None and result.arrays.get("P_imu_only") is not None
    cols = min(3, len(sessions))
    rows = math.ceil(len(sessions) / cols)
    fig = Figure(figsize=(4.2 * cols, 4.0 * rows))
    for i, (s, sl) in enumerate(zip(sessions, _pieces(result), strict=True)):
        ax = fig.add_subplot(rows, cols, i + 1)
        a = {
            k: (None if v is None else v[sl])
            for k, v in result.arrays.items()
            if k.startswith("P_")
        }
        if imu:
            a["P_odometry"] = a["P_imu_only"]
        before = "IMU-only adjustment" if imu else "odometry only"
        _trajectories(
            ax, a, [slice(None)], result.success, _covariance_label(result), before=before
        )
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        title = s["name"]
        if s.get("rmse_after") is not None:
            title += f": RMSE {s['rmse_before']:.3f} -> {s['rmse_after']:.3f} m"
        ax.set_title(title, fontsize=9)
        if i == 0:
            ax.legend(loc="best", fontsize=7)
    fig.suptitle(
        f"{result.info.get('name', '')}: {result.status}" + untrusted_line(result),
        fontsize=10,
        color="black" if trusted(result) else "tab:red",
    )
    fig.tight_layout()
    _save(fig, path)
    return fig


def _ellipses(
    ax: Any, P: Any, cov: Any, covariance: str, count: int = 40, scale: float = 3.0
) -> None:
    """scale-sigma ellipses of the (N, 2, 2) covariances at ``count`` samples along P."""
    import numpy as np
    from matplotlib.patches import Ellipse

    n = P.shape[0]
    for i, k in enumerate(np.unique(np.linspace(0, n - 1, count).round().astype(int))):
        w, v = np.linalg.eigh(cov[k])
        angle = float(np.degrees(np.arctan2(v[1, 1], v[0, 1])))
        width, height = 2 * scale * np.sqrt(np.maximum(w[::-1], 0.0))
        ax.add_patch(
            Ellipse(
                (P[k, 0], P[k, 1]),
                width,
                height,
                angle=angle,
                fill=False,
                lw=0.8,
                color="tab:purple",
                label=f"{scale:g}-sigma ({covariance})" if i == 0 else None,
            )
        )


def cost_figure(result: Drawable, path: Path) -> Figure:
    """Convergence of every solve of the run (the paper's Figure 7, per stage): the
    objective (top) and IPOPT's dual and primal infeasibility (bottom, the dual one is what
    the tolerance is checked on) per iteration, the stages one after another with their
    names and statuses, integer iteration ticks, and the final status in the title (red
    when IPOPT failed)."""
    import numpy as np

    stages = result.convergence or [
        {
            "stage": "solve",
            "status": result.status,
            "iterations": result.iterations,
            "objective": list(result.cost_per_iteration),
            "inf_pr": [],
            "inf_du": [],
        }
    ]
    fig = Figure(figsize=(6.4, 5.2))
    ax, ax_kkt = fig.subplots(2, 1, sharex=True)
    start = 0
    positive = all(v > 0 for st in stages for v in st["objective"])
    for i, st in enumerate(stages):
        obj = np.asarray(st["objective"], dtype=float)
        x = start + np.arange(obj.size)
        color = f"C{i % 10}"
        label = f"{st['stage']}: {st['status']}, {st['iterations']} it"
        ax.plot(x, obj, "o-", ms=2.5, lw=1.0, color=color, label=label)
        for key, style in (("inf_du", "-"), ("inf_pr", ":")):
            v = np.asarray(st.get(key) or [], dtype=float)
            v = np.where(v > 0, v, np.nan)
            if v.size and np.isfinite(v).any():
                ax_kkt.semilogy(start + np.arange(v.size), v, style, lw=1.0, color=color)
        if i:
            for a_ in (ax, ax_kkt):
                a_.axvline(start - 0.5, color="grey", lw=0.6, ls="--")
        start += max(obj.size, 1)
    ax.set_yscale("log" if positive else "symlog")
    ax.set_ylabel("objective")
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="upper right", fontsize=7)
    ax_kkt.set_ylabel("infeasibility")
    ax_kkt.set_xlabel("IPOPT iteration (stages one after another)")
    ax_kkt.grid(alpha=0.3, which="both")
    ax_kkt.plot([], [], "-", color="black", lw=1.0, label="dual (gradient)")
    ax_kkt.plot([], [], ":", color="black", lw=1.0, label="primal")
    ax_kkt.legend(loc="upper right", fontsize=7)
    ax_kkt.xaxis.set_major_locator(MaxNLocator(integer=True))
    title = f"{result.info.get('name', '')}: {result.status}, {result.iterations} iterations"
    if not result.success:
        title = f"FAILED: {title}"
    title += untrusted_line(result)
    ax.set_title(title, fontsize=9, color="black" if trusted(result) else "tab:red")
    fig.tight_layout()
    _save(fig, path)
    return fig


#: The map is masked where its posterior std is above this fraction of the prior's.
MAP_MASK = 0.5


def map_figure(result: Drawable, path: Path) -> Figure:
    """Estimated field magnitude (GP posterior mean or reduced-rank map) with the estimated
    path, masked where the samples do not inform the map (posterior std above MAP_MASK of
    the prior std, mean over the three components), and beside it the posterior std. The
    path is drawn when the arrays hold ``P_estimate`` (a saved map's grid has none)."""
    import numpy as np

    a = result.arrays
    std, prior = a.get("map_std"), a.get("map_prior_std")
    fig = Figure(figsize=(11.0, 4.8) if std is not None else (6.4, 5.4))
    axes = fig.subplots(1, 2) if std is not None else [fig.add_subplot()]
    magnitude = (a["map_field"] ** 2).sum(axis=-1) ** 0.5
    title = f"{result.info.get('name', '')}: {result.status}\nestimated field magnitude"
    if a.get("map_z") is not None:
        title += f" at z = {float(a['map_z']):.3g} m"
    if std is not None:
        ratio = std.mean(axis=-1) / np.maximum(prior.mean(axis=-1), 1e-300)
        magnitude = np.ma.masked_where(ratio > MAP_MASK, magnitude)
        title += f"\n(blank where the posterior std > {MAP_MASK:g} x the prior's)"
    ax = axes[0]
    ax.set_facecolor("0.92")
    mesh = ax.pcolormesh(a["map_x"], a["map_y"], magnitude, shading="auto", cmap="viridis")
    fig.colorbar(mesh, ax=ax, label="|m| (field units)")
    title += untrusted_line(result, 50)
    ax.set_title(title, fontsize=9, color="black" if trusted(result) else "tab:red")
    if std is not None:
        ax = axes[1]
        mesh = ax.pcolormesh(
            a["map_x"], a["map_y"], std.mean(axis=-1), shading="auto", cmap="magma_r"
        )
        fig.colorbar(mesh, ax=ax, label="posterior std per component (field units)")
        where = " given the estimated path" if a.get("P_estimate") is not None else ""
        ax.set_title(f"posterior std{where}", fontsize=9)
    path_drawn = a.get("P_estimate") is not None
    for ax in axes:
        if path_drawn:
            ax.plot(*a["P_estimate"][:, :2].T, "-", color="white", lw=1.0, label="GP-SLAM path")
            ax.plot(*a["P_estimate"][0, :2], "o", color="black", ms=5, label="start")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_aspect("equal")
    if path_drawn:
        axes[0].legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    _save(fig, path)
    return fig


def imu_trajectory_figure(r: Any, path: Path) -> Figure:
    """The plane of motion (x-y) and the 3-D path: truth, strapdown (drawn only where it stays
    within the frame of the others), IMU-only adjustment and GP-SLAM."""
    import numpy as np

    a = r.arrays
    ref = np.vstack([a[k] for k in ("P_true", "P_imu_only", "P_estimate") if a.get(k) is not None])
    lo, hi = ref.min(axis=0), ref.max(axis=0)
    pad = 0.25 * max(float(np.max(hi - lo)), 0.05)
    fig = Figure(figsize=(11.0, 5.2))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 2, 1)
    ax3 = fig.add_subplot(1, 2, 2, projection="3d")
    series = [
        ("P_true", "truth", dict(color="tab:red", lw=2.2, alpha=0.45)),
        ("P_strapdown", "strapdown only", dict(color="tab:gray", lw=1.0, ls=":")),
        ("P_imu_only", "IMU only + zero-position update", dict(color="tab:cyan", lw=1.0, ls="--")),
        ("P_estimate", "GP-SLAM", dict(color="tab:blue", lw=1.0)),
        (
            "P_gp_slam_map",
            "GP-SLAM map pass (not used: homogeneous field)",
            dict(color="tab:orange", lw=0.8, ls="-."),
        ),
    ]
    for key, label, style in series:
        P = a.get(key)
        if P is None:
            continue
        inside = np.all((P >= lo - pad) & (P <= hi + pad), axis=1)
        Pc = np.where(inside[:, None], P, np.nan)
        ax.plot(Pc[:, 0], Pc[:, 1], label=label, **style)
        ax3.plot(Pc[:, 0], Pc[:, 1], Pc[:, 2], label=label, **style)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=7)
    start = ref[0]
    ax.plot(*start[:2], "o", color="black", ms=5, label=None)
    ax3.plot(*start[:, None], "o", color="black", ms=5)
    for axis, k in ((ax3.set_xlim, 0), (ax3.set_ylim, 1), (ax3.set_zlim, 2)):
        axis(lo[k] - pad, hi[k] + pad)  # scaled to the estimate, not to the strapdown
    for axis in (ax3.xaxis, ax3.yaxis, ax3.zaxis):
        axis.set_major_locator(MaxNLocator(4))
    ax3.tick_params(labelsize=7)
    ax3.set_xlabel("x [m]")
    ax3.set_ylabel("y [m]")
    ax3.set_zlabel("z [m]")
    e = r.details["errors"]
    status = r.status if r.success else f"FAILED ({r.status}, {r.details['failed_stage']})"
    lines = [f"{r.info.get('name', '')}: {status}"]
    parts = []
    for key, label in (
        ("strapdown", "strapdown"),
        ("imu_only", "IMU only"),
        ("gp_slam", "GP-SLAM"),
    ):
        if e[key]["rmse"] is not None:
            parts.append(f"{label} {e[key]['rmse']:.4g} m")
    lines.append("position RMSE: " + ", ".join(parts))
    title = "\n".join(lines) + untrusted_line(r)
    fig.suptitle(title, fontsize=9, color="black" if trusted(r) else "tab:red")
    fig.tight_layout()
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=110)
    return fig
