"""The bump lattice (casmag.gp.bumps): a curl-free map whose points touch only the nodes
within a few lengthscales."""

import casadi as ca
import numpy as np
import pytest
import scipy.sparse as sps

from casmag.gp.bumps import BumpBasis, smootherstep
from casmag.gp.kernels import get_kernel
from casmag.gp.localmaps import cached_tiles
from casmag.model.tiledmap import (
    BUMP_RADIUS,
    BUMP_SPACING,
    PairSlots,
    add_own_tiles,
    add_weight_pairs,
    home_points,
    shared_pairs,
    tile_grid,
)

ELL = 0.4


def _lattice(X, **kw):
    tiles = cached_tiles(tile_grid(X, ELL, basis="bumps", **kw))
    assert isinstance(tiles, BumpBasis)
    return tiles


def test_smoothstep_is_flat_to_third_order_at_both_ends():
    """s(0) = 0, s(1) = 1, s' and s'' match differences and vanish at both ends (with s'''
    too, by the closed form), so the bump is C^3."""
    v = np.linspace(0.0, 1.0, 201)
    s, s1, s2 = smootherstep(v)
    assert s[0] == 0.0 and s[-1] == pytest.approx(1.0)
    e = 1e-6
    assert np.allclose((smootherstep(v + e)[0] - smootherstep(v - e)[0]) / (2 * e), s1, atol=1e-7)
    assert np.allclose((smootherstep(v + e)[1] - smootherstep(v - e)[1]) / (2 * e), s2, atol=1e-6)
    ends = smootherstep(np.array([0.0, 1.0]))
    assert np.allclose(ends[1], 0.0) and np.allclose(ends[2], 0.0)
    # s''' = 1680 v (1 - v) (...): the second derivative's slope at the ends is zero
    assert abs(smootherstep(np.array([1e-4]))[2][0]) < 1e-4
    assert abs(smootherstep(np.array([1 - 1e-4]))[2][0]) < 1e-4


@pytest.mark.parametrize("dim", [2, 3])
def test_field_and_jacobians(dim):
    """The weight Jacobian is the field's (linear in the weights), the position Jacobian
    matches central differences of the field, and the field is curl-free (its Jacobian
    over the position axes is symmetric)."""
    rng = np.random.default_rng(dim)
    X = rng.uniform(0.0, 1.5, size=(40, dim))
    tiles = _lattice(X)
    assert tiles.per_tile == (2 if dim == 2 else 1)
    W = rng.normal(size=(tiles.num_tiles, tiles.per_tile))
    field, ids, _, D = tiles.evaluate(X, W)
    assert np.all(ids >= 0) and tiles.inside(X).all()
    assert np.allclose(tiles.design(X) @ W.ravel(), field.T.ravel(), atol=1e-12)
    for a in range(dim):
        dX = np.zeros_like(X)
        dX[:, a] = 1e-6
        fd = (tiles.field(X + dX, W) - tiles.field(X - dX, W)) / 2e-6
        assert np.allclose(D[:, :, a], fd, rtol=0, atol=1e-7 * np.abs(D).max())
    block = D[:, :dim, :dim]
    assert np.allclose(block, np.transpose(block, (0, 2, 1)), atol=1e-12 * np.abs(D).max())


def test_every_node_within_the_radius_is_a_corner():
    """A point's corner nodes hold every node whose bump reaches it (a brute-force search
    over the lattice), and a node's bump is zero beyond its radius."""
    rng = np.random.default_rng(3)
    X = rng.uniform(0.0, 2.0, size=(300, 2))
    tiles = _lattice(X)
    R = BUMP_RADIUS * ELL
    centres = np.array(tiles.grid.origin) + tiles.grid.spacing * tiles.tile_index
    ids = tiles.tile_ids(tiles.cells(X))
    inner = X[tiles.inside(X)]
    for x, row in zip(inner, ids[tiles.inside(X)], strict=True):
        near = set(np.flatnonzero(np.sum((centres - x) ** 2, axis=1) < R**2))
        assert near <= set(row[row >= 0])
    psi, grad, hess = tiles.bump(np.array([[R * 1.0001, 0.0], [0.0, R]]))
    assert np.all(psi == 0.0) and np.all(grad == 0.0) and np.all(hess == 0.0)


