"""A tiled reduced-rank GP potential: every point touches only the tiles around it.

The Hilbert-space basis of ``casmag.gp.reduced_rank`` spans one box, so every sample touches
every weight and the cost of a map grows with its area. Here the potential is a blend of
independent reduced-rank GPs, one per tile of a regular grid of spacing h over the position
axes (the x-y plane for planar data, all three axes for 3-D positions):

    Phi(x) = sum_t w_t(x) Phi_t(x),   Phi_t(x) = phi(x - c_t)^T v_t,   v_t ~ N(0, diag(S)),

with tile centres c_t = origin + h i_t (i_t integer), one basis phi on a box centred at zero
(half-width h + margin along the tiled axes; for planar data [-margin, margin] in z, as in
``casmag.gp.reduced_rank``), the weights of different tiles independent, and the blending
weights

    w_t(x) = prod_a omega((x_a - c_{t,a}) / h),
    omega(u) = cos(pi/2 s(|u|)) for |u| < 1, 0 beyond,  s(a) = 10 a^3 - 15 a^4 + 6 a^5.

s is the smootherstep (s(1 - a) = 1 - s(a), s' = s'' = 0 at 0 and 1), so omega(u)^2 +
omega(u - 1)^2 = 1 on [0, 1] and omega is twice continuously differentiable: the squares of
the blending weights sum to one at every point, and the field is continuous with a continuous
Jacobian in position. A point in the grid cell [c_i, c_i + h) touches the 2^d tiles at its
corners and nothing else.

The field is the gradient of the potential (curl-free by construction):

    m(x) = sum_t [ Phi_t(x) grad w_t(x) + w_t(x) grad Phi_t(x) ].

Its prior: Var Phi(x) = sum_t w_t(x)^2 k(0) = k(0) at every point, and Cov(Phi(x), Phi(x'))
= rho(x, x') k(x, x') with rho = sum_t w_t(x) w_t(x') <= 1 (1 at x = x'), so the approximation
weakens the correlation of points that share no tile and adds the terms of grad w_t to the
field's covariance; both shrink as h / l grows (measured by :func:`covariance` against the
exact kernel, see ``casmag.model.tiledmap``). Only the ``curl_free`` kernel (the potential
with the squared-exponential covariance) is tiled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from itertools import product
from typing import Any

import casadi as ca
import numpy as np
import scipy.sparse as sps

from casmag.gp.kernels import FIELD_DIM
from casmag.gp.reduced_rank import HilbertBasis, cached_basis


def window(u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """omega(u), omega'(u), omega''(u) elementwise (module docstring)."""
    u = np.asarray(u, dtype=float)
    a = np.minimum(np.abs(u), 1.0)
    sgn = np.sign(u)
    s = a**3 * (10.0 - 15.0 * a + 6.0 * a**2)
    s1 = 30.0 * a**2 * (1.0 - a) ** 2
    s2 = 60.0 * a * (1.0 - a) * (1.0 - 2.0 * a)
    half = 0.5 * math.pi
    c, sn = np.cos(half * s), np.sin(half * s)
    inside = np.abs(u) < 1.0
    om = np.where(inside, c, 0.0)
    d1 = np.where(inside, -sn * half * s1 * sgn, 0.0)
    d2 = np.where(inside, -c * (half * s1) ** 2 - sn * half * s2, 0.0)
    return om, d1, d2


