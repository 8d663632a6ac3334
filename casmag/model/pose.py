"""The pose-odometry model: 6-DoF odometry (visual-inertial, wheel, pedestrian) given as
body-frame increments, a plug-in of casmag.model.builder.

Input per interval k -> k+1 (recording columns ``dpx,dpy,dpz,dqw,dqx,dqy,dqz``): the
displacement dp_k in the body frame of sample k and the rotation increment dq_k, so that
dead reckoning is p_{k+1} = p_k + R(q_k) dp_k, q_{k+1} = q_k dq_k (Hamilton quaternions,
w first, q the body-to-map rotation).

Unknowns: positions P (N, 3); orientations q_k = qnom_k (1, d_k / 2) with a nominal
quaternion qnom_k (a parameter: the dead reckoning or a previous estimate) and a Gibbs
vector d_k (the unknown: smooth, no norm constraint, as the IMU model's); a constant
displacement bias b_p (3, per step, body frame) and a constant rotation-rate bias b_w (3,
rad/s, gyroscope-like), each estimated or held at zero. Named cost blocks:

- ``odometry`` (a residual; its exact Hessian unless ``solver.hessian`` is
  ``gauss-newton``, casmag.nlp.NLPBuilder.residual): per interval, the displacement
  (R_k^T (p_{k+1} - p_k) - (dp_k - b_p)) / sigma_p and the rotation
  r(dq_k exp(-b_w dt_k))^-1 q_k^-1 q_{k+1}) / sigma_r, r the rotation residual
  2 w v / |q|^2 (the rotation vector to second order, independent of the sign of q);
- ``bias_prior``: 0.5 |b_p / sigma_bp|^2 + 0.5 |b_w / sigma_bw|^2;
- ``anchor``: the known first pose, 0.5 |(p_0 - a) / sigma_anchor|^2 + 0.5 |r(q_0 qa^-1) /
  sigma_att0|^2;
- ``height`` (``height`` set): 0.5 sum_k ((z_k - a_z) / sigma_height)^2, motion near the
  plane of the start: with a planar map the magnetometer cannot see the height, and
  without this block it drifts with the odometry and the pitch;

and the field model's blocks on y_k = R_k^T (m(p_k) + c) (casmag.model.field through the
rotation, as the IMU model's). The map is 3-D, or ``map_dim`` 2 for motion that stays near a
plane: the field is then a function of (x, y) only, the orientation still 3-D. The map is
the reduced-rank box or the tiles (casmag.model.field.TiledField: each sample touches the
2^map_dim tiles around its position).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from casmag import strapdown as sd
from casmag.gp.tiles import TileGrid
from casmag.model.builder import MotionModel, Pose, Rotation, cached_slam, uncached_slam
from casmag.model.field import BoxOrTiles, ReducedRankField, TiledField, WindowField
from casmag.model.knots import Knots
from casmag.model.rotated import imu_rotation_function, window_unknowns
from casmag.nlp import NLP, NLPBuilder


def pose_step_function() -> ca.Function:
    """SX (p, p1 (3), d, d1 (3), rnom (9), qrel (4), dp (3), dq (4), b_p (3), b_w (3), dt,
    sigma_p, sigma_r) -> whitened residual (6,) of one interval.

    R_k = Rnom_k R(1, d_k / 2); qrel = qnom_k^-1 qnom_{k+1} is formed from the nominal in
    numpy, so the unknowns enter the rotation residual only through the small corrections."""
    p, p1, d, d1 = (ca.SX.sym(s, 3) for s in ("p", "p1", "d", "d1"))
    rnom, qrel = ca.SX.sym("rnom", 9), ca.SX.sym("qrel", 4)
    dp, dq, bp, bw = (
        ca.SX.sym("dp", 3),
        ca.SX.sym("dq", 4),
        ca.SX.sym("b_p", 3),
        ca.SX.sym("b_w", 3),
    )
    dt, sp, sr = ca.SX.sym("dt"), ca.SX.sym("sigma_p"), ca.SX.sym("sigma_r")
    R = ca.mtimes(ca.reshape(rnom, 3, 3), sd.ca_rotmat(sd.ca_gibbs(d)))
    e_p = (ca.mtimes(R.T, p1 - p) - (dp - bp)) / sp
    # (dq exp(-b_w dt))^-1 (1, d/2)^-1 qrel (1, d1/2); unnormalised factors are fine: the
    # rotation residual divides by |q|^2.
    corrected = sd.ca_quat_mul(dq, sd.ca_quat_exp_small(-dt * bw))
    rel = sd.ca_quat_mul(sd.ca_quat_mul(sd.ca_quat_conj(sd.ca_gibbs(d)), qrel), sd.ca_gibbs(d1))
    e_r = sd.ca_rotation_residual(sd.ca_quat_mul(sd.ca_quat_conj(corrected), rel)) / sr
    return ca.Function(
        "pose_step", [p, p1, d, d1, rnom, qrel, dp, dq, bp, bw, dt, sp, sr], [ca.vertcat(e_p, e_r)]
    )


@dataclass(frozen=True)
class PoseMotion(MotionModel):
    """N samples of 6-DoF pose odometry: positions P, orientation corrections D about a
    nominal (``RNOM`` rotation matrices, ``QREL`` nominal relative rotations), the biases
    ``bias_p`` (1, 3) and ``bias_w`` (1, 3), the blocks ``odometry``, ``bias_prior`` and
    ``anchor`` (and ``height``); the field is read in the body frame at P[:, :map_dim].

    Several sessions (``starts``: the first sample of each) share the map: each has its own
    known first pose (rows of ``anchor_p``, ``anchor_q``, ``QNOM0``), its own biases (rows of
    ``bias_p``, ``bias_w``) and height, and no odometry links one session to the next (row
    start - 1 of ``U`` and ``QREL`` is not read)."""

    n: int
    map_dim: int = 3
    height: bool = False
    starts: tuple[int, ...] = (0,)
    name = "pose"

    def declare(self, b: NLPBuilder) -> Pose:
        n, knots = self.n, Knots(self.n, 1, self.starts)
        bounds = knots.bounds
        S = len(bounds)
        P = b.variable("P", (n, 3))
        D = b.variable("D", (n, 3))
        bp = b.variable("bias_p", (S, 3))
        bw = b.variable("bias_w", (S, 3))
        U = b.parameter("U", (n - 1, 7))  # dpx, dpy, dpz, dqw, dqx, dqy, dqz
        dt = b.parameter("dt", (n - 1, 1))
        RNOM = b.parameter("RNOM", (n, 9))
        QREL = b.parameter("QREL", (n - 1, 4))
        sig = {
            k: b.parameter(k, (1, 1))
            for k in ("sigma_p", "sigma_r", "sigma_bp", "sigma_bw", "sigma_anchor", "sigma_att0")
        }
        anchor_p = b.parameter("anchor_p", (S, 3))
        anchor_q = b.parameter("anchor_q", (S, 4))  # the known first orientations
        QNOM0 = b.parameter("QNOM0", (S, 4))
        step = pose_step_function().map(n - S, "serial")
        if S == 1:
            E = step(
                P[:-1, :].T, P[1:, :].T, D[:-1, :].T, D[1:, :].T, RNOM[:-1, :].T, QREL.T,
                U[:, 0:3].T, U[:, 3:7].T, ca.repmat(bp.T, 1, n - 1), ca.repmat(bw.T, 1, n - 1),
                dt.T, sig["sigma_p"], sig["sigma_r"],
            )  # fmt: skip
        else:  # the steps within the sessions
            steps = [i for a, e in bounds for i in range(a, e - 1)]
            nxt = [i + 1 for i in steps]

            def per_step(v: ca.MX) -> ca.MX:
                return ca.horzcat(*[ca.repmat(v[s, :].T, 1, e - a - 1)
                                    for s, (a, e) in enumerate(bounds)])  # fmt: skip

            E = step(
                P[steps, :].T, P[nxt, :].T, D[steps, :].T, D[nxt, :].T, RNOM[steps, :].T,
                QREL[steps, :].T, U[steps, 0:3].T, U[steps, 3:7].T, per_step(bp),
                per_step(bw), dt[steps].T, sig["sigma_p"], sig["sigma_r"],
            )  # fmt: skip
        b.residual("odometry", E, curvature=True)
        b.cost(
            "bias_prior",
            0.5 * ca.sumsqr(bp / sig["sigma_bp"]) + 0.5 * ca.sumsqr(bw / sig["sigma_bw"]),
        )
        anchor = 0
        for s, (a, _) in enumerate(bounds):
            eps = sd.ca_rotation_residual(
                sd.ca_quat_mul(
                    sd.ca_quat_mul(QNOM0[s, :].T, sd.ca_gibbs(D[a, :].T)),
                    sd.ca_quat_conj(anchor_q[s, :].T),
                )
            )
            anchor += 0.5 * ca.sumsqr((P[a, :] - anchor_p[s, :]) / sig["sigma_anchor"])
            anchor += 0.5 * ca.sumsqr(eps / sig["sigma_att0"])
        b.cost("anchor", anchor)
        if self.height:
            sh = b.parameter("sigma_height", (1, 1))
            height = 0
            for s, (a, e) in enumerate(bounds):
                height += 0.5 * ca.sumsqr((P[a:e, 2] - anchor_p[s, 2]) / sh)
            b.cost("height", height)
        rotation = Rotation(imu_rotation_function(), D, "D", RNOM, "RNOM")
        positions = P if self.map_dim == 3 else P[:, : self.map_dim]
        return Pose(positions, n, self.map_dim, "P", None, knots, rotation)


@dataclass(frozen=True)
class PoseStructure(BoxOrTiles):
    """Everything that changes the pose NLP: samples, the map's dimension and its
    reduced-rank ``basis`` key (center, half width, number of functions) or, when the map
    is tiled, its tile ``grid`` with each sample's ``home`` grid point (which fixes the
    Hessian's pose-weight pattern), kernel, Hessian mode of the magnetometer block, the
    solver settings as JSON; ``window``: the map under a given Gaussian prior (block
    ``map_prior``): the box of a sliding window, its prior carried from the earlier windows
    (a WindowField), or a saved map's box or tiles (casmag.solver.staged.PriorMap)."""

    n: int
    map_dim: int
    kernel: str
    basis: tuple | None
    solver: str
    curvature: str = "hybrid"
    height: bool = False
    window: bool = False
    starts: tuple[int, ...] = (0,)
    grid: TileGrid | None = None
    home: tuple[int, ...] = ()

    def field(self) -> ReducedRankField | TiledField:
        if self.tiled:
            return self.tiled_field(self.window)
        if self.window:
            nz = window_unknowns(self.hilbert_basis(), self.kernel)
            return WindowField(
                self.kernel, self.basis, constant_field=True, curvature=self.curvature,
                prior_shape=(nz, 1),
            )  # fmt: skip
        return ReducedRankField(
            self.kernel, self.basis, constant_field=True, curvature=self.curvature
        )


