"""Real magnetometer sequences with motion-capture truth, turned into casmag recordings.

A sequence is three CSV files sharing a prefix (``DIR/N-time.csv``, ``DIR/N-loc.csv``,
``DIR/N-mag.csv``: time [s], planar position [m] from motion capture, magnetometer [uT] in
the world frame; the layout of ``../shared/data/magnetic-data/invensense``). The protocol
(:func:`convert`, ``casmag convert``) is:

1. **Clock alignment.** The magnetometer and the motion capture ran on separate clocks. The
   magnetometer is shifted by the whole number of samples that maximises the GP marginal
   likelihood of the field given the true positions (:func:`clock_offset`; squared
   exponential kernel plus a constant field, hyperparameters from :mod:`casmag.hyper`). On
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
4. **Field** (``field``): ``recorded`` keeps the magnetometer; ``constant`` replaces it by its
   mean plus white noise of ``constant_noise`` uT, a homogeneous field that carries no
   position information (the "never worse" check).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from threadpoolctl import threadpool_limits

from casmag.errors import DataError
from casmag.hyper import estimate_hyperparameters

SOURCE_RATE_TOLERANCE = 1e-3  # relative spread of the sample interval accepted as uniform


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
    return Sequence(seq.name, t, at(seq.loc), at(seq.mag), resampled=spread)


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


def clock_offset(
    seq: Sequence, max_shift: float = 0.5, stride: int = 5, hyper: Any = None
) -> tuple[int, dict[str, Any]]:
    """The magnetometer shift (in source samples; negative: the magnetometer lags the
    positions) that maximises the GP marginal likelihood over |shift| <= max_shift seconds,
    evaluated on every ``stride``-th sample. Returns the shift and a record of the search."""
    n_max = round(max_shift * seq.rate)
    inner = np.arange(n_max, seq.t.shape[0] - n_max, stride)
    if hyper is None:
        hyper = estimate_hyperparameters(seq.loc[inner], seq.mag[inner], "se")
    sf, ell, sm = hyper.sigma_f, hyper.lengthscale, hyper.sigma_m
    sigma_lin = float(np.abs(seq.mag.mean(axis=0)).max() + seq.mag.std())
    shifts = np.arange(-n_max, n_max + 1)
    with threadpool_limits(1):  # small factorisations: threads only contend
        values = np.array(
            [
                log_marginal(seq.loc[inner + s], seq.mag[inner], sf, ell, sm, sigma_lin)
                for s in shifts
            ]
        )
    best = int(shifts[int(np.argmax(values))])
    record = {
        "shift_samples": best,
        "shift_seconds": best / seq.rate,
        "log_marginal_gain": float(values.max() - values[n_max]),
        "hyperparameters": {"sigma_f": sf, "lengthscale": ell, "sigma_m": sm},
    }
    return best, record


def align(seq: Sequence, shift: int) -> Sequence:
    """Pair the magnetometer sample k with the position at k + shift (samples lost at the
    ends are dropped)."""
    n = seq.t.shape[0]
    if shift <= 0:
        L = -shift
        return Sequence(seq.name, seq.t[: n - L], seq.loc[: n - L], seq.mag[L:])
    return Sequence(seq.name, seq.t[shift:], seq.loc[shift:], seq.mag[: n - shift])


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
    motion: Literal["translational", "planar"] = "translational"
    field: Literal["recorded", "constant"] = "recorded"
    constant_noise: float = 1.0
    align: bool = True
    heading_noise: float = 1.0e-3  # planar: heading-increment noise per step [rad]


@dataclass
class Converted:
    """A converted sequence: arguments for :func:`casmag.recording.write_recording` plus a
    record of the protocol (what was applied, measured drift, clock shift)."""

    arrays: dict[str, np.ndarray]
    record: dict[str, Any]


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
    sigma = protocol.noise * float(np.median(np.linalg.norm(dP, axis=1)))
    arrays: dict[str, np.ndarray] = {"t": t, "P_true": P}
    if protocol.motion == "translational":
        angle = rng.uniform(0.0, 2.0 * np.pi)
        bias = protocol.drift / n * np.array([np.cos(angle), np.sin(angle)])
        U = dP + bias + sigma * rng.standard_normal(dP.shape)
        arrays.update(Y=Y, dxy=U)
        P_dr = np.vstack([P[0], P[0] + np.cumsum(U, axis=0)])
        record["odometry"] = {"bias_per_step": bias.tolist(), "noise_per_step": sigma}
    else:
        psi = heading_of_motion(P)
        U0 = planar_increments(P, psi)
        white = rng.standard_normal((n, 3)) * np.array([sigma, sigma, protocol.heading_noise])
        sign = 1.0 if rng.uniform() < 0.5 else -1.0

        def final_error(rate_bias: float) -> float:
            U = U0 + white + np.array([0.0, 0.0, sign * rate_bias])
            return float(np.linalg.norm(planar_dead_reckoning(U, P[0], psi[0])[-1] - P[-1]))

        lo, hi = 0.0, 1e-4
        while final_error(hi) < protocol.drift and hi < 0.1:
            hi *= 2.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if final_error(mid) < protocol.drift else (lo, mid)
        rate_bias = sign * 0.5 * (lo + hi)
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