def test_neighbour_pairs_cover_every_shared_point():
    """Nodes touched by one point are neighbours (the weight block's pattern)."""
    rng = np.random.default_rng(7)
    X = rng.uniform(0.0, 2.0, size=(100, 2))
    tiles = _lattice(X)
    pairs = tiles.neighbours
    keys = set((pairs[:, 0] * tiles.num_tiles + pairs[:, 1]).tolist())
    ids = tiles.tile_ids(tiles.cells(X))
    for row in ids:
        row = row[row >= 0]
        a, b = np.meshgrid(row, row)
        assert set((np.minimum(a, b) * tiles.num_tiles + np.maximum(a, b)).ravel()) <= keys


@pytest.mark.parametrize("dim", [2, 3])
def test_shared_pairs_hold_every_pair_a_sample_can_touch_within_its_home(dim):
    """The weight block's pattern (casmag.model.tiledmap.shared_pairs): every pair of nodes
    one point touches while it stays within h / 2 + s h of its home grid point (s the
    pattern's slack) is in it, and it is a strict subset of the neighbour pairs along a
    path (those hold nodes that no sample reaches)."""
    rng = np.random.default_rng(11)
    n, length = (150, 3.0) if dim == 2 else (30, 0.6)
    X = np.cumsum(rng.normal(scale=0.05, size=(n, dim)), axis=0)
    X[:, 0] += np.linspace(0.0, length, n)
    tiles = _lattice(X)
    home = np.array(home_points(tiles.grid, X)).reshape(-1, dim)
    pairs = shared_pairs(tiles, home)
    T = tiles.num_tiles
    keys = pairs[:, 0] * T + pairs[:, 1]
    near = tiles.neighbours
    assert np.all(np.isin(keys, near[:, 0] * T + near[:, 1])) and keys.size < near.shape[0]
    assert np.all(np.isin(np.arange(T) * (T + 1), keys))  # every node with itself
    h = tiles.grid.spacing
    reach = (0.5 + tiles.home_slack) * h * 0.999
    origin = np.array(tiles.grid.origin)
    for _ in range(4):  # points anywhere within the pattern's slack of their homes
        Z = origin + home * h + rng.uniform(-reach, reach, size=home.shape)
        ids = tiles.tile_ids(tiles.cells(Z))
        a, b = np.broadcast_arrays(ids[:, :, None], ids[:, None, :])
        on = (a >= 0) & (b >= 0)
        assert np.all(np.isin(np.minimum(a, b)[on] * T + np.maximum(a, b)[on], keys))


