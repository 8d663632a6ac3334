"""Kernels (casmag.gp.kernels) against plain numpy references of paper Eq. 7 and 8.

The references below are written from the formulas, independently of casmag:

    SE:        k(r)   = sf^2 exp(-|r|^2 / (2 l^2))                       (per component)
    curl-free: K_H(r) = (1/l^2) (I - (r/l)(r/l)^T) k(r)
    div-free:  K_B(r) = (1/l^2) ((n - 1 - |r/l|^2) I + (r/l)(r/l)^T) k(r),  n = 3

2-D points are embedded at z = 0 for the 3-component kernels, and 3-component matrices are
ordered component-major (row = component * N + point).
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from scipy import integrate

from casmag.gp import kernels
from casmag.gp.kernels import KERNELS, field_covariance, get_kernel

SF, ELL = 0.7, 0.35
RTOL = 1e-12


# --------------------------------------------------------------------------- references
def _embed3(X: np.ndarray) -> np.ndarray:
    """(N, d) points with d <= 3 as (N, 3), missing coordinates zero."""
    X = np.atleast_2d(np.asarray(X, dtype=float))
    out = np.zeros((X.shape[0], 3))
    out[:, : X.shape[1]] = X
    return out


def ref_se_scalar(r: np.ndarray, sf: float, ell: float) -> float:
    r = np.asarray(r, dtype=float)
    return sf**2 * np.exp(-(r @ r) / (2.0 * ell**2))


def ref_curl_free_block(r: np.ndarray, sf: float, ell: float) -> np.ndarray:
    r = np.asarray(r, dtype=float)
    u = r / ell
    return (np.eye(3) - np.outer(u, u)) * ref_se_scalar(r, sf, ell) / ell**2


def ref_div_free_block(r: np.ndarray, sf: float, ell: float, n: int = 3) -> np.ndarray:
    r = np.asarray(r, dtype=float)
    u = r / ell
    return ((n - 1 - u @ u) * np.eye(3) + np.outer(u, u)) * ref_se_scalar(r, sf, ell) / ell**2


def ref_se_matrix(X1: np.ndarray, X2: np.ndarray, sf: float, ell: float) -> np.ndarray:
    K = np.empty((len(X1), len(X2)))
    for i, x in enumerate(X1):
        for j, y in enumerate(X2):
            K[i, j] = ref_se_scalar(np.asarray(x) - np.asarray(y), sf, ell)
    return K


def _component_major(block, X1: np.ndarray, X2: np.ndarray, sf: float, ell: float) -> np.ndarray:
    A, B = _embed3(X1), _embed3(X2)
    n1, n2 = len(A), len(B)
    K = np.empty((3 * n1, 3 * n2))
    for i in range(n1):
        for j in range(n2):
            Kij = block(A[i] - B[j], sf, ell)
            for a in range(3):
                for b in range(3):
                    K[a * n1 + i, b * n2 + j] = Kij[a, b]
    return K


def ref_curl_free_matrix(X1, X2, sf, ell):
    return _component_major(ref_curl_free_block, X1, X2, sf, ell)


def ref_div_free_matrix(X1, X2, sf, ell):
    return _component_major(ref_div_free_block, X1, X2, sf, ell)


REFERENCES = {
    "se": ref_se_matrix,
    "curl_free": ref_curl_free_matrix,
    "div_free": ref_div_free_matrix,
}

# The 3x3 block a 3-component kernel gives at one displacement r (3,)
BLOCKS = {"curl_free": ref_curl_free_block, "div_free": ref_div_free_block}


def _points(seed: int, n: int, d: int, scale: float = 1.0) -> np.ndarray:
    return scale * np.random.default_rng(seed).uniform(-1.0, 1.0, size=(n, d))


def _casadi_eval(kernel, X1: np.ndarray, X2: np.ndarray, sf: float, ell: float) -> np.ndarray:
    """kernel.matrix on SX symbols for points and hyperparameters, evaluated numerically."""
    S1 = ca.SX.sym("X1", *X1.shape)
    S2 = ca.SX.sym("X2", *X2.shape)
    s_sf, s_ell = ca.SX.sym("sf"), ca.SX.sym("ell")
    F = ca.Function("K", [S1, S2, s_sf, s_ell], [kernel.matrix(S1, S2, s_sf, s_ell)])
    return np.array(F(X1, X2, sf, ell))


def _assert_close(got: np.ndarray, want: np.ndarray, rtol: float = RTOL) -> None:
    assert got.shape == want.shape
    scale = np.max(np.abs(want))
    np.testing.assert_allclose(got, want, rtol=rtol, atol=rtol * scale)


# --------------------------------------------------------------------------- reference match
def test_every_registered_kernel_has_a_reference():
    assert set(KERNELS) == set(REFERENCES)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_numpy_matrix_matches_reference(name, d):
    kernel = get_kernel(name)
    X1, X2 = _points(1, 6, d, 0.5), _points(2, 4, d, 0.5)
    got = kernel.matrix(X1, X2, SF, ELL)
    assert isinstance(got, np.ndarray)
    _assert_close(got, REFERENCES[name](X1, X2, SF, ELL))


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_casadi_sx_matrix_matches_reference(name, d):
    kernel = get_kernel(name)
    X1, X2 = _points(3, 5, d, 0.5), _points(4, 3, d, 0.5)
    got = _casadi_eval(kernel, X1, X2, SF, ELL)
    _assert_close(got, REFERENCES[name](X1, X2, SF, ELL))


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_casadi_dm_matrix_matches_reference(name, d):
    kernel = get_kernel(name)
    X1, X2 = _points(5, 4, d, 0.5), _points(6, 4, d, 0.5)
    K = kernel.matrix(ca.DM(X1), ca.DM(X2), SF, ELL)
    F = ca.Function("K", [], [K])
    got = np.array(F()["o0"])
    _assert_close(got, REFERENCES[name](X1, X2, SF, ELL))


@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_single_point_pair_is_the_kernel_block(name):
    """With one point on each side the 3x3 matrix is K(r) itself (component-major)."""
    kernel = get_kernel(name)
    x, y = np.array([[0.1, -0.2, 0.3]]), np.array([[-0.05, 0.1, 0.0]])
    got = kernel.matrix(x, y, SF, ELL)
    if name == "se":
        _assert_close(got, np.array([[ref_se_scalar(x[0] - y[0], SF, ELL)]]))
    else:
        _assert_close(got, BLOCKS[name](x[0] - y[0], SF, ELL))


@pytest.mark.parametrize(
    ("name", "expected"),
    [("se", SF**2), ("curl_free", SF**2 / ELL**2), ("div_free", 2 * SF**2 / ELL**2)],
)
def test_variance(name, expected):
    assert get_kernel(name).variance(SF, ELL) == pytest.approx(expected, rel=RTOL)


@pytest.mark.parametrize("name", sorted(REFERENCES))
def test_field_covariance_matches_reference(name):
    X = _points(7, 5, 3, 0.5)
    got = field_covariance(get_kernel(name), X, SF, ELL)
    want = REFERENCES[name](X, X, SF, ELL)
    if name == "se":
        want = np.kron(np.eye(3), want)
    _assert_close(got, want)


# --------------------------------------------------------------------------- properties
ALL_KERNELS = sorted(KERNELS)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("name", ALL_KERNELS)
def test_symmetric(name, d):
    X = _points(11, 12, d)
    K = get_kernel(name).matrix(X, X, SF, ELL)
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-14 * np.max(np.abs(K)))


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("name", ALL_KERNELS)
def test_positive_semidefinite(name, d):
    X = _points(12, 25, d)
    K = get_kernel(name).matrix(X, X, SF, ELL)
    eig = np.linalg.eigvalsh(0.5 * (K + K.T))
    assert eig.min() >= -1e-10 * eig.max()


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("name", ALL_KERNELS)
def test_field_covariance_shape(name, d):
    N = 7
    C = field_covariance(get_kernel(name), _points(13, N, d), SF, ELL)
    assert C.shape == (3 * N, 3 * N)
    np.testing.assert_allclose(C, C.T, rtol=0, atol=1e-14 * np.max(np.abs(C)))


def test_get_kernel_returns_registered_instances():
    for name, cls in KERNELS.items():
        kernel = get_kernel(name)
        assert isinstance(kernel, cls)
        assert kernel.name == name


def test_get_kernel_unknown_name():
    with pytest.raises(ValueError, match="nope"):
        get_kernel("nope")


# --------------------------------------------------------------------------- curl / divergence
def _block(name: str, r: np.ndarray) -> np.ndarray:
    """casmag's 3x3 K(r) = K(x, x') for x = r, x' = 0."""
    return get_kernel(name).matrix(r[None, :], np.zeros((1, 3)), SF, ELL)