@dataclass(frozen=True)
class TileGrid:
    """Where the tiles are: ``spacing`` h, ``origin`` (d,) the centre of tile index 0,
    ``tiles`` the integer indices (d each) of the tiles present, sorted, and ``basis`` the
    key of the tile basis (``casmag.gp.reduced_rank.cached_basis``: centre zero)."""

    spacing: float
    origin: tuple[float, ...]
    tiles: tuple[tuple[int, ...], ...]
    basis: tuple

    @property
    def dim(self) -> int:
        return len(self.origin)

    @classmethod
    def around(cls, X: np.ndarray, spacing: float, reach: float, basis: tuple) -> TileGrid:
        """The tiles whose support (the open box of half-width h around the centre) comes
        within ``reach`` of a position of X (N, d): the map exists wherever a position can
        move by ``reach``. The origin is the grid point at or below the positions' minimum."""
        X = np.asarray(X, dtype=float)
        h = float(spacing)
        origin = np.floor(X.min(axis=0) / h) * h
        lo = np.floor((X - reach - origin) / h).astype(np.int64)  # cell of x - reach
        hi = np.floor((X + reach - origin) / h).astype(np.int64) + 1
        found: set[tuple[int, ...]] = set()
        for k in range(X.shape[0]):
            axes = [range(int(a), int(b) + 1) for a, b in zip(lo[k], hi[k], strict=True)]
            found.update(product(*axes))
        return cls(h, tuple(float(v) for v in origin), tuple(sorted(found)), basis)


