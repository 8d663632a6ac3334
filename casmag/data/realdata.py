"""Real magnetometer sequences with motion-capture truth, turned into casmag recordings.

A sequence is three CSV files sharing a prefix (``DIR/N-time.csv``, ``DIR/N-loc.csv``,
``DIR/N-mag.csv``: time [s], planar position [m] from motion capture, magnetometer [uT] in
the world frame; the layout of ``../shared/data/magnetic-data/invensense``). The protocol
(:func:`convert`, ``casmag convert``) is:

1. **Clock alignment.** The magnetometer and the motion capture ran on separate clocks. The
   magnetometer is shifted by the whole number of samples that maximises the GP marginal
   likelihood of the field given the true positions (:func:`clock_offset`; squared
   exponential kernel plus a constant field, hyperparameters from :mod:`casmag.gp.hyper`). On
   sequences 1-5 the magnetometer lags by 0.12-0.32 s; at 0.5 m/s that is 6-16 cm, half a
   lengthscale, and unaligned the true trajectory is *less* likely than a drifted one.
   The offset uses the truth, as a calibration of the data set does; the SLAM problem
   never sees the truth.
2. **Resampling** to ``rate`` Hz by keeping every k-th sample (the magnetometer as recorded,
   no smoothing).
3. **Odometry**, seeded:
   - ``translational``: the true increments plus a constant bias and white noise (the
     paper's model). The bias has a uniformly random direction and the magnitude that
     drifts ``drift`` metres over the sequence; the noise is ``noise`` times the median step.
   - ``planar``: body-frame increments (dfwd, dleft, dyaw) from the true positions and the
     heading of motion, with white noise and a constant heading-rate bias whose size is
     found (bisection) so that the final dead-reckoning error is ``drift`` metres. The
     magnetometer is rotated into the heading frame.
   - ``pose``: 6-DoF increments (dpx, dpy, dpz, dq; :mod:`casmag.model.pose`) of the true
     3-D pose. Without a recorded orientation the pose is z = 0, roll = pitch = 0 and yaw
     the heading of motion. White noise (the displacement noise on each of dpx, dpy, dpz;
     ``heading_noise`` [rad] as a rotation vector, dq exp(noise)) and a constant
     rotation-rate bias about the body z axis (dq exp([0, 0, b])), sized by bisection as
     for ``planar`` so that the final 3-D dead-reckoning error is ``drift`` metres. The
     magnetometer is rotated into the body frame, R(q)^T times the world field.
4. **Field** (``field``): ``recorded`` keeps the magnetometer; ``constant`` replaces it by its
   mean plus white noise of ``constant_noise`` uT, a homogeneous field that carries no
   position information (the "never worse" check).

A handheld recording with the device's pose (:func:`load_arkit`: a MATLAB file with ``t``,
``dPos``, ``quat`` and ``m``, the layout of ``../shared/data/arkit``) becomes a sequence
with the device's heading: positions are the cumulative increments (x, y of a z-up world),
the magnetometer is rotated into the world frame with the recorded orientation (sensor
axes turned by :data:`ARKIT_SENSOR_TO_BODY_DEG` about z first), and planar odometry uses
the device's heading instead of the heading of motion, so that dfwd, dleft are along the
device's axes and the planar magnetometer is R(heading)^T times the world field. Pose
odometry uses the recorded orientation and heights (z of the cumulative increments): its
body-frame magnetometer R(q)^T times the world field is the recorded one turned into the
pose's axes. Its protocol (:func:`arkit_protocol`) is the publishing paper's: white noise
0.01 m per step on each displacement component and 0.01 rad on each heading increment (on
each axis of the rotation increment for pose), a heading-rate bias of 0.005 rad/s (sign
drawn from the seed; about the body z axis for pose), no clock shift (one device clock).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import scipy.io
from scipy.linalg import cho_factor, cho_solve
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation, Slerp
from threadpoolctl import threadpool_limits

from casmag import strapdown as sd
from casmag.errors import DataError
from casmag.gp.hyper import estimate_hyperparameters

SOURCE_RATE_TOLERANCE = 1e-3  # relative spread of the sample interval accepted as uniform

#: Rotation about z [deg] from the iPad magnetometer's axes to the axes of ARKit's pose. Of
#: the eight candidates (0, +-90, 180 deg, the pose's rotation or its transpose), +90 with
#: the rotation makes the world-frame field agree with itself where the path crosses
#: itself (:func:`crossing_disagreement`, pairs within 0.15 m and 50 samples apart): RMS
#: difference 1.77 uT on ``square`` (field RMS about its mean 8.3 uT; the next candidate
#: 4.98) and 2.15 uT on ``library`` (next 16.5 uT).
ARKIT_SENSOR_TO_BODY_DEG = 90.0

#: Spacing [s] of the coarse grid of the clock search (:func:`clock_offset`), refined sample
#: by sample around its best shift. The likelihood's peak is one smooth hump some 0.3 s wide
#: at half its gain (sequences 1 and 4 evaluated at every shift; sequence 1 has a second,
#: 720 lower, at +0.22 s). On sequences 1-5 (50 Hz) the search finds the same shifts and
#: gains as every shift evaluated, with 19 evaluations instead of 51 (sequence 1: 27 -> 14 s
#: with the hyperparameters' estimate).
CLOCK_COARSE_SECONDS = 0.1


@dataclass(frozen=True)
class Sequence:
    """A raw sequence: t (N,) [s], loc (N, 2) [m], mag (N, 3) [uT]."""

    name: str
    t: np.ndarray
    loc: np.ndarray
    mag: np.ndarray
    # Jittered time stamps, brought to a uniform grid on reading: the recorded intervals'
    # spread (ptp / median) and row count; None when they were uniform.
    resampled: dict[str, float] | None = None
    # (N,) the device's heading [rad] when the source records its orientation (mag is then
    # in the world frame); None: planar odometry takes the heading of motion.
    heading: np.ndarray | None = None
    # The 3-D pose when the source records its orientation: quat (N, 4) body-to-world unit
    # quaternions (w first), z (N,) heights [m]; None: pose odometry takes z = 0, level
    # and the heading of motion.
    quat: np.ndarray | None = None
    z: np.ndarray | None = None

    @property
    def rate(self) -> float:
        return 1.0 / float(np.median(np.diff(self.t)))


def _load_csv(path: Path, columns: int) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    try:
        A = np.loadtxt(path, delimiter=",", ndmin=2)
    except ValueError as exc:
        raise DataError(f"{path}: not a numeric CSV file ({exc})") from None
    if A.shape[1] != columns:
        raise DataError(f"{path}: has {A.shape[1]} columns, expected {columns}")
    if not np.all(np.isfinite(A)):
        row = int(np.argmax(~np.all(np.isfinite(A), axis=1)))
        raise DataError(f"{path}: row {row + 1} has a non-finite value")
    return A


def load_sequence(prefix: str | Path) -> Sequence:
    """Read ``PREFIX-time.csv``, ``PREFIX-loc.csv`` and ``PREFIX-mag.csv`` (e.g. prefix
    ``.../invensense/1``). Raises DataError naming the file and the reason."""
    prefix = Path(prefix)
    files = {k: prefix.with_name(f"{prefix.name}-{k}.csv") for k in ("time", "loc", "mag")}
    t = _load_csv(files["time"], 1)[:, 0]
    loc = _load_csv(files["loc"], 2)
    mag = _load_csv(files["mag"], 3)
    for k, A in (("loc", loc), ("mag", mag)):
        if A.shape[0] != t.shape[0]:
            raise DataError(f"{files[k]}: has {A.shape[0]} rows, the time file {t.shape[0]}")
    dt = np.diff(t)
    if t.shape[0] < 10 or not np.all(dt > 0):
        raise DataError(f"{files['time']}: times must increase strictly (at least 10 rows)")
    if np.ptp(dt) > SOURCE_RATE_TOLERANCE * np.median(dt) * 10:
        return uniform(Sequence(prefix.name, t, loc, mag))
    return Sequence(prefix.name, t, loc, mag)


def _rotz(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def load_arkit(path: str | Path) -> Sequence:
    """Read a handheld recording with the device's pose (a MATLAB v5 file with ``t`` (N,),
    ``dPos`` (N-1, 3) position increments [m] in a z-up world, ``quat`` (N, 4) orientation,
    scalar first, ``m`` (N, 3) magnetometer [uT] in the sensor's axes). Returns a sequence
    with positions (x, y), the magnetometer in the world frame, the device's heading and its
    3-D pose (heights, orientation). Raises DataError naming the file, the field and the reason."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    try:
        d = scipy.io.loadmat(path, squeeze_me=True)
    except (ValueError, OSError, NotImplementedError) as exc:
        raise DataError(f"{path}: not a MATLAB v5 file ({exc})") from None
    fields = {"t": 1, "dPos": 3, "quat": 4, "m": 3}
    arrays: dict[str, np.ndarray] = {}
    for k, width in fields.items():
        if k not in d:
            raise DataError(f"{path}: no field {k!r} (expected t, dPos, quat, m)")
        try:
            A = np.asarray(d[k], dtype=float)
        except (TypeError, ValueError):
            raise DataError(f"{path}: field {k!r} is not numeric") from None
        A = A.reshape(-1, 1) if width == 1 else A.reshape(A.shape[0], -1)
        if A.shape[1] != width:
            raise DataError(f"{path}: field {k!r} has {A.shape[1]} columns, expected {width}")
        if not np.all(np.isfinite(A)):
            row = int(np.argmax(~np.all(np.isfinite(A), axis=1)))
            raise DataError(f"{path}: field {k!r} row {row + 1} has a non-finite value")
        arrays[k] = A
    t = arrays["t"][:, 0]
    n = t.shape[0]
    for k, rows in (("dPos", n - 1), ("quat", n), ("m", n)):
        if arrays[k].shape[0] != rows:
            raise DataError(f"{path}: field {k!r} has {arrays[k].shape[0]} rows, expected {rows}")
    if n < 10 or not np.all(np.diff(t) > 0):
        raise DataError(f"{path}: field 't' must increase strictly (at least 10 rows)")
    q = arrays["quat"]
    norms = np.linalg.norm(q, axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-3):
        row = int(np.argmax(np.abs(norms - 1.0) > 1e-3))
        raise DataError(f"{path}: field 'quat' row {row + 1} is not a unit quaternion")
    P = np.vstack([np.zeros(3), np.cumsum(arrays["dPos"], axis=0)])
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # body -> world
    mag = np.einsum("kij,jl,kl->ki", R, _rotz(ARKIT_SENSOR_TO_BODY_DEG), arrays["m"])
    heading = np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    quat = q / norms[:, None]
    seq = Sequence(path.stem, t, P[:, :2], mag, heading=heading, quat=quat, z=P[:, 2])
    if np.ptp(np.diff(t)) > SOURCE_RATE_TOLERANCE * np.median(np.diff(t)) * 10:
        return uniform(seq)
    return seq


