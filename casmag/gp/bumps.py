"""A curl-free GP map from compactly supported bumps: every point touches only the few
lattice nodes within a radius R of it.

The potential is a process convolution (white noise smoothed by a kernel) on a regular
lattice of spacing h over the position axes:

    Phi(x) = sum_j v_j psi(x - c_j),   v_j ~ N(0, s^2) independent,

with c_j = origin + h i_j. With psi the Gaussian exp(-|u|^2 / (2 a^2)), a = l / sqrt(2), the
covariance s^2 sum_j psi(x - c_j) psi(x' - c_j) is, up to the lattice's sampling of the
integral, s^2 h^-d (pi a^2)^(d/2) exp(-|x - x'|^2 / (4 a^2)): the squared-exponential of
lengthscale l. Here psi is that Gaussian times a taper that takes it to zero at |u| = R
(flat up to |u|^2 = t0 R^2, then 1 - s(v) with s a smoothstep in |u|^2 whose first three
derivatives vanish at both ends, so psi is three times continuously differentiable: the field
and its Jacobian in position are continuous, and so is the cost's Hessian), and
s^2 is set so that the field's variance is the kernel's sigma_f^2 / l^2 on average over a
lattice cell.

The field is the gradient of the potential, curl-free by construction. For 3-D positions
the lattice is 3-D with one weight per node. For planar positions (the x-y plane) the
lattice is 2-D with two weights per node: Phi(x, y, 0) and its vertical derivative are
independent GPs in the plane (Cov(Phi(x), d Phi(x') / dz') = k (z - z') / l^2 = 0 at z = z'),
with covariances k and k / l^2, so the field in the plane is

    m(x, y) = (d Phi_0 / dx, d Phi_0 / dy, Phi_1),  Phi_0 = sum_j v_j0 psi,  Phi_1 = sum_j v_j1 psi,

exactly the curl-free field's distribution on the plane at this approximation of k.

Against the tiles of casmag.gp.tiles (one 166-function Hilbert basis per tile of 4 l, a
sample touching the 2^d tiles around it), a sample touches the 60 nodes within 3 l (one
weight each, two in the plane), so the Hessian's border and weight block hold far fewer
non-zeros and the KKT system's separators are thinner (measured in casmag.model.tiledmap).

:class:`BumpBasis` has the interface of :class:`casmag.gp.tiles.TiledBasis` (a "tile" is a
lattice node, its ``per_tile`` weights the node's), so the tiled map's cost, Hessian,
covariance and drawing take it unchanged.
"""

from __future__ import annotations

import math
from functools import cached_property
from itertools import product

import casadi as ca
import numpy as np

from casmag.gp.tiles import TiledBasis, TileGrid

#: Key of a bump lattice in :attr:`TileGrid.basis`: (BUMPS, lengthscale, radius / l,
#: taper start as a fraction of R^2, home slack in cells).
BUMPS = "bumps"


def bump_key(lengthscale: float, radius: float, taper_start: float, slack: int = 0) -> tuple:
    """The ``basis`` entry of a :class:`TileGrid` of bumps (see :data:`BUMPS`)."""
    return (BUMPS, float(lengthscale), float(radius), float(taper_start), int(slack))


def is_bump_grid(grid: TileGrid) -> bool:
    return bool(grid.basis) and grid.basis[0] == BUMPS


