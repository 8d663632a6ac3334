"""Plausibility checks on a recording before it is solved: units and columns that read
without error but mean something else (time in milliseconds, increments in centimetres or
cumulative positions in the increment columns, the field in tesla or gauss), and
hyperparameters that cannot map the path walked. Each finding is a warning (a dict with
``check``, ``column`` and ``reason``): printed on stderr by the command line and kept under
``warnings`` in result.json. None refuses the data: a vehicle may be fast, a field may be
weak.

Thresholds (and why):

- ``MAX_SAMPLE_INTERVAL``: 2 s. A magnetometer logged for mapping samples at 1 Hz or
  faster (the shared recordings: 10-100 Hz); a median interval above 2 s is milliseconds
  (or nanoseconds) read as seconds far more often than a 0.5 Hz log.
- ``MAX_SPEED``: 5 m/s for translational and planar odometry, the top of indoor walking and
  robot speeds (the shared recordings: 0.1-1.5 m/s); increments in centimetres give 100
  times the speed, cumulative positions in the increment columns the path's extent per
  sample.
- ``MAX_TURN_RATE``: 10 rad/s (570 deg/s) for the 95th percentile of the planar heading
  rate |dyaw| / dt. The shared recordings' 95th percentiles: 0.44-1.69 rad/s for the robot
  (invensense 1-5), 1.36 and 1.95 rad/s for the handheld iPad (ARKit library, square);
  a heading increment in degrees read as radians multiplies it by 57.
- Field magnitude (median |m|): below 0.01 looks like tesla (Earth's field is 25-65 uT,
  2.5-6.5e-5 T), above 10,000 like nanotesla. Between them the unit cannot be told from
  the magnitude (gauss, microtesla and the simulations' Earth = 1 all occur), and casmag
  reads any unit consistently: what matters is that sigma_m is in the same unit, which
  the next check tests.
- sigma_m larger than the field's own variation over the recording (the median over the
  components of its standard deviation): the noise would explain the whole signal, which
  happens when sigma_m is given in another unit than mx, my, mz (microtesla against
  gauss: 100 times).
- Lengthscale: longer than the dead-reckoned path's extent, the map is one smooth field
  and cannot tell places apart; shorter than the median step, no two samples are
  correlated and the map cannot connect them.

One check refuses (:func:`refuse_simulation_truths`): a problem solved on data that were not
simulated from it (``casmag.solve(problem, data=...)`` with a recording) whose noise or GP
hyperparameters are null. Null means "the simulation's true value", and a recording has no
simulation: those values (sigma_f 0.1, lengthscale 0.1 m, sigma_m 0.002 by default) are
another field's, in another unit.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from casmag.errors import ProblemError

MAX_SAMPLE_INTERVAL = 2.0  # s
MAX_SPEED = 5.0  # m/s
MAX_TURN_RATE = 10.0  # rad/s, 95th percentile of |dyaw| / dt
TESLA_BELOW = 0.01
NANOTESLA_ABOVE = 1.0e4


def _warning(check: str, column: str, reason: str) -> dict[str, str]:
    return {"check": check, "column": column, "reason": reason}


def recording_warnings(
    t: np.ndarray, increments: np.ndarray, Y: np.ndarray, motion: str
) -> list[dict[str, str]]:
    """Findings on the time axis, the motion increments (translational ``dx, dy[, dz]``,
    planar ``dfwd, dleft, dyaw``, pose ``dpx, dpy, dpz``; IMU increments and rotation
    increments are not checked here) and the
    magnetometer of one recording."""
    out: list[dict[str, str]] = []
    t = np.asarray(t, dtype=float)
    dt = float(np.median(np.diff(t))) if t.size > 1 else float("nan")
    if dt > MAX_SAMPLE_INTERVAL:
        out.append(
            _warning(
                "time_unit",
                "t",
                f"median sample interval {dt:.4g} s (over {MAX_SAMPLE_INTERVAL:g} s): is t in "
                "milliseconds or nanoseconds? casmag's time unit is the second",
            )
        )
    if motion in ("translation", "planar", "pose") and increments.size and t.size > 1:
        width = {"translation": None, "planar": 2, "pose": 3}[motion]
        steps = np.linalg.norm(increments[:, :width], axis=1)
        duration = float(t[-1] - t[0])
        speed = float(steps.sum()) / duration if duration > 0 else float("inf")
        names = {"translation": "dx, dy", "planar": "dfwd, dleft", "pose": "dpx, dpy, dpz"}[motion]
        if speed > MAX_SPEED and dt <= MAX_SAMPLE_INTERVAL:
            out.append(
                _warning(
                    "speed",
                    names,
                    f"mean speed {speed:.3g} m/s (over {MAX_SPEED:g} m/s for walking or an "
                    "indoor robot): are the increments in centimetres or millimetres, or "
                    "cumulative positions rather than steps since the previous row, or is t "
                    "in minutes? casmag reads metres per step and seconds",
                )
            )
    if motion == "planar" and increments.size and t.size > 1 and dt <= MAX_SAMPLE_INTERVAL:
        steps_dt = np.diff(t)
        rate = float(np.percentile(np.abs(increments[:, 2]) / steps_dt, 95))
        if rate > MAX_TURN_RATE:
            out.append(
                _warning(
                    "turn_rate",
                    "dyaw",
                    f"95th percentile of the heading rate {rate:.3g} rad/s (over "
                    f"{MAX_TURN_RATE:g} rad/s, {np.degrees(MAX_TURN_RATE):.0f} deg/s): is dyaw "
                    "in degrees? casmag reads radians per step",
                )
            )
    magnitude = float(np.median(np.linalg.norm(np.asarray(Y, dtype=float), axis=1)))
    unit = None
    if magnitude < TESLA_BELOW:
        unit = "tesla (x 1e6 for microtesla)"
    elif magnitude > NANOTESLA_ABOVE:
        unit = "nanotesla (/ 1000 for microtesla)"
    if unit is not None and magnitude > 0:
        out.append(
            _warning(
                "field_unit",
                "mx, my, mz",
                f"median field magnitude {magnitude:.3g} looks like {unit}; Earth's field is "
                "25-65 microtesla",
            )
        )
    return out


def model_warnings(
    P: np.ndarray, Y: np.ndarray, lengthscale: float, sigma_m: float
) -> list[dict[str, str]]:
    """Findings on the lengthscale [m] against the dead-reckoned path P (N, d), and on the
    magnetometer noise sigma_m against the field's variation in Y (N, 3)."""
    P = np.asarray(P, dtype=float)
    if P.shape[0] < 2:
        return []
    Y = np.asarray(Y, dtype=float)
    spread = float(np.median(np.std(Y, axis=0)))
    out = []
    # A constant magnetometer (spread at rounding level) is reported by the field check.
    if spread > 1e-9 * float(np.abs(Y).max()) and sigma_m > spread:
        out.append(
            _warning(
                "sigma_m",
                "model.magnetometer.sigma_m",
                f"{sigma_m:.3g} is larger than the field's own variation over the recording "
                f"({spread:.3g}, median standard deviation of mx, my, mz): is it in another "
                "unit than the recording's field (microtesla against gauss: 100 times)?",
            )
        )
    return out + _lengthscale(P, lengthscale)