def cached_pose_nlp(s: PoseStructure, cache: bool = True) -> NLP:
    """The pose model with the structure's map, built once per process (``cache``
    False: built anew and not kept, e.g. a tiled map's pattern moved for one solve)."""
    build = cached_slam if cache else uncached_slam
    return build(PoseMotion(s.n, s.map_dim, s.height, s.starts), s.field(), s.solver)


# --------------------------------------------------------------------------- numpy
def nominal_parameters(Q: np.ndarray, starts: tuple[int, ...] = (0,)) -> dict[str, np.ndarray]:
    """The NLP parameters of a nominal orientation (N, 4): ``RNOM`` (N, 9, column-major
    rotation matrices), ``QREL`` (N-1, 4) qnom_k^-1 qnom_{k+1}, ``QNOM0`` (S, 4) at the
    first sample of each session (``starts``)."""
    Q = sd.quat_normalize(np.asarray(Q, dtype=float))
    R = sd.quat_to_rotmat(Q)  # (N, 3, 3)
    return {
        "RNOM": R.transpose(0, 2, 1).reshape(-1, 9),  # column-major per row
        "QREL": sd.quat_mul(sd.quat_conj(Q[:-1]), Q[1:]),
        "QNOM0": Q[list(starts)],
    }


def orientations(Q_nominal: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Unit quaternions qnom_k (1, d_k / 2) / |.| of a nominal and its Gibbs corrections."""
    return sd.quat_normalize(sd.quat_mul(Q_nominal, sd.gibbs_quat(np.asarray(D, float))))
