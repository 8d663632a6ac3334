"""The planar odometry-with-heading model of ``casmag slam`` on a recording with
``dfwd,dleft,dyaw`` columns: states (x, y, psi) per sample, a heading-rate bias (constant or
a random walk) and a reduced-rank map read in the body frame, y = Rz(psi)^T (m(x) + c):
:class:`PlanarMotion` with the reduced-rank field model read through a rotation about z
(casmag.model.field, casmag.model.rotated), put together by casmag.model.builder. Its
solve (starts, growing prefixes, the result) is casmag.solver.planar."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from casmag.gp.tiles import TileGrid
from casmag.model.builder import MotionModel, Pose, Rotation, cached_slam, uncached_slam
from casmag.model.field import BoxOrTiles, ReducedRankField, TiledField, WindowField
from casmag.model.knots import Knots
from casmag.model.rotated import planar_rotation_function, window_unknowns
from casmag.nlp import NLP, NLPBuilder


# --------------------------------------------------------------------------- planar model
@dataclass(frozen=True)
class PlanarStructure(BoxOrTiles):
    """Everything that changes the planar NLP: samples, bias model, kernel, the map (a
    reduced-rank ``basis`` key, or a tile ``grid`` with each sample's ``home`` grid point
    when the map is tiled), the solver settings as JSON."""

    n: int
    bias: str
    kernel: str
    basis: tuple | None
    solver: str
    curvature: bool = True
    grid: TileGrid | None = None
    home: tuple[int, ...] = ()
    window: bool = False
    starts: tuple[int, ...] = (0,)

    def field(self) -> ReducedRankField | TiledField:
        """The map with a constant field: the tiles (Gauss-Newton Hessian), or the
        reduced-rank box; with ``curvature`` its Hessian callback carries the second-order
        terms from the start (exact), else Gauss-Newton. With ``window``, the map under a
        given Gaussian prior (block ``map_prior``): the box of a sliding window, its prior
        carried from the earlier windows (a WindowField), or a saved map's box or tiles
        (casmag.solver.staged.PriorMap)."""
        if self.tiled:
            return self.tiled_field(self.window)
        mode = "exact" if self.curvature else "gauss-newton"
        if self.window:
            nz = window_unknowns(self.hilbert_basis(), self.kernel)
            return WindowField(
                self.kernel, self.basis, constant_field=True, curvature=mode, prior_shape=(nz, 1)
            )
        return ReducedRankField(self.kernel, self.basis, constant_field=True, curvature=mode)


@dataclass(frozen=True)
class PlanarMotion(MotionModel):
    """States (x, y, psi) per sample: the odometry residual of the body-frame increments
    (dfwd, dleft, dyaw) turned by the heading, a heading-rate bias (``constant`` or a
    ``random_walk``) with its prior, the known start; the field is read in the body frame
    y = Rz(psi)^T m(p).

    Several sessions (``starts``: the first sample of each) share the map: each has its own
    known start (row s of the parameter ``anchor``) and its own bias (row s when constant;
    a random walk's rows are the steps within the sessions, session s's step i at row
    i - s), and no odometry links one session's last sample to the next one's first (the
    increment between them, row start - 1 of ``U``, is not read)."""

    n: int
    bias: str = "constant"
    starts: tuple[int, ...] = (0,)
    name = "planar"

    def declare(self, b: NLPBuilder) -> Pose:
        n, knots = self.n, Knots(self.n, 1, self.starts)
        bounds = knots.bounds
        S = len(bounds)
        P = b.variable("P", (n, 2))
        psi = b.variable("psi", (n, 1))
        nb = n - S if self.bias == "random_walk" else S
        bias = b.variable("bias", (nb, 1))
        U = b.parameter("U", (n - 1, 3))  # dfwd, dleft, dyaw
        dt = b.parameter("dt", (n - 1, 1))
        sig = {
            k: b.parameter(k, (1, 1))
            for k in ("sigma_disp", "sigma_dyaw", "sigma_bias0", "sigma_anchor", "sigma_psi0")
        }
        anchor = b.parameter("anchor", (S, 3))
        walk = b.parameter("bias_walk", (1, 1)) if self.bias == "random_walk" else None
        p, p1, ps, ps1 = ca.SX.sym("p", 2), ca.SX.sym("p1", 2), ca.SX.sym("psi"), ca.SX.sym("psi1")
        u, bb, h, sd_, sy = (
            ca.SX.sym("u", 3),
            ca.SX.sym("b"),
            ca.SX.sym("dt"),
            ca.SX.sym("sd"),
            ca.SX.sym("sy"),
        )
        c, s_ = ca.cos(ps), ca.sin(ps)
        step = ca.vertcat(c * u[0] - s_ * u[1], s_ * u[0] + c * u[1])
        r = ca.vertcat((p1 - p - step) / sd_, (ps1 - ps - (u[2] - bb * h)) / sy)
        f = ca.Function("planar_step", [p, p1, ps, ps1, u, bb, h, sd_, sy], [r])
        if S == 1:
            P0, P1, psi0, psi1, Uk, dtk = P[:-1, :], P[1:, :], psi[:-1], psi[1:], U, dt
            B = bias if self.bias == "random_walk" else ca.repmat(bias, n - 1, 1)
        else:  # the steps within the sessions
            steps = [i for a, e in bounds for i in range(a, e - 1)]
            nxt = [i + 1 for i in steps]
            P0, P1, psi0, psi1 = P[steps, :], P[nxt, :], psi[steps], psi[nxt]
            Uk, dtk = U[steps, :], dt[steps]
            B = (
                bias
                if self.bias == "random_walk"
                else ca.vertcat(
                    *[ca.repmat(bias[s], e - a - 1, 1) for s, (a, e) in enumerate(bounds)]
                )
            )
        E = f.map(n - S, "serial")(
            P0.T, P1.T, psi0.T, psi1.T, Uk.T, B.T, dtk.T, sig["sigma_disp"], sig["sigma_dyaw"]
        )
        b.residual("odometry", E, curvature=True)
        firsts = [a - s for s, (a, _) in enumerate(bounds)]  # each session's first bias row
        if walk is not None:
            pairs = [j for s, (a, e) in enumerate(bounds) for j in range(a - s, e - 2 - s)]
            if pairs == list(range(n - 2)):
                db, hw = bias[1:] - bias[:-1], dt[:-1]
            else:
                db = bias[[j + 1 for j in pairs]] - bias[pairs]
                hw = dtk[pairs]
            b.cost("bias_walk", 0.5 * ca.sumsqr(db / (walk * ca.sqrt(hw))))
        first_bias = bias[firsts] if self.bias == "random_walk" else bias
        b.cost("bias_prior", 0.5 * ca.sumsqr(first_bias / sig["sigma_bias0"]))
        first = list(self.starts)
        P_first, psi_first = P[first, :], psi[first]
        b.cost(
            "anchor",
            0.5 * ca.sumsqr((P_first - anchor[:, :2]) / sig["sigma_anchor"])
            + 0.5 * ca.sumsqr((psi_first - anchor[:, 2]) / sig["sigma_psi0"]),
        )
        rotation = Rotation(planar_rotation_function(), psi, "psi")
        return Pose(P, n, 2, "P", None, knots, rotation)


def displacement_bias_coupling(
    P: np.ndarray,
    psi: np.ndarray,
    U: np.ndarray,
    sigma_disp: float,
    starts: tuple[int, ...] = (0,),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The odometry block's cross Hessian between the states (P, psi) and a body-frame
    displacement bias b (forward, left) per step, the step read as u - b, at b = 0 (the
    model has no such unknown): (n, 2, 2) against the positions (rows: the position's
    axis, columns: b's component), (n, 2) against the headings, and the steps (k to k + 1
    within a session) it sums. A step's residual r_k = (p_k+1 - p_k - Rz(psi_k)(u_k - b)) /
    sigma_disp gives Rz(psi_k) / sigma_disp^2 on p_k+1, its negative on p_k, and on psi_k
    (u_k,y, -u_k,x) / sigma_disp^2 plus the residual's own term r_k^T Rz'(psi_k) /
    sigma_disp."""
    P = np.asarray(P, dtype=float)
    psi = np.asarray(psi, dtype=float).ravel()
    n = psi.size
    k = np.array(
        [i for a, e in Knots(n, 1, starts).bounds for i in range(a, e - 1)], dtype=np.int64
    )
    w = 1.0 / float(sigma_disp) ** 2
    c, s = np.cos(psi[k]), np.sin(psi[k])
    R = np.stack([np.stack([c, -s], axis=1), np.stack([s, c], axis=1)], axis=1)  # (m, 2, 2)
    H_P = np.zeros((n, 2, 2))
    np.add.at(H_P, k + 1, w * R)
    np.add.at(H_P, k, -w * R)
    u = np.asarray(U, dtype=float)[k, :2]
    step = np.einsum("kab,kb->ka", R, u)
    r = P[k + 1] - P[k] - step  # times sigma_disp
    dR = np.stack([np.stack([-s, -c], axis=1), np.stack([c, -s], axis=1)], axis=1)
    H_psi = np.zeros((n, 2))
    H_psi[k] = w * (np.column_stack([u[:, 1], -u[:, 0]]) + np.einsum("ka,kab->kb", r, dR))
    return H_P, H_psi, k


