"""Quaternions and strapdown integration of IMU increments (paper Eq. 1-2), numpy and CasADi.

Conventions: Hamilton quaternions stored w first, ``q = (w, x, y, z)``. The orientation
``q = q^{LS}`` maps sensor-frame vectors into the local frame, ``v^L = R(q) v^S``. The local
frame has z up, so gravity is ``g^L = (0, 0, -GRAVITY)``.

An IMU reports, for each interval of length T, the rotation increment ``dq`` (sensor frame at
the start of the interval to the sensor frame at its end) and the velocity increment ``dv``
(specific force integrated over the interval, in the sensor frame at its start). Eq. 1:

    q_{t+T} = q_t dq_t
    v_{t+T} = v_t + R(q_t) dv_t + T g
    p_{t+T} = p_t + T v_t + R(q_t) (T / 2) dv_t + (T^2 / 2) g

Biases (Eq. 2) are removed from the increments as ``dq Exp(-b_w T)`` and ``dv - T b_a``: the
simulator adds them the same way, so bias-compensated integration of exact data is exact.

Composing the increments of n consecutive intervals gives the increment between keyframes
("preintegration"): with the keyframe's own frame as reference,

    Dq_{j+1} = Dq_j dq_j Exp(-b_w T)
    Dv_{j+1} = Dv_j + R(Dq_j) (dv_j - T b_a)
    Dp_{j+1} = Dp_j + T Dv_j + R(Dq_j) (T / 2) (dv_j - T b_a)

and then q_{k+1} = q_k Dq, v_{k+1} = v_k + n T g + R(q_k) Dv,
p_{k+1} = p_k + n T v_k + (n T)^2 / 2 g + R(q_k) Dp, which equals n steps of Eq. 1.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

#: Standard gravity [m/s^2]; the local frame's gravity vector is (0, 0, -GRAVITY).
GRAVITY = 9.81


def gravity_vector() -> np.ndarray:
    """(3,) gravity in the local frame (z up) [m/s^2]."""
    return np.array([0.0, 0.0, -GRAVITY])


# --------------------------------------------------------------------------- numpy quaternions
def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a b of (..., 4) quaternions (w first), broadcast over leading axes."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion), (..., 4)."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_normalize(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_exp(phi: np.ndarray) -> np.ndarray:
    """Unit quaternion of the rotation vector phi (..., 3) [rad]: (cos |phi|/2, sin |phi|/2 n).

    Uses the Taylor series of sin(x/2)/x below |phi| = 1e-4, so phi = 0 is exact."""
    phi = np.asarray(phi, dtype=float)
    theta2 = np.sum(phi * phi, axis=-1, keepdims=True)
    theta = np.sqrt(theta2)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    half_sinc = np.where(small, 0.5 - theta2 / 48.0, np.sin(0.5 * safe) / safe)
    w = np.where(small, 1.0 - theta2 / 8.0 + theta2**2 / 384.0, np.cos(0.5 * theta))
    return np.concatenate([w, half_sinc * phi], axis=-1)


def quat_log(q: np.ndarray) -> np.ndarray:
    """Rotation vector (..., 3) of a unit quaternion, angle in [0, pi] (sign of q ignored)."""
    q = np.asarray(q, dtype=float)
    q = np.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    scale = np.where(s < 1e-12, 2.0 / np.maximum(q[..., :1], 1e-300), angle / np.maximum(s, 1e-300))
    return scale * v


def quat_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle [rad] of the rotation between unit quaternions a and b, (...,)."""
    d = quat_mul(quat_conj(a), b)
    return 2.0 * np.arctan2(np.linalg.norm(d[..., 1:], axis=-1), np.abs(d[..., 0]))


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) quaternions (normalised on the way)."""
    w, x, y, z = np.moveaxis(quat_normalize(q), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R(q) v for (..., 4) quaternions and (..., 3) vectors."""
    return np.einsum("...ij,...j->...i", quat_to_rotmat(q), np.asarray(v, dtype=float))


def quat_from_euler(roll: Any, pitch: Any, yaw: Any) -> np.ndarray:
    """Quaternion of R = Rz(yaw) Ry(pitch) Rx(roll) [rad], (..., 4)."""
    roll, pitch, yaw = np.broadcast_arrays(
        *(np.asarray(a, dtype=float) for a in (roll, pitch, yaw))
    )
    zero = np.zeros_like(roll)
    qz = quat_exp(np.stack([zero, zero, yaw], -1))
    qy = quat_exp(np.stack([zero, pitch, zero], -1))
    qx = quat_exp(np.stack([roll, zero, zero], -1))
    return quat_mul(quat_mul(qz, qy), qx)