def smootherstep(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """s(v) = 35 v^4 - 84 v^5 + 70 v^6 - 20 v^7 on [0, 1] and its first two derivatives:
    its first three derivatives vanish at 0 and 1, so the bump is three times continuously
    differentiable and the cost's Hessian in position (which reads the bump's third
    derivatives) continuous."""
    s = v**4 * (35.0 - 84.0 * v + 70.0 * v**2 - 20.0 * v**3)
    s1 = 140.0 * v**3 * (1.0 - v) ** 3
    s2 = 420.0 * v**2 * (1.0 - v) ** 2 * (1.0 - 2.0 * v)
    return s, s1, s2


class BumpBasis(TiledBasis):
    """The bump lattice of a :class:`TileGrid` whose ``basis`` is :func:`bump_key`: field,
    weight Jacobians and position Jacobian at points, for weights ``W`` (T, m), one row per
    node in the grid's order (m = 2 for planar positions, 1 for 3-D)."""

    def __init__(self, grid: TileGrid) -> None:
        if not is_bump_grid(grid):
            raise ValueError("not a bump lattice")
        self.grid = grid
        _, ell, radius, t0, slack = grid.basis
        self.home_slack = int(slack)
        self.lengthscale = float(ell)
        self.a2 = 0.5 * self.lengthscale**2  # a^2, a = l / sqrt(2)
        self.R2 = (float(radius) * self.lengthscale) ** 2
        self.t0 = float(t0)
        self._index_tiles()
        self.corners = self._corner_offsets()

    def _corner_offsets(self) -> np.ndarray:
        """Node offsets from a point's cell whose bump can reach a point of the cell: per
        axis -K + 1 .. K (K = ceil(R / h)), kept where the cell's nearest point to the node
        is within R."""
        h, d = self.grid.spacing, self.grid.dim
        K = math.ceil(math.sqrt(self.R2) / h)
        offs = np.array(list(product(range(1 - K, K + 1), repeat=d)), dtype=np.int64)
        gap = np.maximum(0, np.maximum(offs - 1, -offs)) * h  # cell [0, h) to node o h
        return offs[np.sum(gap**2, axis=1) < self.R2]

    @property
    def per_tile(self) -> int:
        return 2 if self.grid.dim == 2 else 1

    def profile(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """g(t), g'(t), g''(t) of psi(u) = g(|u|^2) (module docstring); zero for t >= R^2."""
        e = np.exp(-0.5 * t / self.a2)
        e1, e2 = -0.5 / self.a2 * e, 0.25 / self.a2**2 * e
        span = self.R2 * (1.0 - self.t0)
        g, g1, g2 = e, e1, e2  # flat part: the Gaussian
        beyond = t >= self.R2
        g[beyond] = g1[beyond] = g2[beyond] = 0.0
        ring = (t > self.t0 * self.R2) & ~beyond  # the taper, 1 - s(v)
        if ring.any():
            v = (t[ring] / self.R2 - self.t0) / (1.0 - self.t0)
            s, s1, s2 = smootherstep(v)
            tau, tau1, tau2 = 1.0 - s, -s1 / span, -s2 / span**2
            er, e1r, e2r = e[ring], e1[ring], e2[ring]
            g[ring] = er * tau
            g1[ring] = e1r * tau + er * tau1
            g2[ring] = e2r * tau + 2.0 * e1r * tau1 + er * tau2
        return g, g1, g2

    def bump(self, u: np.ndarray, second: bool = True) -> tuple[np.ndarray, ...]:
        """psi, grad psi (n, d) and (with ``second``) the Hessian of psi (n, d, d) at
        offsets u (n, d) from a node."""
        g, g1, g2 = self.profile(np.sum(u**2, axis=1))
        grad = 2.0 * g1[:, None] * u
        if not second:
            return g, grad, None
        d = u.shape[1]
        hess = 4.0 * g2[:, None, None] * u[:, :, None] * u[:, None, :]
        hess += 2.0 * g1[:, None, None] * np.eye(d)[None]
        return g, grad, hess

    @cached_property
    def _amplitudes(self) -> np.ndarray:
        """(m,) weight variances per unit sigma_f^2: the field's variance sigma_f^2 / l^2
        on average over a cell (the horizontal components from Phi_0's gradient, and in
        the plane the vertical one from Phi_1)."""
        h, d = self.grid.spacing, self.grid.dim
        q = (np.arange(8) + 0.5) / 8.0 * h  # an 8^d grid of points in a cell
        pts = np.array(list(product(q, repeat=d)))
        grad2 = np.zeros(pts.shape[0])
        val2 = np.zeros(pts.shape[0])
        for off in self.corners:
            g, grad, _ = self.bump(pts - off * h, second=False)
            grad2 += np.sum(grad**2, axis=1)
            val2 += g**2
        target = 1.0 / self.lengthscale**2  # per-component field variance / sigma_f^2
        s_grad = target / (np.mean(grad2) / d)
        if d == 3:
            return np.array([s_grad])
        return np.array([s_grad, target / np.mean(val2)])

    def prior_variances(self, sigma_f, lengthscale=None):  # type: ignore[override]
        """(m,) prior variances of a node's weights (every node has the same): numpy for a
        number, a CasADi (m, 1) column for a symbol. The bump's shape is fixed by the
        lattice's lengthscale (its key), so ``lengthscale`` is not read."""
        amp = self._amplitudes
        if isinstance(sigma_f, (ca.MX, ca.SX, ca.DM)):
            return sigma_f**2 * ca.DM(amp)
        return float(sigma_f) ** 2 * amp

    def evaluate(
        self,
        P: np.ndarray,
        W: np.ndarray,
        jacobians: bool = True,
        positions: bool = True,
        cells: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """As :meth:`TiledBasis.evaluate`: the field m (N, 3), the node ids (N, n_c) (-1
        where the lattice lacks the node), J (N, n_c, 3, m) and D (N, 3, d) = dm / dp;
        ``cells`` as there."""
        P, cells, ids, field, J, D = self._outputs(P, jacobians, positions, cells)
        d, h = P.shape[1], self.grid.spacing
        # Every point against every corner node at once, (N, n_c, ...): offsets U from the
        # nodes, the bump's profile at |U|^2, zero where the lattice lacks the node.
        live = ids >= 0
        U = (P - np.array(self.grid.origin))[:, None, :] - h * (
            cells[:, None, :] + self.corners[None, :, :]
        )
        g, g1, g2 = self.profile(np.einsum("nci,nci->nc", U, U))
        g, g1 = g * live, g1 * live
        grad = 2.0 * g1[..., None] * U  # (N, n_c, d)
        V = W[np.where(live, ids, 0)]  # (N, n_c, m); multiplied by zeros where not live
        field[:, :d] = np.einsum("nc,ncd->nd", V[..., 0], grad)
        if d == 2:
            field[:, 2] = np.einsum("nc,nc->n", V[..., 1], g)
        if J is None:
            return field, ids, J, D
        J[:, :, :d, 0] = grad
        if d == 2:
            J[:, :, 2, 1] = g
        if D is None:
            return field, ids, J, D
        # the bump's Hessian 4 g'' u u^T + 2 g' I, weighted by the potential's weights
        D[:, :d, :] = 4.0 * np.einsum("nc,nci,ncj->nij", V[..., 0] * g2 * live, U, U)
        D[:, :d, :] += 2.0 * np.einsum("nc,nc->n", V[..., 0], g1)[:, None, None] * np.eye(d)
        if d == 2:
            D[:, 2, :] = np.einsum("nc,ncd->nd", V[..., 1], grad)
        return field, ids, J, D