def lengthscale_warnings(P: np.ndarray, lengthscale: float) -> list[dict[str, str]]:
    """Findings on a map's lengthscale [m] against a path P (N, d): longer than its extent,
    or shorter than its median step."""
    return _lengthscale(np.asarray(P, dtype=float), float(lengthscale))


def _lengthscale(P: np.ndarray, lengthscale: float) -> list[dict[str, str]]:
    extent = float(np.ptp(P, axis=0).max())
    step = float(np.median(np.linalg.norm(np.diff(P, axis=0), axis=1)))
    if lengthscale > extent:
        return [
            _warning(
                "lengthscale",
                "model.gp.lengthscale",
                f"{lengthscale:.3g} m is longer than the path's extent ({extent:.3g} m): the "
                "map is one smooth field and cannot tell places apart",
            )
        ]
    if lengthscale < step:
        return [
            _warning(
                "lengthscale",
                "model.gp.lengthscale",
                f"{lengthscale:.3g} m is shorter than the median step ({step:.3g} m): no two "
                "samples are correlated, so the map cannot connect them",
            )
        ]
    return []


def warning_lines(source: Any, warnings: list[dict[str, str]]) -> list[str]:
    """One line per warning, naming the source, the column or key and the reason."""
    return [f"casmag: warning: {source}: {w['column']}: {w['reason']}" for w in warnings]


def announce(
    source: Any, warnings: list[dict[str, str]], on_warning: Callable[[str], None] | None
) -> None:
    """Hand each warning's line (:func:`warning_lines`) to ``on_warning``, when given."""
    if on_warning is not None:
        for line in warning_lines(source, warnings):
            on_warning(line)


#: Model settings whose null takes the simulation's true value: (setting, hyperparameter
#: name in ``model.estimate``, the simulation key it takes).
SIMULATION_TRUTHS = (
    ("model.gp.sigma_f", "sigma_f", "simulation.field.sigma_f"),
    ("model.gp.lengthscale", "lengthscale", "simulation.field.lengthscale"),
    ("model.magnetometer.sigma_m", "sigma_m", "simulation.magnetometer.noise"),
    ("model.odometry.sigma", None, "simulation.odometry.noise"),
)


def refuse_simulation_truths(problem: Any, data: Any) -> None:
    """ProblemError naming the first setting left null (and not estimated) when ``data``
    were not simulated (no simulated field, ``M_true``): its null would take the value of
    a simulation that did not produce the data."""
    if getattr(data, "M_true", None) is not None:
        return
    model = problem.spec.model
    values = {
        "model.gp.sigma_f": model.gp.sigma_f,
        "model.gp.lengthscale": model.gp.lengthscale,
        "model.magnetometer.sigma_m": model.magnetometer.sigma_m,
        "model.odometry.sigma": model.odometry.sigma,
    }
    for key, name, truth in SIMULATION_TRUTHS:
        if values[key] is None and name not in model.estimate:
            raise ProblemError(
                problem.source,
                key,
                f"null takes the simulation's value ({truth}), but the data given were not "
                "simulated from this problem: set it in the data's unit"
                + (
                    ", or list it under model.estimate"
                    if name in ("sigma_f", "lengthscale")
                    else ""
                )
                + " (casmag.slam chooses every value from a recording)",
            )
