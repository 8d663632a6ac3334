"""IMU simulator: hand-held trajectories on a desk, strapdown increments with MEMS errors and a
magnetometer in a physical field (Earth plus dipoles, :mod:`casmag.data.dipoles`).

Pipeline: a scenario gives a planar or 3-D path (rectangle traced several times, spiral out and
back in, handwriting of a word); the path is walked with a smooth speed profile (slower in
tight curves, at rest for ``static`` seconds at both ends) and the device wobbles smoothly in
roll, pitch and yaw. The truth is sampled at the IMU rate; the increments are the exact ones
of Eq. 1 between samples (``casmag.strapdown``), so strapdown integration of error-free
increments reproduces the truth to rounding. The IMU then adds, per interval T,

    dq_meas = dq Exp(T b_w + sqrt(T) gyro_density xi),
    dv_meas = dv + T b_a + sqrt(T) acc_density xi,

with biases b = constant + random walk (Eq. 2), and the magnetometer reads
y = R(q)^T B(p) + noise at every sample.

Random streams: one seed gives independent streams for the wobble, the gyroscope, the
accelerometer, the bias walks and the magnetometer, so changing one noise level leaves the
others' draws unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.interpolate
import scipy.ndimage

from casmag import strapdown as sd
from casmag.data.dipoles import Dipole, DipoleField, earth_field

# --------------------------------------------------------------------------- paths


def _resample(points: np.ndarray, ds: float) -> np.ndarray:
    """Polyline (n, 3) resampled every ds [m] along its length (end point kept)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 1e-12])
    s, points = s[keep], points[keep]
    target = np.linspace(0.0, s[-1], max(int(np.ceil(s[-1] / ds)) + 1, 2))
    return np.column_stack([np.interp(target, s, points[:, a]) for a in range(3)])


def _smooth(points: np.ndarray, radius: float, ds: float) -> np.ndarray:
    """Gaussian smoothing along the path with standard deviation ``radius`` [m] (rounds
    corners to about that radius), ends held fixed."""
    if radius <= 0:
        return points
    return scipy.ndimage.gaussian_filter1d(points, radius / ds, axis=0, mode="nearest")


def rectangle_path(size: tuple[float, float], loops: int) -> np.ndarray:
    """Corners of a rectangle (centred at the origin, plane z = 0) traced ``loops`` times
    counter-clockwise, starting and ending in the middle of the lower side. (n, 3)."""
    a, b = 0.5 * size[0], 0.5 * size[1]
    loop = [(a, -b), (a, b), (-a, b), (-a, -b)]
    pts = [(0.0, -b)] + loop * loops + [(0.0, -b)]
    return np.array([(x, y, 0.0) for x, y in pts])


def spiral_path(start_radius: float, pitch: float, turns: float) -> np.ndarray:
    """Archimedean spiral out (r = r0 + pitch theta / 2 pi) for ``turns`` turns and back in
    half a pitch further out, so the inward pass runs between the outward ones. (n, 3)."""
    theta = np.linspace(0.0, 2 * np.pi * turns, int(400 * turns) + 2)
    r_out = start_radius + pitch * theta / (2 * np.pi)
    out = np.column_stack([r_out * np.cos(theta), r_out * np.sin(theta)])
    back = theta[::-1]
    r_in = start_radius + pitch * (back / (2 * np.pi) + 0.5)
    inward = np.column_stack([r_in * np.cos(back), r_in * np.sin(back)])
    xy = np.vstack([out, inward])
    return np.column_stack([xy - xy[0], np.zeros(len(xy))])


