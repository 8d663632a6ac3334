"""Hilbert-space reduced-rank basis (casmag.gp.reduced_rank) against numpy references.

The references below are written from the formulas, independently of casmag:

    phi_j(x)  = prod_k L_k^(-1/2) sin(pi j_k (x_k - c_k + L_k) / (2 L_k))
    lambda_j  = sum_k (pi j_k / (2 L_k))^2
    S_SE(w)   = sf^2 (2 pi l^2)^(d/2) exp(-l^2 w^2 / 2)
    k_SE(r)   = sf^2 exp(-|r|^2 / (2 l^2))
    K_H(r)    = -d_a d_b k_SE(r) = (1/l^2)(delta_ab - r_a r_b / l^2) k_SE(r)   (curl-free)

Kernel approximations are compared with casmag's exact kernels and with these references.
"""

from __future__ import annotations

import itertools

import casadi as ca
import numpy as np
import pytest

from casmag.gp.kernels import get_kernel
from casmag.gp.reduced_rank import (
    Domain,
    HilbertBasis,
    approx_kernel_matrix,
    default_margin,
    default_num_basis,
    domain_for,
    evaluate_field,
)

SF, ELL = 0.7, 0.35
EXTENT = np.array([[0.0, 0.0], [6.0, 6.0]])  # a 6 m x 6 m data area
APPROX_TOL = 1e-2  # max abs kernel error relative to the prior variance


# --------------------------------------------------------------------------- references
def ref_phi(X: np.ndarray, indices: np.ndarray, center: np.ndarray, half: np.ndarray):
    """(N, M) eigenfunctions by the formula, one loop per basis function."""
    out = np.ones((X.shape[0], indices.shape[0]))
    for m, j in enumerate(indices):
        for k in range(X.shape[1]):
            L = half[k]
            out[:, m] *= np.sin(np.pi * j[k] * (X[:, k] - center[k] + L) / (2 * L)) / np.sqrt(L)
    return out


def ref_eigenvalues(indices: np.ndarray, half: np.ndarray) -> np.ndarray:
    return np.sum((np.pi * indices / (2 * half)) ** 2, axis=1)


def ref_se(X1: np.ndarray, X2: np.ndarray, sf: float, ell: float) -> np.ndarray:
    r2 = np.sum((X1[:, None, :] - X2[None, :, :]) ** 2, axis=-1)
    return sf**2 * np.exp(-r2 / (2 * ell**2))


def ref_curl_free(X1: np.ndarray, X2: np.ndarray, sf: float, ell: float) -> np.ndarray:
    """Component-major K_H, 2-D points embedded at z = 0."""
    P1 = np.column_stack([X1, np.zeros((X1.shape[0], 3 - X1.shape[1]))])
    P2 = np.column_stack([X2, np.zeros((X2.shape[0], 3 - X2.shape[1]))])
    R = P1[:, None, :] - P2[None, :, :]
    k = ref_se(P1, P2, sf, ell) / ell**2
    blocks = [
        [(float(a == b) - R[..., a] * R[..., b] / ell**2) * k for b in range(3)] for a in range(3)
    ]
    return np.block(blocks)


def brute_force_indices(half: np.ndarray, jmax: int) -> tuple[np.ndarray, np.ndarray]:
    """All multi-indices in the cube [1, jmax]^d and their eigenvalues."""
    idx = np.array(list(itertools.product(range(1, jmax + 1), repeat=half.size)))
    return idx, ref_eigenvalues(idx, half)


def random_inside(rng: np.random.Generator, domain: Domain, n: int, shrink: float = 0.9):
    return domain.center + shrink * rng.uniform(-1, 1, (n, domain.dim)) * domain.half_width


