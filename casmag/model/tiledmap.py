"""The tiled map (casmag.gp.tiles) inside the MAP problem: cost, gradient and Gauss-Newton
Hessian of the magnetometer block with numpy, read in the map frame.

Every sample touches the 2^d tiles at the corners of its grid cell, so the Hessian of the
magnetometer block is sparse: the weight block holds an m x m block for each pair of
neighbouring tiles (indices at most one apart along every axis), and the knot-weight border
holds, for each knot, the tiles around its samples' starting positions. Its size grows with
the number of tiles the path visits, not with the area of the box around the path, and
neither does the time to fill it (one BLAS product per occupied grid cell).

The border's pattern is fixed when the NLP is built, from the samples' positions then
(``home``: the nearest grid point of each sample): tiles within one index of it along every
axis, so a sample can move at least h/2 in any direction within a solve and keep its
Hessian entries. Entries of a sample that moved further are left out of the Gauss-Newton
Hessian (the gradient stays exact, so IPOPT still converges, more slowly);
:attr:`TiledGaussNewton.dropped` counts the (sample, tile, knot) terms left out per
evaluation, and the solve's statistics carry the largest count
(``hessian_terms_dropped``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np
import scipy.sparse as sps

from casmag.gp.kernels import FIELD_DIM
from casmag.gp.reduced_rank import Domain, default_num_basis
from casmag.gp.tiles import TiledBasis, TileGrid
from casmag.model.knots import Knots
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
TILE_SPACING = 4.0
TILE_MARGIN = 0.5
TILE_DEPTH = 2.0
TILE_OMEGA = 3.5


def tile_grid(
    X: np.ndarray,
    lengthscale: float,
    spacing: float | None = None,
    reach: float | None = None,
) -> TileGrid:
    """The tiles for positions X (N, d): spacing h (default TILE_SPACING l), every tile
    whose support comes within ``reach`` (default 3 l, as the box margin of the global
    map) of a position, and the tile basis (curl-free, frequencies up to TILE_OMEGA / l)."""
    X = np.asarray(X, dtype=float)
    ell = float(lengthscale)
    h = TILE_SPACING * ell if spacing is None else float(spacing)
    reach = 3.0 * ell if reach is None else float(reach)
    mg = TILE_MARGIN * ell
    d = X.shape[1]
    half = [h + mg] * d + ([TILE_DEPTH * ell] if d == 2 else [])
    domain = Domain(np.zeros(FIELD_DIM), np.array(half))
    m = default_num_basis(domain, ell, omega_factor=TILE_OMEGA, max_basis=1 << 20)
    return TileGrid.around(X, h, reach, ((0.0,) * FIELD_DIM, tuple(half), m))


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

    def gradient(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        kn, d, lay = self.knots, self.dim, self.lay
        P, w, c, Y, sigma = self.unpack(x, p)
        W = self.weights(w)
        T, m = W.shape
        g_P = np.empty((kn.n, d))
        g_W = np.zeros((T, m))
        g_c = np.zeros(FIELD_DIM)
        for r in self.chunks():
            field, ids, J, D = self.tiles.evaluate(P[r], W)
            R = Y[r] - field - c
            g_P[r] = -np.einsum("kc,kca->ka", R, D)
            contrib = np.einsum("kobm,kb->kom", J, R)  # (n, 2^d, m)
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


@dataclass(frozen=True)
class _Border:
    """The knot-weight border's (knot, tile) pairs, sorted by key knot * T + tile."""

    keys: np.ndarray
    knot: np.ndarray
    tile: np.ndarray


