"""Quaternions and strapdown integration against plain numpy / scipy references."""

import casadi as ca
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from casmag import strapdown as sd

G = np.array([0.0, 0.0, -sd.GRAVITY])


def _random_quats(rng, n):
    q = rng.standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _scipy(q):
    """scipy Rotation of w-first quaternions."""
    return Rotation.from_quat(np.column_stack([q[..., 1:], q[..., :1]]))


def _reference_strapdown(p0, v0, R0, rotvecs, dv, T, b_w, b_a):
    """Eq. 1 with rotation matrices and scipy's exponential map, bias removed per step."""
    p, v, R = np.array(p0, float), np.array(v0, float), np.array(R0, float)
    out = [(p.copy(), v.copy(), R.copy())]
    for k in range(len(dv)):
        dR = Rotation.from_rotvec(rotvecs[k]).as_matrix()
        corr = Rotation.from_rotvec(-T * b_w).as_matrix()
        a = dv[k] - T * b_a
        p = p + T * v + R @ (0.5 * T * a) + 0.5 * T**2 * G
        v = v + R @ a + T * G
        R = R @ dR @ corr
        out.append((p.copy(), v.copy(), R.copy()))
    return out


def test_quaternion_algebra_matches_scipy():
    rng = np.random.default_rng(0)
    a, b = _random_quats(rng, 50), _random_quats(rng, 50)
    ab = sd.quat_mul(a, b)
    np.testing.assert_allclose(
        sd.quat_to_rotmat(ab), (_scipy(a) * _scipy(b)).as_matrix(), atol=1e-12
    )
    np.testing.assert_allclose(sd.quat_to_rotmat(a), _scipy(a).as_matrix(), atol=1e-12)
    phi = rng.standard_normal((50, 3))
    np.testing.assert_allclose(
        sd.quat_to_rotmat(sd.quat_exp(phi)), Rotation.from_rotvec(phi).as_matrix(), atol=1e-12
    )
    small = 1e-6 * rng.standard_normal((5, 3))
    np.testing.assert_allclose(sd.quat_log(sd.quat_exp(small)), small, rtol=1e-9, atol=1e-18)
    mid = 0.5 * rng.standard_normal((20, 3))
    np.testing.assert_allclose(sd.quat_log(sd.quat_exp(mid)), mid, atol=1e-12)
    v = rng.standard_normal((50, 3))
    np.testing.assert_allclose(sd.rotate(a, v), _scipy(a).apply(v), atol=1e-12)
    np.testing.assert_allclose(sd.quat_angle(a, ab), _scipy(b).magnitude(), atol=1e-9)
    eul = np.column_stack([rng.uniform(-1, 1, 20), rng.uniform(-1, 1, 20), rng.uniform(-3, 3, 20)])
    q = sd.quat_from_euler(eul[:, 0], eul[:, 1], eul[:, 2])
    np.testing.assert_allclose(
        sd.quat_to_rotmat(q), Rotation.from_euler("ZYX", eul[:, ::-1]).as_matrix(), atol=1e-12
    )
    np.testing.assert_allclose(sd.euler_from_quat(q), eul, atol=1e-12)


def test_casadi_quaternions_match_numpy():
    rng = np.random.default_rng(1)
    a, b = _random_quats(rng, 1)[0], _random_quats(rng, 1)[0]
    np.testing.assert_allclose(
        np.asarray(sd.ca_quat_mul(ca.DM(a), ca.DM(b))).ravel(), sd.quat_mul(a, b), atol=1e-14
    )
    # The homogeneous rotation matrix ignores the quaternion's norm.
    np.testing.assert_allclose(
        np.asarray(sd.ca_rotmat(ca.DM(3.7 * a))), sd.quat_to_rotmat(a), atol=1e-14
    )
    phi = 1e-3 * rng.standard_normal(3)
    np.testing.assert_allclose(
        np.asarray(sd.ca_quat_exp_small(ca.DM(phi))).ravel(), sd.quat_exp(phi), atol=1e-17
    )
    delta = rng.standard_normal(3)
    np.testing.assert_allclose(
        np.asarray(sd.ca_rotmat(sd.ca_gibbs(ca.DM(delta)))),
        sd.quat_to_rotmat(sd.gibbs_quat(delta)),
        atol=1e-14,
    )
    # The rotation residual is sin(angle) * axis, for either sign of q.
    rv = 0.3 * rng.standard_normal(3)
    q = sd.quat_exp(rv)
    angle = np.linalg.norm(rv)
    for sign in (1.0, -1.0):
        res = np.asarray(sd.ca_rotation_residual(ca.DM(sign * 2.0 * q))).ravel()
        np.testing.assert_allclose(res, np.sin(angle) * rv / angle, atol=1e-14)


