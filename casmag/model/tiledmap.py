"""The tiled map (casmag.gp.tiles) inside the MAP problem: cost, gradient and Gauss-Newton
Hessian of the magnetometer block with numpy, read in the map frame.

Every sample touches the 2^d tiles at the corners of its grid cell, so the Hessian of the
magnetometer block is sparse: the weight block holds an m x m block for each pair of
tiles near enough to share a point (for the Hilbert tiles, indices at most one apart
along every axis) that some sample's pattern holds both of (:func:`shared_pairs`), and
the knot-weight border holds, for each knot, the tiles around its samples' starting
positions. Its size grows with the number of tiles the path visits, not with the area of
the box around the path, and neither does the time to fill it (one BLAS product per
occupied grid cell).

The border's pattern is fixed when the NLP is built, from the samples' positions then
(``home``: the nearest grid point of each sample): tiles within one index of it along every
axis, so a sample can move at least h/2 in any direction within a solve and keep its
Hessian entries. Entries of a sample that moved further are left out of the Gauss-Newton
Hessian (the gradient stays exact, so IPOPT still converges, more slowly);
:attr:`TiledGaussNewton.dropped` counts the (sample, tile, knot) terms and the tile pairs
left out per evaluation, and the solve's statistics carry the largest count
(``hessian_terms_dropped``).

A thinner pattern, only the 2^d tiles of the cell each sample was in, makes a cheaper KKT
factor but drops far more terms. Measured 2026-11-29, each run alone: on ``library``
(ARKit, 74 tiles, 4 IPOPT iterations from the dead reckoning) IPOPT's search directions
took 17 s against 31-42 s; but the planar walk of ``problems/planar/walk.yaml`` with 1,500
samples over 30 x 20 m (seed 1, curl-free tiles, growing warm start) went from 584 s,
28 final iterations and RMSE 7.90 -> 0.31 m to every stage ending in its five re-homed
rounds and the last at the iteration limit (1,175 s, cost 43,435 against 2,847).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from itertools import product
from typing import Any

import casadi as ca
import numpy as np
import scipy.sparse as sps
from scipy.optimize import brentq

from casmag.gp.bumps import bump_key
from casmag.gp.kernels import FIELD_DIM
from casmag.gp.reduced_rank import Domain, default_num_basis
from casmag.gp.tiles import TiledBasis, TileGrid
from casmag.linalg import solve_spd
from casmag.model.knots import Knots
from casmag.model.rotated import RotatedMapLayout
from casmag.model.rrmap import (
    HessianCallback,
    MapLayout,
    MapModel,
    Pattern,
    constant_field_values,
    knot_chain_values,
)

#: Tile spacing h, margin of a tile's basis box beyond the tile's support and the box's
#: half-depth in z for planar positions, all in lengthscales, and the basis' frequencies up
#: to TILE_OMEGA / l: 166 functions per tile. Chosen on three measurements (the README's
#: Tiled map section has them all):
#: - field prediction from 300 noisy samples of a GP draw (RMSE, exact GP 0.0892): the
#:   blend's extra field variance falls as (l / h)^2, so the spacing matters most (h = 2 / 3 /
#:   4 l: 0.110 / 0.100 / 0.093 with margin 2 l); the margin hardly matters, because the
#:   blending weight vanishes towards the box's faces (h = 3 l: 2 / 1 / 0.5 l, 0.0998 /
#:   0.0997 / 0.1002);
#: - the prior variance of the vertical component (planar positions): 0.80 of the exact
#:   kernel's with the box 1.5 l deep, 0.95 at 2 l (the Dirichlet faces in z);
#: - positions (120-sample walk, seeds 2, 3 and 4; exact GP 0.0102 / 0.0105 / 0.0150 m):
#:   these defaults 0.0098 / 0.0111 / 0.0148 m; with the box 1.5 l deep (seeds 2, 3):
#:   0.0101 / 0.0111 m, h = 3 l 0.0102 / 0.0119 m, frequencies to 3 / l 0.0106 / 0.0112 m;
#:   the first layout tried (h = 3 l, margin and
#:   depth 2 l, 4 / l: 325 functions) 0.0119 / 0.0120 m in ten times the time.
#: Frequencies to 3 / l (101 functions a tile) on a building-floor walk
#: (``problems/planar/walk.yaml``, 1,500 samples over 30 x 20 m, curl-free tiles, growing
#: warm start, each run alone, 2026-11-29): seed 1 0.825 m, not trusted, in 232 s wall
#: against 0.313 m, trusted, in 584 s at 3.5 / l; seed 2 (wrong basin both, flagged)
#: 3.25 m in 1,034 s against 11.36 m in 1,909 s, from 7.90 and 8.75 m. Fewer functions
#: cost accuracy before they save the time the building scale needs.
TILE_SPACING = 4.0
TILE_MARGIN = 0.5
TILE_DEPTH = 2.0
TILE_OMEGA = 3.5


#: The tiled map's basis: ``bumps`` (casmag.gp.bumps: compactly supported bumps on a
#: lattice of BUMP_SPACING l, radius BUMP_RADIUS l; the default) or ``hilbert`` (one
#: reduced-rank Hilbert basis per tile of TILE_SPACING l, blended). Measured 2026-12-02,
#: each run alone: the building-floor walk (``problems/planar/walk.yaml``, 1,500 samples
#: over 30 x 20 m, curl-free tiles, seed 1) 64-65 s wall, 1.5 GiB, RMSE 7.90 -> 0.165 m with
#: the bumps against 420 s, 4.6 GiB, 0.313 m with the Hilbert tiles; seed 2 3:22 to a wrong
#: basin (4.74 m, flagged) where the Hilbert tiles took 1,909 s to 11.36 m (2026-11-29);
#: the 120-sample walk of the tests, seeds 2 / 3: 0.0106 / 0.0104 m and mean 1-sigma
#: 0.0131 / 0.0101 m against the exact GP's 0.0102 / 0.0105 m and 0.0132 / 0.0101 m.
#: Every motion model takes the bumps since 2026-12-06 (the translational model had kept
#: the Hilbert tiles, on walks where the bumps' lattice was 0.75 l; :func:`bump_spacing`
#: now lays it from the field's strength). Measured 2026-12-06, each run alone, 4,000
#: samples over 6 x 6 m in the dipole field, RMSE after [m] bumps / Hilbert:
#: ``problems/bench/walk.yaml`` (curl-free, the file's l = 0.35 m, no warm start) seeds
#: 1 / 2 / 3 0.0093 / 0.0097, 0.0615 / 0.0881, 0.0132 / 0.0084 (16 / 16, 61 / 41, 46 / 45
#: iterations; 1.9 against 1.3 GiB); ``casmag slam`` on ``casmag.experiments.dipolewalk``
#: recordings (hyperparameters estimated) seeds 1 / 2 0.0251 / 0.0236 (Hilbert of
#: 2026-12-02) and 0.0273 / 0.0514 m, 3:03 against 4:03-4:26 wall, 2.2-2.4 against 3.8-4.2
#: GiB. Over 20 x 20 m (10,000 samples, its 4,000-sample stage) the bumps took 18.0 s per
#: IPOPT iteration and 2.2 GiB, the Hilbert tiles 48.3 s: each point lies under four
#: tiles of 166 functions coupled densely to their neighbours, and the KKT factor fills
#: accordingly (IPOPT's timing statistics there: the linear solves 92 % of an iteration
#: with the Hilbert tiles, 79 % with the bumps).
#: ``model.gp.tile_basis: hilbert`` keeps the Hilbert tiles.
TILE_BASES = ("bumps", "hilbert")
TILE_BASIS = "bumps"

#: The bump lattice's spacing and the bumps' radius in lengthscales, where the taper
#: starts (a fraction of R^2) and the cells of slack in the Hessian's pattern
#: (:func:`home_tiles`). Spacing, radius and taper chosen by the field covariance against
#: the exact curl-free kernel at 200 points over 3 x 3 m (l = 0.4 m, planar; largest entry
#: error over the largest entry, the variance ratio's range): h = l, R = 2 l: 0.21,
#: 0.79-1.17; h = 0.75 l, R = 2.2 l: 0.049, 0.98-1.02; h = 0.75 l, R = 3 l (60 nodes a
#: sample): 0.0054, 0.995-1.005; h = l, R = 3 l: 0.14; the Hilbert tiles: 0.51, 0.95-1.51.
#: R = 2.2 l located the 120-sample walk (seed 2) at 0.0060 m with a mean 1-sigma of
#: 0.0095 m against the exact GP's 0.0102 and 0.0132 m: a bump cut short is a prior with
#: more high-frequency power than the squared exponential; R = 2.8-3 l agree with it.
#: The slack: with none, the building-floor walk needed five re-homed rounds in its last
#: stage (the samples left their pattern) and ``library`` (ARKit) ended at the iteration
#: limit; with 2 cells, one round each on the walk (66 s, the same estimate) and
#: ``library`` converged. Positions ask for more than the covariance shows: on 4,000-sample
#: translational dipole walks (field 14 times the noise) ``casmag slam`` located at 0.098 /
#: 0.236 m with h = 0.75 l, 0.076 m (seed 2) at 0.6 l, 0.045 m at 0.5 l, the Hilbert tiles
#: 0.024 / 0.051 m (README, Tiled map); the planar floor walk did not gain from 0.5 l (0.202 against
#: 0.165 m, 8 min against 64-65 s). BUMP_SPACING is now the coarsest lattice:
#: :func:`bump_spacing` lays a finer one where the field is strong against the noise.
#: A shorter radius shrinks the KKT factor but not the solve (measured 2026-12-07, each run
#: alone, ``problems/bench/walk.yaml`` in the dipole field): 10,000 samples over 50 x 70 m
#: from the truth 22.0 / 14.0 / 10.8 s an IPOPT iteration at 3 / 2.5 / 2.2 l; 4,000
#: samples over 6 x 6 m, seeds 1 / 2, at 2.5 l 48 / 91 iterations against 16 / 46 at 3 l
#: (70 / 139 s against 46 / 110 s), RMSE 0.0208 / 0.0391 m against 0.0093 / 0.0615 m.
BUMP_SPACING = 0.75
BUMP_RADIUS = 3.0

#: The finest lattice :func:`bump_spacing` lays [lengthscales], and the part of the field
#: the lattice may leave out, as an amplitude over the magnetometer's noise.
BUMP_SPACING_FINEST = 0.5
BUMP_UNRESOLVED = 0.02
BUMP_TAPER = 0.6
BUMP_SLACK = 2


def unresolved_field(spacing: float) -> float:
    """The part of a curl-free field with the squared-exponential potential that a bump
    lattice of ``spacing`` lengthscales cannot hold: the RMS amplitude, over the field's
    own, of the field's spectrum (|w|^2 exp(-|w|^2 l^2 / 2) in the plane) beyond the
    lattice's Nyquist frequency pi / h, sqrt((1 + u) exp(-u)) with u = (pi l / h)^2 / 2.
    0.039 at 0.75 l, 0.0041 at 0.6 l, 0.00024 at 0.5 l."""
    u = 0.5 * (np.pi / float(spacing)) ** 2
    return float(np.sqrt((1.0 + u) * np.exp(-u)))


def bump_spacing(sigma_f: float | None, lengthscale: float, sigma_m: float | None) -> float:
    """The bump lattice's spacing in lengthscales for the curl-free field of ``sigma_f``
    and ``lengthscale`` read with the noise ``sigma_m`` (its components have the standard
    deviation sigma_f / l, so the field is sigma_f / (l sigma_m) times the noise): the
    coarsest spacing, between BUMP_SPACING_FINEST and BUMP_SPACING, whose
    :func:`unresolved_field` times that ratio is at most BUMP_UNRESOLVED; BUMP_SPACING when
    sigma_f or sigma_m is not known. A coarse-to-fine stage's longer lengthscale is a
    smoother field, so its lattice is coarser in its lengthscales.

    What a lattice leaves out does not average away over the samples: it moves the path.
    Measured 2026-12-02, each run alone (``casmag solve problems/planar/walk.yaml --set
    simulation.trajectory.samples=750 --set "simulation.trajectory.area=[15.0, 10.0]"
    --set model.gp.form=tiled --set model.gp.kernel=curl_free``, the field 17-20 times its
    noise): seeds 1 / 2 / 3 RMSE 0.080 / 0.425 / 0.114 m at 0.75 l (seed 2 not trusted,
    mean NEES 196), 0.051-0.056 / 0.066 / 0.053 m at 0.5-0.6 l, one box (seed 1) 0.052 m;
    with ten times the noise (the field 2.1 times it) 0.175 m at 0.75 l, 0.142 m at
    0.55 l. This rule takes 0.55 l and 0.65 l there; 0.75 l below about half the noise."""
    if sigma_f is None or sigma_m is None:
        return BUMP_SPACING
    field_to_noise = float(sigma_f) / (float(lengthscale) * float(sigma_m))
    if not np.isfinite(field_to_noise) or field_to_noise <= 0.0:
        return BUMP_SPACING
    if unresolved_field(BUMP_SPACING) * field_to_noise <= BUMP_UNRESOLVED:
        return BUMP_SPACING
    if unresolved_field(BUMP_SPACING_FINEST) * field_to_noise >= BUMP_UNRESOLVED:
        return BUMP_SPACING_FINEST
    excess = lambda h: unresolved_field(h) * field_to_noise - BUMP_UNRESOLVED  # noqa: E731
    return float(brentq(excess, BUMP_SPACING_FINEST, BUMP_SPACING, xtol=1e-6))


def tile_grid(
    X: np.ndarray,
    lengthscale: float,
    spacing: float | None = None,
    reach: float | None = None,
    basis: str | None = None,
    lattice: float | None = None,
    field: tuple[float, float] | None = None,
) -> TileGrid:
    """The tiles for positions X (N, d): spacing h [m] (default TILE_SPACING l, or for bumps
    ``lattice`` l, default :func:`bump_spacing` from ``field``, the field's sigma_f and the
    magnetometer's sigma_m, BUMP_SPACING l without it), every tile whose support comes
    within ``reach`` (default 3 l, as the box margin of the global map) of a position, and
    the tile basis (``basis``, default TILE_BASIS: curl-free, frequencies up to TILE_OMEGA
    / l, or bumps of radius BUMP_RADIUS l)."""
    X = np.asarray(X, dtype=float)
    ell = float(lengthscale)
    reach = 3.0 * ell if reach is None else float(reach)
    kind = TILE_BASIS if basis is None else basis
    if kind not in TILE_BASES:
        raise ValueError(f"tile basis {kind!r} is not one of {', '.join(TILE_BASES)}")
    if kind == "bumps":
        if spacing is not None:
            h = float(spacing)
        elif lattice is not None:
            h = float(lattice) * ell
        else:
            sigma_f, sigma_m = (None, None) if field is None else field
            h = bump_spacing(sigma_f, ell, sigma_m) * ell
        radius = BUMP_RADIUS * ell
        # nodes whose bump reaches a point within `reach` of a position
        return TileGrid.around(
            X,
            h,
            max(reach + radius - h, 0.0),
            bump_key(ell, BUMP_RADIUS, BUMP_TAPER, BUMP_SLACK),
        )
    h = TILE_SPACING * ell if spacing is None else float(spacing)
    mg = TILE_MARGIN * ell
    d = X.shape[1]
    half = [h + mg] * d + ([TILE_DEPTH * ell] if d == 2 else [])
    domain = Domain(np.zeros(FIELD_DIM), np.array(half))
    m = default_num_basis(domain, ell, omega_factor=TILE_OMEGA, max_basis=1 << 20)
    return TileGrid.around(X, h, reach, ((0.0,) * FIELD_DIM, tuple(half), m))


def in_pattern(keys: np.ndarray, key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each ``key`` sits in the sorted pattern ``keys`` and whether it is there (an
    empty pattern holds none: every sample left the tiles it was laid around)."""
    pos = np.searchsorted(keys, key)
    ok = pos < keys.size
    ok[ok] = keys[pos[ok]] == key[ok]
    return pos, ok


def home_tiles(tiles: TiledBasis, home: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tiles a sample whose nearest grid point is ``home`` (N, d) touches from any
    point within h / 2 + s h of it (s the basis' ``home_slack``): the corner tiles of the
    (2 + 2 s)^d cells around that grid point (for the Hilbert tiles, s = 0: those within
    one index along every axis; :func:`home_offsets`). As (samples, tile ids), flat
    arrays, each pair once, tiles the map lacks left out."""
    ids = tiles.ids_at(np.asarray(home, dtype=np.int64)[:, None, :] + home_offsets(tiles)[None])
    k, o = np.nonzero(ids >= 0)
    return k, ids[k, o]


def home_offsets(tiles: TiledBasis) -> np.ndarray:
    """(n, d) the tile index offsets from a sample's home grid point of the tiles
    :func:`home_tiles` gives it, sorted."""
    s = tiles.home_slack
    cells = np.array(list(product(range(-1 - s, s + 1), repeat=tiles.grid.dim)), dtype=np.int64)
    return np.unique(
        (cells[:, None, :] + tiles.corners[None, :, :]).reshape(-1, tiles.grid.dim), axis=0
    )


def shared_pairs(tiles: TiledBasis, home: np.ndarray) -> np.ndarray:
    """(pairs, 2) tile ids t <= t', sorted: every tile with itself, and the pairs of tiles
    that a sample's Hessian pattern (:func:`home_tiles`, homes ``home`` (N, d)) holds, near
    enough to share a point (:meth:`TiledBasis.pairs_among`). The weight block's pattern:
    a pair of :attr:`TiledBasis.neighbours` beyond every sample's pattern is a structural
    zero that IPOPT's linear solver would factor all the same."""
    held = np.zeros(tiles.num_tiles, dtype=bool)
    held[home_tiles(tiles, np.asarray(home, dtype=np.int64).reshape(-1, tiles.grid.dim))[1]] = True
    return tiles.pairs_among(held)


def home_points(grid: TileGrid, P: np.ndarray) -> tuple[int, ...]:
    """The nearest grid point of each position P (N, d), flattened (a hashable key)."""
    n = np.rint((np.asarray(P, dtype=float) - np.array(grid.origin)) / grid.spacing)
    return tuple(int(v) for v in n.astype(np.int64).ravel())


class TiledMapModel(MapModel):
    """The magnetometer block's data at a point (x, p) (:class:`MapModel`'s layout; the
    weights are the tiles' (T, m), tile after tile) and its cost and gradient."""

    CHUNK = 1024

    def __init__(self, tiles: TiledBasis, knots: Knots, dim: int, layout: MapLayout) -> None:
        self.tiles, self.knots, self.dim, self.lay = tiles, knots, dim, layout
        self.n_w = tiles.num_weights

    def weights(self, w: np.ndarray) -> np.ndarray:
        return w.reshape(self.tiles.num_tiles, self.tiles.per_tile)

    def cost(self, x: np.ndarray, p: np.ndarray) -> float:
        P, w, c, Y, sigma = self.unpack(x, p)
        W = self.weights(w)
        total = 0.0
        for r in self.chunks():
            total += float(np.sum((Y[r] - self.tiles.field(P[r], W) - c) ** 2))
        return 0.5 * total / sigma**2

    def sample_gradients(
        self,
        P: np.ndarray,
        W: np.ndarray,
        c: np.ndarray,
        Y: np.ndarray,
        cells: np.ndarray | None = None,
    ) -> tuple[np.ndarray, ...]:
        """Each sample's own gradient of 0.5 |y - m - c|^2 (not divided by sigma_m^2) at
        rows P (k, d): its corner tiles (k, 2^d), the gradients in its position (k, d) and
        in its corner tiles' weights (k, 2^d, m), the residuals (k, 3), dm/dv (k, 2^d, 3,
        m) and dm/dp (k, 3, d). ``cells``: read in these grid cells (TiledBasis.evaluate)."""
        field, ids, J, D = self.tiles.evaluate(P, W, cells=cells)
        R = Y - field - c
        g_p = -np.einsum("kc,kca->ka", R, D)
        return ids, g_p, -np.einsum("kobm,kb->kom", J, R), R, J, D

    def gradient(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        kn, d, lay = self.knots, self.dim, self.lay
        P, w, c, Y, sigma = self.unpack(x, p)
        W = self.weights(w)
        T, m = W.shape
        g_P = np.empty((kn.n, d))
        g_W = np.zeros((T, m))
        g_c = np.zeros(FIELD_DIM)
        for r in self.chunks():
            ids, g_P[r], g_w, R, _, _ = self.sample_gradients(P[r], W, c, Y[r])
            contrib = -g_w  # (n, 2^d, m)
            live = ids >= 0
            sel = sps.csr_matrix(
                (np.ones(int(live.sum())), (ids[live], np.arange(int(live.sum())))),
                shape=(T, int(live.sum())),
            )
            g_W -= sel @ contrib[live]
            g_c -= R.sum(axis=0)
        out = np.zeros(lay.n_x)
        out[lay.C : lay.C + kn.count * d] = (kn.matrix.T @ g_P).ravel(order="F")
        out[lay.W : lay.W + self.n_w] = g_W.ravel()
        if lay.c is not None:
            out[lay.c : lay.c + FIELD_DIM] = g_c
        return out / sigma**2

    def residual_jacobian(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, Any]:
        """The whitened residuals e = (y - m - c) / sigma_m (N, 3) at x and their Jacobian
        (3N, n_x) with respect to x, a scipy CSR matrix whose rows are the residuals sample
        by sample: in the knot corrections through P = Q + A C, the corner tiles' weights
        and the constant field (casmag.solver.uncertainty's correction for correlated
        residuals; J^T J is the block's Gauss-Newton Hessian)."""
        kn, d, lay = self.knots, self.dim, self.lay
        P, w, c, Y, sigma = self.unpack(x, p)
        W = self.weights(w)
        m = W.shape[1]
        N, inv = kn.n, 1.0 / sigma
        e = np.empty((N, FIELD_DIM))
        D = np.empty((N, FIELD_DIM, d))
        rows, cols, vals = [], [], []
        for r in self.chunks():
            field, ids, J, D[r] = self.tiles.evaluate(P[r], W)
            e[r] = (Y[r] - field - c) * inv
            k, o = np.nonzero(ids >= 0)
            row = 3 * (r.start + k)[:, None, None] + np.arange(FIELD_DIM)[None, :, None]
            col = lay.W + ids[k, o][:, None, None] * m + np.arange(m)[None, None, :]
            rows.append(np.broadcast_to(row, (k.size, FIELD_DIM, m)).ravel())
            cols.append(np.broadcast_to(col, (k.size, FIELD_DIM, m)).ravel())
            vals.append(-inv * J[k, o].ravel())
        shape = (FIELD_DIM * N, lay.n_x)
        out = sps.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=shape
        )
        # positions: rows 3k + b, columns a N + k of P (column-major), then dP/dC = I_d (x) A
        k_b = np.arange(FIELD_DIM * N)
        at = (k_b, k_b // FIELD_DIM)
        JP = sps.hstack(
            [sps.csr_matrix((-inv * D[:, :, a].ravel(), at), shape=(shape[0], N)) for a in range(d)]
        )
        JC = (JP @ sps.block_diag([kn.matrix] * d)).tocoo()
        out = out + sps.csr_matrix((JC.data, (JC.row, lay.C + JC.col)), shape=shape)
        if lay.c is not None:
            const = (k_b, lay.c + k_b % FIELD_DIM)
            out = out + sps.csr_matrix((np.full(k_b.size, -inv), const), shape=shape)
        return e, out.tocsr()


@dataclass(frozen=True)
class _Border:
    """The knot-weight border's (knot, tile) pairs, sorted by key knot * T + tile."""

    keys: np.ndarray
    knot: np.ndarray
    tile: np.ndarray


class TiledGaussNewton(HessianCallback):
    """Hessian (upper triangle) of the tiled magnetometer block: the knot block A^T
    diag(D^T D) A, the border A^T D^T J over the (knot, tile) pairs of the pattern, the
    weight block J^T J over neighbouring tile pairs, and the constant field's rows. Not
    scaled by lam_f (the caller multiplies), like
    :class:`casmag.model.rrmap.GaussNewtonHessian`.

    Those are the Gauss-Newton terms. In mode ``exact``, and in mode ``hybrid`` (the
    default) once the block's cost falls by less than :attr:`SWITCH` of itself, each
    sample's position block and its border against its tiles are the exact second
    derivatives instead: central differences of the sample's own gradient
    (:meth:`TiledMapModel.sample_gradients`) along each position axis, all samples at once
    (a sample's cost depends on its own position only); the weight and constant-field
    blocks have no second-order terms. Measured in README, Tiled map."""

    #: Central-difference step for positions [m].
    STEP = 1e-6
    #: hybrid: the exact terms after two evaluations in a row whose cost fell by less
    #: than SWITCH (20 %), not after one: a first Gauss-Newton step that mostly fits the
    #: map falls little, and the exact Hessian there is indefinite (IPOPT regularised it
    #: with 1e4, 10^3.5, 10^3; steps of 1e-2 against 3 in IPOPT's ||d||). Measured on
    #: 2026-11-28, each run alone, no warm start: 4,000 samples over 6 x 6 m in the dipole
    #: field 21 -> 17 iterations (137 -> 97 s in IPOPT; Gauss-Newton alone 25); the
    #: 2,000-sample walk (problems/bench/walk.yaml, curl-free) 22 -> 17 iterations (184 ->
    #: 135 s); the same positions. The global box went the other way on the real field
    #: (seq5-drift0.5: 46 -> 65 iterations), so it keeps one.
    SWITCH_AFTER = 2
    #: hybrid: and by less than one unit of the cost (a nat of the posterior), as well as
    #: less than 20 % of it. On a large map 20 % is reached at once: the cost is mostly the
    #: noise's, and the first Gauss-Newton steps lower it by a few per cent, so the exact
    #: terms came in at the third iteration, where they are indefinite (IPOPT regularised
    #: at every iteration, 10^2 down to 10^-1.1, ||d|| 2e-3 to 0.5). Measured 2026-12-07,
    #: each run alone, one batch from the dead reckoning (problems/bench/walk.yaml, the
    #: tiles, curl-free): 2,000 samples over 50 x 70 m in the dipole field 87 -> 46
    #: iterations (669 -> 269 s; Gauss-Newton alone stopped at 150, converging only
    #: linearly); 4,000 samples over 6 x 6 m (dipoles) 16 iterations either
    #: way, 49.7 -> 38.9 s solve; 2,000 samples over 6 x 6 m (Fourier field) 20 -> 13
    #: iterations, 40.7 -> 15.7 s; the same positions.
    SWITCH_UNITS = 1.0

    def __init__(
        self,
        name: str,
        model: TiledMapModel,
        home: tuple[int, ...],
        n_g: int = 0,
        mode: str = "hybrid",
    ) -> None:
        ca.Callback.__init__(self)
        self.set_mode(mode)
        self.model, self.n_g = model, n_g
        self.tiles, self.knots, self.dim, self.lay = (
            model.tiles, model.knots, model.dim, model.lay
        )  # fmt: skip
        home_arr = np.array(home, dtype=np.int64).reshape(-1, self.dim)
        self._border = self._border_pairs(home_arr)
        self._pairs = shared_pairs(self.tiles, home_arr)
        self._slots = PairSlots(self.tiles, self._pairs)
        self._pattern()
        self.construct(name, {})

    def reset(self) -> None:
        super().reset()
        self.dropped = []

    def residual_jacobian(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, Any]:
        """:meth:`TiledMapModel.residual_jacobian` (casmag.solver.uncertainty)."""
        return self.model.residual_jacobian(x, p)

    def _border_pairs(self, home: np.ndarray) -> _Border:
        tiles, kn = self.tiles, self.knots
        T = tiles.num_tiles
        # each knot's samples' homes once (a knot's samples mostly share a few)
        at = np.column_stack([np.concatenate([kn.left, kn.left + 1]), np.vstack([home, home])])
        at = np.unique(at, axis=0)
        k, ids = home_tiles(tiles, at[:, 1:])
        keys = np.unique(at[k, 0] * T + ids)
        return _Border(keys, keys // T, keys % T)

    def _pattern(self) -> None:
        K, d, lay = self.knots.count, self.dim, self.lay
        m, T = self.tiles.per_tile, self.tiles.num_tiles
        pat = Pattern()
        cidx = [lay.C + a * K + np.arange(K) for a in range(d)]
        pat.knot_chain(cidx)
        wm = np.arange(m)
        bd = self._border
        for a in range(d):  # (pair, weight) order
            pat.add((lay.C + a * K + bd.knot)[:, None], lay.W + bd.tile[:, None] * m + wm)
        rows, cols, self._ww_flat = weight_pair_pattern(self._pairs, m)
        pat.add(lay.W + rows, lay.W + cols)
        if lay.c is not None:
            pat.constant_field(cidx, lay.W + np.arange(T * m), lay.c)
        self._set_pattern(*pat.arrays(), lay.n_x, lay.n_p)

    def _exact_rows(
        self,
        P: np.ndarray,
        W: np.ndarray,
        c: np.ndarray,
        Y: np.ndarray,
        ids: np.ndarray,
        r: slice,
        s_pp: dict[tuple[int, int], np.ndarray],
        pairs: list[tuple[int, int]],
        rows_a: np.ndarray,
    ) -> None:
        """Replace the Gauss-Newton position products and border rows of the samples ``r``
        by their exact second derivatives (the differences read in each sample's own
        cell, so that its corner tiles stay those of ``ids``)."""
        cells = self.tiles.cells(P)
        (H_p, H_w), same = local_derivatives(
            lambda P_: self.model.sample_gradients(P_, W, c, Y, cells)[:3], [P], ids, self.STEP
        )
        idx = np.flatnonzero(same)
        for a, b in pairs:
            s_pp[a, b][r.start + idx] = 0.5 * (H_p[idx, a, b] + H_p[idx, b, a])
        rows_a[idx] = np.moveaxis(H_w, -1, 2)[idx]

    def values(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        kn, d, lay = self.knots, self.dim, self.lay
        m, T = self.tiles.per_tile, self.tiles.num_tiles
        N, K = kn.n, kn.count
        P, w, c, Y, sigma = self.model.unpack(x, p)
        W = self.model.weights(w)
        inv2 = 1.0 / sigma**2
        exact = self._use_exact(self.model.cost(x, p) if self.mode == "hybrid" else 0.0)
        left, alpha = kn.left, kn.alpha
        A = kn.matrix
        pairs = [(a, b) for a in range(d) for b in range(a, d)]
        s_pp = {ab: np.empty(N) for ab in pairs}
        own = {ab: np.zeros(K) for ab in pairs}  # knots' products of dropped pairs
        bd = self._border
        border = np.zeros((bd.keys.size, d, m))
        WW = np.zeros((self._pairs.shape[0], m, m))
        c_knot = np.zeros((FIELD_DIM, d, K)) if lay.c is not None else None
        c_w = np.zeros((FIELD_DIM, T, m)) if lay.c is not None else None
        dropped = 0
        for r in self.model.chunks():
            _, ids, J, D = self.tiles.evaluate(P[r], W)
            for a, b in pairs:
                s_pp[a, b][r] = np.einsum("kc,kc->k", D[:, :, a], D[:, :, b])
            # border: rows_a (n, 2^d, d, m) = sum_b D[k, b, a] J[k, o, b]
            rows_a = np.einsum("kba,kobm->koam", D, J)
            if exact:
                self._exact_rows(P[r], W, c, Y[r], ids, r, s_pp, pairs, rows_a)
            live = ids >= 0
            kk, oo = np.nonzero(live)
            lk, ak = left[r][kk], alpha[r][kk]
            for knot, factor in ((lk, 1.0 - ak), (lk + 1, ak)):
                key = knot * T + ids[kk, oo]
                pos, ok = in_pattern(bd.keys, key)
                ok &= factor != 0.0
                out_ = ~ok & (factor != 0.0)
                dropped += int(np.sum(out_))
                if out_.any():  # the dropped products' factors' own (add_own_tiles)
                    f2, Dk = factor[out_] ** 2, D[kk[out_]]
                    for a, b in pairs:
                        np.add.at(
                            own[a, b],
                            knot[out_],
                            f2 * np.einsum("kc,kc->k", Dk[:, :, a], Dk[:, :, b]),
                        )
                    add_own_tiles(WW, self._slots, ids, kk[out_], oo[out_], J)
                sel = sps.csr_matrix(
                    (factor[ok], (pos[ok], np.arange(int(ok.sum())))),
                    shape=(bd.keys.size, int(ok.sum())),
                )
                border += (sel @ rows_a[kk[ok], oo[ok]].reshape(-1, d * m)).reshape(-1, d, m)
            dropped += add_weight_pairs(WW, self._slots, ids, J)
            if c_knot is not None:
                j0, j1 = int(left[r.start]), int(left[r.stop - 1]) + 2
                Ar = A[r][:, j0:j1]
                for b in range(FIELD_DIM):
                    for a in range(d):
                        c_knot[b, a, j0:j1] += Ar.T @ D[:, b, a]
                add_constant_weights(c_w, ids, J)
        self.dropped.append(dropped)
        out = knot_chain_values(kn, s_pp, d, inv2, own)
        out += [border[:, a, :] * inv2 for a in range(d)]
        out.append(WW.ravel()[self._ww_flat] * inv2)
        if c_knot is not None:
            out += constant_field_values(c_knot, c_w.reshape(FIELD_DIM, -1), N, inv2)
        return np.concatenate([np.ravel(v) for v in out])


class PairSlots:
    """Where each pair of a grid cell's corner tiles sits in the weight block's pattern
    (``pairs`` (P, 2), t <= t', sorted, every tile with itself among them: :func:`shared_pairs`),
    read from a table instead of searched for.

    Tile ids ascend with the lexicographic order of the tile index, so for two corners of
    one cell the lower id is the corner whose offset is lexicographically smaller, and the
    pair is (t, the tile at t's index + their offset difference): a row per tile that is in
    a pair with another tile, a column per offset difference. The table is a lookup, so the
    slots of a cell's n_c (n_c + 1) / 2 corner pairs are one gather. Measured 2026-12-06 on
    a 1,500-sample planar walk over 30 x 20 m (124 corners a cell, 418,511 pairs): the
    weight block of an evaluation filled in 0.31-0.45 s against 1.04-1.19 s with a search
    per group of samples (``add_weight_pairs``); the table of 17.8 million pairs is laid in
    2.2 s."""

    def __init__(self, tiles: TiledBasis, pairs: np.ndarray) -> None:
        T, C = tiles.num_tiles, tiles.corners
        size = int(pairs.shape[0])
        # a tile's pair with itself is its first (the pairs are sorted, t <= t')
        self.self_slot = np.searchsorted(pairs[:, 0], np.arange(T))
        got = pairs[np.minimum(self.self_slot, size - 1)]
        if not (np.array_equal(got[:, 0], np.arange(T)) and np.array_equal(got[:, 1], got[:, 0])):
            raise ValueError("the pattern lacks a tile's pair with itself")
        o1, o2 = np.triu_indices(C.shape[0])
        diff = C[o2] - C[o1]
        first = np.argmax(diff != 0, axis=1)  # the first axis that differs decides
        neg = diff[np.arange(diff.shape[0]), first] < 0
        #: per corner pair p: its corners (a, b), the pair's lower id at corner a
        self.a, self.b = np.where(neg, o2, o1), np.where(neg, o1, o2)
        offs, self.col = np.unique(C[self.b] - C[self.a], axis=0, return_inverse=True)
        self.col = self.col.ravel()
        # each pair of the pattern into its row (its first tile) and column (the offset
        # from its first tile to its second, as a step in the lattice's flat index)
        p0, p1 = pairs[:, 0], pairs[:, 1]
        leads = np.zeros(T, dtype=bool)
        leads[p0[p0 != p1]] = True
        rows = np.flatnonzero(leads)
        self.row = np.full(T, -1, dtype=np.int64)
        self.row[rows] = np.arange(rows.size)
        idx = tiles.tile_index
        # strides of a box wide enough that distinct offsets make distinct jumps
        span = idx.max(axis=0) - idx.min(axis=0) + 2 * np.abs(offs).max(axis=0) + 1
        strides = np.concatenate([np.cumprod(span[::-1])[::-1][1:], [1]])
        flat = (idx - idx.min(axis=0)) @ strides
        jump = offs @ strides
        lo = int(jump.min())
        col_of = np.full(int(jump.max()) - lo + 1, -1, dtype=np.int64)
        col_of[jump - lo] = np.arange(offs.shape[0])
        step = flat[p1] - flat[p0] - lo
        inside = (step >= 0) & (step < col_of.size)
        col = col_of[np.where(inside, step, 0)]
        r = self.row[p0]
        on = r >= 0  # all but the pairs with itself of tiles paired with none else
        if not np.all(inside & (col >= 0) | ~on):
            raise ValueError("the pattern holds a pair no grid cell's corners make")
        index = np.int32 if size < np.iinfo(np.int32).max else np.int64
        self.table = np.full((rows.size, offs.shape[0]), -1, dtype=index)
        self.table[r[on], col[on]] = np.flatnonzero(on)

    def slots(self, tid: np.ndarray) -> np.ndarray:
        """(n_c (n_c + 1) / 2,) the slot of each corner pair (a, b) of a cell whose corner
        tiles are ``tid`` (n_c,): -1 where either tile is missing (-1) or the pattern
        lacks the pair."""
        ta, tb = tid[self.a], tid[self.b]
        r = self.row[np.maximum(ta, 0)]
        if tid.min() >= 0 and r.min() >= 0:
            return self.table[r, self.col]
        out = np.full(ta.size, -1, dtype=np.int64)
        live = (ta >= 0) & (tb >= 0)
        on = live & (r >= 0)
        out[on] = self.table[r[on], self.col[on]]
        own = live & (r < 0) & (ta == tb)
        out[own] = self.self_slot[ta[own]]
        return out


def add_weight_pairs(WW: np.ndarray, slots: PairSlots, ids: np.ndarray, J: np.ndarray) -> int:
    """Add J^T J of samples with corner tiles ``ids`` (n, n_c) and weight Jacobians J (n,
    n_c, 3, m) to the blocks WW (pairs, m, m) of the pattern's tile pairs (``slots``): one
    product per group of samples with the same corner tiles. The field's rotation does not
    enter (R R^T = I). A pair the pattern lacks (a sample beyond its home's tiles,
    :func:`shared_pairs`) is left out and its two tiles' own products added again, which
    keeps the matrix positive semi-definite (as :func:`add_own_tiles`); returns how many
    (sample, pair) products were left out."""
    m, n_c = J.shape[3], ids.shape[1]
    left_out = 0
    groups, inverse = np.unique(ids, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(groups.shape[0] + 1))
    a, b = slots.a, slots.b
    # where block (a, b)'s entry (i, j) sits in the group's product (n_c m, n_c m)
    wm = np.arange(m)
    flat = ((a[:, None, None] * m + wm[None, :, None]) * (n_c * m)
            + b[:, None, None] * m + wm[None, None, :])  # fmt: skip
    WWf = WW.reshape(-1, m * m)
    for g in range(groups.shape[0]):
        k = order[bounds[g] : bounds[g + 1]]
        Jg = J[k].transpose(0, 2, 1, 3).reshape(k.size * FIELD_DIM, n_c * m)
        G = Jg.T @ Jg
        tid = groups[g]
        at = slots.slots(tid)
        held = at >= 0
        if held.all():
            WWf[at] += G.ravel()[flat].reshape(-1, m * m)  # distinct pairs within a group
            continue
        WWf[at[held]] += G.ravel()[flat[held]].reshape(-1, m * m)
        lost = ~held & (tid[a] >= 0) & (tid[b] >= 0)
        if lost.any():
            left_out += int(lost.sum()) * k.size
            Gb = G.reshape(n_c, m, n_c, m)
            for corner in (a[lost], b[lost]):
                np.add.at(WW, slots.self_slot[tid[corner]], Gb[corner, :, corner, :])
    return left_out


def weight_pair_pattern(pairs: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The weight block's upper triangle over the tile pairs (pairs, 2) (t <= t'), pair
    after pair, row-major within a block (a tile with itself: its upper triangle): the
    rows and columns among the weights (tile t's at t m .. t m + m - 1) and, for values
    kept as WW (pairs, m, m), where each entry is in ``WW.ravel()``."""
    diag = pairs[:, 0] == pairs[:, 1]
    iu = np.triu_indices(m)
    full = np.divmod(np.arange(m * m), m)
    lengths = np.where(diag, iu[0].size, m * m)
    start = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    a = np.empty(int(lengths.sum()), dtype=np.int64)
    b = np.empty_like(a)
    for sel, (la, lb) in ((diag, iu), (~diag, full)):
        at = (start[sel][:, None] + np.arange(la.size)[None, :]).ravel()
        a[at] = np.tile(la, int(sel.sum()))
        b[at] = np.tile(lb, int(sel.sum()))
    pair = np.repeat(np.arange(pairs.shape[0]), lengths)
    rows = pairs[pair, 0] * m + a
    cols = pairs[pair, 1] * m + b
    return rows, cols, pair * m * m + a * m + b


def add_own_tiles(
    WW: np.ndarray, slots: PairSlots, ids: np.ndarray, kk: np.ndarray, oo: np.ndarray,
    J: np.ndarray,
) -> None:  # fmt: skip
    """Keep the Gauss-Newton matrix positive semi-definite where a sample's border against
    one of its tiles lies outside the pattern (the sample moved beyond its ``home``) and
    is dropped: each dropped product u^T v of the sample's position (or pose) Jacobian u
    and the tile's weight Jacobian v is replaced by u^T u and v^T v on the two diagonal
    blocks, since |u x + v y|^2 - 2 (u x)^T (v y) + |u x|^2 + |v y|^2 = |u x + v y|^2 +
    |u x - v y|^2. Dropped alone, the products leave the matrix indefinite (measured on
    the hand-held ``square`` recording: eigenvalues down to -3.8 against the whitened
    prior's 1), and IPOPT then regularises every iteration. This adds the v^T v: the
    weight Jacobians J (n, n_c, 3, m) of the dropped pairs' chunk rows ``kk`` and corners
    ``oo`` (in ``ids``) to their tiles' own blocks in WW; the caller adds the u^T u."""
    v = J[kk, oo]  # (dropped, 3, m)
    np.add.at(WW, slots.self_slot[ids[kk, oo]], np.einsum("kim,kin->kmn", v, v))


def add_constant_weights(c_w: np.ndarray, ids: np.ndarray, J: np.ndarray) -> None:
    """Add the constant field's rows against the weights, sum_k J_k (3, T, m): the same
    with and without a rotation (R R^T = I)."""
    T, m = c_w.shape[1], c_w.shape[2]
    k, o = np.nonzero(ids >= 0)
    t = ids[k, o]
    for b in range(FIELD_DIM):
        for j in range(m):
            c_w[b, :, j] += np.bincount(t, weights=J[k, o, b, j], minlength=T)


def tile_normal_equations(
    tiles: TiledBasis, P: np.ndarray, R: np.ndarray, upper: bool = False
) -> tuple[sps.csc_matrix, np.ndarray]:
    """A^T A (symmetric: both triangles, or with ``upper`` its upper triangle alone) and
    A^T r of the field's design A at positions P (N, d) against the residuals R (N, 3) (r
    component-major, as :meth:`TiledBasis.design`), assembled from one dense product per
    group of samples with the same corner tiles (:func:`add_weight_pairs`) instead of a
    sparse product of the design with itself: 4,000 samples on 49 tiles took 25.8 s as a
    sparse product."""
    T, m = tiles.num_tiles, tiles.per_tile
    P, R = np.asarray(P, dtype=float), np.asarray(R, dtype=float)
    pairs = shared_pairs(tiles, np.array(home_points(tiles.grid, P)).reshape(P.shape))
    slots = PairSlots(tiles, pairs)
    WW = np.zeros((pairs.shape[0], m, m))
    rhs = np.zeros((T, m))
    zero = np.zeros((T, m))
    for s in range(0, P.shape[0], TiledMapModel.CHUNK):
        r = slice(s, s + TiledMapModel.CHUNK)
        _, ids, J, _ = tiles.evaluate(P[r], zero, positions=False)
        add_weight_pairs(WW, slots, ids, J)
        contrib = np.einsum("kobm,kb->kom", J, R[r])
        k, o = np.nonzero(ids >= 0)
        for j in range(m):
            rhs[:, j] += np.bincount(ids[k, o], weights=contrib[k, o, j], minlength=T)
    wm = np.arange(m)
    shape = (pairs.shape[0], m, m)
    rows = np.broadcast_to(pairs[:, 0, None, None] * m + wm[None, :, None], shape)
    cols = np.broadcast_to(pairs[:, 1, None, None] * m + wm[None, None, :], shape)
    if upper:  # a tile with itself: the block's upper triangle (t < t': all of it)
        on = (rows <= cols).ravel()
        vals, i, j = WW.ravel()[on], rows.ravel()[on], cols.ravel()[on]
    else:
        lower = pairs[:, 0] != pairs[:, 1]  # the off-diagonal blocks again, transposed
        vals = np.concatenate([WW.ravel(), WW[lower].ravel()])
        i = np.concatenate([rows.ravel(), cols[lower].ravel()])
        j = np.concatenate([cols.ravel(), rows[lower].ravel()])
    AtA = sps.csc_matrix((vals, (i, j)), shape=(T * m, T * m))
    AtA.eliminate_zeros()  # neighbouring tiles no sample shares
    return AtA, rhs.ravel()


def ridge_tile_weights(
    tiles: TiledBasis,
    P: np.ndarray,
    Y: np.ndarray,
    c0: np.ndarray,
    sigma_m: float,
    sigma_f: float,
    lengthscale: float,
) -> np.ndarray:
    """Posterior mean of the tiles' weights given the field Y (N, 3) in the map frame at
    positions P (N, d), with the constant c0 removed: (m, T), the NLP's ``W``. A direct
    sparse solve of the normal equations (:func:`tile_normal_equations`) with MUMPS
    (casmag.linalg.solve_spd: 16.7 s against SuperLU's 189.5 s at 261 tiles, 2.9 against
    14.3 s on ``library``'s 74). Conjugate gradients preconditioned
    with the diagonal were used before and did not converge: at their 1,000 iterations
    the weights were 32 % (4,000 samples over 6 x 6 m, 49 tiles, 52 s) and 19 % (10,000
    samples over 20 x 20 m, 290 tiles, 264 s, 1.5 GiB) of the largest weight away from
    the solution; SuperLU took 6 s and 208 s (4.5 GiB) there. Preconditioned
    per tile instead, they needed 1,793 iterations (25 s) to 1e-8 at 49 tiles."""
    AtA, Atr = tile_normal_equations(tiles, P, np.asarray(Y) - c0, upper=True)
    S_t = np.tile(tiles.prior_variances(sigma_f, lengthscale), tiles.num_tiles)
    G = (AtA / sigma_m**2 + sps.diags(1.0 / S_t)).tocsc()
    w = solve_spd(G, Atr / sigma_m**2, upper=True)
    return w.reshape(tiles.num_tiles, tiles.per_tile).T


# --------------------------------------------------------------------------- rotated
class RotatedTiledModel:
    """The magnetometer read through the pose's rotation on a tiled map,

        0.5 sum_k |(y_k - R(o_k)^T (m(p_k) + c)) / sigma_m|^2,

    for motion models whose magnetometer turns with the body (planar with heading, IMU):
    cost and gradient with numpy on a :class:`casmag.model.rotated.RotatedMapLayout` (one
    position and orientation row per sample). The unknowns ``W`` (m, T) are the whitened
    weights V, the tiles' weights sqrt(S) V with S the prior variances (from the
    parameters sigma_f and lengthscale), as for the rotated global map: the prior
    variances span orders of magnitude, and with the weights themselves IPOPT crawled
    (planar walk of the tests: 150 iterations at a dual infeasibility of 5e-3)."""

    CHUNK = 1024

    def __init__(self, tiles: TiledBasis, rotation: ca.Function, layout: RotatedMapLayout):
        self.tiles, self.lay = tiles, layout
        self.n, self.d = layout.pos.shape
        self.r = layout.rot.shape[1]
        self.n_w = tiles.num_weights
        o, u = ca.SX.sym("o", self.r), ca.SX.sym("u", FIELD_DIM)
        aux = ca.SX.sym("aux", layout.aux.shape[1])
        R = rotation(o, aux)
        Rtu = ca.mtimes(R.T, u)
        self._rot = ca.Function("rot_jac", [o, aux, u], [ca.vec(R), ca.vec(ca.jacobian(Rtu, o))])
        self._maps: dict[int, ca.Function] = {}

    def chunks(self) -> list[slice]:
        return [slice(s, min(self.n, s + self.CHUNK)) for s in range(0, self.n, self.CHUNK)]

    def scale(self, p: np.ndarray) -> np.ndarray:
        """(m,) sqrt(S): a tile's weights over the unknowns (the same for every tile)."""
        lay = self.lay
        S = self.tiles.prior_variances(float(p[lay.sigma_f]), float(p[lay.lengthscale]))
        return np.sqrt(np.ravel(S))

    def unpack(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, ...]:
        """Positions (n, d), orientation unknowns (n, r) and parameters (n, a), the tiles'
        weights (T, m), constant field (3,), samples Y (n, 3) and sigma_m at the NLP point."""
        lay, n = self.lay, self.n
        P = x[lay.pos] if lay.pos_nominal is None else x[lay.pos] + p[lay.pos_nominal]
        o = x[lay.rot]
        aux = p[lay.aux] if lay.aux.shape[1] else np.zeros((n, 0))
        V = x[lay.W : lay.W + self.n_w].reshape(self.tiles.num_tiles, self.tiles.per_tile)
        W = V * self.scale(p)[None, :]
        c = x[lay.c : lay.c + FIELD_DIM] if lay.c is not None else np.zeros(FIELD_DIM)
        Y = p[lay.Y : lay.Y + FIELD_DIM * n].reshape(n, FIELD_DIM, order="F")
        return P, o, aux, W, c, Y, float(p[lay.sigma_m])

    def rotations(
        self, o: np.ndarray, aux: np.ndarray, u: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """R (k, 3, 3) of each row and d(R^T u)/do (k, 3, r)."""
        k = o.shape[0]
        f = self._maps.get(k)
        if f is None:
            f = self._maps[k] = self._rot.map(k)
        Rv, Jv = f(o.T, aux.T, u.T)
        R = np.asarray(Rv).T.reshape(k, 3, 3, order="F")
        return R, np.asarray(Jv).T.reshape(k, 3, self.r, order="F")

    def residuals(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """(n, 3) y_k - R_k^T (m(p_k) + c), not divided by sigma_m."""
        P, o, aux, W, c, Y, _ = self.unpack(x, p)
        out = np.empty((self.n, FIELD_DIM))
        for r in self.chunks():
            u = self.tiles.evaluate(P[r], W, jacobians=False)[0] + c
            R, _ = self.rotations(o[r], aux[r], u)
            out[r] = Y[r] - np.einsum("kba,kb->ka", R, u)
        return out

    def cost(self, x: np.ndarray, p: np.ndarray) -> float:
        sigma = float(p[self.lay.sigma_m])
        return 0.5 * float(np.sum(self.residuals(x, p) ** 2)) / sigma**2

    def sample_gradients(
        self,
        P: np.ndarray,
        o: np.ndarray,
        aux: np.ndarray,
        W: np.ndarray,
        c: np.ndarray,
        Y: np.ndarray,
        cells: np.ndarray | None = None,
    ) -> tuple[np.ndarray, ...]:
        """Each sample's own gradient of 0.5 |y - R^T (m + c)|^2 (not divided by
        sigma_m^2) at rows P (k, d), o (k, r): its corner tiles (k, 2^d) and the gradients
        in its position and orientation (k, d + r), in its corner tiles' weights (k, 2^d,
        m) and in the constant field (k, 3); plus the block's Jacobian pieces R (k, 3, 3),
        dm/dp (k, 3, d), d(R^T u)/do (k, 3, r) and dm/dv (k, 2^d, 3, m). ``cells``: read in
        these grid cells (TiledBasis.evaluate)."""
        field, ids, J, D = self.tiles.evaluate(P, W, cells=cells)
        u = field + c
        R, Jo = self.rotations(o, aux, u)
        e = Y - np.einsum("kba,kb->ka", R, u)
        Re = np.einsum("kab,kb->ka", R, e)  # the residual in the map frame
        g_loc = np.concatenate(
            [-np.einsum("kb,kba->ka", Re, D), -np.einsum("ka,kai->ki", e, Jo)], axis=1
        )
        g_w = -np.einsum("kobm,kb->kom", J, Re)
        return ids, g_loc, g_w, -Re, R, D, Jo, J

    def gradient(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        lay, d = self.lay, self.d
        P, o, aux, W, c, Y, sigma = self.unpack(x, p)
        T, m = W.shape
        g_loc = np.empty((self.n, d + self.r))
        g_W, g_c = np.zeros((T, m)), np.zeros(FIELD_DIM)
        for r in self.chunks():
            ids, g_loc[r], g_w, g_ck, *_ = self.sample_gradients(P[r], o[r], aux[r], W, c, Y[r])
            live = ids >= 0
            np.add.at(g_W, ids[live], g_w[live])
            g_c += g_ck.sum(axis=0)
        out = np.zeros(lay.n_x)
        np.add.at(out, lay.pos.ravel(), g_loc[:, :d].ravel())
        np.add.at(out, lay.rot.ravel(), g_loc[:, d:].ravel())
        out[lay.W : lay.W + self.n_w] = (g_W * self.scale(p)[None, :]).ravel()
        if lay.c is not None:
            out[lay.c : lay.c + FIELD_DIM] = g_c
        return out / sigma**2

    def residual_jacobian(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, Any]:
        """The whitened residuals e = (y - R^T (m + c)) / sigma_m (n, 3) at x and their
        Jacobian (3n, n_x) with respect to x, a scipy CSR matrix whose rows are the
        residuals sample by sample: in each sample's position and orientation unknowns, its
        corner tiles' whitened weights and the constant field (as
        casmag.model.rotated.RotatedFieldGaussNewton.residual_jacobian for the global map)."""
        lay, n = self.lay, self.n
        P, o, aux, W, c, Y, sigma = self.unpack(x, p)
        inv, scale, m = 1.0 / sigma, self.scale(p), W.shape[1]
        local = np.hstack([lay.pos, lay.rot])  # (n, nl)
        e = np.empty((n, FIELD_DIM))
        rows, cols, vals = [], [], []

        def add(row: np.ndarray, col: np.ndarray, val: np.ndarray) -> None:
            rows.append(np.broadcast_to(row, val.shape).ravel())
            cols.append(np.broadcast_to(col, val.shape).ravel())
            vals.append(val.ravel())

        comp = np.arange(FIELD_DIM)
        for r in self.chunks():
            ids, _, _, minus_Re, R, D, Jo, J = self.sample_gradients(P[r], o[r], aux[r], W, c, Y[r])
            Rt = np.transpose(R, (0, 2, 1))  # Rt[k, a, b] = R_k[b, a]
            e[r] = -np.einsum("kab,kb->ka", Rt, minus_Re) * inv
            row = 3 * np.arange(r.start, r.stop)[:, None] + comp  # (k, 3)
            loc = -inv * np.concatenate([np.einsum("kab,kbj->kaj", Rt, D), Jo], axis=2)
            add(row[:, :, None], local[r][:, None, :], loc)
            k, c_ = np.nonzero(ids >= 0)
            Jw = -inv * np.einsum("kab,kbi->kai", Rt[k], J[k, c_]) * scale
            weight = lay.W + ids[k, c_][:, None] * m + np.arange(m)  # (k, m)
            add(row[k][:, :, None], weight[:, None, :], Jw)
            if lay.c is not None:
                add(row[:, :, None], (lay.c + comp)[None, None, :], -inv * Rt)
        out = sps.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(FIELD_DIM * n, lay.n_x),
        )
        return e, out


class RotatedTiledGaussNewton(HessianCallback):
    """Hessian (upper triangle, not scaled by lam_f) of :class:`RotatedTiledModel`: per
    sample the block of its position and orientation unknowns, L_k^T L_k with L_k =
    -[R^T dm/dp, d(R^T u)/do] / sigma_m; the border of those unknowns against the tiles
    around the sample's ``home`` grid point (within one index along every axis, fixed at
    construction as in :class:`TiledGaussNewton`; terms of a sample that moved further are
    dropped and counted); the weight block over neighbouring tile pairs and the constant
    field's rows, both as without a rotation (R R^T = I).

    Those are the Gauss-Newton terms. In mode ``exact``, and in mode ``hybrid`` (the
    default) once the block's cost falls by less than :attr:`SWITCH` of itself, the blocks
    that involve a sample's position or orientation are its exact second derivatives
    instead: central differences of the sample's own gradient
    (:meth:`RotatedTiledModel.sample_gradients`) in each of its d + r local unknowns, all
    samples at once (a sample's cost depends on its own pose only), 2 (d + r) extra
    evaluations; the weight and constant-field blocks have no second-order terms (the
    residual is linear in them). Measured on the planar walk of the tests (186 samples,
    25 tiles): Gauss-Newton alone stopped at the iteration limit (150) at a dual
    infeasibility of 3e-3, its positions as good as the box's (0.0107 m against 0.0116)
    but the objective creeping by 1e-7 per iteration: the second-order terms of the
    field (the exact position block has eigenvalues down to -1,200 where Gauss-Newton's
    are positive) make the plain Gauss-Newton steps converge only linearly."""

    #: hybrid: the exact blocks once the block's cost falls by less than 1 % between
    #: evaluations (the rotated global map's switch).
    SWITCH = 0.01
    #: Central-difference steps for positions [m] and orientation unknowns.
    STEP = 1e-6

    def __init__(
        self, name: str, model: RotatedTiledModel, home: tuple[int, ...], mode: str = "hybrid"
    ) -> None:
        ca.Callback.__init__(self)
        self.set_mode(mode)
        self.model, self.tiles, self.lay = model, model.tiles, model.lay
        self.n, self.d = model.n, model.d
        self.local = np.hstack([self.lay.pos, self.lay.rot])  # (n, nl)
        home_arr = np.array(home, dtype=np.int64).reshape(-1, self.d)
        T = self.tiles.num_tiles
        k, ids = home_tiles(self.tiles, home_arr)
        self._keys = np.unique(k * T + ids)
        self._pairs = shared_pairs(self.tiles, home_arr)
        self._slots = PairSlots(self.tiles, self._pairs)
        self._pattern()
        self.construct(name, {})

    def reset(self) -> None:
        super().reset()
        self.dropped = []

    def residual_jacobian(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, Any]:
        """:meth:`RotatedTiledModel.residual_jacobian` (casmag.solver.uncertainty)."""
        return self.model.residual_jacobian(x, p)

    def _pattern(self) -> None:
        lay, local = self.lay, self.local
        m, T = self.tiles.per_tile, self.tiles.num_tiles
        nl = local.shape[1]
        pat = Pattern()
        for i in range(nl):
            for j in range(i, nl):
                pat.add(local[:, i], local[:, j])
        sample, tile = self._keys // T, self._keys % T
        wm = np.arange(m)
        for i in range(nl):  # (pair, weight) order
            pat.add(local[sample, i][:, None], lay.W + tile[:, None] * m + wm)
        rows, cols, self._ww_flat = weight_pair_pattern(self._pairs, m)
        pat.add(lay.W + rows, lay.W + cols)
        if lay.c is not None:
            pat.constant_field([local[:, i] for i in range(nl)], lay.W + np.arange(T * m), lay.c)
        self._set_pattern(*pat.arrays(), lay.n_x, lay.n_p)

    def _exact_rows(
        self,
        model: RotatedTiledModel,
        r: slice,
        P: np.ndarray,
        o: np.ndarray,
        aux: np.ndarray,
        W: np.ndarray,
        c: np.ndarray,
        Y: np.ndarray,
        ids: np.ndarray,
        LL: np.ndarray,
        rows: np.ndarray,
        c_loc: np.ndarray,
        inv: float,
    ) -> None:
        """Replace the Gauss-Newton local, border and constant-field rows of the samples
        ``r`` by their exact second derivatives (the differences read in each sample's
        own cell, so that its corner tiles stay those of ``ids``)."""
        cells = self.tiles.cells(P[r])
        (H_loc, H_w, H_c), same = local_derivatives(
            lambda P_, o_: model.sample_gradients(P_, o_, aux[r], W, c, Y[r], cells)[:4],
            [P[r], o[r]],
            ids,
            self.STEP,
        )
        H_loc = 0.5 * (H_loc + np.transpose(H_loc, (0, 2, 1)))  # (k, nl, nl)
        H_w = np.moveaxis(H_w, -1, 2)  # (k, 2^d, nl, m)
        inv2 = inv * inv
        k = np.flatnonzero(same)
        LL[r.start + k] = H_loc[k] * inv2
        rows[k] = H_w[k] * inv2
        c_loc[:, r.start + k, :] = np.transpose(H_c[k], (1, 0, 2)) * inv2

    def values(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        model, lay = self.model, self.lay
        m, T = self.tiles.per_tile, self.tiles.num_tiles
        n, nl = self.n, self.local.shape[1]
        P, o, aux, W, c, Y, sigma = model.unpack(x, p)
        sc = model.scale(p)  # d W / d V, per weight of a tile
        inv = 1.0 / sigma
        exact = self._use_exact(model.cost(x, p) if self.mode == "hybrid" else 0.0)
        LL = np.empty((n, nl, nl))
        border = np.zeros((self._keys.size, nl, m))
        WW = np.zeros((self._pairs.shape[0], m, m))
        c_loc = np.zeros((FIELD_DIM, n, nl))
        c_w = np.zeros((FIELD_DIM, T, m))
        dropped = 0
        for r in model.chunks():
            field, ids, J, D = self.tiles.evaluate(P[r], W)
            R, Jo = model.rotations(o[r], aux[r], field + c)
            L = -inv * np.concatenate([np.einsum("kba,kbj->kaj", R, D), Jo], axis=2)
            G = -inv * np.einsum("kab,kbl->kal", R, L)  # d r / d(c) against the unknowns
            LL[r] = np.einsum("kai,kaj->kij", L, L)
            c_loc[:, r, :] = np.transpose(G, (1, 0, 2))
            rows = np.einsum("kbi,kobm->koim", G, J)
            kk, oo = np.nonzero(ids >= 0)
            key = (r.start + kk) * T + ids[kk, oo]
            pos, ok = in_pattern(self._keys, key)
            gn_out = LL[r.start + kk[~ok]].copy()  # Gauss-Newton products of the dropped
            if exact:
                self._exact_rows(model, r, P, o, aux, W, c, Y, ids, LL, rows, c_loc, inv)
            dropped += int(np.sum(~ok))
            border[pos[ok]] += rows[kk[ok], oo[ok]]
            dropped += add_weight_pairs(WW, self._slots, ids, J)
            if not ok.all():  # each dropped product's factors' own (add_own_tiles)
                np.add.at(LL, r.start + kk[~ok], gn_out)
                add_own_tiles(WW, self._slots, ids, kk[~ok], oo[~ok], J)
            add_constant_weights(c_w, ids, J)
        self.dropped.append(dropped)
        out = [LL[:, i, j] for i in range(nl) for j in range(i, nl)]
        out += [border[:, i, :] * sc[None, :] for i in range(nl)]  # (pair, weight) order
        ss = np.outer(sc, sc).ravel() * (inv * inv)
        out.append(WW.ravel()[self._ww_flat] * ss[self._ww_flat % (m * m)])
        if lay.c is not None:
            for b in range(FIELD_DIM):
                out += [c_loc[b, :, i] for i in range(nl)]
                out.append((c_w[b] * sc[None, :]).ravel() * (inv * inv))
                out.append(np.array([n * inv * inv]))
        return np.concatenate([np.ravel(v) for v in out])


def local_derivatives(
    gradients: Callable[..., tuple[np.ndarray, ...]],
    local: list[np.ndarray],
    ids: np.ndarray,
    step: float,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Central differences of per-sample gradients in each sample's own unknowns.

    ``gradients(*local)`` returns (corner tiles (k, 2^d), g_1, g_2, ...) with each g_i a
    per-sample array (k, ...); ``local`` holds the samples' unknowns (k, w_j) it reads
    (positions, orientations). Every sample's gradients depend on its own unknowns only,
    so perturbing one column of every sample at once gives that column's derivative for all
    samples: 2 sum_j w_j evaluations. Returns, per g_i, the derivatives stacked on a last
    axis (k, ..., sum_j w_j) and (k,) whether every perturbed evaluation kept the sample's
    corner tiles ``ids`` (where not, a difference spans two tiles' supports)."""
    out: list[list[np.ndarray]] = []
    same = np.ones(ids.shape[0], dtype=bool)
    for a, arr in enumerate(local):
        for col in range(arr.shape[1]):
            sides = []
            for sign in (1.0, -1.0):
                moved = [v.copy() if b == a else v for b, v in enumerate(local)]
                moved[a][:, col] += sign * step
                ids_j, *g = gradients(*moved)
                same &= np.all(ids_j == ids, axis=1)
                sides.append(g)
            out.append([(gp - gm) / (2 * step) for gp, gm in zip(*sides, strict=True)])
    return [np.stack(parts, axis=-1) for parts in zip(*out, strict=True)], same


def left_map_tiles(tiles: TiledBasis, P: np.ndarray) -> dict[str, Any] | None:
    """The ``left_map_tiles`` flag of an estimate with positions P (n, d) whose grid cell
    lacks a corner tile (None when every position has all of them): the tiles were laid
    within ``model.gp.margin`` of the initial trajectory, and beyond them the blend is not
    whole, so the field there is not the GP model's. Needs no truth."""
    out = ~tiles.inside(np.asarray(P, dtype=float))
    if not out.any():
        return None
    return {
        "name": "left_map_tiles",
        "reason": (
            f"{int(out.sum())} of {P.shape[0]} estimated positions lie where the tiled map "
            "lacks a tile (laid around the initial trajectory): the map there is not the GP "
            "model, so the estimate there is an artefact of the approximation"
        ),
        "evidence": {"positions_outside": int(out.sum()), "positions": int(P.shape[0])},
    }
