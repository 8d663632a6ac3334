"""IMU recordings (``dqw,dqx,dqy,dqz,dvx,dvy,dvz`` columns, casmag.data.recording) as the
IMU model's data (:class:`casmag.data.imusim.ImuData`): :func:`imu_data`.

The model's first keyframe is at rest (velocity zero) with a levelled attitude, as in the
simulations: the recording must lie still for its first ``rest_seconds``. Those samples
give the initial roll and pitch (the mean specific force, casmag.data.imusim.levelled_attitude)
and the sensors' white noise (:func:`rest_noise`): at rest the gyroscope measures its bias
plus noise, the accelerometer gravity plus its bias plus noise, and the magnetometer one
field plus noise, so each sample's spread about the mean is the sensor's own noise. The
heading of the first keyframe defines the map frame: the true heading when the recording
has a true orientation and the estimate starts at the truth (``anchor`` ``truth``), else 0.

The IMU model takes one sample interval T (the velocity update adds gravity times T):
casmag.data.recording resamples a recording whose intervals are not uniform onto a uniform
grid when it reads it, so the intervals here are within :data:`PERIOD_TOLERANCE` of the
median (:func:`sample_period` refuses others, naming the row).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from casmag import strapdown as sd
from casmag.data.imusim import ImuData, Truth, levelled_attitude
from casmag.data.recording import IMU_PERIOD_TOLERANCE, Recording
from casmag.errors import DataError, one_line

#: Largest relative difference of a sample interval from the median interval
#: (casmag.data.recording.IMU_PERIOD_TOLERANCE, where it is explained).
PERIOD_TOLERANCE = IMU_PERIOD_TOLERANCE
#: Fewest samples at rest for the levelling and the noise estimate.
MIN_REST_SAMPLES = 10
#: A start that does not look at rest (warning): the mean specific force further than this
#: fraction from gravity, or the gyroscope turning more than REST_TURN_DEG over the rest.
REST_FORCE_TOLERANCE = 0.03
REST_TURN_DEG = 2.0


@dataclass(frozen=True)
class RestNoise:
    """The sensors' white noise estimated at rest (:func:`rest_noise`): gyroscope density
    [deg/s/sqrt(Hz)], accelerometer density [m/s^2/sqrt(Hz)], magnetometer per sample
    [field units]; ``samples`` used, mean specific force [m/s^2] and the angle turned over
    them [deg]."""

    gyro_noise_density: float
    acc_noise_density: float
    sigma_m: float
    samples: int
    specific_force: float
    turned_deg: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def sample_period(rec: Recording) -> float:
    """The recording's sample interval [s]: the median, every interval within
    :data:`PERIOD_TOLERANCE` of it (DataError naming the row otherwise)."""
    dt = np.diff(rec.t)
    T = float(np.median(dt))
    off = np.abs(dt - T) > PERIOD_TOLERANCE * T
    if T <= 0 or off.any():
        i = int(np.argmax(off)) if off.any() else 0
        raise DataError(
            one_line(
                f"{rec.path}: row {i + 3}: t is {dt[i]:.6g} s after the previous row against "
                f"a median interval of {T:.6g} s; the IMU model needs uniform sample times "
                f"(within {PERIOD_TOLERANCE:.0%})"
            )
        )
    return T


def rest_samples(rec: Recording, T: float, rest_seconds: float) -> int:
    """How many IMU intervals the first ``rest_seconds`` hold (DataError when fewer than
    :data:`MIN_REST_SAMPLES`, naming ``model.initial.rest_seconds``)."""
    n = min(round(rest_seconds / T), rec.increments.shape[0])
    if n < MIN_REST_SAMPLES:
        raise DataError(
            one_line(
                f"{rec.path}: model.initial.rest_seconds: {rest_seconds:g} s holds {n} "
                f"samples at {1 / T:.4g} Hz; the levelling and the noise estimate need at "
                f"least {MIN_REST_SAMPLES}"
            )
        )
    return n


def rest_noise(rec: Recording, T: float, n: int) -> RestNoise:
    """The white noise of the gyroscope, accelerometer and magnetometer from the first n
    intervals (module docstring): each axis's sample standard deviation about its mean,
    the root mean square over the axes; a density is the per-sample deviation times
    sqrt(T) (:func:`_density`). When the recording was resampled, from its rows as
    recorded over the same time (``rec.imu_samples``, each over its own interval: resampled
    increments average neighbouring samples, which hides part of the noise), and the
    magnetometer from its own samples (``rec.mag_samples``). The magnetometer's is at least
    its rounding noise (:func:`quantisation_floor`), NaN when the rest holds fewer than two
    of its samples."""
    dq, dv = rec.increments[:n, :4], rec.increments[:n, 4:]
    turned = np.degrees(np.linalg.norm(sd.quat_log(sd.compose_increments(dq, dv, T, n)[0][0])))
    force_mean = float(np.linalg.norm((dv / T).mean(axis=0)))
    dt = np.full(n, T)
    if rec.imu_samples is not None:  # resampled: the rows as recorded, each its interval
        tr, inc = rec.imu_samples
        rest = tr[1:] <= rec.t[n] + 1e-9 * T
        dt, dq, dv = np.diff(tr)[rest], inc[rest, :4], inc[rest, 4:]
    spread = lambda x: float(np.sqrt(np.mean(np.var(x, axis=0, ddof=1))))  # noqa: E731
    Y = rec.Y
    at_rest = Y[: n + 1]
    if rec.mag_samples is not None:  # its own samples, not the interpolated rows
        tm, Y = rec.mag_samples
        at_rest = Y[(tm >= rec.t[0]) & (tm <= rec.t[n])]
    sigma_m = np.nan  # too few samples at rest (one magnetometer sample or none)
    if at_rest.shape[0] >= 2:
        sigma_m = max(spread(at_rest), quantisation_floor(Y))
    return RestNoise(
        gyro_noise_density=float(np.degrees(_density(sd.quat_log(dq), dt))),
        acc_noise_density=_density(dv, dt),
        sigma_m=sigma_m,
        samples=int(n),
        specific_force=force_mean,
        turned_deg=float(turned),
    )


def _density(x: np.ndarray, dt: np.ndarray) -> float:
    """The noise density of increments x (n, 3) integrated over the intervals dt (n,): a
    white rate r with density s integrates to x = r dt with standard deviation s sqrt(dt),
    so (x / dt - mean rate) sqrt(dt) has standard deviation s; the root mean square over
    the axes of each one's sample standard deviation."""
    w = np.sqrt(dt)[:, None]
    deviation = (x / dt[:, None] - x.sum(axis=0) / dt.sum()) * w
    return float(np.sqrt(np.mean(np.var(deviation, axis=0, ddof=1))))