def cached_planar_nlp(s: PlanarStructure, cache: bool = True) -> NLP:
    """The planar model with the structure's map, built once per process (``cache``
    False: built anew and not kept, e.g. a tiled map's pattern moved for one solve)."""
    build = cached_slam if cache else uncached_slam
    return build(PlanarMotion(s.n, s.bias, s.starts), s.field(), s.solver)


def dead_reckon_planar(U: np.ndarray, p0: np.ndarray, psi0: float, bias_dt: Any = 0.0) -> tuple:
    """(N, 2) positions and (N,) headings from (N-1, 3) increments (dfwd, dleft, dyaw), with
    an optional heading increment correction bias_dt ((N-1,) or scalar) removed."""
    n = U.shape[0] + 1
    psi = np.empty(n)
    psi[0] = psi0
    psi[1:] = psi0 + np.cumsum(U[:, 2] - bias_dt)
    c, s = np.cos(psi[:-1]), np.sin(psi[:-1])
    step = np.column_stack([c * U[:, 0] - s * U[:, 1], s * U[:, 0] + c * U[:, 1]])
    P = np.vstack([p0, p0 + np.cumsum(step, axis=0)])
    return P, psi


def dead_reckon_sessions(
    U: np.ndarray, anchors: np.ndarray, starts: tuple[int, ...] = (0,)
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) positions and (N,) headings of sessions stacked end to end (``starts``: the
    first sample of each; the increment before one, row start - 1 of ``U``, not read),
    each dead-reckoned from its row (x, y, psi) of ``anchors``."""
    n = U.shape[0] + 1
    P, psi = np.empty((n, 2)), np.empty(n)
    for a, e, x0 in zip(starts, [*starts[1:], n], anchors, strict=True):
        P[a:e], psi[a:e] = dead_reckon_planar(U[a : e - 1], x0[:2], float(x0[2]))
    return P, psi
