"""A reduced-rank field map on a grid, for every motion model: its field, its posterior
standard deviation given the estimated path, and its prior standard deviation.

The map is m(x) = A(x) w + c, with A(x) the basis rows (squared exponential: phi(x) for each
component; curl-free: the gradient of phi, one scalar potential) and c the constant field.
Its weights' posterior precision given the magnetometer at the estimated positions (taken
as known) is sum_k A(p_k)^T A(p_k) / sigma_m^2 + diag(1 / S), S the prior variances. A
magnetometer in the body frame, y = R^T m(p), gives the same precision: R R^T = I. The
grid is horizontal (at the path's median height for 3-D paths); ``map.png`` draws it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg

from casmag.gp.kernels import FIELD_DIM
from casmag.gp.reduced_rank import HilbertBasis
from casmag.gp.tiles import TiledBasis

#: Grid points per axis of a map drawn by map.png.
GRID_POINTS = 90

#: Points per block when the basis rows are formed (a dense (n, M) block per component for
#: a building-scale recording would take gigabytes).
CHUNK = 2_000


def grid_over(
    P: np.ndarray, lengthscale: float, points: int = GRID_POINTS
) -> tuple[np.ndarray, np.ndarray]:
    """A square grid (points x points) over the positions' horizontal bounding box plus
    one lengthscale."""
    lo, hi = P[:, :2].min(axis=0) - lengthscale, P[:, :2].max(axis=0) + lengthscale
    return np.meshgrid(np.linspace(lo[0], hi[0], points), np.linspace(lo[1], hi[1], points))


def chunks(n: int) -> list[slice]:
    return [slice(i, min(i + CHUNK, n)) for i in range(0, n, CHUNK)]


def weight_rows(basis: HilbertBasis, kernel: str, X: np.ndarray) -> list[np.ndarray]:
    """The map's rows d m_c / d w at points X: SE [phi] (one (n, M) block for every
    component), curl-free [d phi / dx_c for c = x, y, z]."""
    if kernel == "se":
        return [basis.phi(X)]
    grads = basis.grad_phi(X)
    return [grads[:, c, :] for c in range(FIELD_DIM)]


def field_at(basis: HilbertBasis, kernel: str, X: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(n, 3) the map without its constant at points X, from weights (M, 3) (SE) or (M, 1)
    (curl-free potential); CHUNK points at a time."""
    W = np.asarray(weights, dtype=float).reshape(basis.num_basis, -1, order="F")
    parts = []
    for r in chunks(X.shape[0]):
        rows = weight_rows(basis, kernel, X[r])
        parts.append(
            rows[0] @ W if kernel == "se" else np.column_stack([a @ W[:, 0] for a in rows])
        )
    return np.vstack(parts)


def reduced_rank_std(
    basis: HilbertBasis,
    kernel: str,
    hyper: dict[str, float],
    P: np.ndarray,
    grid: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(posterior std, prior std), each (G, 3) per field component at the grid points, of
    the reduced-rank map given the magnetometer (noise ``hyper["sigma_m"]``) at the positions
    P (N, d); the constant field left out (every sample informs it)."""
    S = basis.prior_variances(kernel, hyper["sigma_f"], hyper["lengthscale"]).ravel()
    G = np.diag(1.0 / S)
    for rows in chunks(P.shape[0]):
        G += sum(a.T @ a for a in weight_rows(basis, kernel, P[rows])) / hyper["sigma_m"] ** 2
    L = np.linalg.cholesky(G)
    parts = []
    for rows in chunks(grid.shape[0]):
        post, prior = [], []
        for ag in weight_rows(basis, kernel, grid[rows]):
            V = scipy.linalg.solve_triangular(L, ag.T, lower=True)
            post.append((V**2).sum(axis=0))
            prior.append((ag**2 * S).sum(axis=1))
        parts.append((np.column_stack(post), np.column_stack(prior)))
    post, prior = (np.vstack([part[i] for part in parts]) for i in (0, 1))
    if kernel == "se":  # one basis for every component
        post, prior = np.tile(post, FIELD_DIM), np.tile(prior, FIELD_DIM)
    return np.sqrt(np.maximum(post, 0.0)), np.sqrt(prior)


def unwhitened(basis: HilbertBasis, kernel: str, hyper: dict[str, float], V: Any) -> np.ndarray:
    """Map weights sqrt(S) V from the whitened weights V (M, k) the IMU and planar NLPs
    solve for."""
    S = basis.prior_variances(kernel, hyper["sigma_f"], hyper["lengthscale"])
    return np.asarray(V, dtype=float) * np.sqrt(np.ravel(S))[:, None]


def map_grid(P: np.ndarray, lengthscale: float) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The grid map.png draws over the positions P (N, d): ``map_x``, ``map_y`` (G, G) [m]
    and, for a 3-D path, ``map_z`` (the grid's height [m], the path's median), and its
    points (G^2, d)."""
    gx, gy = grid_over(P, lengthscale)
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    out: dict[str, np.ndarray] = {"map_x": gx, "map_y": gy}
    if P.shape[1] == 3:
        z = float(np.median(P[:, 2]))
        pts = np.column_stack([pts, np.full(pts.shape[0], z)])
        out["map_z"] = np.array(z)
    return out, pts


def map_arrays(
    basis: HilbertBasis,
    kernel: str,
    weights: np.ndarray,
    c: np.ndarray | None,
    hyper: dict[str, float],
    P: np.ndarray,
) -> dict[str, np.ndarray]:
    """The arrays map.png draws, for a reduced-rank map with weights (M, 3) (SE) or (M, 1)
    (curl-free potential) and constant field c (3,): ``map_x``, ``map_y`` (G, G) [m],
    ``map_field``, ``map_std``, ``map_prior_std`` (G, G, 3) and, for a 3-D path, ``map_z``
    (the grid's height [m], the path's median)."""
    out, pts = map_grid(P, hyper["lengthscale"])
    gx = out["map_x"]
    m = field_at(basis, kernel, pts, weights)
    if c is not None:
        m = m + np.ravel(c)
    std, prior = reduced_rank_std(basis, kernel, hyper, P, pts)
    shape = (*gx.shape, FIELD_DIM)
    out.update(
        map_field=m.reshape(shape), map_std=std.reshape(shape), map_prior_std=prior.reshape(shape)
    )
    return out


def tiled_map_arrays(
    tiles: TiledBasis,
    W: np.ndarray,
    c: np.ndarray | None,
    lengthscale: float,
    P: np.ndarray,
) -> dict[str, np.ndarray]:
    """The arrays map.png draws for a tiled map (casmag.gp.tiles) with weights W (T, m):
    ``map_x``, ``map_y``, ``map_field`` (and ``map_z`` for a 3-D path) as
    :func:`map_arrays`; its posterior standard deviation is not computed (map.png then
    draws the field alone). Grid points where the map lacks a tile get NaN."""
    out, pts = map_grid(P, lengthscale)
    m = tiles.field(pts, W) + (0.0 if c is None else np.ravel(c))
    m[~tiles.inside(pts)] = np.nan
    out["map_field"] = m.reshape(*out["map_x"].shape, FIELD_DIM)
    return out
