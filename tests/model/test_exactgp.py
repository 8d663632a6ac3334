"""The numpy exact GP prior (casmag.model.exact) against CasADi's automatic derivatives of the
symbolic prior (casmag.gp.reference.ExactGPPrior), and inside the MAP problem."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from casmag.gp.kernels import FIELD_DIM, get_kernel
from casmag.gp.reference import ExactGPPrior
from casmag.model.exact import ExactLayout, ExactPriorHessian, ExactPriorModel
from casmag.model.knots import Knots


def _reference(kernel: str, n: int, dim: int, every: int, estimate: bool, logdet: bool):
    """The prior blocks at a random point, by the numpy model and by CasADi's AD of the
    symbolic prior: (model, hessian callback, x, p, [f_q, f_d, grad_q, grad_d, hess])."""
    rng = np.random.default_rng(7)
    kn = Knots(n, every)
    K = kn.count
    n_hyper = 2 if estimate else 0
    n_x = K * dim + FIELD_DIM * n + n_hyper
    n_p = n * dim + (0 if estimate else 2)
    if estimate:
        sf, ll = ("x", K * dim + FIELD_DIM * n), ("x", K * dim + FIELD_DIM * n + 1)
    else:
        sf, ll = ("p", n * dim), ("p", n * dim + 1)
    lay = ExactLayout(n_x=n_x, n_p=n_p, C=0, M=K * dim, Q=0, sigma_f=sf, lengthscale=ll)
    model = ExactPriorModel(get_kernel(kernel), kn, dim, 1e-6, lay, logdet)
    x = np.concatenate([rng.normal(0, 0.03, K * dim), rng.normal(0, 1, FIELD_DIM * n)])
    p = rng.normal(0, 0.2, n * dim)
    if estimate:
        x = np.concatenate([x, [np.log(0.7), np.log(0.15)]])
    else:
        p = np.concatenate([p, [0.7, 0.15]])
    xs, ps = ca.MX.sym("x", n_x), ca.MX.sym("p", n_p)
    C = ca.reshape(xs[: K * dim], K, dim)
    P = ca.reshape(ps[: n * dim], n, dim) + ca.mtimes(kn.casadi_matrix(), C)
    M = ca.reshape(xs[K * dim : K * dim + FIELD_DIM * n], n, FIELD_DIM)
    src = xs if estimate else ps
    off = K * dim + FIELD_DIM * n if estimate else n * dim
    sigma_f = ca.exp(src[off]) if estimate else src[off]
    ell = ca.exp(src[off + 1]) if estimate else src[off + 1]
    prior = ExactGPPrior(get_kernel(kernel), n, dim, 1e-6)
    fq = 0.5 * prior.quadratic(P, M, sigma_f, ell)
    fd = 0.5 * prior.log_det(P, sigma_f, ell) if logdet else ca.MX(0)
    F = ca.Function(
        "ref",
        [xs, ps],
        [fq, fd, ca.gradient(fq, xs), ca.gradient(fd, xs), ca.hessian(fq + fd, xs)[0]],
    )
    ref = [np.array(v, dtype=float) for v in F(x, p)]
    return model, ExactPriorHessian("h", model), x, p, ref


@pytest.mark.parametrize(
    ("kernel", "n", "dim", "every", "estimate", "logdet"),
    [
        ("se", 12, 2, 1, True, True),
        ("se", 15, 2, 4, False, False),
        ("se", 10, 3, 1, False, True),
        ("curl_free", 10, 2, 1, True, True),
        ("curl_free", 9, 3, 3, True, True),
        ("div_free", 8, 3, 1, False, False),
    ],
)
def test_values_gradient_and_hessian_match_automatic_differentiation(
    kernel: str, n: int, dim: int, every: int, estimate: bool, logdet: bool
) -> None:
    model, hess, x, p, (fq, fd, gq, gd, H) = _reference(kernel, n, dim, every, estimate, logdet)
    vq, vd = model.values(x, p)
    assert vq == pytest.approx(fq.item(), rel=1e-10)
    if logdet:
        assert vd == pytest.approx(fd.item(), rel=1e-10, abs=1e-10)
    mq, md = model.gradient(x, p)
    np.testing.assert_allclose(mq, gq.ravel(), rtol=0, atol=1e-10 * np.abs(gq).max())
    if logdet:
        np.testing.assert_allclose(md, gd.ravel(), rtol=0, atol=1e-10 * np.abs(gd).max())
    Hm = np.zeros_like(H)
    Hm[hess._rows, hess._cols] = hess.values(x, p)
    Hu = np.triu(H)
    np.testing.assert_allclose(Hm, Hu, rtol=0, atol=1e-10 * np.abs(Hu).max())
    # every structural non-zero of the reference is in the callback's pattern
    pattern = np.zeros(H.shape, dtype=bool)
    pattern[hess._rows, hess._cols] = True
    assert not np.any((np.abs(Hu) > 0) & ~pattern)


def test_not_positive_definite_gives_nan_not_a_crash() -> None:
    model, _, x, p, _ = _reference("se", 6, 2, 1, True, True)
    x, p = x.copy(), p.copy()
    x[: 6 * 2] = 0.0
    p[: 6 * 2] = 0.0  # all samples at one point: C is all ones, singular without jitter
    model.jitter = 0.0
    q, _ = model.values(x, p)
    assert np.isnan(q)
    assert np.all(np.isnan(model.gradient(x, p)[0]))
    assert np.all(np.isnan(ExactPriorHessian("h", model).values(x, p)))
