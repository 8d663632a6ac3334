"""The exact GP prior's log-determinant: block LDL^T against numpy, where log(det) fails."""

import casadi as ca
import numpy as np
import pytest

from casmag.gp.kernels import get_kernel
from casmag.gp.reference import ExactGPPrior, block_log_det, logdet_block_size


def _spiral(n=81, step=0.05, r0=0.05, pitch=0.03):
    """The paper base case's sample positions: an Archimedean spiral walked in equal steps."""
    b = pitch / (2 * np.pi)
    theta, pts = r0 / b, []
    for _ in range(n):
        r = b * theta
        pts.append((r * np.cos(theta), r * np.sin(theta)))
        theta += step / np.hypot(r, b)
    return np.array(pts)


def _K(kernel, P, sigma_f, ell, jitter=1e-6):
    k = get_kernel(kernel)
    K = k.matrix(P, P, sigma_f, ell)
    return K + jitter * k.variance(sigma_f, ell) * np.eye(K.shape[0])


def _functions(kernel, P, block=None, derivatives=True):
    """log|K| of the full 3N x 3N field covariance, with its gradient and Hessian with respect
    to (vec P, l), as a CasADi function of (P, sigma_f, l); ``block`` overrides the block size
    (to test several blocks on a small matrix)."""
    prior = ExactGPPrior(get_kernel(kernel), len(P), P.shape[1])
    if block is not None:
        prior.block = block
    Pm, sf, ell = ca.MX.sym("P", *P.shape), ca.MX.sym("sf"), ca.MX.sym("l")
    x = ca.vertcat(ca.vec(Pm), ell)
    ld = prior.log_det(Pm, sf, ell)
    outs = [ld, ca.gradient(ld, x), ca.hessian(ld, x)[0]] if derivatives else [ld]
    return prior, ca.Function("ld", [Pm, sf, ell], outs)


def _analytic_hessian(kernel, P, ell):
    """Hessian of log|K| in (vec P, l) from dC and d2C (CasADi) and numpy linear algebra:
    copies x (tr(C^-1 d2C_ij) - tr(C^-1 dC_i C^-1 dC_j)); sigma_f drops out."""
    k = get_kernel(kernel)
    Pm, lm = ca.MX.sym("P", *P.shape), ca.MX.sym("l")
    zero = ca.MX.zeros(1, P.shape[1])
    C = k.matrix(Pm, Pm, 1.0, lm)
    C = C + 1e-6 * k.matrix(zero, zero, 1.0, lm)[0, 0] * ca.MX.eye(C.shape[0])
    x = ca.vertcat(ca.vec(Pm), lm)
    A = ca.MX.sym("A", *C.shape)
    J = ca.Function("J", [Pm, lm], [C, ca.jacobian(ca.vec(C), x)])
    H2 = ca.Function("H2", [Pm, lm, A], [ca.hessian(ca.sum1(ca.sum2(A * C)), x)[0]])
    Cv, Jv = (np.array(v) for v in J(P, ell))
    Ci = np.linalg.inv(Cv)
    m = Cv.shape[0]
    Y = [Ci @ Jv[:, i].reshape(m, m, order="F") for i in range(Jv.shape[1])]
    second = np.array([[np.sum(Yi * Yj.T) for Yj in Y] for Yi in Y])
    return (3 if k.output_dim == 1 else 1) * (np.array(H2(P, ell, Ci)) - second)


def _reference(kernel, P, sigma_f, ell):
    """numpy's slogdet of the 3N x 3N covariance (three copies of the N x N one for 'se')."""
    sign, ld = np.linalg.slogdet(_K(kernel, P, sigma_f, ell))
    assert sign == 1.0
    return ld * (3 if get_kernel(kernel).output_dim == 1 else 1)


def test_old_form_underflows_where_block_form_is_right():
    """The base case's 81 x 81 correlation at l = 0.15 m has log det -790, below the log of
    the smallest double: log(det(C)) is -inf, the block form matches numpy's slogdet."""
    P = _spiral()
    C = _K("se", P, 1.0, 0.15)
    X = ca.MX.sym("C", *C.shape)
    old = float(ca.Function("f", [X], [ca.log(ca.det(X))])(C))
    assert old == -np.inf
    ref = np.linalg.slogdet(C)[1]
    assert ref < -745
    _, f = _functions("se", P, derivatives=False)
    value = float(f(P, 0.1, 0.15))
    assert value == pytest.approx(_reference("se", P, 0.1, 0.15), rel=1e-10, abs=0)