# --------------------------------------------------------------------------- domain
def test_domain_around_grows_bounding_box() -> None:
    X = np.array([[0.0, 1.0], [4.0, -2.0], [1.0, 3.0]])
    dom = Domain.around(X, 0.5)
    np.testing.assert_allclose(dom.lower, [-0.5, -2.5])
    np.testing.assert_allclose(dom.upper, [4.5, 3.5])
    assert dom.dim == 2
    assert dom.contains(X).all()
    assert not dom.contains(np.array([[5.0, 0.0]]))[0]
    with pytest.raises(ValueError):
        Domain.around(X, 0.0)
    with pytest.raises(ValueError):
        Domain(center=np.zeros(2), half_width=np.array([1.0, 0.0]))


def test_domain_for_curl_free_planar_is_a_3d_box_around_the_plane() -> None:
    margin = default_margin(ELL)
    assert margin == pytest.approx(3 * ELL)
    dom = domain_for("curl_free", EXTENT, ELL)
    assert dom.dim == 3
    np.testing.assert_allclose(dom.lower, [-margin, -margin, -margin])
    np.testing.assert_allclose(dom.upper, [6 + margin, 6 + margin, margin])
    assert domain_for("se", EXTENT, ELL).dim == 2
    # HilbertBasis(input_dim=3) extends a 2-D domain the same way.
    basis = HilbertBasis(
        Domain.around(EXTENT, margin), 10, lengthscale_for_default=ELL, input_dim=3
    )
    np.testing.assert_allclose(basis.domain.half_width, dom.half_width)


# --------------------------------------------------------------------------- eigenfunctions
@pytest.mark.parametrize(
    ("center", "half", "m"),
    [(np.array([0.4]), np.array([1.3]), 8), (np.array([0.2, -0.5]), np.array([1.0, 0.6]), 12)],
)
def test_eigenfunctions_match_formula_and_are_orthonormal(center, half, m) -> None:
    basis = HilbertBasis(Domain(center, half), m)
    d = half.size
    # Indices: the m smallest eigenvalues, in ball (ascending eigenvalue) order.
    _, lam_all = brute_force_indices(half, 20)
    np.testing.assert_allclose(basis.eigenvalues, np.sort(lam_all)[:m], rtol=1e-12)
    np.testing.assert_allclose(basis.eigenvalues, ref_eigenvalues(basis.indices, half))
    np.testing.assert_allclose(basis.sqrt_eigenvalues, np.sqrt(basis.eigenvalues))
    assert basis.indices.shape == (m, d) and basis.indices.min() >= 1

    # Midpoint rule on a fine grid.
    n = 2000 if d == 1 else 400
    axes = [c - L + (np.arange(n) + 0.5) * (2 * L / n) for c, L in zip(center, half, strict=True)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, d)
    cell = np.prod(2 * half / n)
    P = basis.phi(grid)
    np.testing.assert_allclose(P, ref_phi(grid, basis.indices, center, half), atol=1e-12)
    gram = P.T @ P * cell
    assert np.abs(gram - np.eye(m)).max() < 1e-3


@pytest.mark.parametrize("d", [2, 3])
def test_eigenfunctions_solve_dirichlet_laplace_problem(d: int) -> None:
    rng = np.random.default_rng(11)
    dom = Domain(rng.uniform(-1, 1, d), rng.uniform(0.5, 1.5, d))
    basis = HilbertBasis(dom, 20)
    X = random_inside(rng, dom, 25)
    h = 1e-4
    lap = -2 * d * basis.phi(X)
    for k in range(d):
        e = np.zeros(d)
        e[k] = h
        lap += basis.phi(X + e) + basis.phi(X - e)
    lap /= h**2
    P = basis.phi(X)
    scale = basis.eigenvalues.max() * np.abs(P).max()
    assert np.abs(-lap - basis.eigenvalues * P).max() < 1e-5 * scale

    # Zero on every face.
    for k in range(d):
        for side in (-1.0, 1.0):
            Y = random_inside(rng, dom, 10, shrink=1.0)
            Y[:, k] = dom.center[k] + side * dom.half_width[k]
            assert np.abs(basis.phi(Y)).max() < 1e-12