def crossing_disagreement(
    P: np.ndarray, M: np.ndarray, radius: float = 0.15, min_gap: int = 50
) -> tuple[float, int]:
    """RMS difference [field units] of the world-frame field M (N, 3) between samples within
    ``radius`` of each other and at least ``min_gap`` samples apart (where the path crosses
    itself), and the number of such pairs: a check of a recording's frame conventions."""
    pairs = np.array(sorted(cKDTree(P).query_pairs(radius)), dtype=np.int64).reshape(-1, 2)
    pairs = pairs[np.abs(pairs[:, 0] - pairs[:, 1]) >= min_gap]
    if pairs.shape[0] == 0:
        return float("nan"), 0
    d = M[pairs[:, 0]] - M[pairs[:, 1]]
    return float(np.sqrt(np.mean(d**2))), int(pairs.shape[0])


def arkit_protocol(**given: Any) -> Protocol:
    """The protocol of a handheld recording with pose (module docstring), ``given`` settings
    replacing its defaults."""
    base = Protocol(
        motion="planar",
        align=False,
        heading_rate_bias=0.005,
        step_noise=0.01,
        heading_noise=0.01,
    )
    if "drift" in given:  # a final drift asked for: the bias is found for it
        base = replace(base, heading_rate_bias=None)
    if "noise" in given:  # noise as a fraction of the median step asked for
        base = replace(base, step_noise=None)
    return replace(base, **given)