@pytest.mark.parametrize("dim", [2, 3])
def test_weight_pairs_fill_the_pattern_as_the_dense_products(dim):
    """add_weight_pairs (the slots read from PairSlots' table) against J^T J summed densely
    over the samples: every pair the pattern holds equal, the pairs it lacks (samples
    moved beyond their homes) counted and their nodes' own products added, and the own
    products of add_own_tiles in each node's slot with itself."""
    rng = np.random.default_rng(5)
    n, length = (120, 3.0) if dim == 2 else (30, 0.6)
    X = np.cumsum(rng.normal(scale=0.05, size=(n, dim)), axis=0)
    X[:, 0] += np.linspace(0.0, length, n)
    tiles = _lattice(X)
    T, m = tiles.num_tiles, tiles.per_tile
    pairs = shared_pairs(tiles, np.array(home_points(tiles.grid, X)).reshape(-1, dim))
    slots = PairSlots(tiles, pairs)
    keys = pairs[:, 0] * T + pairs[:, 1]
    h = tiles.grid.spacing
    Z = X + rng.normal(scale=(1.0 + tiles.home_slack) * h, size=X.shape)  # some beyond
    _, ids, J, _ = tiles.evaluate(Z, rng.normal(size=(T, m)), positions=False)
    WW = np.zeros((pairs.shape[0], m, m))
    left_out = add_weight_pairs(WW, slots, ids, J)
    rows, cols, vals = [], [], []  # J as a sparse (3 n, T m) design
    for k in range(n):
        for o in np.flatnonzero(ids[k] >= 0):
            for i in range(3):
                rows += [3 * k + i] * m
                cols += list(ids[k, o] * m + np.arange(m))
                vals += list(J[k, o, i])
    Jd = sps.csr_matrix((vals, (rows, cols)), shape=(3 * n, T * m))
    full = (Jd.T @ Jd).tocsr()
    held = set(keys.tolist())
    own = np.zeros((T, m, m))  # what a pair the pattern lacks adds to its nodes
    lost = 0
    for k in range(n):
        o = np.flatnonzero(ids[k] >= 0)
        live = ids[k, o]
        for i in range(live.size):
            for j in range(i + 1, live.size):
                t1, t2 = sorted((live[i], live[j]))
                if t1 * T + t2 not in held:
                    lost += 1
                    for t, c in ((live[i], o[i]), (live[j], o[j])):
                        own[t] += J[k, c].T @ J[k, c]
    assert lost > 0 and left_out == lost
    r = pairs[:, 0, None, None] * m + np.arange(m)[None, :, None]
    c = pairs[:, 1, None, None] * m + np.arange(m)[None, None, :]
    r, c = np.broadcast_arrays(r, c)
    expect = np.asarray(full[r.ravel(), c.ravel()]).reshape(WW.shape)
    expect[pairs[:, 0] == pairs[:, 1]] += own[pairs[pairs[:, 0] == pairs[:, 1], 0]]
    np.testing.assert_allclose(WW, expect, rtol=1e-12, atol=1e-12 * np.abs(expect).max())
    kk = np.arange(0, n, 3)
    oo = np.array([np.flatnonzero(ids[k] >= 0)[0] for k in kk])
    WW2 = np.zeros_like(WW)
    add_own_tiles(WW2, slots, ids, kk, oo, J)
    want = np.zeros((T, m, m))
    for k, o in zip(kk, oo, strict=True):
        want[ids[k, o]] += J[k, o].T @ J[k, o]
    np.testing.assert_allclose(WW2[slots.self_slot], want, atol=1e-14)
    assert np.count_nonzero(np.abs(WW2).sum(axis=(1, 2))) == np.count_nonzero(
        np.abs(want).sum(axis=(1, 2))
    )


@pytest.mark.parametrize("dim", [2, 3])
def test_covariance_against_the_exact_curl_free_kernel(dim):
    """The lattice's field covariance against the exact curl-free kernel (the potential's
    squared exponential), relative to its largest entry: 0.0054 measured in the plane at
    the defaults (the Hilbert tiles of 4 l: 0.51, test_tiles), and the variance within 1 %
    of the kernel's everywhere."""
    rng = np.random.default_rng(0)
    n = 120 if dim == 2 else 60
    X = rng.uniform(0.0, 3.0 if dim == 2 else 1.2, size=(n, dim))
    Z = np.column_stack([X, np.zeros(n)]) if dim == 2 else X
    exact = np.asarray(get_kernel("curl_free").matrix(Z, Z, 0.7, ELL))
    K = _lattice(X).covariance(X, X, 0.7, ELL)
    assert np.abs(K - exact).max() < 0.015 * np.abs(exact).max()
    assert np.allclose(np.diag(K) / np.diag(exact), 1.0, atol=0.01)


def test_prior_variances_numeric_and_symbolic():
    """The weights' prior variances scale with sigma_f^2, the same as numbers and as a
    CasADi expression; in the plane the vertical potential's are 1 / l^2 of the others'
    up to the bump's shape (the field's components share one variance)."""
    X = np.random.default_rng(1).uniform(0.0, 1.0, size=(10, 2))
    tiles = _lattice(X)
    S1, S2 = tiles.prior_variances(1.0, ELL), tiles.prior_variances(2.0, ELL)
    assert S1.shape == (2,) and np.allclose(S2, 4.0 * S1)
    sf = ca.MX.sym("sigma_f")
    S = ca.Function("S", [sf], [tiles.prior_variances(sf, ELL)])
    assert np.allclose(np.asarray(S(2.0)).ravel(), S2)
    assert tiles.grid.spacing == pytest.approx(BUMP_SPACING * ELL)


