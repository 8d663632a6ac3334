"""Tightly-coupled IMU and magnetometer GP-SLAM (paper Eq. 1-3 and 6): the IMU motion model
(:class:`ImuMotion`, a plug-in of casmag.model.builder), its keyframes and averaged
magnetometer. The staged solve is casmag.solver.imu.

IMU model. States at keyframes k = 0..K-1 (every n-th IMU sample): position p_k, velocity
v_k, orientation q_k = qbar_k (1, d_k / 2) / |.| with a nominal qbar_k (a parameter) and a
Gibbs vector d_k (the unknown; smooth, no norm constraint needed), gyroscope and
accelerometer biases b_w, b_a (per keyframe for the random walk of Eq. 2, or one constant
pair). Named cost blocks (negative log-densities):

- ``imu``: 0.5 sum_k |L_k^-1 e_k|^2, e_k = (rotation, velocity, position) residual of the
  composed increments between keyframes (``casmag.strapdown``); L_k the Cholesky factor of
  the composed increments' noise covariance. Error state: the unknowns are corrections
  dP, dV, D to a nominal trajectory (positions PNOM + dP, velocities VNOM + dV,
  orientations qnom (1, D / 2)), and the residual's large terms (gravity, the nominal's
  own increments) are formed once per solve from the nominal
  (:func:`imu_nominal_terms`), first order in the biases' change from the nominal ones.
  Every solve re-centres (casmag.solver.imu): once the biases have converged, so the
  result is exact in them, and whenever IPOPT stops making measurable progress.
- ``bias_walk``: 0.5 sum_k |(b_{k+1} - b_k) / (s sqrt(dt))|^2 for both biases (Eq. 2).
- ``bias_prior``: zero-mean prior on the first biases (turn-on bias range).
- ``initial_state``: known start position, at rest, levelled tilt, known heading.
- ``zero_position``: optional weak prior |p_k - p_0|^2 / sigma^2 on every keyframe (the
  paper's "within a one metre sphere").
- ``magnetometer``: 0.5 sum_k |(y_k - R_k^T (m(p_k) + c)) / sigma_m|^2 (Eq. 3) with a 3-D
  reduced-rank map (weights w, constant field c) or the exact GP (field values at keyframes).
- ``gp_prior``, ``constant_field_prior``: the map's priors (Eq. 6); the reduced-rank
  map's unknowns are whitened weights V (weights sqrt(S) V), so ``gp_prior`` is 0.5 |V|^2.

Hessian: Gauss-Newton for the imu and magnetometer residuals (the magnetometer's dense map
blocks formed with numpy in casmag.model.rotated.RotatedFieldGaussNewton, optionally with
its second-order terms, which make it exact), CasADi's exact Hessian for all other blocks.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import casadi as ca
import numpy as np
import scipy.linalg
import scipy.sparse

from casmag import strapdown as sd
from casmag.data.imusim import ImuData
from casmag.gp.reduced_rank import HilbertBasis, cached_basis
from casmag.model.builder import (
    FieldModel,
    LoopClosures,
    MotionModel,
    NoField,
    Pose,
    Rotation,
    cached_slam,
)
from casmag.model.field import ExactField, ReducedRankField, WindowField
from casmag.model.knots import Knots
from casmag.model.rotated import (
    imu_rotation_function,
)
from casmag.nlp import NLP, NLPBuilder
from casmag.problem.spec import SolverSpec


# --------------------------------------------------------------------------- IMU NLP
@dataclass(frozen=True)
class ImuStructure:
    """Everything that changes the symbolic IMU problem (and so needs a new build)."""

    K: int  # keyframes
    n: int  # IMU intervals per keyframe interval
    T: float  # IMU interval [s]
    bias: str  # "random_walk" or "constant"
    zero_position: bool
    form: str  # "none", "reduced_rank", "exact"
    kernel: str
    basis: tuple | None  # reduced rank: (center, half_width, num_basis)
    jitter: float
    solver: str  # SolverSpec as JSON
    imu_hessian: str = "gauss-newton"  # or "exact": CasADi's Hessian of the imu block
    zero_centre: str = "start"  # or "free": the zero-position sphere's centre is estimated
    closures: tuple[tuple[int, int], ...] = ()  # form none: loop-closure pairs (LoopClosures)
    #: The map under a Gaussian prior (``map_mean``, ``map_precision``) in place of the GP
    #: prior: the one carried from earlier sliding windows, or a saved map's posterior
    #: (casmag.solver.staged.PriorMap).
    window: bool = False
    anchored: bool = False  # a sliding window's first state under a prior (ImuMotion)
    #: The first keyframe of each session (ImuMotion ``starts``), cut to those below K.
    starts: tuple[int, ...] = (0,)

    def __post_init__(self) -> None:
        object.__setattr__(self, "starts", tuple(int(a) for a in self.starts if a < self.K))

    def hilbert_basis(self) -> HilbertBasis:
        return cached_basis(self.basis)


def _rt_minus_identity(v: Any, y: Any) -> Any:
    """(R^T - I) y for the rotation R of the quaternion (1, v) (any v), without forming
    R - I from R (no cancellation for small v): R^T = I + 2 / (1 + |v|^2) (-[v]x + [v]x^2)."""
    cy = ca.cross(v, y)
    return 2.0 / (1.0 + ca.dot(v, v)) * (-cy + ca.cross(v, cy))


def imu_residual_function() -> ca.Function:
    """SX function of one keyframe interval -> whitened residual (9,), in error state about a
    nominal trajectory and nominal biases (:func:`imu_nominal_terms`): inputs (dp, dv, d,
    dp1, dv1, d1, b_w, b_a, bbar (6), y (6), e0 (6), jb (54), qres (4), rrel_t (9), rnom (9),
    linv (81), dt).

    Positions p = pnom + dp, velocities v = vnom + dv and orientations R = Rnom R(1, d / 2)
    at both ends. y = (Rnom^T (vnom1 - vnom - dt g), Rnom^T (pnom1 - pnom - dt vnom -
    dt^2 g / 2)) and e0 = y - (Dv, Dp) at the nominal biases bbar, jb the Jacobian of the
    preintegrated (rotation, Dv, Dp) in the biases there (first order in b - bbar, which the
    caller re-centres to zero), qres = Dq^-1 qrel_nom, rrel_t = R(qrel_nom)^T. Every large
    term of the residual (gravity and the nominal's own increments: 0.2 m and 2 m/s over a
    0.2 s interval) is formed once, in numpy, from the nominal; the unknowns enter only
    through corrections. Formed from absolute states, the gradient carried rounding noise of
    about eps |g dt^2| lambda_max (lambda_max up to 6e11 for a precise IMU at 5 Hz keyframes:
    measured 1e-5 to 9e-5 at the optimum of a 12 cm rectangle, above IPOPT's tolerance)."""
    names = ("dp", "dv", "d", "dp1", "dv1", "d1", "b_w", "b_a")
    dp, dv, d, dp1, dv1, d1, bw, ba = (ca.SX.sym(s, 3) for s in names)
    bbar, y, e0 = ca.SX.sym("bbar", 6), ca.SX.sym("y", 6), ca.SX.sym("e0", 6)
    jb, qres = ca.SX.sym("jb", 54), ca.SX.sym("qres", 4)
    rrel_t, rnom, linv = ca.SX.sym("rrel_t", 9), ca.SX.sym("rnom", 9), ca.SX.sym("linv", 81)
    dt = ca.SX.sym("dt")
    J = ca.reshape(jb, 9, 6)
    db = ca.vertcat(bw, ba) - bbar
    Rn_t = ca.reshape(rnom, 3, 3).T
    half = 0.5 * d
    z_v = ca.mtimes(Rn_t, dv1 - dv)
    z_p = ca.mtimes(Rn_t, dp1 - dp - dt * dv)
    e_v = _rt_minus_identity(half, y[0:3] + z_v) + z_v + e0[0:3] - ca.mtimes(J[3:6, :], db)
    e_p = _rt_minus_identity(half, y[3:6] + z_p) + z_p + e0[3:6] - ca.mtimes(J[6:9, :], db)
    phi = ca.mtimes(J[0:3, :], db)
    back = ca.mtimes(ca.reshape(rrel_t, 3, 3), half)  # qrel^-1 (d / 2) qrel
    qe = sd.ca_quat_mul(
        sd.ca_quat_mul(ca.vertcat(1, -0.5 * phi), qres),
        sd.ca_quat_mul(ca.vertcat(1, -back), sd.ca_gibbs(d1)),
    )
    e_r = sd.ca_rotation_residual(qe)
    r = ca.mtimes(ca.reshape(linv, 9, 9), ca.vertcat(e_r, e_v, e_p))
    inputs = [dp, dv, d, dp1, dv1, d1, bw, ba, bbar, y, e0, jb, qres, rrel_t, rnom, linv, dt]
    return ca.Function("imu_residual", inputs, [r])


@lru_cache(maxsize=8)
def imu_nominal_function(n: int, T: float) -> ca.Function:
    """SX function of one interval at given biases: (b_w, b_a, dq (4n), dv (3n)) -> (Dq (4),
    Dv (3), Dp (3), J (54): the Jacobian (9 x 6, column-major) of (rotation of Dq(b)
    relative to Dq(bbar), Dv, Dp) in (b_w, b_a) at bbar = the given biases)."""
    pre = sd.preintegration_function(n, T)
    bw, ba = ca.SX.sym("b_w", 3), ca.SX.sym("b_a", 3)
    dq, dv, ref = ca.SX.sym("dq", 4 * n), ca.SX.sym("dv", 3 * n), ca.SX.sym("ref", 4)
    Dq, Dv, Dp = pre(bw, ba, dq, dv)
    phi = sd.ca_rotation_residual(sd.ca_quat_mul(sd.ca_quat_conj(ref), Dq))
    J = ca.jacobian(ca.vertcat(phi, Dv, Dp), ca.vertcat(bw, ba))
    J = ca.substitute(J, ref, Dq)
    return ca.Function("imu_nominal", [bw, ba, dq, dv], [Dq, Dv, Dp, ca.vec(J)])


def imu_nominal_terms(
    kf: Keyframes,
    n: int,
    T: float,
    P: np.ndarray,
    V: np.ndarray,
    Q: np.ndarray,
    BW: np.ndarray,
    BA: np.ndarray,
) -> dict[str, np.ndarray]:
    """The parameters of :func:`imu_residual_function` per interval (K-1 rows) for the
    nominal trajectory (P, V, Q at the K keyframes) and nominal biases BW, BA (one row, or
    one per keyframe): BBAR, IMU_Y, IMU_E0, IMU_J, QRES, RREL_T, plus RNOM (K, 9)."""  # fmt: skip
    K = P.shape[0]
    dt = n * T
    g = sd.gravity_vector()
    R = sd.quat_to_rotmat(Q)  # (K, 3, 3)
    Rt = np.transpose(R[:-1], (0, 2, 1))
    yv = np.einsum("kij,kj->ki", Rt, V[1:] - V[:-1] - dt * g)
    yp = np.einsum("kij,kj->ki", Rt, P[1:] - P[:-1] - dt * V[:-1] - 0.5 * dt**2 * g)
    bw = per_keyframe(BW, kf.starts, K)[:-1]
    ba = per_keyframe(BA, kf.starts, K)[:-1]
    f = imu_nominal_function(n, T).map(K - 1, "serial")
    Dq, Dv, Dp, J = (np.asarray(v).T for v in f(bw.T, ba.T, kf.DQ.T, kf.DV.T))
    qrel = sd.quat_mul(sd.quat_conj(Q[:-1]), Q[1:])
    rrel_t = sd.quat_to_rotmat(qrel)  # R(qrel)^T column-major = R(qrel) row-major
    return {
        "BBAR": np.hstack([bw, ba]),
        "IMU_Y": np.hstack([yv, yp]),
        "IMU_E0": np.hstack([yv - Dv, yp - Dp]),
        "IMU_J": J,
        "QRES": sd.quat_mul(sd.quat_conj(Dq), qrel),
        "RREL_T": rrel_t.reshape(K - 1, 9),
        "RNOM": R.transpose(0, 2, 1).reshape(K, 9),
        "QNOM0": Q[list(kf.starts)],
    }


def per_keyframe(b: np.ndarray, starts: tuple[int, ...], K: int) -> np.ndarray:
    """Biases (rows of 3) at each of K keyframes: ``b`` has one row per keyframe (a random
    walk) or one per session (constant biases; ``starts``: each session's first keyframe,
    every session at least 2 keyframes long, so the two cannot be confused)."""
    b = np.asarray(b, dtype=float).reshape(-1, 3)
    if b.shape[0] == K:
        return b
    if b.shape[0] != len(starts):
        raise ValueError(f"biases: {K} or {len(starts)} rows, got {b.shape[0]}")
    return np.repeat(b, np.diff([*starts, K]), axis=0)


def session_of(starts: tuple[int, ...], rows: Any) -> list[int]:
    """The session of each keyframe (or interval from it) in ``rows``."""
    return [int(v) for v in np.searchsorted(np.asarray(starts), np.asarray(rows), "right") - 1]


#: IPOPT's ``tiny_step_tol`` for the IMU model's solves (IPOPT's default is ten machine
#: epsilons): a step below this fraction of 1 + |x| in every unknown is taken whole, without
#: a line search. The unknowns are corrections about the nominal (m, m/s, rad), the biases
#: (rad/s, m/s^2) and the map's weights, so such a step is below a nanometre or a
#: nanoradian, under what the objective resolves in double precision. Measured on the
#: noise-free rectangle of the tests (tests/solver/test_imu.py): the second GP-SLAM pass
#: reached a point where the dual infeasibility stayed at 2.5e-5 (tol 1e-5) and the line
#: search cut every 1e-10 step by 2^-17 to 2^-28 (the objective unchanged in double
#: precision); with one BLAS thread it then took 34 iterations, with two 13. Taken whole,
#: the step ends the solve: 13 iterations with either, the largest position error the same
#: to 1e-14 m. On the problems/imu scenarios (seeds 1-5) nine runs solved again with
#: IPOPT's own value gave the same iterations and estimates.
IMU_TINY_STEP = 1e-9


@dataclass(frozen=True)
class ImuMotion(MotionModel):
    """The IMU model at K keyframes, n IMU intervals of T s apart: error-state unknowns
    dP, dV, D about a nominal trajectory, biases BW, BA (per keyframe or constant), the
    blocks ``imu`` (a residual: Gauss-Newton, or CasADi's exact Hessian with
    ``imu_hessian: exact``), ``bias_walk``, ``bias_prior``, ``initial_state`` and
    ``zero_position``; the field is read in the body frame R = Rnom R(1, D / 2).

    ``starts``: several sessions of one field (the first keyframe of each), one map: no
    ``imu`` residual or bias walk from a session's last keyframe to the next one's first,
    and each session has its own initial state (rows of ``p0``, ``v0``, ``q0``, ``QNOM0``),
    constant biases (rows of BW, BA) or the bias prior on its first keyframe's, and its own
    zero-position centre (its ``p0``; ``zero_centre`` ``free`` needs one session).

    ``anchored`` (a window of the sliding windows, casmag.solver.imu.ImuStaged): the first
    state's prior is 0.5 r^T I r on its position, velocity and (world-frame) rotation errors
    r with the precision ``anchor_info`` (9 x 9: the inverse of the previous window's
    Laplace covariance there, correlations kept), and the zero-position sphere's centre is
    the parameter ``centre``."""

    K: int
    n: int
    T: float
    bias: str = "random_walk"
    zero_position: bool = False
    zero_centre: str = "start"
    imu_hessian: str = "gauss-newton"
    anchored: bool = False
    starts: tuple[int, ...] = (0,)
    name = "imu"

    def solver(self, solver: SolverSpec) -> SolverSpec:
        """IPOPT's ``tiny_step_tol`` at :data:`IMU_TINY_STEP` unless the problem sets it."""
        if "tiny_step_tol" in solver.ipopt:
            return solver
        return solver.model_copy(update={"ipopt": {**solver.ipopt, "tiny_step_tol": IMU_TINY_STEP}})

    def declare(self, b: NLPBuilder) -> Pose:
        K, n, starts = self.K, self.n, self.starts
        S = len(starts)
        if S > 1 and (self.anchored or (self.zero_position and self.zero_centre == "free")):
            raise ValueError("sliding windows and a free zero-position centre: one session")
        # The intervals within a session: [lo[i], hi[i]] (all of them for one session).
        inner = [k for k in range(K - 1) if k + 1 not in starts]
        lo: Any = slice(0, K - 1) if S == 1 else inner
        hi: Any = slice(1, K) if S == 1 else [k + 1 for k in inner]
        dP = b.variable("dP", (K, 3))
        dV = b.variable("dV", (K, 3))
        D = b.variable("D", (K, 3))
        Kb = K if self.bias == "random_walk" else S
        BW = b.variable("BW", (Kb, 3))
        BA = b.variable("BA", (Kb, 3))
        # The nominal trajectory and what the residual needs of it (imu_nominal_terms).
        RNOM = b.parameter("RNOM", (K, 9))
        PNOM = b.parameter("PNOM", (K, 3))
        VNOM = b.parameter("VNOM", (K, 3))
        nom = {
            name: b.parameter(name, (K - 1, w))
            for name, w in (
                ("BBAR", 6), ("IMU_Y", 6), ("IMU_E0", 6), ("IMU_J", 54), ("QRES", 4), ("RREL_T", 9)
            )
        }  # fmt: skip
        LINV = b.parameter("LINV", (K - 1, 81))
        p0, v0 = b.parameter("p0", (S, 3)), b.parameter("v0", (S, 3))
        if self.anchored:  # the first state's precision: anchor_info
            sig = {k: b.parameter(k, (1, 1)) for k in ("sigma_bw0", "sigma_ba0")}
        else:
            names = ("sigma_p0", "sigma_v0", "sigma_tilt", "sigma_yaw", "sigma_bw0", "sigma_ba0")
            sig = {k: b.parameter(k, (1, 1)) for k in names}
        if self.bias == "random_walk":
            BWi, BAi = BW[lo, :], BA[lo, :]
        elif S == 1:
            BWi, BAi = ca.repmat(BW, K - 1, 1), ca.repmat(BA, K - 1, 1)
        else:
            own = session_of(starts, inner)
            BWi, BAi = BW[own, :], BA[own, :]
        resid = imu_residual_function().map(K - 1 if S == 1 else len(inner), "serial")
        E = resid(
            dP[lo, :].T, dV[lo, :].T, D[lo, :].T, dP[hi, :].T, dV[hi, :].T, D[hi, :].T,
            BWi.T, BAi.T, nom["BBAR"][lo, :].T, nom["IMU_Y"][lo, :].T, nom["IMU_E0"][lo, :].T,
            nom["IMU_J"][lo, :].T, nom["QRES"][lo, :].T, nom["RREL_T"][lo, :].T,
            RNOM[lo, :].T, LINV[lo, :].T, n * self.T,
        )  # fmt: skip
        P = PNOM + dP  # absolute positions for the map and the priors (weakly curved there)
        if self.imu_hessian == "exact":
            b.cost("imu", 0.5 * ca.sumsqr(E))
        else:
            b.residual("imu", E)
        if self.bias == "random_walk":
            rw_w, rw_a = b.parameter("sigma_walk_w", (1, 1)), b.parameter("sigma_walk_a", (1, 1))
            dt = n * self.T
            b.cost(
                "bias_walk",
                0.5 * ca.sumsqr((BW[hi, :] - BW[lo, :]) / (rw_w * np.sqrt(dt)))
                + 0.5 * ca.sumsqr((BA[hi, :] - BA[lo, :]) / (rw_a * np.sqrt(dt))),
            )
        # Each session's first biases (one row per session when constant).
        first: Any = (
            0 if S == 1 else (list(starts) if self.bias == "random_walk" else list(range(S)))
        )
        b.cost(
            "bias_prior",
            0.5 * ca.sumsqr(BW[first, :] / sig["sigma_bw0"])
            + 0.5 * ca.sumsqr(BA[first, :] / sig["sigma_ba0"]),
        )
        # Error of each session's first orientation against the known one, as a small
        # rotation in the local (world) frame (tilt: x, y; yaw: z): of qnom_a (1, d_a / 2)
        # q0^-1. Against q0 itself, not the nominal, which moves to each stage's estimate.
        QNOM0, Q0 = b.parameter("QNOM0", (S, 4)), b.parameter("q0", (S, 4))
        initial = 0
        for s, a in enumerate(starts):
            eps = sd.ca_rotation_residual(
                sd.ca_quat_mul(
                    sd.ca_quat_mul(QNOM0[s, :].T, sd.ca_gibbs(D[a, :].T)),
                    sd.ca_quat_conj(Q0[s, :].T),
                )
            )
            ep = (dP[a, :] + (PNOM[a, :] - p0[s, :])).T
            ev = (dV[a, :] + (VNOM[a, :] - v0[s, :])).T
            if self.anchored:  # r = (position, velocity, rotation) error, 0.5 r^T Info r
                info = b.parameter("anchor_info", (9, 9))
                r = ca.vertcat(ep, ev, eps)
                initial += 0.5 * ca.dot(r, ca.mtimes(info, r))
            else:
                initial += (
                    0.5 * ca.sumsqr(ep / sig["sigma_p0"])
                    + 0.5 * ca.sumsqr(ev / sig["sigma_v0"])
                    + 0.5 * ca.sumsqr(eps[0:2] / sig["sigma_tilt"])
                    + 0.5 * (eps[2] / sig["sigma_yaw"]) ** 2
                )
        b.cost("initial_state", initial)
        if self.zero_position:
            sz = b.parameter("sigma_zero", (1, 1))
            if self.anchored:
                centre = ca.repmat(b.parameter("centre", (1, 3)), K, 1)
            elif self.zero_centre == "free":
                centre = ca.repmat(b.variable("zero_centre", (1, 3)), K, 1)
            elif S == 1:
                centre = ca.repmat(p0, K, 1)
            else:  # each keyframe about its session's start
                centre = p0[session_of(starts, range(K)), :]
            b.cost("zero_position", 0.5 * ca.sumsqr((P - centre) / sz))
        rotation = Rotation(imu_rotation_function(), D, "D", RNOM, "RNOM")
        return Pose(P, K, 3, "dP", "PNOM", Knots(K, 1), rotation)


def imu_field(s: ImuStructure) -> FieldModel:
    """The field model of an IMU structure: none (the IMU-only adjustment), the exact GP at
    the keyframes or the reduced-rank map, each with Earth's field as a constant (without
    it the GP prior would reward spreading the positions to decorrelate Earth's field)."""
    if s.form == "none":
        return LoopClosures(s.closures) if s.closures else NoField()
    if s.form == "exact":
        return ExactField(s.kernel, s.jitter, constant_field=True)
    if s.window:  # the map under a prior: earlier windows' or a saved map's
        return WindowField(s.kernel, s.basis, constant_field=True, metis=False)
    # MUMPS's own ordering: the IMU solves were measured with it (METIS not measured here).
    return ReducedRankField(s.kernel, s.basis, constant_field=True, metis=False)


def cached_imu_nlp(s: ImuStructure) -> NLP:
    """The built NLP for a structure, built once per process."""
    motion = ImuMotion(
        s.K, s.n, s.T, s.bias, s.zero_position, s.zero_centre, s.imu_hessian, s.anchored,
        s.starts,
    )  # fmt: skip
    return cached_slam(motion, imu_field(s), s.solver)


# --------------------------------------------------------------------------- keyframes
@dataclass
class Keyframes:
    """The data at keyframe rate: indices (K,) of the keyframe samples, DQ (K-1, 4n),
    DV (K-1, 3n) increments per interval, LINV (K-1, 81) whitening of the composed
    increments, Y (K, 3) magnetometer at keyframes (in the keyframe's body frame, averaged
    over ``samples`` samples: noise sigma_m * sigma_scale; ``share``: magnetometer samples
    per IMU sample, below 1 when a slower magnetometer was interpolated to the IMU's
    samples, casmag.data.imusim.ImuData.mag_share). Several sessions (``starts``: the
    first keyframe of each): the interval from a session's last keyframe to the next one's
    first is a stand-in (no rotation, no velocity change, unit whitening) the model does
    not read."""

    idx: np.ndarray
    DQ: np.ndarray
    DV: np.ndarray
    LINV: np.ndarray
    Y: np.ndarray
    samples: int = 1
    starts: tuple[int, ...] = (0,)
    share: float = 1.0

    @property
    def sigma_scale(self) -> float:
        """The keyframe magnetometer's noise over one sample's: 1 / sqrt(max(1, samples x
        share)). An average of ``samples`` values interpolated linearly from a magnetometer
        with ``share`` samples per IMU sample holds about samples x share of them; its
        variance is below 1 / max(1, samples x share) of one sample's (measured for
        share 0.1-0.75 and 1, 5, 11 samples: at most 0.96 of that bound)."""
        return 1.0 / float(np.sqrt(max(1.0, self.samples * self.share)))


def keyframes(
    data: ImuData, n: int, gyro_density: float, acc_density: float, samples: int = 1
) -> Keyframes:
    """Group the increments n at a time (whole groups only) and whiten their composition;
    the magnetometer at each keyframe averaged over ``samples`` (odd) samples centred on it
    (``averaged_magnetometer``). Several sessions (``data.starts``): each one's keyframes
    from its own first sample, each at least 2 (ValueError)."""
    ends = [*data.starts[1:], data.n_samples]
    parts = [
        _session_keyframes(data, a, e, n, gyro_density, acc_density, samples)
        for a, e in zip(data.starts, ends, strict=True)
    ]
    if len(parts) == 1:
        return parts[0]
    gap = {  # the stand-in interval between sessions (not read)
        "DQ": np.tile([1.0, 0.0, 0.0, 0.0], (1, n)),
        "DV": np.zeros((1, 3 * n)),
        "LINV": np.eye(9).reshape(1, 81),
    }
    rows = {
        key: np.vstack([v for kf in parts for v in (getattr(kf, key), gap[key])][:-1])
        for key in gap
    }
    sizes = [kf.idx.size for kf in parts]
    return Keyframes(
        idx=np.concatenate([kf.idx for kf in parts]),
        Y=np.vstack([kf.Y for kf in parts]),
        samples=samples,
        share=data.mag_share,
        starts=tuple(int(a) for a in np.cumsum([0, *sizes[:-1]])),
        **rows,
    )


def _session_keyframes(
    data: ImuData, a: int, e: int, n: int, gyro_density: float, acc_density: float,
    samples: int,
) -> Keyframes:  # fmt: skip
    """The keyframes of the samples [a, e) (indices into the whole data)."""
    K = (e - 1 - a) // n + 1
    if K < 2:
        raise ValueError(f"the session from sample {a}: {e - a} samples, under 2 keyframes")
    m = (K - 1) * n
    dq, dv = data.dq[a : a + m], data.dv[a : a + m]
    S = sd.preintegration_covariance(dq, dv, data.T, n, gyro_density, acc_density)
    Lc = np.linalg.cholesky(S)
    eye = np.eye(9)
    Linv = np.stack([scipy.linalg.solve_triangular(L, eye, lower=True) for L in Lc])
    idx = np.arange(K) * n
    Y = averaged_magnetometer(data.Y[a:e], data.dq[a : e - 1], idx, samples)
    return Keyframes(
        idx=idx + a,
        DQ=dq.reshape(K - 1, 4 * n),
        DV=dv.reshape(K - 1, 3 * n),
        LINV=Linv.transpose(0, 2, 1).reshape(K - 1, 81),  # column-major 9x9
        Y=Y,
        samples=samples,
        share=data.mag_share,
    )


def averaged_magnetometer(
    Y: np.ndarray, dq: np.ndarray, idx: np.ndarray, samples: int
) -> np.ndarray:
    """Magnetometer samples Y (N, 3) averaged over ``samples`` (odd) consecutive samples
    around each index in idx, each rotated into the body frame at the index by the gyro
    increments dq (N-1, 4) (R_i^T R_j, the relative rotation integrated from the gyro); the
    window is shifted to stay inside the recording. The relative rotations come from one
    cumulative gyro attitude G (G_0 = identity, G_{j+1} = G_j dq_j): R_i^T R_j = G_i^T G_j,
    so the average is G_i^T mean_j(G_j y_j)."""
    if samples == 1:
        return Y[idx].copy()
    N = Y.shape[0]
    G = np.empty((N, 4))
    G[0] = (1.0, 0.0, 0.0, 0.0)
    for j in range(N - 1):
        G[j + 1] = sd.quat_mul(G[j : j + 1], dq[j : j + 1])[0]
    G /= np.linalg.norm(G, axis=1, keepdims=True)
    Z = np.vstack([np.zeros((1, 3)), np.cumsum(sd.rotate(G, Y), axis=0)])
    h = samples // 2
    lo = np.clip(idx - h, 0, max(0, N - samples))
    hi = np.minimum(lo + samples, N)
    mean = (Z[hi] - Z[lo]) / (hi - lo)[:, None]
    return sd.rotate(sd.quat_conj(G[idx]), mean)


def prefix_keyframes(kf: Keyframes, K: int) -> Keyframes:
    """The first K keyframes' data."""
    return window_keyframes(kf, 0, K)


def window_keyframes(kf: Keyframes, a: int, K: int) -> Keyframes:
    """The data of the K keyframes from keyframe a (the sessions that start there)."""
    return Keyframes(
        idx=kf.idx[a : a + K],
        DQ=kf.DQ[a : a + K - 1],
        DV=kf.DV[a : a + K - 1],
        LINV=kf.LINV[a : a + K - 1],
        Y=kf.Y[a : a + K],
        samples=kf.samples,
        share=kf.share,
        starts=(0, *(s - a for s in kf.starts if a < s < a + K)),
    )