def uniform(seq: Sequence) -> Sequence:
    """A sequence with jittered or uneven time stamps on a uniform grid at its median
    interval (positions and magnetometer interpolated linearly in time): the clock search
    and the decimation of :func:`convert` count in samples."""
    dt = np.diff(seq.t)
    step = float(np.median(dt))
    t = seq.t[0] + step * np.arange(int(np.floor((seq.t[-1] - seq.t[0]) / step)) + 1)

    def at(A: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(t, seq.t, A[:, k]) for k in range(A.shape[1])])

    spread = {"interval_spread": float(np.ptp(dt) / step), "rows": int(seq.t.size)}
    heading = None if seq.heading is None else np.interp(t, seq.t, seq.heading)
    z = None if seq.z is None else np.interp(t, seq.t, seq.z)
    quat = None
    if seq.quat is not None:  # slerp (times clipped: the grid may pass the end by rounding)
        slerp = Slerp(seq.t, Rotation.from_quat(seq.quat[:, [1, 2, 3, 0]]))
        quat = slerp(np.clip(t, seq.t[0], seq.t[-1])).as_quat()[:, [3, 0, 1, 2]]
    return Sequence(
        seq.name, t, at(seq.loc), at(seq.mag), resampled=spread, heading=heading, quat=quat, z=z
    )