def euler_from_quat(q: np.ndarray) -> np.ndarray:
    """(..., 3) roll, pitch, yaw [rad] with R = Rz(yaw) Ry(pitch) Rx(roll)."""
    R = quat_to_rotmat(q)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = -np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], -1)


def gibbs_quat(delta: np.ndarray) -> np.ndarray:
    """Unit quaternion (1, delta / 2) / sqrt(1 + |delta|^2 / 4) of a Gibbs vector (..., 3).

    The local orientation parameterisation of the IMU problem: smooth everywhere, equal to
    the rotation vector to second order, and covering every rotation below 180 degrees."""
    delta = np.asarray(delta, dtype=float)
    u = np.concatenate([np.ones((*delta.shape[:-1], 1)), 0.5 * delta], axis=-1)
    return quat_normalize(u)


# --------------------------------------------------------------------------- numpy strapdown
def strapdown(
    p0: np.ndarray,
    v0: np.ndarray,
    q0: np.ndarray,
    dq: np.ndarray,
    dv: np.ndarray,
    T: float,
    b_w: np.ndarray | None = None,
    b_a: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Strapdown integration (Eq. 1) of n increments from the initial state.

    p0, v0: (3,) [m, m/s]; q0: (4,); dq: (n, 4); dv: (n, 3) [m/s]; T: interval [s];
    b_w, b_a: gyroscope [rad/s] and accelerometer [m/s^2] biases to remove, (3,) or (n, 3).
    Returns P (n+1, 3), V (n+1, 3), Q (n+1, 4).
    """
    dq, dv = np.asarray(dq, dtype=float), np.asarray(dv, dtype=float)
    n = dq.shape[0]
    if b_w is not None:
        dq = quat_mul(dq, quat_exp(-T * np.broadcast_to(b_w, (n, 3))))
    if b_a is not None:
        dv = dv - T * np.broadcast_to(b_a, (n, 3))
    g = gravity_vector()
    P, V, Q = np.empty((n + 1, 3)), np.empty((n + 1, 3)), np.empty((n + 1, 4))
    P[0], V[0], Q[0] = p0, v0, quat_normalize(q0)
    for k in range(n):
        Rdv = rotate(Q[k], dv[k])
        P[k + 1] = P[k] + T * V[k] + 0.5 * T * Rdv + 0.5 * T**2 * g
        V[k + 1] = V[k] + Rdv + T * g
        Q[k + 1] = quat_normalize(quat_mul(Q[k], dq[k]))
    return P, V, Q


def quat_prefix(dq: np.ndarray) -> np.ndarray:
    """Prefix products of the quaternions dq (n, 4): row k is dq_0 dq_1 ... dq_k,
    normalised, taken in log2(n) vectorised steps."""
    Q = quat_normalize(np.array(dq, dtype=float))
    shift = 1
    while shift < Q.shape[0]:
        Q[shift:] = quat_normalize(quat_mul(Q[:-shift], Q[shift:]))
        shift *= 2
    return Q


def compose_increments(
    dq: np.ndarray, dv: np.ndarray, T: float, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Compose groups of n consecutive increments into keyframe increments (no bias).

    dq (m n, 4), dv (m n, 3) -> Dq (m, 4), Dv (m, 3), Dp (m, 3), each in the frame of the
    group's first sample (module docstring). Only whole groups are used."""
    dq, dv = np.asarray(dq, dtype=float), np.asarray(dv, dtype=float)
    m = dq.shape[0] // n
    Dq = np.tile([1.0, 0.0, 0.0, 0.0], (m, 1))
    Dv, Dp = np.zeros((m, 3)), np.zeros((m, 3))
    for j in range(n):
        idx = np.arange(m) * n + j
        Rdv = rotate(Dq, dv[idx])
        Dp = Dp + T * Dv + 0.5 * T * Rdv
        Dv = Dv + Rdv
        Dq = quat_normalize(quat_mul(Dq, dq[idx]))
    return Dq, Dv, Dp


def preintegration_covariance(
    dq: np.ndarray, dv: np.ndarray, T: float, n: int, gyro_density: float, acc_density: float
) -> np.ndarray:
    """(m, 9, 9) covariance of the composed increments' errors (rotation, Dv, Dp) from white
    gyroscope and accelerometer noise of the given densities [rad/s/sqrt(Hz)],
    [m/s^2/sqrt(Hz)], propagated to first order through the composition above.

    Rotation error is a right perturbation Dq Exp(e); Dv and Dp errors are in the keyframe's
    frame. Per interval the angle noise has variance gyro_density^2 T and the velocity
    increment noise acc_density^2 T per axis."""
    dq, dv = np.asarray(dq, dtype=float), np.asarray(dv, dtype=float)
    m = dq.shape[0] // n
    Dq = np.tile([1.0, 0.0, 0.0, 0.0], (m, 1))
    S = np.zeros((m, 9, 9))
    qa, qv = gyro_density**2 * T, acc_density**2 * T
    eye = np.eye(3)
    for j in range(n):
        idx = np.arange(m) * n + j
        R = quat_to_rotmat(Dq)  # (m, 3, 3)
        dR = quat_to_rotmat(dq[idx])
        A = np.zeros((m, 9, 9))
        A[:, 0:3, 0:3] = np.transpose(dR, (0, 2, 1))
        skew = _skew(dv[idx])
        A[:, 3:6, 0:3] = -R @ skew
        A[:, 3:6, 3:6] = eye
        A[:, 6:9, 0:3] = -0.5 * T * (R @ skew)
        A[:, 6:9, 3:6] = T * eye
        A[:, 6:9, 6:9] = eye
        B = np.zeros((m, 9, 6))
        B[:, 0:3, 0:3] = eye
        B[:, 3:6, 3:6] = R
        B[:, 6:9, 3:6] = 0.5 * T * R
        Qn = np.diag([qa] * 3 + [qv] * 3)
        S = A @ S @ np.transpose(A, (0, 2, 1)) + B @ Qn @ np.transpose(B, (0, 2, 1))
        Dq = quat_normalize(quat_mul(Dq, dq[idx]))
    return S


def _skew(v: np.ndarray) -> np.ndarray:
    x, y, z = np.moveaxis(np.asarray(v, dtype=float), -1, 0)
    o = np.zeros_like(x)
    return np.stack(
        [np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], axis=-2
    )


# --------------------------------------------------------------------------- pose odometry
def dead_reckon_pose(
    U: np.ndarray,
    p0: np.ndarray,
    q0: np.ndarray,
    bias_p: np.ndarray | None = None,
    bias_w: np.ndarray | None = None,
    dt: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) positions and (N, 4) unit quaternions from (N-1, 7) increments (dp, dq), with
    optional biases removed: dp - b_p and dq exp(-b_w dt)."""
    U = np.asarray(U, dtype=float)
    n = U.shape[0] + 1
    dq = quat_normalize(U[:, 3:7])
    if bias_w is not None and np.any(bias_w):
        h = np.ones(n - 1) if dt is None else np.asarray(dt, dtype=float)
        dq = quat_mul(dq, quat_exp(-h[:, None] * np.asarray(bias_w, float).reshape(1, 3)))
    dp = U[:, 0:3] - (0.0 if bias_p is None else np.asarray(bias_p, float).reshape(1, 3))
    Q = np.empty((n, 4))
    Q[0] = quat_normalize(np.asarray(q0, dtype=float))
    for k in range(n - 1):
        Q[k + 1] = quat_mul(Q[k], dq[k])
    Q = quat_normalize(Q)
    P = np.vstack([np.asarray(p0, float).reshape(1, 3), np.zeros((n - 1, 3))])
    P[1:] = P[0] + np.cumsum(rotate(Q[:-1], dp), axis=0)
    return P, Q


def turn_heading(
    P: np.ndarray, Q: np.ndarray, t: np.ndarray, rate: float, V: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A trajectory (positions P, orientations Q body to local, velocities V) with a
    heading-rate ``rate`` [rad/s] about the vertical (z) removed: the orientation and
    velocity at time t turned by -rate (t - t[0]), each step's displacement by the turn at
    its start, from P[0]. For pose odometry dead-reckoned from body-frame increments this
    is exact: the same increments from the turned orientations."""
    theta = -rate * (np.asarray(t, dtype=float) - float(t[0]))
    c, s = np.cos(theta), np.sin(theta)

    def turned(v: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
        return np.column_stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]])

    P = np.asarray(P, dtype=float)
    steps = turned(np.diff(P, axis=0), c[:-1], s[:-1])
    P_t = np.vstack([P[:1], P[:1] + np.cumsum(steps, axis=0)])
    half = 0.5 * theta
    qz = np.column_stack([np.cos(half), np.zeros_like(half), np.zeros_like(half), np.sin(half)])
    Q_t = quat_normalize(quat_mul(qz, np.asarray(Q, dtype=float)))
    return P_t, Q_t, None if V is None else turned(np.asarray(V, dtype=float), c, s)