class TiledGaussNewton(HessianCallback):
    """Gauss-Newton Hessian (upper triangle) of the tiled magnetometer block: the knot
    block A^T diag(D^T D) A, the border A^T D^T J over the (knot, tile) pairs of the
    pattern, the weight block J^T J over neighbouring tile pairs, and the constant field's
    rows. Not scaled by lam_f (the caller multiplies), like
    :class:`casmag.model.rrmap.GaussNewtonHessian`."""

    def __init__(
        self, name: str, model: TiledMapModel, home: tuple[int, ...], n_g: int = 0
    ) -> None:
        ca.Callback.__init__(self)
        self.set_mode("gauss-newton")
        self.model, self.n_g = model, n_g
        self.tiles, self.knots, self.dim, self.lay = (
            model.tiles, model.knots, model.dim, model.lay
        )  # fmt: skip
        self._border = self._border_pairs(np.array(home, dtype=np.int64).reshape(-1, self.dim))
        self._pairs = self.tiles.neighbours
        self._pair_key = self._pairs[:, 0] * self.tiles.num_tiles + self._pairs[:, 1]
        self._pattern()
        self.construct(name, {})

    def reset(self) -> None:
        super().reset()
        self.dropped = []

    def _border_pairs(self, home: np.ndarray) -> _Border:
        tiles, kn = self.tiles, self.knots
        T = tiles.num_tiles
        keys = []
        offsets = np.array(list(np.ndindex(*(3,) * self.dim))) - 1
        for off in offsets:
            ids = tiles.tile_ids(home + off)[:, 0]  # the tile at home + off (corner 0)
            ok = ids >= 0
            for j in (kn.left[ok], kn.left[ok] + 1):
                keys.append(j * T + ids[ok])
        k = np.unique(np.concatenate(keys))
        return _Border(k, k // T, k % T)

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
        iu = np.triu_indices(m)
        for t1, t2 in self._pairs:  # pair after pair, row-major within the block
            if t1 == t2:
                pat.add(lay.W + t1 * m + iu[0], lay.W + t1 * m + iu[1])
            else:
                pat.add(lay.W + t1 * m + wm[:, None], lay.W + t2 * m + wm[None, :])
        if lay.c is not None:
            pat.constant_field(cidx, lay.W + np.arange(T * m), lay.c)
        self._set_pattern(*pat.arrays(), lay.n_x, lay.n_p)

    def values(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        kn, d, lay = self.knots, self.dim, self.lay
        m, T = self.tiles.per_tile, self.tiles.num_tiles
        N, K = kn.n, kn.count
        P, w, _, _, sigma = self.model.unpack(x, p)
        W = self.model.weights(w)
        inv2 = 1.0 / sigma**2
        self._use_exact(0.0)
        left, alpha = kn.left, kn.alpha
        A = kn.matrix
        pairs = [(a, b) for a in range(d) for b in range(a, d)]
        s_pp = {ab: np.empty(N) for ab in pairs}
        bd = self._border
        border = np.zeros((bd.keys.size, d, m))
        WW = np.zeros((self._pairs.shape[0], m, m))
        c_knot = np.zeros((FIELD_DIM, d, K)) if lay.c is not None else None
        c_w = np.zeros((FIELD_DIM, T, m)) if lay.c is not None else None
        dropped = 0
        for r in self.model.chunks():
            _, ids, J, D = self.tiles.evaluate(P[r], W)
            n_c = ids.shape[1]
            for a, b in pairs:
                s_pp[a, b][r] = np.einsum("kc,kc->k", D[:, :, a], D[:, :, b])
            # border: rows_a (n, 2^d, m) = sum_b D[k, b, a] J[k, o, b]
            rows_a = np.einsum("kba,kobm->koam", D, J)
            live = ids >= 0
            kk, oo = np.nonzero(live)
            lk, ak = left[r][kk], alpha[r][kk]
            for knot, factor in ((lk, 1.0 - ak), (lk + 1, ak)):
                key = knot * T + ids[kk, oo]
                pos = np.searchsorted(bd.keys, key)
                ok = (pos < bd.keys.size) & (bd.keys[np.minimum(pos, bd.keys.size - 1)] == key)
                ok &= factor != 0.0
                dropped += int(np.sum(~ok & (factor != 0.0)))
                sel = sps.csr_matrix(
                    (factor[ok], (pos[ok], np.arange(int(ok.sum())))),
                    shape=(bd.keys.size, int(ok.sum())),
                )
                border += (sel @ rows_a[kk[ok], oo[ok]].reshape(-1, d * m)).reshape(-1, d, m)
            # weight block: one product per group of samples with the same corner tiles
            groups, inverse = np.unique(ids, axis=0, return_inverse=True)
            inverse = inverse.ravel()
            order = np.argsort(inverse, kind="stable")
            bounds = np.searchsorted(inverse[order], np.arange(groups.shape[0] + 1))
            for g in range(groups.shape[0]):
                k = order[bounds[g] : bounds[g + 1]]
                Jg = J[k].transpose(0, 2, 1, 3).reshape(k.size * FIELD_DIM, n_c * m)
                G = Jg.T @ Jg
                tid = groups[g]
                for o1 in range(n_c):
                    for o2 in range(o1, n_c):
                        t1, t2 = tid[o1], tid[o2]
                        if t1 < 0 or t2 < 0:
                            continue
                        blk = G[o1 * m : (o1 + 1) * m, o2 * m : (o2 + 1) * m]
                        if t1 > t2:
                            t1, t2, blk = t2, t1, blk.T
                        i = int(np.searchsorted(self._pair_key, t1 * T + t2))
                        WW[i] += blk
            if c_knot is not None:
                j0, j1 = int(left[r.start]), int(left[r.stop - 1]) + 2
                Ar = A[r][:, j0:j1]
                for b in range(FIELD_DIM):
                    for a in range(d):
                        c_knot[b, a, j0:j1] += Ar.T @ D[:, b, a]
                    for o in range(n_c):
                        ok = ids[:, o] >= 0
                        np.add.at(c_w[b], ids[ok, o], J[ok, o, b])
        self.dropped.append(dropped)
        out = knot_chain_values(kn, s_pp, d, inv2)
        out += [border[:, a, :] * inv2 for a in range(d)]
        iu = np.triu_indices(m)
        for i, (t1, t2) in enumerate(self._pairs):
            out.append((WW[i][iu] if t1 == t2 else WW[i]) * inv2)
        if c_knot is not None:
            out += constant_field_values(c_knot, c_w.reshape(FIELD_DIM, -1), N, inv2)
        return np.concatenate([np.ravel(v) for v in out])


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