class TiledBasis:
    """The tiled potential of a :class:`TileGrid`: field, weight Jacobians and position
    Jacobian at points (numpy), for weights ``W`` (T, m), one row per tile in the grid's
    order."""

    CHUNK = 1024
    #: Cells beyond the two around a sample's home grid point whose tiles its Hessian
    #: pattern holds (casmag.model.tiledmap.home_tiles): none for these tiles of 4 l.
    home_slack = 0

    def __init__(self, grid: TileGrid) -> None:
        self.grid = grid
        self.basis: HilbertBasis = cached_basis(grid.basis)
        if self.basis.input_dim != FIELD_DIM:
            raise ValueError("the tiled map is the curl-free field of a 3-D potential")
        self._index_tiles()
        self.corners = np.array(list(product((0, 1), repeat=grid.dim)), dtype=np.int64)

    def _index_tiles(self) -> None:
        """``tile_index`` (T, d), the grid's tile indices, and the lookup from an index to
        its tile id (-1: no such tile) that :meth:`tile_ids` reads."""
        idx = np.array(self.grid.tiles, dtype=np.int64).reshape(-1, self.grid.dim)
        self.tile_index = idx
        self._lo = idx.min(axis=0)
        shape = idx.max(axis=0) - self._lo + 1
        self._lookup = np.full(tuple(int(s) for s in shape), -1, dtype=np.int64)
        self._lookup[tuple((idx - self._lo).T)] = np.arange(idx.shape[0])

    @property
    def num_tiles(self) -> int:
        return int(self.tile_index.shape[0])

    @property
    def per_tile(self) -> int:
        """m: basis functions (weights) per tile."""
        return self.basis.num_basis

    @property
    def num_weights(self) -> int:
        return self.num_tiles * self.per_tile

    @cached_property
    def neighbours(self) -> np.ndarray:
        """(pairs, 2) tile ids t <= t' of tiles that can share a point (their index
        difference is one between two of a cell's corner tiles: at most one along every
        axis here), sorted."""
        return self.pairs_among(np.ones(self.num_tiles, dtype=bool))

    def pairs_among(self, held: np.ndarray) -> np.ndarray:
        """(pairs, 2) tile ids t <= t', sorted: every tile with itself, and the pairs of
        tiles that can share a point (:attr:`neighbours`) both ``held`` (T,) bool. Tile ids
        are in the order of their sorted indices, so each such pair comes once, from the
        difference of two corners that is lexicographically positive."""
        d, T = self.grid.dim, self.num_tiles
        diffs = np.unique(
            (self.corners[:, None, :] - self.corners[None, :, :]).reshape(-1, d), axis=0
        )
        t = np.flatnonzero(held)
        keys = [np.arange(T) * (T + 1)]
        for off in diffs[[tuple(v) > (0,) * d for v in diffs]]:
            other = self.ids_at(self.tile_index[t] + off)
            ok = other >= 0
            ok[ok] = held[other[ok]]
            keys.append(t[ok] * T + other[ok])
        k = np.sort(np.concatenate(keys))
        return np.column_stack([k // T, k % T])

    def cells(self, P: np.ndarray) -> np.ndarray:
        """(N, d) integer grid cell of each position (its lower corner's tile index)."""
        g = self.grid
        return np.floor((P - np.array(g.origin)) / g.spacing).astype(np.int64)

    def ids_at(self, index: np.ndarray) -> np.ndarray:
        """The tile id at each integer tile index (..., d) (-1: no such tile in the map)."""
        lut = self._lookup
        j = np.asarray(index, dtype=np.int64) - self._lo
        ok = np.all((j >= 0) & (j < np.array(lut.shape)), axis=-1)
        flat = np.ravel_multi_index(
            tuple(np.moveaxis(np.where(ok[..., None], j, 0), -1, 0)), lut.shape
        )
        return np.where(ok, lut.ravel()[flat], -1).astype(np.int64)

    def tile_ids(self, cells: np.ndarray) -> np.ndarray:
        """(N, 2^d) id of each corner tile of the cells (-1: no such tile in the map)."""
        return self.ids_at(np.asarray(cells)[:, None, :] + self.corners[None, :, :])

    def inside(self, P: np.ndarray) -> np.ndarray:
        """(N,) bool: the position has every corner tile in the map (the blend is whole)."""
        return np.all(self.tile_ids(self.cells(np.asarray(P, dtype=float))) >= 0, axis=1)

    def _outputs(
        self, P: np.ndarray, jacobians: bool, positions: bool, cells: np.ndarray | None
    ) -> tuple[np.ndarray, ...]:
        """What :meth:`evaluate` fills: the positions as floats, their cells and corner
        tile ids, and zeroed field (N, 3), J (N, corners, 3, m) and D (N, 3, d) (None where
        not asked for)."""
        P = np.asarray(P, dtype=float)
        N, d = P.shape
        cells = self.cells(P) if cells is None else cells
        ids = self.tile_ids(cells)
        n_c = self.corners.shape[0]
        field = np.zeros((N, FIELD_DIM))
        J = np.zeros((N, n_c, FIELD_DIM, self.per_tile)) if jacobians else None
        D = np.zeros((N, FIELD_DIM, d)) if jacobians and positions else None
        return P, cells, ids, field, J, D

    def evaluate(
        self,
        P: np.ndarray,
        W: np.ndarray,
        jacobians: bool = True,
        positions: bool = True,
        cells: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """At positions P (N, d) with weights W (T, m): the field m (N, 3), the corner tile
        ids (N, 2^d), the weight Jacobians J (N, 2^d, 3, m) (dm_b / dv_t for each corner
        tile; zero for an absent tile) and the position Jacobian D (N, 3, d) = dm / dp.
        Without ``jacobians`` the last two are None (the field alone, cheaper); without
        ``positions`` D is None (no second derivatives of the basis). ``cells`` (N, d)
        reads each point in the given grid cell instead of its own (a point just outside
        the cell gets the blend of the cell's corners, which is the field's to second order
        there: difference quotients across a cell's edge)."""
        P, cells, ids, field, J, D = self._outputs(P, jacobians, positions, cells)
        d = P.shape[1]
        g, basis = self.grid, self.basis
        h = g.spacing
        for o, off in enumerate(self.corners):
            live = ids[:, o] >= 0
            if not live.any():
                continue
            rows = np.flatnonzero(live)
            x = P[rows] - (np.array(g.origin) + h * (cells[rows] + off))  # local coordinates
            om, d1, d2 = window(x / h)
            wgt = np.prod(om, axis=1)
            gw = np.zeros((rows.size, FIELD_DIM))  # grad w (zero along untiled axes)
            for a in range(d):
                gw[:, a] = d1[:, a] / h * np.prod(np.delete(om, a, axis=1), axis=1)
            phi = basis.phi(x)
            grads = basis.grad_phi(x)  # (n, 3, m)
            v = W[ids[rows, o]]  # (n, m)
            s = np.einsum("km,km->k", phi, v)
            gv = np.einsum("kbm,km->kb", grads, v)  # grad Phi_t (n, 3)
            field[rows] += s[:, None] * gw + wgt[:, None] * gv
            if not jacobians:
                continue
            J[rows, o] = gw[:, :, None] * phi[:, None, :] + wgt[:, None, None] * grads
            if D is None:
                continue
            sec = basis.second_derivatives(x)
            for a in range(d):
                # d^2 w / dp_b dp_a for b < d (zero beyond)
                hw = np.zeros((rows.size, FIELD_DIM))
                for b in range(d):
                    if b == a:
                        f = d2[:, a] / h**2
                    else:
                        f = d1[:, a] * d1[:, b] / h**2
                    rest = [c for c in range(d) if c not in (a, b)]
                    hw[:, b] = f * (np.prod(om[:, rest], axis=1) if rest else 1.0)
                Hv = np.column_stack(
                    [np.einsum("km,km->k", sec[min(a, b), max(a, b)], v) for b in range(FIELD_DIM)]
                )
                D[rows, :, a] += (
                    gv[:, a : a + 1] * gw + s[:, None] * hw + gw[:, a : a + 1] * gv
                    + wgt[:, None] * Hv
                )  # fmt: skip
        return field, ids, J, D

    def field(self, P: np.ndarray, W: np.ndarray) -> np.ndarray:
        """(N, 3) field at P (N, d), in chunks."""
        P = np.asarray(P, dtype=float)
        out = np.empty((P.shape[0], FIELD_DIM))
        for s in range(0, P.shape[0], self.CHUNK):
            out[s : s + self.CHUNK] = self.evaluate(P[s : s + self.CHUNK], W, jacobians=False)[0]
        return out

    def design(self, P: np.ndarray) -> sps.csr_matrix:
        """The field at P (N, d) as a sparse linear map of the stacked weights: (3 N, T m),
        component-major rows (all x components, then y, then z)."""
        P = np.asarray(P, dtype=float)
        N = P.shape[0]
        m_ = self.per_tile
        zero = np.zeros((self.num_tiles, m_))
        _, ids, J, _ = self.evaluate(P, zero, positions=False)
        rows, cols, vals = [], [], []
        for o in range(ids.shape[1]):
            live = np.flatnonzero(ids[:, o] >= 0)
            for b in range(FIELD_DIM):
                rows.append(np.repeat(b * N + live, m_))
                cols.append((ids[live, o][:, None] * m_ + np.arange(m_)).ravel())
                vals.append(J[live, o, b].ravel())
        return sps.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(FIELD_DIM * N, self.num_weights),
        )

    def prior_variances(self, sigma_f: Any, lengthscale: Any) -> Any:
        """(m,) prior variances of one tile's weights (every tile has the same): numpy for
        numbers, a CasADi (m, 1) column when either is a CasADi symbol."""
        S = self.basis.prior_variances("curl_free", sigma_f, lengthscale)
        return S if isinstance(S, (ca.MX, ca.SX, ca.DM)) else np.asarray(S)

    def covariance(
        self, X1: np.ndarray, X2: np.ndarray, sigma_f: float, lengthscale: float
    ) -> np.ndarray:
        """The tiled map's prior covariance of the field at X1 and X2, (3 N1, 3 N2)
        component-major like ``casmag.gp.kernels.CurlFree.matrix``."""
        S = np.tile(self.prior_variances(sigma_f, lengthscale), self.num_tiles)
        A1, A2 = self.design(X1), self.design(X2)
        return np.asarray((A1.multiply(S[None, :]) @ A2.T).todense())