@pytest.mark.parametrize("kernel, n", [("se", 30), ("curl_free", 12)])
@pytest.mark.parametrize("ell", [0.05, 0.1, 0.4])
def test_value_gradient_and_hessian(kernel, n, ell):
    """Value against slogdet; gradient against central differences of slogdet in l and a
    few position coordinates; Hessian against central differences of the gradient. The
    first samples of the base case's spiral, factorised in three blocks of 13 rows or less."""
    P = _spiral(n)
    sigma_f = 0.1
    _, f = _functions(kernel, P, block=13)
    value, grad, hess = (np.array(v) for v in f(P, sigma_f, ell))
    assert value.item() == pytest.approx(_reference(kernel, P, sigma_f, ell), rel=1e-10, abs=0)
    grad = grad.ravel()
    n = P.size
    h = 1e-6 * ell
    fd_l = (_reference(kernel, P, sigma_f, ell + h) - _reference(kernel, P, sigma_f, ell - h)) / (
        2 * h
    )
    assert grad[n] == pytest.approx(fd_l, rel=1e-5)
    for i in (0, 17, n - 1):  # entries of vec(P), column-major
        dP = np.zeros(n)
        dP[i] = 1e-7
        dP = dP.reshape(P.shape, order="F")
        fd = (
            _reference(kernel, P + dP, sigma_f, ell) - _reference(kernel, P - dP, sigma_f, ell)
        ) / 2e-7
        assert grad[i] == pytest.approx(fd, rel=1e-4, abs=1e-4 * np.abs(grad).max())
    # Hessian against the analytic form, computed separately with numpy: copies x
    # (tr(C^-1 d2C) - tr(C^-1 dC_i C^-1 dC_j)). Measured agreement: 5e-7 of the largest entry
    # at l = 0.4 m (C nearly singular), 4e-8 at 0.1 m, 4e-13 at 0.05 m.
    ref = _analytic_hessian(kernel, P, ell)
    np.testing.assert_allclose(hess, ref, rtol=0, atol=1e-5 * np.abs(ref).max())
    # ... and central differences of the gradient, where C is well enough conditioned for
    # them (l <= 0.1 m; at 0.4 m rounding in the gradient dominates a difference quotient).
    if ell > 0.1:
        return
    for j in (n, 5):  # Hessian columns: l and one position coordinate
        e = np.zeros(n + 1)
        e[j] = 1e-6 * (ell if j == n else 1.0)
        Pp = P + e[:n].reshape(P.shape, order="F")
        Pm_ = P - e[:n].reshape(P.shape, order="F")
        gp = np.array(f(Pp, sigma_f, ell + e[n])[1]).ravel()
        gm = np.array(f(Pm_, sigma_f, ell - e[n])[1]).ravel()
        fd = (gp - gm) / (2 * e[j])
        np.testing.assert_allclose(hess[:, j], fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max())


def test_sigma_f_enters_as_log():
    """log|K| = 2 (3N) log sigma_f + log|C|: the gradient in log sigma_f is 2 x 3N."""
    P = _spiral(20)
    _, f = _functions("se", P)
    a = float(f(P, 0.1, 0.1)[0])
    b = float(f(P, 1.0, 0.1)[0])
    assert b - a == pytest.approx(2 * 3 * 20 * np.log(10.0), rel=1e-12)


@pytest.mark.parametrize("block", [1, 3, 7, 30])
def test_block_log_det_matches_slogdet(block):
    """Any block size gives the same log det of a random SPD matrix (seeded)."""
    rng = np.random.default_rng(3)
    A = rng.standard_normal((30, 30))
    A = A @ A.T / 30 + 1e-3 * np.eye(30)
    X = ca.MX.sym("A", 30, 30)
    f = ca.Function("f", [X], [block_log_det(X, block)])
    assert float(f(A)) == pytest.approx(np.linalg.slogdet(A)[1], rel=1e-10, abs=1e-10)


def test_block_size_keeps_blocks_representable():
    """jitter^b stays above exp(-600); smaller jitter, smaller blocks; never above n."""
    assert logdet_block_size(1e-6, 81) == 43
    assert logdet_block_size(1e-6, 20) == 20
    assert logdet_block_size(1e-12, 300) == 21
    assert logdet_block_size(0.0, 300) == 16  # machine epsilon
    assert logdet_block_size(1.0, 300) == 300
    for jitter in (1e-3, 1e-6, 1e-9):
        b = logdet_block_size(jitter, 10_000)
        assert b * np.log(jitter) >= -600 > (b + 1) * np.log(jitter)
