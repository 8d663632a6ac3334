"""The tiled reduced-rank potential (casmag.gp.tiles)."""

import numpy as np
import pytest

from casmag.gp.kernels import get_kernel
from casmag.gp.tiles import TiledBasis, window
from casmag.model.tiledmap import tile_grid

ELL = 0.4


def test_window_squares_sum_to_one_and_derivatives():
    """omega(u)^2 + omega(u - 1)^2 = 1 on [0, 1]; omega', omega'' match differences;
    omega and omega' vanish at |u| = 1 (C^1 there, so the field is continuous)."""
    u = np.linspace(0.0, 1.0, 101)
    assert np.allclose(window(u)[0] ** 2 + window(u - 1.0)[0] ** 2, 1.0, atol=1e-14)
    v = np.linspace(-1.3, 1.3, 261)
    e = 1e-6
    assert np.allclose((window(v + e)[0] - window(v - e)[0]) / (2 * e), window(v)[1], atol=1e-8)
    # omega''' jumps at |u| = 1, so the difference there is off by O(e)
    assert np.allclose((window(v + e)[1] - window(v - e)[1]) / (2 * e), window(v)[2], atol=1e-4)
    edge = window(np.array([-1.0, 1.0]))
    assert np.allclose(edge[0], 0.0) and np.allclose(edge[1], 0.0)


@pytest.mark.parametrize("dim", [2, 3])
def test_field_jacobians(dim):
    """Each point touches its cell's 2^d corner tiles; the weight Jacobian is the field's
    (linear in the weights: design @ w is the field), the position Jacobian matches
    central differences of the field."""
    rng = np.random.default_rng(dim)
    X = rng.uniform(0.0, 1.5, size=(25, dim))
    tiles = TiledBasis(tile_grid(X, ELL, reach=0.2, basis="hilbert"))
    W = rng.normal(size=(tiles.num_tiles, tiles.per_tile))
    field, ids, _, D = tiles.evaluate(X, W)
    assert ids.shape == (25, 2**dim) and np.all(ids >= 0) and tiles.inside(X).all()
    assert np.allclose(tiles.design(X) @ W.ravel(), field.T.ravel(), atol=1e-10)
    for a in range(dim):
        dX = np.zeros_like(X)
        dX[:, a] = 1e-6
        fd = (tiles.field(X + dX, W) - tiles.field(X - dX, W)) / 2e-6
        assert np.allclose(D[:, :, a], fd, rtol=1e-6, atol=1e-6 * np.abs(D).max())


def test_weight_jacobians_without_the_position_jacobian():
    """``positions=False`` gives the same field and weight Jacobians, and no D."""
    rng = np.random.default_rng(5)
    X = rng.uniform(0.0, 1.5, size=(20, 2))
    tiles = TiledBasis(tile_grid(X, ELL, reach=0.2, basis="hilbert"))
    W = rng.normal(size=(tiles.num_tiles, tiles.per_tile))
    full = tiles.evaluate(X, W)
    lean = tiles.evaluate(X, W, positions=False)
    assert lean[3] is None and full[3] is not None
    for a, b in zip(full[:3], lean[:3], strict=True):
        assert np.array_equal(a, b)


def test_neighbour_pairs_cover_every_shared_point():
    """Tiles touched by one point are neighbours (the weight block's pattern)."""
    rng = np.random.default_rng(7)
    X = rng.uniform(0.0, 3.0, size=(200, 2))
    tiles = TiledBasis(tile_grid(X, ELL, basis="hilbert"))
    pairs = {tuple(p) for p in tiles.neighbours}
    ids = tiles.tile_ids(tiles.cells(X))
    for row in ids:
        for a in row:
            for b in row:
                assert (min(a, b), max(a, b)) in pairs


def test_covariance_against_the_exact_curl_free_kernel():
    """The tiled prior's field covariance against the exact curl-free kernel, relative to
    the component variance sigma_f^2 / l^2: the blend adds field variance from the
    blending weights' gradients, which falls with the spacing (measured: 2.05 at h = 2 l,
    0.92 at 3 l, 0.50 at 4 l (the default), 0.20 at 6 l); nowhere is the variance much
    below the exact one (the basis' faces and its truncation at 3.5 / l remove 5-7 %)."""
    rng = np.random.default_rng(0)
    X = rng.uniform(0.0, 4 * ELL, size=(30, 2))
    exact = get_kernel("curl_free").matrix(X, X, 0.5, ELL)
    errors = []
    for h in (2.0, 3.0, 4.0, 6.0):
        tiles = TiledBasis(tile_grid(X, ELL, spacing=h * ELL, reach=0.5 * ELL, basis="hilbert"))
        K = tiles.covariance(X, X, 0.5, ELL)
        errors.append(np.abs(K - exact).max() / (0.5**2 / ELL**2))
        assert np.all(np.diag(K) > 0.9 * np.diag(exact))
    assert errors == sorted(errors, reverse=True)
    assert errors[2] < 0.6 and errors[3] < 0.25