def test_phi_chunking_and_padding() -> None:
    rng = np.random.default_rng(3)
    dom = Domain(np.array([1.0, 2.0, 0.0]), np.array([2.0, 1.5, 0.7]))
    basis = HilbertBasis(dom, 40)
    X = random_inside(rng, dom, 37)
    np.testing.assert_allclose(basis.phi(X, chunk_rows=5), basis.phi(X), rtol=0, atol=0)
    np.testing.assert_allclose(basis.grad_phi(X, chunk_rows=4), basis.grad_phi(X), atol=0)
    # Planar points are the plane z = 0.
    X2 = X[:, :2]
    X3 = np.column_stack([X2, np.zeros(len(X2))])
    np.testing.assert_array_equal(basis.phi(X2), basis.phi(X3))
    np.testing.assert_array_equal(basis.grad_phi(X2), basis.grad_phi(X3))


# --------------------------------------------------------------------------- gradients, casadi
@pytest.mark.parametrize("d", [2, 3])
def test_grad_phi_matches_finite_differences(d: int) -> None:
    rng = np.random.default_rng(5 + d)
    dom = Domain(rng.uniform(-1, 1, d), rng.uniform(0.5, 1.5, d))
    basis = HilbertBasis(dom, 30)
    X = random_inside(rng, dom, 15)
    G = basis.grad_phi(X)
    assert G.shape == (15, d, 30)
    h = 1e-6
    for k in range(d):
        e = np.zeros(d)
        e[k] = h
        fd = (basis.phi(X + e) - basis.phi(X - e)) / (2 * h)
        np.testing.assert_allclose(G[:, k, :], fd, atol=1e-6 * np.abs(G).max())


@pytest.mark.parametrize(("d", "position_dim"), [(2, None), (3, None), (3, 2)])
def test_casadi_functions_match_numpy(d: int, position_dim: int | None) -> None:
    rng = np.random.default_rng(17 + d)
    dom = Domain(rng.uniform(-1, 1, d), rng.uniform(0.5, 1.5, d))
    basis = HilbertBasis(dom, 25)
    p = position_dim or d
    X = random_inside(rng, dom, 8)[:, :p]
    f_phi, f_grad = basis.phi_sx(position_dim), basis.grad_phi_sx(position_dim)
    assert f_phi.size_in(0) == (p, 1) and f_phi.size_out(0) == (25, 1)
    assert f_grad.size_out(0) == (d, 25)
    P, G = basis.phi(X), basis.grad_phi(X)
    for i, x in enumerate(X):
        np.testing.assert_allclose(np.asarray(f_phi(x)).ravel(), P[i], atol=1e-13)
        np.testing.assert_allclose(np.asarray(f_grad(x)), G[i], atol=1e-12)
    # Mapped over samples (the NLP use), with symbolic positions.
    Xs = ca.MX.sym("X", p, X.shape[0])
    mapped = ca.Function("m", [Xs], [f_phi.map(X.shape[0])(Xs)])
    np.testing.assert_allclose(np.asarray(mapped(X.T)), P.T, atol=1e-13)


@pytest.mark.parametrize("kernel_name", ["se", "curl_free"])
def test_field_sx_matches_evaluate_field(kernel_name: str) -> None:
    rng = np.random.default_rng(23)
    dom = domain_for(kernel_name, EXTENT, 1.0)
    basis = HilbertBasis(dom, 50)
    X = rng.uniform(0, 6, (9, 2))
    w = rng.normal(size=(50, 3) if kernel_name == "se" else 50)
    c = rng.normal(size=3)
    F = evaluate_field(basis, kernel_name, X, w, constant=c, chunk_rows=4)
    if kernel_name == "se":
        ref = basis.phi(X) @ w + c
    else:
        ref = basis.grad_phi(X) @ w + c
    np.testing.assert_allclose(F, ref, atol=1e-12)
    f = basis.field_sx(kernel_name, position_dim=2)
    for i, x in enumerate(X):
        np.testing.assert_allclose(np.asarray(f(x, w, c)).ravel(), F[i], atol=1e-12)