def _jacobian_fd(name: str, r: np.ndarray, h: float) -> np.ndarray:
    """D[a, b, c] = d/dx_a K_bc(x - x') at x - x' = r, by central differences."""
    D = np.empty((3, 3, 3))
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        D[a] = (_block(name, r + e) - _block(name, r - e)) / (2 * h)
    return D


def _curl_and_div(name: str, r: np.ndarray) -> tuple[float, float]:
    D = _jacobian_fd(name, r, h=1e-5 * ELL)
    # curl on the first argument: d_a K_bc - d_b K_ac for every a, b, c
    curl = D - np.transpose(D, (1, 0, 2))
    # divergence on the first argument: sum_a d_a K_ac
    div = np.einsum("aac->c", D)
    scale = SF**2 / ELL**3  # size of a first derivative of the kernel
    return float(np.max(np.abs(curl)) / scale), float(np.max(np.abs(div)) / scale)


DISPLACEMENTS = list(_points(21, 5, 3, ELL))


@pytest.mark.parametrize("r", DISPLACEMENTS)
def test_curl_free_kernel_has_zero_curl_but_nonzero_divergence(r):
    curl, div = _curl_and_div("curl_free", r)
    assert curl < 1e-7
    assert div > 1e-2


@pytest.mark.parametrize("r", DISPLACEMENTS)
def test_div_free_kernel_has_zero_divergence_but_nonzero_curl(r):
    curl, div = _curl_and_div("div_free", r)
    assert div < 1e-7
    assert curl > 1e-2