def pose_increments(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """(N-1, 7) increments (dp in the earlier body frame, dq) of a trajectory: the inverse
    of :func:`dead_reckon_pose`."""
    Q = quat_normalize(np.asarray(Q, dtype=float))
    dp = rotate(quat_conj(Q[:-1]), np.diff(np.asarray(P, float), axis=0))
    dq = quat_mul(quat_conj(Q[:-1]), Q[1:])
    dq = dq * np.where(dq[:, :1] < 0, -1.0, 1.0)
    return np.column_stack([dp, dq])


# --------------------------------------------------------------------------- CasADi
def ca_quat_mul(a: Any, b: Any) -> Any:
    """Hamilton product of two (4, 1) CasADi quaternions (w first)."""
    aw, ax, ay, az = a[0], a[1], a[2], a[3]
    bw, bx, by, bz = b[0], b[1], b[2], b[3]
    return ca.vertcat(
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def ca_quat_conj(q: Any) -> Any:
    return ca.vertcat(q[0], -q[1], -q[2], -q[3])


def ca_rotmat(q: Any) -> Any:
    """(3, 3) rotation matrix of a (4, 1) CasADi quaternion of any non-zero norm: the
    homogeneous form divided by |q|^2, a smooth rational function."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    n2 = w * w + x * x + y * y + z * z
    R = ca.vertcat(
        ca.horzcat(w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)),
        ca.horzcat(2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)),
        ca.horzcat(2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z),
    )
    return R / n2


def ca_gibbs(delta: Any) -> Any:
    """Unnormalised quaternion (1, delta / 2) of a Gibbs vector; use with ca_rotmat or
    normalise (see :func:`gibbs_quat`)."""
    return ca.vertcat(1, 0.5 * delta)


def ca_quat_exp_small(phi: Any) -> Any:
    """Exp of a small rotation vector as a polynomial (no square root, so derivatives exist
    at 0): cos(t/2) and sin(t/2)/t by their Taylor series to t^6, exact to double precision
    for |phi| < 1e-2 (bias times one IMU interval is far smaller)."""
    t2 = ca.dot(phi, phi)
    w = 1 - t2 / 8 + t2**2 / 384 - t2**3 / 46080
    s = 0.5 - t2 / 48 + t2**2 / 3840 - t2**3 / 645120
    return ca.vertcat(w, s * phi)


def ca_rotation_residual(q: Any) -> Any:
    """sin(angle) * axis of the rotation q (any norm): 2 w v / |q|^2. Smooth, independent of
    the sign of q, equal to the rotation vector to second order."""
    return 2 * q[0] * q[1:4] / ca.dot(q, q)


def preintegration_function(n: int, T: float) -> ca.Function:
    """SX function (b_w (3), b_a (3), dq (4 n), dv (3 n)) -> (Dq (4), Dv (3), Dp (3)): the
    bias-compensated composition of n increments (module docstring), exact in the biases."""
    b_w, b_a = ca.SX.sym("b_w", 3), ca.SX.sym("b_a", 3)
    dq, dv = ca.SX.sym("dq", 4 * n), ca.SX.sym("dv", 3 * n)
    corr = ca_quat_exp_small(-T * b_w)
    Dq = ca.SX([1, 0, 0, 0])
    Dv, Dp = ca.SX.zeros(3), ca.SX.zeros(3)
    for j in range(n):
        a = dv[3 * j : 3 * j + 3] - T * b_a
        Ra = ca.mtimes(ca_rotmat(Dq), a)
        Dp = Dp + T * Dv + 0.5 * T * Ra
        Dv = Dv + Ra
        Dq = ca_quat_mul(ca_quat_mul(Dq, dq[4 * j : 4 * j + 4]), corr)
    return ca.Function(
        "preintegration",
        [b_w, b_a, dq, dv],
        [Dq, Dv, Dp],
        ["b_w", "b_a", "dq", "dv"],
        ["Dq", "Dv", "Dp"],
    )


def strapdown_step_function(T: float) -> ca.Function:
    """SX function (p, v, q, dq, dv, b_w, b_a) -> (p+, v+, q+): one step of Eq. 1 with the
    biases removed (the CasADi counterpart of :func:`strapdown`)."""
    p, v, b_w, b_a = (ca.SX.sym(s, 3) for s in ("p", "v", "b_w", "b_a"))
    q, dq, dv = ca.SX.sym("q", 4), ca.SX.sym("dq", 4), ca.SX.sym("dv", 3)
    g = ca.DM(gravity_vector())
    Rdv = ca.mtimes(ca_rotmat(q), dv - T * b_a)
    p1 = p + T * v + 0.5 * T * Rdv + 0.5 * T**2 * g
    v1 = v + Rdv + T * g
    q1 = ca_quat_mul(ca_quat_mul(q, dq), ca_quat_exp_small(-T * b_w))
    return ca.Function("strapdown_step", [p, v, q, dq, dv, b_w, b_a], [p1, v1, q1])