def log_marginal(
    P: np.ndarray,
    Y: np.ndarray,
    sigma_f: float,
    lengthscale: float,
    sigma_m: float,
    sigma_lin: float,
) -> float:
    """log p(Y | P) of a squared-exponential GP per field component plus a constant field of
    prior standard deviation sigma_lin and white noise sigma_m (up to a constant)."""
    d2 = np.sum((P[:, None, :] - P[None, :, :]) ** 2, axis=-1)
    K = sigma_f**2 * np.exp(-0.5 * d2 / lengthscale**2) + sigma_lin**2
    K[np.diag_indices_from(K)] += sigma_m**2
    c = cho_factor(K, lower=True)
    alpha = cho_solve(c, Y)
    return float(-0.5 * np.sum(Y * alpha) - Y.shape[1] * np.sum(np.log(np.diag(c[0]))))


def coarse_to_fine_argmax(
    f: Callable[[int], float], n: int, zero: int, step: int
) -> tuple[int, dict[int, float]]:
    """The index in range(n) of f's largest value, f evaluated on every ``step``-th index
    counted from ``zero`` (and both ends), then on every index within ``step`` of the best of
    those. Returns the index and the values evaluated (``zero`` among them). The likelihood
    of a shift is smooth in it: its peak spans many fine steps, so that the coarse grid
    lands on the peak's flank and the fine pass on its top."""
    coarse = sorted({0, n - 1, *range(zero % step, n, step)})
    values = {i: f(i) for i in coarse}
    top = max(values, key=values.get)
    for i in range(max(0, top - step + 1), min(n, top + step)):
        if i not in values:
            values[i] = f(i)
    return max(values, key=values.get), values