@pytest.fixture
def motion():
    rng = np.random.default_rng(2)
    n, T = 60, 0.01
    rotvecs = 0.02 * rng.standard_normal((n, 3))  # up to ~1 rad/s
    dv = T * (np.array([0.0, 0.0, sd.GRAVITY]) + 0.5 * rng.standard_normal((n, 3)))
    q0 = sd.quat_normalize(np.array([0.9, 0.1, -0.2, 0.3]))
    return {
        "n": n,
        "T": T,
        "rotvecs": rotvecs,
        "dq": sd.quat_exp(rotvecs),
        "dv": dv,
        "p0": np.array([0.1, -0.2, 0.3]),
        "v0": np.array([0.05, 0.0, -0.02]),
        "q0": q0,
        "b_w": np.array([0.01, -0.02, 0.03]),
        "b_a": np.array([0.05, 0.02, -0.04]),
    }


def test_strapdown_matches_rotation_matrix_reference(motion):
    m = motion
    P, V, Q = sd.strapdown(m["p0"], m["v0"], m["q0"], m["dq"], m["dv"], m["T"], m["b_w"], m["b_a"])
    ref = _reference_strapdown(
        m["p0"], m["v0"], sd.quat_to_rotmat(m["q0"]), m["rotvecs"], m["dv"], m["T"],
        m["b_w"], m["b_a"],
    )  # fmt: skip
    np.testing.assert_allclose(P, np.array([r[0] for r in ref]), atol=1e-12)
    np.testing.assert_allclose(V, np.array([r[1] for r in ref]), atol=1e-12)
    np.testing.assert_allclose(sd.quat_to_rotmat(Q), np.array([r[2] for r in ref]), atol=1e-12)


def test_casadi_strapdown_step_matches_numpy(motion):
    m = motion
    step = sd.strapdown_step_function(m["T"])
    P, V, Q = sd.strapdown(m["p0"], m["v0"], m["q0"], m["dq"], m["dv"], m["T"], m["b_w"], m["b_a"])
    p, v, q = m["p0"], m["v0"], m["q0"]
    for k in range(m["n"]):
        p, v, q = (
            np.asarray(a).ravel() for a in step(p, v, q, m["dq"][k], m["dv"][k], m["b_w"], m["b_a"])
        )
    np.testing.assert_allclose(p, P[-1], atol=1e-12)
    np.testing.assert_allclose(v, V[-1], atol=1e-12)
    assert sd.quat_angle(q, Q[-1]) < 1e-12


def test_composed_increments_equal_n_steps(motion):
    """Composition of n increments, applied at a keyframe, equals n steps of Eq. 1; the
    CasADi composition with biases equals numpy strapdown with the biases removed."""
    m, n = motion, 10
    dq, dv, T = m["dq"], m["dv"], m["T"]
    Dq, Dv, Dp = sd.compose_increments(dq, dv, T, n)
    P, V, Q = sd.strapdown(m["p0"], m["v0"], m["q0"], dq, dv, T)
    dt = n * T
    for k in range(len(Dq)):
        i, j = k * n, (k + 1) * n
        R = sd.quat_to_rotmat(Q[i])
        np.testing.assert_allclose(P[j], P[i] + dt * V[i] + 0.5 * dt**2 * G + R @ Dp[k], atol=1e-12)
        np.testing.assert_allclose(V[j], V[i] + dt * G + R @ Dv[k], atol=1e-12)
        assert sd.quat_angle(Q[j], sd.quat_mul(Q[i], Dq[k])) < 1e-12
    pre = sd.preintegration_function(n, T)
    Pb, Vb, Qb = sd.strapdown(m["p0"], m["v0"], m["q0"], dq, dv, T, m["b_w"], m["b_a"])
    for k in range(len(Dq)):
        i, j = k * n, (k + 1) * n
        out = pre(m["b_w"], m["b_a"], dq[i:j].ravel(), dv[i:j].ravel())
        Dqb, Dvb, Dpb = (np.asarray(a).ravel() for a in out)
        R = sd.quat_to_rotmat(Qb[i])
        np.testing.assert_allclose(
            Pb[j], Pb[i] + dt * Vb[i] + 0.5 * dt**2 * G + R @ Dpb, atol=1e-12
        )
        np.testing.assert_allclose(Vb[j], Vb[i] + dt * G + R @ Dvb, atol=1e-12)
        assert sd.quat_angle(Qb[j], sd.quat_mul(Qb[i], Dqb)) < 1e-12