# --------------------------------------------------------------------------- spectral density
R_VALUES_1D = [0.0, 0.1, 0.37, 0.8]
R_VALUES_2D = [np.array([0.0, 0.0]), np.array([0.12, -0.05]), np.array([0.3, 0.25])]


def _inverse_ft_1d(S, r: float, weight=lambda w: 1.0) -> float:
    # the density is even, so the imaginary part vanishes
    val, _ = integrate.quad(
        lambda w: weight(w) * S(np.array(w)) * np.cos(w * r),
        -np.inf,
        np.inf,
        epsabs=0,
        epsrel=1e-11,
    )
    return val / (2 * np.pi)


def _omega_grid_2d():
    w = np.linspace(-12.0 / ELL, 12.0 / ELL, 801)
    W1, W2 = np.meshgrid(w, w, indexing="ij")
    return w, W1, W2


def _inverse_ft_2d(S_grid, W1, W2, w, r) -> float:
    integrand = S_grid * np.cos(W1 * r[0] + W2 * r[1])
    return integrate.trapezoid(integrate.trapezoid(integrand, w, axis=1), w) / (2 * np.pi) ** 2


@pytest.mark.parametrize("name", ["se", "curl_free"])
@pytest.mark.parametrize("r", R_VALUES_1D)
def test_spectral_density_1d_gives_scalar_kernel(name, r):
    kernel = get_kernel(name)
    got = _inverse_ft_1d(lambda w: kernel.spectral_density(w, SF, ELL, 1), r)
    want = ref_se_scalar(np.array([r]), SF, ELL)
    if name == "se":
        # the kernel itself, evaluated by casmag on 1-D points
        assert kernel.matrix(np.array([[r]]), np.zeros((1, 1)), SF, ELL)[0, 0] == pytest.approx(
            want, rel=1e-12
        )
    assert got == pytest.approx(want, rel=1e-6)