# Single-stroke glyphs in a unit em (x-height 0.5, ascender 1, descender -0.4), one polyline
# each, entering at the left and leaving at the right on the baseline (cursive joins).
_GLYPHS: dict[str, list[tuple[float, float]]] = {
    "a": [
        (0.0, 0.0),
        (0.45, 0.35),
        (0.3, 0.5),
        (0.05, 0.35),
        (0.1, 0.05),
        (0.35, 0.1),
        (0.45, 0.5),
        (0.45, 0.1),
        (0.6, 0.0),
    ],
    "c": [
        (0.0, 0.0),
        (0.05, 0.2),
        (0.45, 0.45),
        (0.25, 0.5),
        (0.05, 0.3),
        (0.15, 0.02),
        (0.5, 0.05),
        (0.6, 0.0),
    ],
    "g": [
        (0.0, 0.0),
        (0.45, 0.35),
        (0.3, 0.5),
        (0.05, 0.35),
        (0.1, 0.05),
        (0.35, 0.1),
        (0.45, 0.5),
        (0.45, -0.3),
        (0.25, -0.4),
        (0.05, -0.3),
        (0.6, 0.0),
    ],
    "m": [
        (0.0, 0.0),
        (0.05, 0.5),
        (0.2, 0.5),
        (0.3, 0.3),
        (0.3, 0.0),
        (0.35, 0.45),
        (0.5, 0.5),
        (0.6, 0.3),
        (0.6, 0.0),
        (0.75, 0.0),
    ],
    "n": [(0.0, 0.0), (0.05, 0.5), (0.25, 0.5), (0.35, 0.3), (0.35, 0.0), (0.5, 0.0)],
    "s": [
        (0.0, 0.0),
        (0.3, 0.45),
        (0.45, 0.45),
        (0.2, 0.5),
        (0.1, 0.35),
        (0.4, 0.2),
        (0.35, 0.03),
        (0.1, 0.05),
        (0.5, 0.0),
    ],
    "e": [
        (0.0, 0.0),
        (0.45, 0.25),
        (0.35, 0.48),
        (0.1, 0.45),
        (0.05, 0.15),
        (0.25, 0.0),
        (0.55, 0.05),
        (0.6, 0.0),
    ],
    "x": [
        (0.0, 0.0),
        (0.1, 0.1),
        (0.45, 0.5),
        (0.3, 0.5),
        (0.15, 0.3),
        (0.15, 0.2),
        (0.45, 0.0),
        (0.6, 0.0),
    ],
}


def handwriting_path(word: str, height: float, passes: int, lift: float) -> np.ndarray:
    """The word written in joined single strokes, ``height`` [m] per em, ``passes`` times over
    itself; between passes the pen lifts by ``lift`` [m] and returns to the start. (n, 3)."""
    pts: list[tuple[float, float]] = []
    x0 = 0.0
    for ch in word:
        glyph = _GLYPHS[ch]
        pts.extend((x0 + gx, gy) for gx, gy in glyph)
        x0 += glyph[-1][0]
    one = np.array([(height * x, height * y, 0.0) for x, y in pts])
    path = [one]
    for _ in range(passes - 1):
        end, start = one[-1], one[0]
        up = np.array([0.0, 0.0, lift])
        path.append(np.vstack([end + up, start + up]))
        path.append(one)
    out = np.vstack(path)
    return out - out[0]


# --------------------------------------------------------------------------- truth
@dataclass(frozen=True)
class Truth:
    """The true motion sampled at the IMU rate: t (N,) [s]; P, V (N, 3) [m, m/s] in the
    local frame; Q (N, 4) orientation q^{LS} (w first). A recording's truth
    (casmag.data.imurec) has no velocity and may lack P or Q (None)."""

    t: np.ndarray
    P: np.ndarray | None
    V: np.ndarray | None
    Q: np.ndarray | None


def _window(u: np.ndarray, ramp: float) -> np.ndarray:
    """1 inside [ramp, 1 - ramp], raised-cosine ramps to 0 at u = 0 and u = 1."""
    w = np.ones_like(u)
    lo, hi = u < ramp, u > 1 - ramp
    w[lo] = 0.5 - 0.5 * np.cos(np.pi * u[lo] / ramp)
    w[hi] = 0.5 - 0.5 * np.cos(np.pi * (1 - u[hi]) / ramp)
    return np.clip(w, 0.0, 1.0)