def quantisation_floor(Y: np.ndarray) -> float:
    """The magnetometer's rounding noise, step / sqrt(12) with the step the smallest gap
    between distinct values of a component over the whole recording (the largest over the
    components): a quantised sensor at rest can repeat one value, a spread of zero that is
    not its noise."""
    steps = []
    for column in np.asarray(Y, dtype=float).T:
        gaps = np.diff(np.unique(column))
        steps.append(float(gaps.min()) if gaps.size else 0.0)
    return max(steps) / np.sqrt(12.0)


def rest_warnings(noise: RestNoise, rest_seconds: float) -> list[dict[str, str]]:
    """A warning when the first ``rest_seconds`` do not look at rest (the levelling and
    the noise estimate assume it): the mean specific force off gravity by more than
    :data:`REST_FORCE_TOLERANCE`, or more than :data:`REST_TURN_DEG` turned."""
    off = abs(noise.specific_force / sd.GRAVITY - 1.0)
    if off <= REST_FORCE_TOLERANCE and noise.turned_deg <= REST_TURN_DEG:
        return []
    return [
        {
            "check": "not_at_rest",
            "column": "model.initial.rest_seconds",
            "reason": (
                f"the first {rest_seconds:g} s do not look at rest: mean specific force "
                f"{noise.specific_force:.3g} m/s^2 against {sd.GRAVITY:g}, "
                f"{noise.turned_deg:.3g} deg turned; the initial attitude and the noise "
                "estimated there assume the device lies still"
            ),
        }
    ]


def imu_data(rec: Recording, rest_seconds: float, anchor: str = "truth") -> tuple[ImuData, int]:
    """The IMU model's data of an IMU recording (module docstring) and the number of rest
    intervals at its start. Truth (positions ``x_true,y_true,z_true`` and the orientation
    ``qw_true..qz_true``, either or both) is kept for evaluation; true positions must be
    3-D (DataError). With ``anchor`` ``origin`` the estimate is in the frame of the first
    keyframe (position 0, heading 0), so the truth is not kept."""
    if rec.motion != "imu":
        raise DataError(f"{rec.path}: motion input is {rec.motion!r}, expected 'imu'")
    if rec.P_true is not None and rec.P_true.shape[1] != 3:
        raise DataError(
            f"{rec.path}: z_true: an IMU recording's true positions are 3-D (x_true, y_true, "
            "z_true)"
        )
    T = sample_period(rec)
    n = rest_samples(rec, T, rest_seconds)
    dq, dv = rec.increments[:, :4], rec.increments[:, 4:]
    at_truth = anchor == "truth"
    yaw = 0.0
    if at_truth and rec.q_true is not None:
        yaw = float(sd.euler_from_quat(rec.q_true[0])[2])
    p0 = rec.P_true[0].copy() if at_truth and rec.P_true is not None else np.zeros(3)
    truth = None
    if at_truth and (rec.P_true is not None or rec.q_true is not None):
        truth = Truth(t=rec.t, P=rec.P_true, V=None, Q=rec.q_true)
    data = ImuData(
        T=T, dq=dq, dv=dv, Y=rec.Y, p0=p0, v0=np.zeros(3),
        q0=levelled_attitude(dv, T, n, yaw), truth=truth, mag_share=rec.mag_share,
    )  # fmt: skip
    return data, n