def clock_offset(
    seq: Sequence, max_shift: float = 0.5, stride: int = 5, hyper: Any = None
) -> tuple[int, dict[str, Any]]:
    """The magnetometer shift (in source samples; negative: the magnetometer lags the
    positions) that maximises the GP marginal likelihood over |shift| <= max_shift seconds,
    evaluated on every ``stride``-th sample; shifts searched :data:`CLOCK_COARSE_SECONDS`
    apart, then sample by sample around the best (:func:`coarse_to_fine_argmax`). Returns
    the shift and a record of the search."""
    n_max = round(max_shift * seq.rate)
    inner = np.arange(n_max, seq.t.shape[0] - n_max, stride)
    if hyper is None:
        hyper = estimate_hyperparameters(seq.loc[inner], seq.mag[inner], "se")
    sf, ell, sm = hyper.sigma_f, hyper.lengthscale, hyper.sigma_m
    sigma_lin = float(np.abs(seq.mag.mean(axis=0)).max() + seq.mag.std())
    shifts = np.arange(-n_max, n_max + 1)

    def value(i: int) -> float:
        return log_marginal(seq.loc[inner + shifts[i]], seq.mag[inner], sf, ell, sm, sigma_lin)

    step = max(1, round(CLOCK_COARSE_SECONDS * seq.rate))
    with threadpool_limits(1):  # small factorisations: threads only contend
        top, values = coarse_to_fine_argmax(value, shifts.size, n_max, step)
    best = int(shifts[top])
    record = {
        "shift_samples": best,
        "shift_seconds": best / seq.rate,
        "log_marginal_gain": float(values[top] - values[n_max]),
        "hyperparameters": {"sigma_f": sf, "lengthscale": ell, "sigma_m": sm},
        "shifts_evaluated": len(values),
    }
    return best, record


def align(seq: Sequence, shift: int) -> Sequence:
    """Pair the magnetometer sample k with the position at k + shift (samples lost at the
    ends are dropped)."""
    n = seq.t.shape[0]
    # The pose (positions, heading, orientation, heights) keeps the positions' clock.
    pose_rows = slice(0, n + shift) if shift <= 0 else slice(shift, n)
    mag_rows = slice(-shift, n) if shift <= 0 else slice(0, n - shift)

    def rows(A: np.ndarray | None) -> np.ndarray | None:
        return None if A is None else A[pose_rows]

    return Sequence(
        seq.name, seq.t[pose_rows], seq.loc[pose_rows], seq.mag[mag_rows],
        heading=rows(seq.heading), quat=rows(seq.quat), z=rows(seq.z),
    )  # fmt: skip


def heading_of_motion(P: np.ndarray, window: int = 5) -> np.ndarray:
    """(N,) heading [rad] of the direction of travel, from centred differences over
    ``window`` samples, unwrapped; samples while standing still take the last heading."""
    n = P.shape[0]
    i0 = np.clip(np.arange(n) - window, 0, n - 1)
    i1 = np.clip(np.arange(n) + window, 0, n - 1)
    d = P[i1] - P[i0]
    psi = np.arctan2(d[:, 1], d[:, 0])
    moving = np.linalg.norm(d, axis=1) > 1e-3
    for k in range(1, n):
        if not moving[k]:
            psi[k] = psi[k - 1]
    return np.unwrap(psi)