def test_a_coarser_lattice_leaves_out_more_of_the_field():
    """Least-squares fits of the lattice to draws of the exact curl-free GP in the plane
    (30 x 30 points over 2.4 x 2.4 m, noise 1e-3 of the field, read in the middle where
    the lattice covers every side): what is left is below the spectral bound
    unresolved_field (measured 0.007-0.009 of the field at 0.75 l, 0.0015-0.0024 at
    0.65 l, the noise at 0.55 l, over seeds 0-2), and falls with the spacing."""
    from casmag.model.tiledmap import unresolved_field

    g = np.linspace(0.0, 2.4, 30)
    X = np.array([(a, b) for a in g for b in g])
    Z = np.column_stack([X, np.zeros(len(X))])
    K = np.asarray(get_kernel("curl_free").matrix(Z, Z, 0.7, ELL))
    y = np.linalg.cholesky(K + 1e-8 * K.diagonal().max() * np.eye(len(K))) @ (
        np.random.default_rng(0).normal(size=len(K))
    )
    middle = np.tile(np.all(np.abs(X - 1.2) <= 0.6, axis=1), 3)
    noise = 1e-3 * 0.7 / ELL
    left = {}
    for h in (0.75, 0.65, 0.55):
        tiles = _lattice(X, lattice=h)
        A = tiles.design(X)
        A = A.toarray() if hasattr(A, "toarray") else np.asarray(A)
        prior = np.tile(np.ravel(tiles.prior_variances(0.7, ELL)), tiles.num_tiles)
        w = np.linalg.solve(A.T @ A / noise**2 + np.diag(1.0 / prior), A.T @ y / noise**2)
        left[h] = np.sqrt(np.mean((A @ w - y)[middle] ** 2)) / (0.7 / ELL)
        assert left[h] < unresolved_field(h)
    assert left[0.65] < 0.5 * left[0.75] and left[0.55] < left[0.65]
    assert left[0.75] > 3e-3  # the lattice of 0.75 l does leave part of the field out


def test_bump_spacing_follows_the_field_against_the_noise():
    """The lattice is the coarsest (0.75 l) for a weak or unknown field, finer as the field
    grows against the noise, never below 0.5 l; each spacing leaves at most
    BUMP_UNRESOLVED of the noise unresolved."""
    from casmag.model.tiledmap import (
        BUMP_SPACING_FINEST,
        BUMP_UNRESOLVED,
        bump_spacing,
        unresolved_field,
    )

    # field over noise sigma_f / (l sigma_m), here at l = 0.5 m, sigma_m = 0.1
    ratio = lambda s: bump_spacing(s * 0.05, 0.5, 0.1)  # noqa: E731
    assert bump_spacing(None, 0.5, 0.1) == bump_spacing(1.0, 0.5, None) == BUMP_SPACING
    assert ratio(0.3) == BUMP_SPACING
    strengths = [0.6, 1.0, 2.1, 5.0, 14.5, 19.5, 50.0]
    spacings = [ratio(s) for s in strengths]
    assert np.all(np.diff(spacings) < 0)
    assert BUMP_SPACING_FINEST < spacings[-1] < spacings[0] < BUMP_SPACING
    for s, h in zip(strengths, spacings, strict=True):
        assert unresolved_field(h) * s == pytest.approx(BUMP_UNRESOLVED, rel=1e-4)
    assert ratio(1e4) == BUMP_SPACING_FINEST
    # the spacings the measured walks took (README, Tiled map)
    assert ratio(19.5) == pytest.approx(0.545, abs=0.005)
    assert ratio(2.1) == pytest.approx(0.645, abs=0.005)
    # only the ratio counts: a twice longer lengthscale at twice sigma_f, the same lattice
    assert bump_spacing(2.0, 1.0, 0.1) == bump_spacing(1.0, 0.5, 0.1)