# --------------------------------------------------------------------------- prior
@pytest.mark.parametrize("kernel_name", ["se", "curl_free"])
def test_prior_variances_numpy_and_casadi(kernel_name: str) -> None:
    dom = domain_for(kernel_name, EXTENT, ELL)
    basis = HilbertBasis(dom, 60)
    d = dom.dim
    w = basis.sqrt_eigenvalues
    ref = SF**2 * (2 * np.pi * ELL**2) ** (d / 2) * np.exp(-0.5 * ELL**2 * w**2)
    S = basis.prior_variances(kernel_name, SF, ELL)
    np.testing.assert_allclose(S, ref, rtol=1e-12)
    np.testing.assert_allclose(basis.prior_std(kernel_name, SF, ELL), np.sqrt(ref), rtol=1e-12)
    for sym in (ca.SX, ca.MX):
        sf, ell = sym.sym("sf"), sym.sym("ell")
        fs = ca.Function("S", [sf, ell], [basis.prior_variances(kernel_name, sf, ell)])
        np.testing.assert_allclose(np.asarray(fs(SF, ELL)).ravel(), ref, rtol=1e-12)
        fstd = ca.Function("s", [sf, ell], [basis.prior_std(kernel_name, sf, ell)])
        np.testing.assert_allclose(np.asarray(fstd(SF, ELL)).ravel(), np.sqrt(ref), rtol=1e-12)
    with pytest.raises(NotImplementedError):
        basis.prior_variances("div_free", SF, ELL)


# --------------------------------------------------------------------------- approximation
def test_se_approximation_matches_exact_kernel() -> None:
    rng = np.random.default_rng(2020)
    dom = domain_for("se", EXTENT, ELL)
    basis = HilbertBasis(dom, lengthscale_for_default=ELL)
    X = rng.uniform(0, 6, (50, 2))
    exact = get_kernel("se").matrix(X, X, SF, ELL)
    np.testing.assert_allclose(exact, ref_se(X, X, SF, ELL), rtol=1e-12)
    K = approx_kernel_matrix(basis, "se", X, X, SF, ELL)
    assert K.shape == exact.shape
    err = np.abs(K - exact).max() / SF**2
    assert err < APPROX_TOL, (basis.num_basis, err)
    # Cross-covariance between different point sets too.
    Y = rng.uniform(0, 6, (7, 2))
    cross = approx_kernel_matrix(basis, "se", X, Y, SF, ELL)
    assert np.abs(cross - ref_se(X, Y, SF, ELL)).max() / SF**2 < APPROX_TOL
    # The constant field adds sigma_lin^2 everywhere (one component at a time).
    K_lin = approx_kernel_matrix(basis, "se", X, X, SF, ELL, sigma_lin=0.3)
    np.testing.assert_allclose(K_lin - K, 0.09, atol=1e-14)
    # A basis of 16 functions cannot represent a 0.35 m lengthscale over 8 m.
    small = HilbertBasis(dom, 16)
    assert np.abs(approx_kernel_matrix(small, "se", X, X, SF, ELL) - exact).max() > 10 * (
        APPROX_TOL * SF**2
    )