def walk(
    path: np.ndarray,
    speed: float,
    rate: float,
    static: float,
    corner_radius: float,
    wobble_deg: tuple[float, float, float],
    attitude_deg: tuple[float, float, float],
    rng: np.random.Generator,
    ramp_seconds: float = 1.0,
) -> Truth:
    """Walk a path polyline (n, 3) at about ``speed`` [m/s] (slower where it curves
    tightly), at rest for ``static`` s before and after; sample at ``rate`` [Hz].

    The orientation is Rz(yaw) Ry(pitch) Rx(roll) with the constant ``attitude_deg``
    (roll, pitch, yaw) plus smooth random wobble of amplitudes ``wobble_deg`` while moving.
    """
    ds = 5e-4
    X = _smooth(_resample(path, ds), corner_radius, ds)
    X = X - X[0] + path[0]
    seg = np.linalg.norm(np.diff(X, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 1e-9])
    s, X = s[keep], X[keep]
    curve = scipy.interpolate.CubicSpline(s, X, axis=0)
    # Curvature-dependent speed: a hand slows down in tight turns.
    d1, d2 = curve(s, 1), curve(s, 2)
    kappa = (
        np.linalg.norm(np.cross(d1, d2), axis=1) / np.maximum(np.linalg.norm(d1, axis=1), 1e-9) ** 3
    )
    kappa = scipy.ndimage.gaussian_filter1d(kappa, 0.02 / ds, mode="nearest")
    # Never below a quarter of the cruising speed, so cusps of handwriting stay brief.
    v_s = np.maximum(speed / np.sqrt(1.0 + (kappa * 0.04) ** 2), 0.25 * speed)
    tau = np.concatenate([[0.0], np.cumsum(np.diff(s) / (0.5 * (v_s[1:] + v_s[:-1])))])
    s_of_tau = scipy.interpolate.CubicSpline(tau, s)
    # Real time: tau advances with a raised-cosine start and stop, so speed and acceleration
    # vanish at both ends of the motion.
    t_move = tau[-1] + ramp_seconds
    dt_fine = 1e-3
    u = np.arange(0.0, t_move + dt_fine / 2, dt_fine) / t_move
    w = _window(u, ramp_seconds / t_move)
    warp = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]))])
    warp *= tau[-1] / warp[-1]
    p_fine = curve(np.clip(s_of_tau(warp), 0.0, s[-1]))
    n_static = round(static * rate)
    t_fine = u * t_move
    spline = scipy.interpolate.CubicSpline(t_fine, p_fine, axis=0, bc_type="clamped")
    t_motion = np.arange(0.0, t_fine[-1], 1.0 / rate)
    P_move, V_move = spline(t_motion), spline(t_motion, 1)
    # Wobble: three sinusoids per angle, random frequencies 0.05-0.5 Hz and phases.
    ang = np.zeros((t_motion.size, 3))
    win = _window(t_motion / t_motion[-1], min(0.5, ramp_seconds / t_motion[-1]))
    for a in range(3):
        f = rng.uniform(0.05, 0.5, 3)
        ph = rng.uniform(0, 2 * np.pi, 3)
        sig = np.sin(2 * np.pi * f[:, None] * t_motion[None, :] + ph[:, None]).sum(0) / 3
        sig -= sig[0]
        ang[:, a] = np.radians(wobble_deg[a]) * sig * win
    ang += np.radians(np.asarray(attitude_deg, dtype=float))
    Q_move = sd.quat_from_euler(ang[:, 0], ang[:, 1], ang[:, 2])
    # Static periods before and after.
    P = np.vstack([np.repeat(P_move[:1], n_static, 0), P_move, np.repeat(P_move[-1:], n_static, 0)])
    V = np.vstack([np.zeros((n_static, 3)), V_move, np.zeros((n_static, 3))])
    Q = np.vstack([np.repeat(Q_move[:1], n_static, 0), Q_move, np.repeat(Q_move[-1:], n_static, 0)])
    t = np.arange(P.shape[0]) / rate
    # Truth consistent with Eq. 1: positions are the trapezoidal integral of the velocities.
    T = 1.0 / rate
    P = P[0] + np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * T * (V[1:] + V[:-1]), axis=0)])
    return Truth(t=t, P=P, V=V, Q=Q)


def exact_increments(truth: Truth) -> tuple[np.ndarray, np.ndarray]:
    """Error-free increments between samples: dq (N-1, 4) = q_k^-1 q_{k+1} and
    dv (N-1, 3) = R_k^T (v_{k+1} - v_k - T g), so Eq. 1 reproduces the truth."""
    T = truth.t[1] - truth.t[0]
    dq = sd.quat_mul(sd.quat_conj(truth.Q[:-1]), truth.Q[1:])
    dv_L = truth.V[1:] - truth.V[:-1] - T * sd.gravity_vector()
    dv = np.einsum("kji,kj->ki", sd.quat_to_rotmat(truth.Q[:-1]), dv_L)
    return dq, dv


# --------------------------------------------------------------------------- sensors
@dataclass(frozen=True)
class ImuErrors:
    """MEMS error model. Densities: gyro [rad/s/sqrt(Hz)], acc [m/s^2/sqrt(Hz)]; constant
    biases b_w [rad/s], b_a [m/s^2] (3,); bias random walks [rad/s/sqrt(s)], [m/s^2/sqrt(s)]."""

    gyro_density: float
    acc_density: float
    gyro_bias: np.ndarray
    acc_bias: np.ndarray
    gyro_walk: float
    acc_walk: float


