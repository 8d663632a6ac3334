"""The magnetometer's lag behind the motion, estimated without truth.

A magnetometer and an odometry source on separate clocks, or a filter inside the sensor,
put the field sample of time t at the position of an earlier time. Over a few seconds the
dead reckoning is accurate to a small fraction of a lengthscale, so the lag can be read
from the recording itself: the shift of the magnetometer against the dead-reckoned path
that maximises the GP marginal likelihood of the field (squared exponential plus a
constant field, hyperparameters from casmag.gp.hyper) summed over windows of
:data:`WINDOW_SECONDS`, searched over +-:data:`MAX_LAG_SECONDS` in steps of a fifth of a
sample (positions interpolated linearly in time).

Measured on the robot sequences (``../shared/data/magnetic-data``, 10 Hz, 0.5 m of drift,
recorded timing, ``casmag convert --no-align``): 0.26, 0.26 and 0.28 s on sequences 1, 3
and 5 against 0.26, 0.24 and 0.28 s found with the motion-capture truth
(casmag.data.realdata.clock_offset), log-likelihood gains 1,231, 692 and 417 over no shift (an
exploratory search with other windows: 0.26-0.28 s on all five, 0.18-0.28 s with truth).
A lag left in the data limits the estimate to about speed x lag (0.06-0.07 m here):
sequences 3 and 5 (0.5 m of drift, seeds 3 and 5, sigma_m 2 uT) reached 0.056 m on
sequence 5 with the lag in the data and 0.013 / 0.019 m (sequences 5 / 3) with 0.28 /
0.24 s removed. With the windowed marginal likelihood's sigma_m (0.4-0.8 uT) removing
it alone changed little (0.069 -> 0.080 m, 0.059 -> 0.041 m): that noise level also has
to come from where the path returns (casmag.solver.recslam.refit_sigma_m).

``casmag slam`` records the estimate in ``info["magnetometer_lag"]`` and warns when it is a
sample or more; ``--mag-lag SECONDS`` (``casmag.slam(..., mag_lag=...)``) removes a given
lag, ``--mag-lag auto`` the estimated one when it is significant (every recording; see
casmag.solver.recslam.refit_sigma_m for why it is not the default of translational
recordings; IMU recordings estimate it on the path solved instead of a dead reckoning,
casmag.solver.imurec.imu_lag; planar and pose recordings, whose magnetometer is in the body
frame, with its attitude lagging or its row's own: casmag.solver.oriented.oriented_lag).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from threadpoolctl import threadpool_limits

from casmag.data.realdata import log_marginal
from casmag.gp.hyper import estimate_hyperparameters

if TYPE_CHECKING:
    from casmag.data.recording import Recording

#: Window of the likelihood sum [s]: short against the dead reckoning's drift.
WINDOW_SECONDS = 10.0
#: Largest lag searched [s], either way.
MAX_LAG_SECONDS = 0.5
#: A lag whose log-likelihood gain over none is below this is not reported. Measured: the
#: robot sequences' lags 315-1,230; the handheld ``square`` recording (planar, heading
#: 42 deg RMS off in its dead reckoning) 22.7 for a lag of -0.36 s that its truth does not
#: show (-0.08 s, gain 12.9 on the true path), ``library`` 29.5 at 0.04 s.
MIN_GAIN = 100.0
#: Samples per window and most windows of the hyperparameters when none are given.
HYPER_WINDOW = (30, 16)


@dataclass(frozen=True)
class LagEstimate:
    """lag_seconds: the magnetometer's lag [s] (positive: its sample of time t is the field
    at the position of time t - lag); gain: log-likelihood gain over no lag; significant:
    gain >= MIN_GAIN, |lag| at least one sample interval and inside the range searched (a
    maximum at the end of the range is no estimate: the likelihood still rises there, as
    it does when the path drifts within a window); windows: windows summed.
    attitude_lags: for a magnetometer in the body frame (planar and pose recordings), whether
    its attitude lags with its position (a sensor late on its own clock reads the field in
    the frame of the earlier time) or the row's attitude is its own (the position lags
    alone: a late position source, or a field turned into the body frame at its row); None
    for a field in the world frame."""

    lag_seconds: float
    gain: float
    significant: bool
    windows: int
    window_seconds: float
    sample_interval: float
    attitude_lags: bool | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def estimate_lag(
    t: np.ndarray,
    P: np.ndarray,
    Y: np.ndarray,
    hyper: Any = None,
    frame: Callable[[np.ndarray], np.ndarray] | None = None,
) -> LagEstimate | None:
    """The magnetometer's lag behind positions P (N, d) (the dead reckoning), field Y (N, 3)
    in the world frame, times t (N,); None when the recording is shorter than two windows.
    hyper: sigma_f, lengthscale, sigma_m of the field (default: estimated on short windows,
    :data:`HYPER_WINDOW`). ``frame``: Y is in the body frame, and ``frame(rows)`` gives the
    body-to-world rotations (N, 3, 3) at fractional row numbers (the dead-reckoned attitude
    interpolated), so that each shift turns the field with the attitude of the time it
    moves the position to (a magnetometer that lags reads the field in the frame of the
    earlier time; turned with the attitude of its own row instead, a platform turning at
    omega rad/s puts an error of omega x lag into the heading)."""
    t, P, Y = np.asarray(t, float), np.asarray(P, float), np.asarray(Y, float)
    n = t.size
    rows = np.arange(n, dtype=float)

    def world(shift: float) -> np.ndarray:
        return Y if frame is None else np.einsum("nij,nj->ni", frame(rows + shift), Y)

    dt = float(np.median(np.diff(t)))
    W = max(10, round(WINDOW_SECONDS / dt))
    reach = round(MAX_LAG_SECONDS / dt)
    starts = list(range(reach, n - W - reach, W))
    if len(starts) < 2:
        return None
    Y0 = world(0.0)
    if hyper is None:  # short windows: the search needs the scales, not their last digit
        window, most = HYPER_WINDOW
        hyper = estimate_hyperparameters(P, Y0, "se", window=window, max_windows=most)
    sigma_lin = float(np.abs(Y0.mean(axis=0)).max() + Y0.std()) or 1.0
    shifts = np.round(np.arange(-reach, reach + 1e-9, 0.2), 6)  # samples, of the positions
    values = np.zeros(shifts.size)
    with threadpool_limits(1):  # small factorisations: threads only contend
        for j, sh in enumerate(shifts):
            Ps = np.column_stack([np.interp(rows + sh, rows, P[:, q]) for q in range(P.shape[1])])
            Ys = world(sh)
            h = (hyper.sigma_f, hyper.lengthscale, hyper.sigma_m, sigma_lin)
            values[j] = sum(log_marginal(Ps[s : s + W], Ys[s : s + W], *h) for s in starts)
    best = int(np.argmax(values))
    lag = float(-shifts[best] * dt)
    gain = float(values[best] - values[int(np.argmin(np.abs(shifts)))])
    return LagEstimate(
        lag_seconds=lag,
        gain=gain,
        significant=bool(
            gain >= MIN_GAIN
            and abs(lag) >= dt * (1.0 - 1e-9)
            and 0 < best < shifts.size - 1  # not at the end of the range searched
        ),
        windows=len(starts),
        window_seconds=W * dt,
        sample_interval=dt,
    )


def shift_magnetometer(t: np.ndarray, Y: np.ndarray, lag: float) -> np.ndarray:
    """The magnetometer with a lag of ``lag`` seconds removed: row k becomes the field
    recorded at t_k + lag (linear interpolation; the end rows hold the last value)."""
    t = np.asarray(t, float)
    return np.column_stack([np.interp(t + lag, t, Y[:, q]) for q in range(Y.shape[1])])


def with_lag_removed(rec: Recording, mag_lag: float | None, how: str = "as asked") -> Recording:
    """The recording with a magnetometer lag of ``mag_lag`` seconds removed (unchanged for
    None or 0), the change noted as a warning."""
    if not mag_lag:
        return rec
    note = {
        "check": "magnetometer_lag",
        "column": "mx,my,mz",
        "reason": f"shifted by {mag_lag:g} s (a lag removed, {how})",
    }
    return dataclasses.replace(
        rec, Y=shift_magnetometer(rec.t, rec.Y, mag_lag), notes=(*rec.notes, note)
    )


def lag_warning(est: LagEstimate | None, path: str = "the dead reckoning") -> list[dict[str, str]]:
    """A casmag.data.checks warning when the estimated lag is significant (``path``: what
    the lag was estimated against)."""
    if est is None or not est.significant:
        return []
    return [
        {
            "check": "magnetometer_lag",
            "column": "mx,my,mz",
            "reason": (
                f"the magnetometer appears to lag the motion by {est.lag_seconds:.2f} s "
                f"(log-likelihood gain {est.gain:.0f} on {est.windows} windows of "
                f"{est.window_seconds:.0f} s of {path}); --mag-lag "
                f"{est.lag_seconds:.2f} removes it"
            ),
        }
    ]