def test_preintegration_covariance_matches_monte_carlo(motion):
    m, n = motion, 20
    rng = np.random.default_rng(3)
    T, gd, ad = m["T"], 0.01, 0.02
    dq, dv = m["dq"][:n], m["dv"][:n]
    Dq0, Dv0, Dp0 = sd.compose_increments(dq, dv, T, n)
    S = sd.preintegration_covariance(dq, dv, T, n, gd, ad)[0]
    reps = 3000  # Monte Carlo draws, composed all at once as groups of n increments
    dqn = sd.quat_mul(
        np.tile(dq, (reps, 1)), sd.quat_exp(gd * np.sqrt(T) * rng.standard_normal((reps * n, 3)))
    )
    dvn = np.tile(dv, (reps, 1)) + ad * np.sqrt(T) * rng.standard_normal((reps * n, 3))
    Dq, Dv, Dp = sd.compose_increments(dqn, dvn, T, n)
    e_r = sd.quat_log(sd.quat_mul(sd.quat_conj(Dq0[0]), Dq))
    errs = np.column_stack([e_r, Dv - Dv0[0], Dp - Dp0[0]])
    C = np.cov(np.array(errs).T)
    sd_model, sd_mc = np.sqrt(np.diag(S)), np.sqrt(np.diag(C))
    np.testing.assert_allclose(sd_mc, sd_model, rtol=0.1)
    # Correlations too (velocity-position and rotation-velocity couplings).
    corr = lambda A: A / np.outer(np.sqrt(np.diag(A)), np.sqrt(np.diag(A)))  # noqa: E731
    np.testing.assert_allclose(corr(C), corr(S), atol=0.1)


def test_turn_heading_removes_a_vertical_rate_from_a_pose_dead_reckoning():
    """Turned by a heading rate about the vertical, a pose dead reckoning is the same
    body-frame displacements from the turned orientations (exact), its first pose kept, its
    last orientation turned by rate x duration about z, velocities turned with it."""
    rng = np.random.default_rng(4)
    n = 25
    dq = sd.quat_exp(rng.normal(0.0, 0.05, (n - 1, 3)))
    U = np.column_stack([rng.normal(0.1, 0.05, (n - 1, 3)), dq])
    t = np.concatenate([[2.0], 2.0 + np.cumsum(np.full(n - 1, 0.5))])
    P, Q = sd.dead_reckon_pose(
        U, np.array([1.0, 2.0, 3.0]), sd.quat_exp(np.array([[0.1, -0.2, 0.3]]))[0]
    )
    V = rng.standard_normal((n, 3))
    rate = 0.03
    Pt, Qt, Vt = sd.turn_heading(P, Q, t, rate, V)
    np.testing.assert_allclose(np.diff(Pt, axis=0), sd.rotate(Qt[:-1], U[:, :3]), atol=1e-12)
    np.testing.assert_array_equal(Pt[0], P[0])
    turn = sd.quat_mul(Qt[-1:], sd.quat_conj(Q[-1:]))[0]
    np.testing.assert_allclose(turn, [np.cos(-rate * 6.0), 0, 0, np.sin(-rate * 6.0)], atol=1e-12)
    np.testing.assert_allclose(Vt[:, 2], V[:, 2])
    np.testing.assert_allclose(np.linalg.norm(Vt, axis=1), np.linalg.norm(V, axis=1))
