"""Figures (PNG, matplotlib's Agg canvas; no global pyplot state).

The figures read a result and never the other way round: they take any object with the
attributes of :class:`Drawable` or :class:`DrawableErrors` (casmag.result.Result and the
IMU and planar results), so this module imports nothing of casmag's.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


class Drawable(Protocol):
    """What the figures read of a result: ``info["name"]`` (and ``info["sessions"]``), the
    arrays (``P_odometry``, ``P_estimate``, ``P_true``, ``P_cov``, ``map_x``, ``map_y``,
    ``map_field``), the IPOPT status, iterations and cost per iteration."""

    info: dict[str, Any]
    arrays: dict[str, Any]
    status: str
    iterations: int
    cost_per_iteration: list[float]


class DrawableErrors(Drawable, Protocol):
    """A :class:`Drawable` with its errors before and after [m] (None when unknown)."""

    rmse_before: float | None
    max_before: float | None
    rmse_after: float | None
    max_after: float | None


def _save(fig: Figure, path: Path) -> None:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=120)


def trajectory_figure(result: DrawableErrors, path: Path) -> None:
    """Odometry-only (dashed), estimate (solid) and truth (triangles), as in the paper's
    Figures 1-4, with the errors in the title; with the Laplace covariances, 3-sigma
    ellipses at about 40 points along the estimate."""
    a = result.arrays
    fig = Figure(figsize=(6.0, 5.6))
    ax = fig.add_subplot()
    _trajectories(ax, a, _pieces(result))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    title = result.info.get("name", "")
    if result.rmse_before is not None and result.rmse_after is not None:
        title += (
            f"\nRMSE {result.rmse_before:.4f} m -> {result.rmse_after:.4f} m, "
            f"max {result.max_before:.4f} m -> {result.max_after:.4f} m"
        )
    ax.set_title(title, fontsize=9)
    _save(fig, path)


def _pieces(result: Drawable) -> list[slice]:
    """The sample ranges drawn as separate lines: one per session (casmag.multisession)."""
    sessions = result.info.get("sessions")
    if not sessions:
        return [slice(None)]
    return [slice(s["first_sample"], s["first_sample"] + s["n_samples"]) for s in sessions]


def _trajectories(ax: object, a: dict, pieces: list[slice], ellipses: bool = True) -> None:
    for i, sl in enumerate(pieces):
        first = i == 0
        ax.plot(
            *a["P_odometry"][sl, :2].T,
            "--",
            color="tab:cyan",
            lw=1.4,
            label="odometry only" if first else None,
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
        ax.plot(
            *a["P_estimate"][sl, :2].T,
            "-",
            color="tab:blue",
            lw=1.4,
            label="GP-SLAM" if first else None,
        )
    if ellipses and a.get("P_cov") is not None and a["P_cov"].shape[1] == 2:
        _ellipses(ax, a["P_estimate"], a["P_cov"])


def sessions_figure(result: Drawable, path: Path) -> None:
    """One panel per session of a multi-session solve (casmag.multisession): odometry-only,
    estimate and truth, with the session's errors in its title."""
    import math

    sessions = result.info["sessions"]
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
        _trajectories(ax, a, [slice(None)], ellipses=True)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        title = s["name"]
        if s.get("rmse_after") is not None:
            title += f": RMSE {s['rmse_before']:.3f} -> {s['rmse_after']:.3f} m"
        ax.set_title(title, fontsize=9)
        if i == 0:
            ax.legend(loc="best", fontsize=7)
    fig.suptitle(result.info.get("name", ""), fontsize=10)
    fig.tight_layout()
    _save(fig, path)


def _ellipses(ax: object, P: object, cov: object, count: int = 40, scale: float = 3.0) -> None:
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
                label=f"{scale:g}-sigma (Laplace)" if i == 0 else None,
            )
        )


def cost_figure(result: Drawable, path: Path) -> None:
    """Objective and constraint violation per IPOPT iteration (the paper's Figure 7)."""
    fig = Figure(figsize=(6.0, 3.6))
    ax = fig.add_subplot()
    cost = result.cost_per_iteration
    offset = min(cost)
    ax.semilogy(range(len(cost)), [c - offset + 1e-12 for c in cost], "o-", ms=3)
    ax.set_xlabel("IPOPT iteration")
    ax.set_ylabel("cost - final cost")
    ax.grid(alpha=0.3, which="both")
    ax.set_title(
        f"{result.info.get('name', '')}: {result.status}, {result.iterations} iterations",
        fontsize=9,
    )
    fig.tight_layout()
    _save(fig, path)


def map_figure(result: Drawable, path: Path) -> None:
    """Estimated field magnitude over the area (GP posterior mean or reduced-rank map) with
    the estimated path."""
    a = result.arrays
    fig = Figure(figsize=(6.4, 5.4))
    ax = fig.add_subplot()
    magnitude = (a["map_field"] ** 2).sum(axis=-1) ** 0.5
    mesh = ax.pcolormesh(a["map_x"], a["map_y"], magnitude, shading="auto", cmap="viridis")
    fig.colorbar(mesh, ax=ax, label="|m| (field units)")
    ax.plot(*a["P_estimate"][:, :2].T, "-", color="white", lw=1.0, label="GP-SLAM path")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"{result.info.get('name', '')}: estimated field magnitude", fontsize=9)
    _save(fig, path)