def test_curl_free_approximation_matches_exact_kernel() -> None:
    rng = np.random.default_rng(2018)
    dom = domain_for("curl_free", EXTENT, ELL)
    basis = HilbertBasis(dom, lengthscale_for_default=ELL)
    X = rng.uniform(0, 6, (50, 2))  # the plane z = 0
    exact = get_kernel("curl_free").matrix(X, X, SF, ELL)
    # casmag's K_H is the covariance of grad(potential) (sign convention of the basis).
    np.testing.assert_allclose(exact, ref_curl_free(X, X, SF, ELL), rtol=1e-12, atol=1e-14)
    K = approx_kernel_matrix(basis, "curl_free", X, X, SF, ELL)
    assert K.shape == (150, 150)
    variance = SF**2 / ELL**2
    err = np.abs(K - exact).max() / variance
    assert err < APPROX_TOL, (basis.num_basis, err)
    # The z component (z-derivative of the potential) is represented, not zero.
    zz = K[100:, 100:]
    assert np.abs(np.diag(zz) / variance - 1).max() < APPROX_TOL
    # Constant field: sigma_lin^2 on same-component blocks only.
    D = approx_kernel_matrix(basis, "curl_free", X, X, SF, ELL, sigma_lin=0.5) - K
    np.testing.assert_allclose(D, np.kron(np.eye(3), np.full((50, 50), 0.25)), atol=1e-12)
    # A 60-function basis is far off.
    small = HilbertBasis(dom, 60)
    K_small = approx_kernel_matrix(small, "curl_free", X, X, SF, ELL)
    assert np.abs(K_small - exact).max() / variance > 10 * APPROX_TOL
    # The curl-free field needs the 3-D potential box.
    with pytest.raises(ValueError, match="3-D"):
        approx_kernel_matrix(HilbertBasis(Domain.around(X, 1.0), 10), "curl_free", X, X, SF, ELL)


def test_3d_positions_curl_free() -> None:
    rng = np.random.default_rng(9)
    ell = 0.6
    X = rng.uniform(0, 2, (20, 3))
    basis = HilbertBasis(domain_for("curl_free", X, ell), lengthscale_for_default=ell)
    K = approx_kernel_matrix(basis, "curl_free", X, X, SF, ell)
    err = np.abs(K - ref_curl_free(X, X, SF, ell)).max() / (SF**2 / ell**2)
    assert err < APPROX_TOL, (basis.num_basis, err)


# --------------------------------------------------------------------------- default size
def test_default_num_basis_is_ball_count_and_grows() -> None:
    dom = domain_for("se", EXTENT, ELL)
    m = default_num_basis(dom, ELL, 2)
    # Brute-force count of sqrt(lambda) <= 4 / l.
    _, lam = brute_force_indices(dom.half_width, 60)
    assert m == int(np.sum(np.sqrt(lam) <= 4 / ELL))
    assert HilbertBasis(dom, lengthscale_for_default=ELL).num_basis == m

    counts = [default_num_basis(dom, ell) for ell in (1.0, 0.7, 0.5, 0.35)]
    assert all(a < b for a, b in itertools.pairwise(counts)), counts
    doms = [Domain.around(EXTENT * s, default_margin(ELL)) for s in (0.5, 1.0, 1.5)]
    sizes = [default_num_basis(dm, ELL) for dm in doms]
    assert all(a < b for a, b in itertools.pairwise(sizes)), sizes
    m3 = [default_num_basis(domain_for("curl_free", EXTENT * s, 0.5), 0.5) for s in (1, 2)]
    assert m3[0] < m3[1]
    # Capped, silently.
    assert default_num_basis(dom, 0.01) == 4000
    assert default_num_basis(dom, ELL, max_basis=100) == 100
    with pytest.raises(ValueError):
        default_num_basis(dom, ELL, 3)


def test_second_derivatives_match_finite_differences_of_the_gradient():
    rng = np.random.default_rng(5)
    domain = Domain(np.array([0.0, 0.0, 0.0]), np.array([1.0, 1.2, 0.8]))
    basis = HilbertBasis(domain, 40)
    X = rng.uniform(-0.5, 0.5, (6, 3))
    H = basis.second_derivatives(X)
    h = 1e-6
    for a in range(3):
        step = np.zeros(3)
        step[a] = h
        dG = (basis.grad_phi(X + step) - basis.grad_phi(X - step)) / (2 * h)  # (N, d, M)
        for b in range(3):
            np.testing.assert_allclose(H[(min(a, b), max(a, b))], dG[:, b, :], atol=1e-6)