def _rot(psi: np.ndarray) -> np.ndarray:
    c, s = np.cos(psi), np.sin(psi)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def planar_increments(P: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """(N-1, 3) body-frame increments dfwd, dleft [m] and dyaw [rad]."""
    dP = np.diff(P, axis=0)
    body = np.einsum("kji,kj->ki", _rot(psi[:-1]), dP)
    return np.column_stack([body, np.diff(psi)])


def planar_dead_reckoning(U: np.ndarray, p0: np.ndarray, psi0: float) -> np.ndarray:
    psi = psi0 + np.concatenate([[0.0], np.cumsum(U[:, 2])])
    steps = np.einsum("kij,kj->ki", _rot(psi[:-1]), U[:, :2])
    return np.vstack([p0, p0 + np.cumsum(steps, axis=0)])


@dataclass(frozen=True)
class Protocol:
    """Settings of :func:`convert` (see the module docstring)."""

    rate: float = 10.0
    drift: float = 0.5
    noise: float = 0.01
    seed: int = 0
    motion: Literal["translational", "planar", "pose"] = "translational"
    field: Literal["recorded", "constant"] = "recorded"
    constant_noise: float = 1.0
    align: bool = True
    # planar: heading-increment noise per step [rad]; pose: rotation-vector noise per step
    # and axis [rad].
    heading_noise: float = 1.0e-3
    # planar (pose): a heading-rate (body z rotation-rate) bias [rad/s] (sign drawn from the
    # seed) instead of the one that drifts ``drift`` metres; all motions: displacement noise
    # [m per step and component] instead of ``noise`` times the median step.
    heading_rate_bias: float | None = None
    step_noise: float | None = None


@dataclass
class Converted:
    """A converted sequence: arguments for :func:`casmag.data.recording.write_recording` plus a
    record of the protocol (what was applied, measured drift, clock shift)."""

    arrays: dict[str, np.ndarray]
    record: dict[str, Any]


def rate_bias_per_step(final_error: Any, protocol: Protocol, rate: float) -> float:
    """The size of the heading-rate bias per step: the protocol's (rad/s) at ``rate`` Hz, or
    the one (bisection) at which ``final_error(bias)``, the dead reckoning's final error
    with that bias applied (of the seed's sign), reaches ``protocol.drift``."""
    if protocol.heading_rate_bias is not None:
        return protocol.heading_rate_bias / rate
    lo, hi = 0.0, 1e-4
    while final_error(hi) < protocol.drift and hi < 0.1:
        hi *= 2.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if final_error(mid) < protocol.drift else (lo, mid)
    return 0.5 * (lo + hi)


def convert(seq: Sequence, protocol: Protocol = Protocol()) -> Converted:
    """Apply the protocol to a sequence; deterministic for a given seed."""
    rng = np.random.default_rng(protocol.seed)
    record: dict[str, Any] = {"sequence": seq.name, "protocol": asdict(protocol)}
    if seq.resampled is not None:
        record["resampled"] = seq.resampled
    if protocol.align:
        shift, search = clock_offset(seq)
        record["clock"] = search
        seq = align(seq, shift)
    stride = max(1, round(seq.rate / protocol.rate))
    idx = np.arange(0, seq.t.shape[0], stride)
    t, P, Y = seq.t[idx] - seq.t[idx[0]], seq.loc[idx], seq.mag[idx]
    record["rate"] = 1.0 / float(np.median(np.diff(t)))
    record["samples"] = int(t.shape[0])
    if protocol.field == "constant":
        Y = Y.mean(axis=0) + protocol.constant_noise * rng.standard_normal(Y.shape)
    dP = np.diff(P, axis=0)
    n = dP.shape[0]
    sigma = (
        protocol.noise * float(np.median(np.linalg.norm(dP, axis=1)))
        if protocol.step_noise is None
        else protocol.step_noise
    )
    arrays: dict[str, np.ndarray] = {"t": t, "P_true": P}
    if protocol.motion == "translational":
        angle = rng.uniform(0.0, 2.0 * np.pi)
        bias = protocol.drift / n * np.array([np.cos(angle), np.sin(angle)])
        U = dP + bias + sigma * rng.standard_normal(dP.shape)
        arrays.update(Y=Y, dxy=U)
        P_dr = np.vstack([P[0], P[0] + np.cumsum(U, axis=0)])
        record["odometry"] = {"bias_per_step": bias.tolist(), "noise_per_step": sigma}
    elif protocol.motion == "pose":
        pose_arrays, P_dr = _pose_odometry(seq, idx, P, Y, sigma, protocol, rng, record)
        arrays.update(pose_arrays)
        P = pose_arrays["P_true"]  # 3-D errors
    else:
        psi = heading_of_motion(P) if seq.heading is None else seq.heading[idx]
        U0 = planar_increments(P, psi)
        white = rng.standard_normal((n, 3)) * np.array([sigma, sigma, protocol.heading_noise])
        sign = 1.0 if rng.uniform() < 0.5 else -1.0

        def final_error(rate_bias: float) -> float:
            U = U0 + white + np.array([0.0, 0.0, sign * rate_bias])
            return float(np.linalg.norm(planar_dead_reckoning(U, P[0], psi[0])[-1] - P[-1]))

        rate_bias = sign * rate_bias_per_step(final_error, protocol, record["rate"])
        U = U0 + white + np.array([0.0, 0.0, rate_bias])
        R = _rot(psi)
        Yb = Y.copy()
        Yb[:, :2] = np.einsum("kji,kj->ki", R, Y[:, :2])  # R(psi)^T y
        arrays.update(Y=Yb, planar=U, yaw_true=psi)
        P_dr = planar_dead_reckoning(U, P[0], psi[0])
        record["odometry"] = {
            "heading_rate_bias_per_step": rate_bias,
            "heading_rate_bias_deg_s": float(np.degrees(rate_bias) * record["rate"]),
            "noise_per_step": sigma,
            "heading_noise_per_step": protocol.heading_noise,
        }
    err = np.linalg.norm(P_dr - P, axis=1)
    record["odometry"].update(
        final_drift=float(err[-1]), rmse=float(np.sqrt(np.mean(err**2))), max=float(err.max())
    )
    return Converted(arrays, record)


def _pose_odometry(
    seq: Sequence,
    idx: np.ndarray,
    P: np.ndarray,
    Y: np.ndarray,
    sigma: float,
    protocol: Protocol,
    rng: np.random.Generator,
    record: dict[str, Any],
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The ``pose`` odometry of :func:`convert` at the kept samples ``idx`` (P (N, 2) the
    planar positions, Y (N, 3) the world-frame field): arrays ``Y`` (body frame), ``pose``,
    ``P_true`` (N, 3) and ``q_true``, and the dead reckoning (N, 3); fills
    ``record["odometry"]``."""
    if seq.quat is None:  # level, heading of motion, in the plane z = 0
        Q = sd.quat_from_euler(0.0, 0.0, heading_of_motion(P))
        z = np.zeros(P.shape[0])
    else:
        Q = seq.quat[idx]
        z = np.zeros(P.shape[0]) if seq.z is None else seq.z[idx]
    Q = Q / np.linalg.norm(Q, axis=1, keepdims=True)
    P3 = np.column_stack([P, z])
    U0 = sd.pose_increments(P3, Q)
    n = U0.shape[0]
    white = rng.standard_normal((n, 6)) * np.repeat([sigma, protocol.heading_noise], 3)
    sign = 1.0 if rng.uniform() < 0.5 else -1.0
    dp = U0[:, :3] + white[:, :3]
    dq = sd.quat_mul(U0[:, 3:], sd.quat_exp(white[:, 3:]))

    def increments(bias: float) -> np.ndarray:
        q = sd.quat_mul(dq, sd.quat_exp(np.array([0.0, 0.0, bias])))
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        return np.column_stack([dp, q * np.where(q[:, :1] < 0, -1.0, 1.0)])

    def final_error(rate_bias: float) -> float:
        P_dr, _ = sd.dead_reckon_pose(increments(sign * rate_bias), P3[0], Q[0])
        return float(np.linalg.norm(P_dr[-1] - P3[-1]))

    bias = sign * rate_bias_per_step(final_error, protocol, record["rate"])
    U = increments(bias)
    P_dr, _ = sd.dead_reckon_pose(U, P3[0], Q[0])
    record["odometry"] = {
        "rotation_rate_bias_per_step": bias,
        "rotation_rate_bias_deg_s": float(np.degrees(bias) * record["rate"]),
        "rotation_rate_bias_axis": "body z",
        "noise_per_step": sigma,
        "rotation_noise_per_step": protocol.heading_noise,
    }
    Yb = sd.rotate(sd.quat_conj(Q), Y)  # R(q)^T y
    return {"Y": Yb, "pose": U, "P_true": P3, "q_true": Q}, P_dr
