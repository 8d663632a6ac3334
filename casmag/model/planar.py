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

from casmag.gp.reduced_rank import HilbertBasis, cached_basis
from casmag.gp.tiles import TiledBasis, TileGrid, cached_tiles
from casmag.model.builder import MotionModel, Pose, Rotation, cached_slam
from casmag.model.field import ReducedRankField, TiledField, WindowField
from casmag.model.knots import Knots
from casmag.model.rotated import planar_rotation_function, window_unknowns
from casmag.nlp import NLP, NLPBuilder


# --------------------------------------------------------------------------- planar model
@dataclass(frozen=True)
class PlanarStructure:
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

    @property
    def tiled(self) -> bool:
        return self.grid is not None

    def hilbert_basis(self) -> HilbertBasis:
        assert self.basis is not None, "a tiled map has no global basis"
        return cached_basis(self.basis)

    def tiles(self) -> TiledBasis:
        assert self.grid is not None
        return cached_tiles(self.grid)

    def field(self) -> ReducedRankField | TiledField:
        """The map with a constant field: the tiles (Gauss-Newton Hessian), or the
        reduced-rank box; with ``curvature`` its Hessian callback carries the second-order
        terms from the start (exact), else Gauss-Newton. With ``window``, the box of a
        sliding window, its prior carried from the earlier windows (a WindowField)."""
        if self.grid is not None:
            if self.window:
                raise ValueError("sliding windows need the reduced-rank map, not tiles")
            return TiledField(self.grid, self.home, constant_field=True)
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
    y = Rz(psi)^T m(p)."""

    n: int
    bias: str = "constant"
    name = "planar"

    def declare(self, b: NLPBuilder) -> Pose:
        n = self.n
        P = b.variable("P", (n, 2))
        psi = b.variable("psi", (n, 1))
        nb = n - 1 if self.bias == "random_walk" else 1
        bias = b.variable("bias", (nb, 1))
        U = b.parameter("U", (n - 1, 3))  # dfwd, dleft, dyaw
        dt = b.parameter("dt", (n - 1, 1))
        sig = {
            k: b.parameter(k, (1, 1))
            for k in ("sigma_disp", "sigma_dyaw", "sigma_bias0", "sigma_anchor", "sigma_psi0")
        }
        anchor = b.parameter("anchor", (1, 3))
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
        B = bias if self.bias == "random_walk" else ca.repmat(bias, n - 1, 1)
        E = f.map(n - 1, "serial")(
            P[:-1, :].T,
            P[1:, :].T,
            psi[:-1].T,
            psi[1:].T,
            U.T,
            B.T,
            dt.T,
            sig["sigma_disp"],
            sig["sigma_dyaw"],
        )
        b.residual("odometry", E)
        if walk is not None:
            b.cost("bias_walk", 0.5 * ca.sumsqr((bias[1:] - bias[:-1]) / (walk * ca.sqrt(dt[:-1]))))
        b.cost("bias_prior", 0.5 * (bias[0] / sig["sigma_bias0"]) ** 2)
        b.cost(
            "anchor",
            0.5 * ca.sumsqr((P[0, :] - anchor[0, :2]) / sig["sigma_anchor"])
            + 0.5 * ((psi[0] - anchor[0, 2]) / sig["sigma_psi0"]) ** 2,
        )
        rotation = Rotation(planar_rotation_function(), psi, "psi")
        return Pose(P, n, 2, "P", None, Knots(n, 1), rotation)


def cached_planar_nlp(s: PlanarStructure) -> NLP:
    """The planar model with the structure's map, built once per process."""
    return cached_slam(PlanarMotion(s.n, s.bias), s.field(), s.solver)


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