@pytest.mark.parametrize("name", ["se", "curl_free"])
@pytest.mark.parametrize("ri", range(len(R_VALUES_2D)))
def test_spectral_density_2d_gives_scalar_kernel(name, ri):
    r = R_VALUES_2D[ri]
    kernel = get_kernel(name)
    w, W1, W2 = _omega_grid_2d()
    S = kernel.spectral_density(np.hypot(W1, W2), SF, ELL, 2)
    got = _inverse_ft_2d(S, W1, W2, w, r)
    want = ref_se_scalar(r, SF, ELL)
    if name == "se":
        assert kernel.matrix(r[None, :], np.zeros((1, 2)), SF, ELL)[0, 0] == pytest.approx(
            want, rel=1e-12
        )
    assert got == pytest.approx(want, rel=1e-6)


@pytest.mark.parametrize("r", R_VALUES_1D)
def test_curl_free_is_hessian_of_potential_1d(r):
    """K_H,xx(r) on the x axis = (2 pi)^-1 ∫ w^2 S(w) cos(w r) dw (gradient of the potential)."""
    kernel = get_kernel("curl_free")
    got = _inverse_ft_1d(lambda w: kernel.spectral_density(w, SF, ELL, 1), r, weight=lambda w: w**2)
    K = kernel.matrix(np.array([[r, 0.0, 0.0]]), np.zeros((1, 3)), SF, ELL)
    assert got == pytest.approx(K[0, 0], rel=1e-6, abs=1e-9 * SF**2 / ELL**2)


@pytest.mark.parametrize("ri", range(len(R_VALUES_2D)))
def test_curl_free_is_hessian_of_potential_2d(ri):
    """K_H,ab(r) in the plane = (2 pi)^-2 ∫ w_a w_b S(w) cos(w . r) dw for a, b in {x, y}."""
    r = R_VALUES_2D[ri]
    kernel = get_kernel("curl_free")
    w, W1, W2 = _omega_grid_2d()
    S = kernel.spectral_density(np.hypot(W1, W2), SF, ELL, 2)
    K = kernel.matrix(r[None, :], np.zeros((1, 2)), SF, ELL)
    Wa = (W1, W2)
    for a in range(2):
        for b in range(2):
            got = _inverse_ft_2d(Wa[a] * Wa[b] * S, W1, W2, w, r)
            assert got == pytest.approx(K[a, b], rel=1e-6, abs=1e-9 * SF**2 / ELL**2)


def test_div_free_has_no_spectral_density():
    with pytest.raises(NotImplementedError):
        get_kernel("div_free").spectral_density(np.array([0.0, 1.0]), SF, ELL, 2)


# --------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("name", ALL_KERNELS)
def test_gradient_at_coincident_points_is_finite(name):
    P = ca.SX.sym("P", 2, 2)
    K = get_kernel(name).matrix(P, P, 1.0, 0.3)
    total = ca.sum1(ca.sum2(K))
    J = ca.jacobian(total, P)
    H = ca.hessian(total, P)[0]
    F = ca.Function("g", [P], [J, H])
    same = np.array([[0.2, -0.4], [0.2, -0.4]])
    for out in F(same):
        assert np.all(np.isfinite(np.array(out)))
    # also finite with every point at the origin
    for out in F(np.zeros((2, 2))):
        assert np.all(np.isfinite(np.array(out)))


def test_module_field_dim_is_three():
    assert kernels.FIELD_DIM == 3