@dataclass(frozen=True)
class ImuData:
    """Everything a solver sees, plus the truth (None for real data).

    T: IMU interval [s]; dq (N-1, 4), dv (N-1, 3): measured increments; Y (N, 3):
    magnetometer in the sensor frame [a.u.]; p0, v0 (3,): known initial position and
    velocity; q0 (4,): initial attitude estimate (levelled roll and pitch, known heading).
    Truth: ``truth`` (positions, velocities, orientations), b_w, b_a (N, 3) biases at each
    sample, M (N, 3) field in the local frame at the true positions."""

    T: float
    dq: np.ndarray
    dv: np.ndarray
    Y: np.ndarray
    p0: np.ndarray
    v0: np.ndarray
    q0: np.ndarray
    truth: Truth | None = None
    b_w: np.ndarray | None = None
    b_a: np.ndarray | None = None
    M: np.ndarray | None = None
    #: Several sessions of one field (:func:`stack_sessions`): the first sample of each;
    #: the increment row before a later session's first sample is not read.
    starts: tuple[int, ...] = (0,)
    #: Each session's known initial state, rows (p0, v0, q0) (S, 10); None: one session
    #: from (p0, v0, q0).
    initial: np.ndarray | None = None
    #: Magnetometer samples per IMU sample (at most 1): below 1 when a slower magnetometer
    #: was interpolated to the IMU's samples (casmag.data.recording.Recording.mag_share), so
    #: that an average over several IMU samples holds fewer independent magnetometer samples.
    mag_share: float = 1.0

    @property
    def n_samples(self) -> int:
        return self.Y.shape[0]

    def initial_states(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each session's initial position (S, 3), velocity (S, 3) and attitude (S, 4)."""
        if self.initial is None:
            row = np.concatenate([self.p0, self.v0, self.q0]).reshape(1, 10)
        else:
            row = np.asarray(self.initial, dtype=float).reshape(-1, 10)
        return row[:, 0:3], row[:, 3:6], row[:, 6:10]


def _stacked(parts: list[np.ndarray | None]) -> np.ndarray | None:
    """The arrays one under the other, or None when any is missing."""
    return None if any(v is None for v in parts) else np.vstack(parts)


def stack_sessions(sessions: list[ImuData]) -> ImuData:
    """Several IMU recordings of one field, in one frame, stacked end to end as one
    ImuData with ``starts`` (the first sample of each) and each one's initial state in
    ``initial``: one IMU interval T (ValueError otherwise), a no-motion increment row
    (identity rotation, zero velocity change; not read) before each later session, the
    truth's times shifted to follow on, truth arrays kept when every session has them, the
    smallest magnetometer share."""
    first = sessions[0]
    for d in sessions[1:]:
        if abs(d.T - first.T) > 1e-9 * first.T:
            raise ValueError(f"sessions: one IMU interval, got {first.T} and {d.T} s")
    gap_q, gap_v = np.array([[1.0, 0.0, 0.0, 0.0]]), np.zeros((1, 3))
    dq = np.vstack([v for d in sessions for v in (d.dq, gap_q)][:-1])
    dv = np.vstack([v for d in sessions for v in (d.dv, gap_v)][:-1])
    starts = tuple(int(a) for a in np.cumsum([0] + [d.n_samples for d in sessions[:-1]]))
    initial = np.vstack([np.hstack(d.initial_states()) for d in sessions])
    truth = None
    if all(d.truth is not None for d in sessions):
        times, offset = [], 0.0
        for d in sessions:
            times.append(d.truth.t - d.truth.t[0] + offset)  # type: ignore[union-attr]
            offset = times[-1][-1] + first.T
        truth = Truth(
            t=np.concatenate(times),
            P=_stacked([d.truth.P for d in sessions]),  # type: ignore[union-attr]
            V=_stacked([d.truth.V for d in sessions]),  # type: ignore[union-attr]
            Q=_stacked([d.truth.Q for d in sessions]),  # type: ignore[union-attr]
        )
    return ImuData(
        T=first.T, dq=dq, dv=dv, Y=np.vstack([d.Y for d in sessions]),
        p0=first.p0, v0=first.v0, q0=first.q0, truth=truth,
        b_w=_stacked([d.b_w for d in sessions]), b_a=_stacked([d.b_a for d in sessions]),
        M=_stacked([d.M for d in sessions]), starts=starts, initial=initial,
        mag_share=min(d.mag_share for d in sessions),
    )  # fmt: skip


def levelled_attitude(dv: np.ndarray, T: float, n: int, yaw: float) -> np.ndarray:
    """Attitude (4,) from the mean specific force of the first n increments (device at
    rest): roll and pitch from the direction of gravity in the sensor frame, heading given."""
    f = np.mean(dv[:n], axis=0) / T
    roll = np.arctan2(f[1], f[2])
    pitch = np.arctan2(-f[0], np.hypot(f[1], f[2]))
    return sd.quat_from_euler(roll, pitch, yaw)


def measure(
    truth: Truth,
    errors: ImuErrors,
    field: DipoleField,
    mag_noise: float,
    streams: dict[str, np.random.Generator],
    levelling_seconds: float,
) -> ImuData:
    """Increments with MEMS errors and the magnetometer along a true motion."""
    T = float(truth.t[1] - truth.t[0])
    dq, dv = exact_increments(truth)
    n = dq.shape[0]
    walk_w = np.vstack(
        [
            np.zeros((1, 3)),
            np.cumsum(errors.gyro_walk * np.sqrt(T) * streams["walk"].standard_normal((n, 3)), 0),
        ]
    )
    walk_a = np.vstack(
        [
            np.zeros((1, 3)),
            np.cumsum(errors.acc_walk * np.sqrt(T) * streams["walk"].standard_normal((n, 3)), 0),
        ]
    )
    b_w = errors.gyro_bias + walk_w  # (N, 3): bias at each sample, used over the next interval
    b_a = errors.acc_bias + walk_a
    angle = T * b_w[:-1] + errors.gyro_density * np.sqrt(T) * streams["gyro"].standard_normal(
        (n, 3)
    )
    dq_meas = sd.quat_mul(dq, sd.quat_exp(angle))
    dv_meas = (
        dv + T * b_a[:-1] + errors.acc_density * np.sqrt(T) * streams["acc"].standard_normal((n, 3))
    )
    M = field(truth.P)
    Y = np.einsum("kji,kj->ki", sd.quat_to_rotmat(truth.Q), M)
    Y = Y + mag_noise * streams["mag"].standard_normal(Y.shape)
    n_level = max(1, round(levelling_seconds / T))
    yaw0 = sd.euler_from_quat(truth.Q[0])[2]
    q0 = levelled_attitude(dv_meas, T, n_level, yaw0)
    return ImuData(
        T=T,
        dq=dq_meas,
        dv=dv_meas,
        Y=Y,
        p0=truth.P[0].copy(),
        v0=np.zeros(3),
        q0=q0,
        truth=truth,
        b_w=b_w,
        b_a=b_a,
        M=M,
    )


def random_streams(seed: int) -> dict[str, np.random.Generator]:
    """Independent generators for the wobble, gyroscope, accelerometer, bias walks and
    magnetometer, all from one seed."""
    names = ("wobble", "gyro", "acc", "walk", "mag")
    seqs = np.random.SeedSequence(seed).spawn(len(names))
    return {n: np.random.default_rng(s) for n, s in zip(names, seqs, strict=True)}


def dipole_field(
    earth_intensity: float,
    inclination_deg: float,
    declination_deg: float,
    dipoles: list[tuple[str, list[float], list[float]]],
) -> DipoleField:
    """Earth's field scaled by ``earth_intensity`` plus (name, position, moment) dipoles."""
    return DipoleField(
        earth=earth_intensity * earth_field(inclination_deg, declination_deg),
        dipoles=tuple(
            Dipole(np.asarray(p, dtype=float), np.asarray(m, dtype=float), name)
            for name, p, m in dipoles
        ),
    )


# --------------------------------------------------------------------------- problems
def scenario_path(scenario: Any) -> np.ndarray:
    """The path polyline (n, 3) of a scenario spec (``casmag.problem.imu``)."""
    if scenario.kind == "rectangle":
        return rectangle_path(tuple(scenario.size), scenario.loops)
    if scenario.kind == "spiral":
        return spiral_path(scenario.start_radius, scenario.pitch, scenario.turns)
    if scenario.kind == "handwriting":
        return handwriting_path(scenario.word, scenario.height, scenario.passes, scenario.lift)
    raise ValueError(f"unknown scenario kind {scenario.kind!r}")


def simulate_imu(problem: Any) -> ImuData:
    """The data set an IMU problem (``casmag.problem.imu.ImuProblem``) describes, from its
    seed."""
    sim = problem.spec.simulation
    streams = random_streams(problem.spec.seed)
    sc = sim.scenario
    truth = walk(
        scenario_path(sc),
        speed=sc.speed,
        rate=sim.imu.rate,
        static=sc.static,
        corner_radius=sc.corner_radius,
        wobble_deg=tuple(sc.wobble_deg),
        attitude_deg=tuple(sc.attitude_deg),
        rng=streams["wobble"],
    )
    imu = sim.imu
    errors = ImuErrors(
        gyro_density=float(np.radians(imu.gyro_noise_density)),
        acc_density=imu.acc_noise_density,
        gyro_bias=np.radians(np.asarray(imu.gyro_bias, dtype=float)),
        acc_bias=np.asarray(imu.acc_bias, dtype=float),
        gyro_walk=float(np.radians(imu.gyro_bias_walk)),
        acc_walk=imu.acc_bias_walk,
    )
    f = sim.field
    field = dipole_field(
        f.earth_intensity,
        f.inclination_deg,
        f.declination_deg,
        [(d.name, d.position, d.moment) for d in f.dipoles],
    )
    return measure(truth, errors, field, sim.magnetometer.noise, streams, imu.levelling_seconds)


# --------------------------------------------------------------------------- planar odometry
@dataclass(frozen=True)
class PlanarData:
    """A simulated planar recording: t (N,) [s]; U (N-1, 3) increments dfwd, dleft [m] and
    dyaw [rad] in the body frame; Y (N, 3) magnetometer in the heading-rotated body frame;
    truth P (N, 2) [m], psi (N,) [rad]; the true heading-rate bias [rad/s]."""

    t: np.ndarray
    U: np.ndarray
    Y: np.ndarray
    P: np.ndarray
    psi: np.ndarray
    bias: float


def simulate_planar(
    seed: int,
    field: DipoleField,
    size: tuple[float, float] = (3.0, 2.0),
    loops: int = 3,
    step: float = 0.1,
    rate: float = 10.0,
    corner_radius: float = 0.3,
    heading_bias_deg: float = 0.3,
    disp_noise: float = 0.005,
    dyaw_noise_deg: float = 0.05,
    mag_noise: float = 0.01,
) -> PlanarData:
    """Pedestrian or wheel odometry along a rounded rectangle traced ``loops`` times (a step
    of ``step`` m per sample at ``rate`` Hz), heading along the path. Increments get white
    noise (disp_noise [m], dyaw_noise_deg [deg] per step) and the heading increments a
    constant heading-rate bias [deg/s]; the magnetometer reads Rz(psi)^T B(p) + noise in the
    plane z = 0."""
    rng_o, rng_m = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
    ds = 1e-3
    X = _smooth(_resample(rectangle_path(size, loops), ds), corner_radius, ds)
    seg = np.linalg.norm(np.diff(X, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    target = np.arange(0.0, s[-1], step)
    P = np.column_stack([np.interp(target, s, X[:, a]) for a in range(2)])
    d = np.diff(P, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0])
    psi = np.unwrap(np.concatenate([heading, heading[-1:]]))
    c, sn = np.cos(psi[:-1]), np.sin(psi[:-1])
    fwd, left = c * d[:, 0] + sn * d[:, 1], -sn * d[:, 0] + c * d[:, 1]
    t = np.arange(P.shape[0]) / rate
    bias = float(np.radians(heading_bias_deg))
    noise = rng_o.standard_normal((d.shape[0], 3))
    U = np.column_stack(
        [
            fwd + disp_noise * noise[:, 0],
            left + disp_noise * noise[:, 1],
            np.diff(psi) + bias / rate + np.radians(dyaw_noise_deg) * noise[:, 2],
        ]
    )
    B = field(np.column_stack([P, np.zeros(P.shape[0])]))
    R = sd.quat_to_rotmat(sd.quat_from_euler(0.0 * psi, 0.0 * psi, psi))
    Y = np.einsum("kji,kj->ki", R, B) + mag_noise * rng_m.standard_normal(B.shape)
    return PlanarData(t=t, U=U, Y=Y, P=P, psi=psi, bias=bias)
