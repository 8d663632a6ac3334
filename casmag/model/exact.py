"""The exact GP prior block of the MAP problem, evaluated with numpy (LAPACK).

With the field values m at the N sample positions P as unknowns (paper Eq. 5-6), the prior
adds

    f(P, m, sigma_f, l) = 0.5 m^T K^-1 m                      (cost block ``gp_prior``)
                        + 0.5 log |K|   (estimated sigma_f or l; block ``gp_logdet``)

with K = sigma_f^2 C(P, l) (C the correlation matrix plus a relative jitter). A CasADi graph
of this block differentiates a symbolic factorisation of C, whose Hessian costs O(N^3)
virtual-machine operations per evaluation: on the paper's 81-sample base case 0.19 s per
Hessian (97 % of the solve) and about 20 s to build. Here every evaluation is one Cholesky
factorisation and a few dense products, with the exact gradient and Hessian written out:
with A = C^-1, alpha = A m, C_a = dC/dtheta_a (theta: positions and log l),

    d/dtheta_a  m^T A m      = -alpha^T C_a alpha
    d2/dtheta_a dtheta_b     =  2 alpha^T C_a A C_b alpha - alpha^T C_ab alpha
    d/dm, d2/dm dtheta_a     =  2 alpha, -2 A C_a alpha;   d2/dm2 = 2 A
    d/dtheta_a log|C|        =  tr(A C_a)
    d2/dtheta_a dtheta_b     =  tr(A C_ab) - tr(A C_a A C_b).

An entry C_ij depends on (p_i, p_j, l) only, so its first and second derivatives come from
one small SX function of a pair, mapped over the N^2 pairs; the second-derivative terms are
contracted pairwise (sum_ij W_ij d2 C_ij) and scattered into the Hessian. A position
derivative C_a (sample t, axis k) is non-zero in block row and column t only,
C_a = E_t G_a^T + G_a E_t^T (the kernels are stationary, so the diagonal block is constant),
which turns tr(A C_a A C_b) into products of A G and G^T A G.

The positions reach the unknowns through the knots, P = Q + A_knots C (casmag.model.knots), so the
position gradient and Hessian are mapped to the knots with A_knots.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sps
from threadpoolctl import ThreadpoolController

from casmag.gp.kernels import FIELD_DIM, Kernel
from casmag.model.knots import Knots
from casmag.model.rrmap import HessianCallback, NumpyCost


@dataclass(frozen=True)
class ExactLayout:
    """Where the prior's unknowns sit in x and p (offsets into the stacked vectors).

    C: knot corrections (K, d) column-major in x; M: field values at the samples (N, 3)
    column-major in x; Q: dead-reckoned positions (N, d) in p, or None when the positions
    are the variables themselves (P = C, one knot per sample). sigma_f, lengthscale:
    (``"x"``, offset of log value) when estimated, else (``"p"``, offset of the value).
    """

    n_x: int
    n_p: int
    C: int
    M: int
    Q: int | None
    sigma_f: tuple[str, int]
    lengthscale: tuple[str, int]


class ExactPriorModel:
    """Value, gradient and exact Hessian of the exact GP prior blocks at a point (x, p).

    The factorisation and the first derivatives at the last point are cached, so IPOPT's
    calls for the cost, the gradient and the Hessian at one iterate share them.
    """

    def __init__(
        self,
        kernel: Kernel,
        knots: Knots,
        dim: int,
        jitter: float,
        layout: ExactLayout,
        logdet: bool,
    ) -> None:
        self.kernel, self.knots, self.dim, self.jitter = kernel, knots, dim, jitter
        self.lay, self.logdet = layout, logdet
        self.N = knots.n
        self.R = kernel.output_dim  # 1: same C for each field component; 3: coupled
        self.n_k = self.N * self.R  # size of C
        self.ncol = FIELD_DIM if self.R == 1 else 1  # right-hand sides m
        self.copies = FIELD_DIM if self.R == 1 else 1  # log|K| counts C this often
        self.est_sf = layout.sigma_f[0] == "x"
        self.est_l = layout.lengthscale[0] == "x"
        self._pair_fns()
        i, j = np.divmod(np.arange(self.N * self.N), self.N)
        self._pi, self._pj = i, j
        self._diag = (i == j).astype(float)[None, :]
        self._cache: dict[str, Any] = {}

    # ------------------------------------------------------------------ pair functions
    def _pair_fns(self) -> None:
        d, R = self.dim, self.R
        z = ca.SX.sym("z", 2 * d + 1)  # p_i, p_j, log l
        diag = ca.SX.sym("diag")
        w = ca.SX.sym("w", R * R)  # column-major R x R weights
        ell = ca.exp(z[2 * d])
        pi, pj = z[:d].T, z[d : 2 * d].T
        k = self.kernel.matrix(pi, pj, 1.0, ell)
        zero = ca.SX.zeros(1, d)
        variance = self.kernel.matrix(zero, zero, 1.0, ell)[0, 0]
        k = k + diag * self.jitter * variance * ca.SX.eye(R)
        J = ca.jacobian(ca.vec(k), z)  # (R^2, nz), row r + R s
        H = ca.hessian(ca.sum1(ca.sum2(ca.reshape(w, R, R) * k)), z)[0]
        self._f_jac = ca.Function("gp_pair_jac", [z, diag], [ca.vec(J)])
        self._f_hess = ca.Function("gp_pair_hess", [z, diag, w], [ca.vec(H)])
        self._maps: dict[tuple[str, int], ca.Function] = {}

    def _mapped(self, which: str, n: int) -> ca.Function:
        key = (which, n)
        if key not in self._maps:
            fn = self._f_jac if which == "jac" else self._f_hess
            self._maps[key] = fn.map(n)
        return self._maps[key]

    # ------------------------------------------------------------------ unpacking
    def unpack(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, float, float, np.ndarray]:
        """Positions P (N, d), log sigma_f, log l, and m (n_k, ncol) at the NLP point."""
        lay, kn, d = self.lay, self.knots, self.dim
        C = x[lay.C : lay.C + kn.count * d].reshape(kn.count, d, order="F")
        if lay.Q is None:
            Q = np.zeros((self.N, d))
        else:
            Q = p[lay.Q : lay.Q + self.N * d].reshape(self.N, d, order="F")
        vec = x[lay.M : lay.M + self.N * FIELD_DIM]
        m = vec.reshape(self.n_k, self.ncol, order="F")
        return kn.positions(Q, C), self._log(lay.sigma_f, x, p), self._log(lay.lengthscale, x, p), m

    @staticmethod
    def _log(where: tuple[str, int], x: np.ndarray, p: np.ndarray) -> float:
        kind, off = where
        return float(x[off]) if kind == "x" else float(np.log(p[off]))

    # ------------------------------------------------------------------ evaluation
    def _factor(self, x: np.ndarray, p: np.ndarray) -> dict[str, Any]:
        key = x.tobytes() + p.tobytes()
        if self._cache.get("key") == key:
            return self._cache
        P, ls, ll, m = self.unpack(x, p)
        C = np.asarray(self.kernel.matrix(P, P, 1.0, np.exp(ll)), dtype=float)
        var = self.kernel.variance(1.0, float(np.exp(ll)))
        C = C + self.jitter * var * np.eye(self.n_k)
        try:
            cf = sla.cho_factor(C, lower=True, check_finite=True)
        except (np.linalg.LinAlgError, ValueError):
            cf = None
        self._cache = {"key": key, "P": P, "ls": ls, "ll": ll, "m": m, "cf": cf}
        if cf is not None:
            alpha = sla.cho_solve(cf, m)
            self._cache.update(
                alpha=alpha,
                Q=float(np.sum(m * alpha)),
                logdetC=2.0 * float(np.sum(np.log(np.diag(cf[0])))),
            )
        return self._cache

    def values(self, x: np.ndarray, p: np.ndarray) -> tuple[float, float]:
        """(0.5 m^T K^-1 m, 0.5 log|K|) at the NLP point (NaN when C is not positive
        definite there, which makes IPOPT shorten its step)."""
        c = self._factor(x, p)
        if c["cf"] is None:
            return float("nan"), float("nan")
        s2 = _inverse_square(c["ls"])
        quad = 0.5 * s2 * c["Q"]
        n_total = self.N * FIELD_DIM
        logdet = 0.5 * (n_total * 2.0 * c["ls"] + self.copies * c["logdetC"])
        return quad, logdet

    def _first(self, c: dict[str, Any]) -> dict[str, Any]:
        """Pair Jacobians and the first-derivative quantities (cached with the factor)."""
        if "G" in c:
            return c
        N, R, d = self.N, self.R, self.dim
        P = c["P"]
        # every ordered pair (i, j): p_i, p_j, log l
        Z = np.vstack([P[self._pi].T, P[self._pj].T, np.full((1, N * N), c["ll"])])
        J = np.asarray(self._mapped("jac", N * N)(Z, self._diag))  # (R^2 nz, N^2)
        nz = 2 * d + 1
        J = J.T.reshape(N, N, nz, R, R)  # [i, j, z, s, r]
        J = np.transpose(J, (0, 1, 4, 3, 2))  # [i, j, r, s, z] = dC[(i,r),(j,s)]/dz
        # G[i, r, t, k, s] = dC[(i,r),(t,s)]/dp_tk for i != t (zero at i = t)
        G = np.transpose(J[:, :, :, :, d : 2 * d], (0, 2, 1, 4, 3)).copy()
        G[np.arange(N), :, np.arange(N), :, :] = 0.0
        Cl = np.transpose(J[:, :, :, :, 2 * d], (2, 0, 3, 1)).reshape(self.n_k, self.n_k)
        alpha = c["alpha"]
        ab = alpha.reshape(R, N, self.ncol)  # [r, i, c]
        # V[(r,i), (t,k), c] = (C_a alpha_c)[(r,i)]
        X1 = np.einsum("irtks,ric->tksc", G, ab)  # G_a^T alpha_c, placed in block t
        X2 = np.einsum("irtks,stc->ritkc", G, ab)  # G_a alpha_c[block t]
        V = X2.copy()
        V[:, np.arange(N), np.arange(N), :, :] += np.transpose(X1, (2, 0, 1, 3))
        V = V.reshape(self.n_k, N * d, self.ncol)  # columns t-major: (t, k) -> t d + k
        Vl = (Cl @ alpha)[:, None, :]
        V = np.concatenate([V, Vl], axis=1)  # (n_k, N d + 1, ncol)
        c.update(Z=Z, J=J, G=G, Cl=Cl, V=V)
        return c

    def gradient(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n_x,) gradients of the quadratic and of the log-determinant block."""
        c = self._factor(x, p)
        gq, gd = np.zeros(self.lay.n_x), np.zeros(self.lay.n_x)
        if c["cf"] is None:
            gq[:], gd[:] = np.nan, np.nan
            return gq, gd
        c = self._first(c)
        N, d, lay = self.N, self.dim, self.lay
        s2 = _inverse_square(c["ls"])
        alpha, V = c["alpha"], c["V"]
        Qth = -np.einsum("qc,qac->a", alpha, V)  # (N d + 1,)
        self._put_theta(gq, 0.5 * s2 * Qth)
        gq[lay.M : lay.M + self.N * FIELD_DIM] = s2 * alpha.ravel(order="F")
        if self.est_sf:
            gq[lay.sigma_f[1]] = -s2 * c["Q"]
        if self.logdet:
            A = c["A"] = _inverse(c["cf"])
            Ab = A.reshape(self.R, N, self.R, N)
            Lp = 2.0 * np.einsum("irtks,rist->tk", c["G"], Ab).reshape(N * d)
            Ll = float(np.sum(A * c["Cl"]))
            self._put_theta(gd, 0.5 * self.copies * np.append(Lp, Ll))
            if self.est_sf:
                gd[lay.sigma_f[1]] = self.N * FIELD_DIM
        return gq, gd

    def _put_theta(self, g: np.ndarray, gth: np.ndarray) -> None:
        """Add a gradient over (positions t-major (N, d), log l) into x-space."""
        N, d, kn, lay = self.N, self.dim, self.knots, self.lay
        gP = gth[: N * d].reshape(N, d)
        g[lay.C : lay.C + kn.count * d] += (kn.matrix.T @ gP).ravel(order="F")
        if self.est_l:
            g[lay.lengthscale[1]] += gth[N * d]

    # ------------------------------------------------------------------ Hessian
    def local_hessian(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Dense Hessian of the prior blocks over (positions (N, d) t-major, log l, m
        (column-major), log sigma_f), all of them whether estimated or not."""
        c = self._first(self._factor(x, p))
        N, d, nk, ncol = self.N, self.dim, self.n_k, self.ncol
        nth = N * d + 1
        s2 = _inverse_square(c["ls"])
        cf, alpha, V = c["cf"], c["alpha"], c["V"]
        A = c.get("A")
        if A is None:
            A = c["A"] = _inverse(cf)
        # theta-theta: 0.5 s2 (2 sum_c V_c^T A V_c) ...
        AV = (A @ V.reshape(nk, -1)).reshape(V.shape)
        Vt = np.transpose(V, (2, 1, 0))  # (ncol, theta, nk)
        Htt = s2 * np.sum(Vt @ np.transpose(AV, (2, 0, 1)), axis=0)
        # ... + sum_ij W_ij d2 C_ij, W = 0.5 copies A [logdet] - 0.5 s2 sum_c alpha_c alpha_c^T
        W = -0.5 * s2 * (alpha @ alpha.T)
        if self.logdet:
            W = W + 0.5 * self.copies * A
        Htt += self._pair_second(c, W)
        if self.logdet:
            Htt -= 0.5 * self.copies * self._trace_products(c, A)
        # m blocks
        nm = nk * ncol
        Hmm = np.zeros((nm, nm))
        for k in range(ncol):
            Hmm[k * nk : (k + 1) * nk, k * nk : (k + 1) * nk] = s2 * A
        Hmt = -s2 * np.transpose(AV, (2, 0, 1)).reshape(nm, nth)  # (m column-major, theta)
        # log sigma_f
        Qth = -np.einsum("qc,qac->a", alpha, V)
        hs_t = -s2 * Qth
        hs_m = -2.0 * s2 * alpha.ravel(order="F")
        hs_s = 2.0 * s2 * c["Q"]
        n = nth + nm + 1
        H = np.empty((n, n))
        H[:nth, :nth] = Htt
        H[:nth, nth : nth + nm] = Hmt.T
        H[nth : nth + nm, :nth] = Hmt
        H[nth : nth + nm, nth : nth + nm] = Hmm
        H[n - 1, :nth], H[:nth, n - 1] = hs_t, hs_t
        H[n - 1, nth : nth + nm], H[nth : nth + nm, n - 1] = hs_m, hs_m
        H[n - 1, n - 1] = hs_s
        return H

    def _pair_second(self, c: dict[str, Any], W: np.ndarray) -> np.ndarray:
        """sum_ij W_ij d2 C_ij / dtheta dtheta over (positions t-major, log l)."""
        N, R, d = self.N, self.R, self.dim
        nz = 2 * d + 1
        Wb = W.reshape(R, N, R, N)  # [r, i, s, j]
        w = np.transpose(Wb, (1, 3, 0, 2)).reshape(N * N, R, R)  # pair (i, j) -> [r, s]
        wv = np.transpose(w, (2, 1, 0)).reshape(R * R, N * N)  # vec column-major per pair
        h = np.asarray(self._mapped("hess", N * N)(c["Z"], self._diag, wv))  # (nz^2, N^2)
        h = h.T.reshape(N, N, nz, nz)  # symmetric, so the vec order does not matter
        pi, pj, pl = slice(0, d), slice(d, 2 * d), 2 * d
        H = np.zeros((N, d, N, d))
        H += np.transpose(h[:, :, pi, pj], (0, 2, 1, 3))  # [i, a, j, b]
        H += np.transpose(h[:, :, pj, pi], (1, 2, 0, 3))  # pair (j, i): p_i second
        diag = h[:, :, pi, pi].sum(axis=1) + h[:, :, pj, pj].sum(axis=0)  # (N, d, d)
        H[np.arange(N), :, np.arange(N), :] += diag
        out = np.zeros((N * d + 1, N * d + 1))
        out[: N * d, : N * d] = H.reshape(N * d, N * d)
        hl = (h[:, :, pi, pl].sum(axis=1) + h[:, :, pj, pl].sum(axis=0)).reshape(N * d)
        out[: N * d, N * d] = out[N * d, : N * d] = hl
        out[N * d, N * d] = h[:, :, pl, pl].sum()
        return out

    def _trace_products(self, c: dict[str, Any], A: np.ndarray) -> np.ndarray:
        """tr(A C_a A C_b) over (positions t-major, log l)."""
        N, R, d, nk = self.N, self.R, self.dim, self.n_k
        G, Cl = c["G"], c["Cl"]
        Gm = np.transpose(G, (1, 0, 2, 3, 4)).reshape(nk, N * d * R)  # rows (r, i)
        U = A @ Gm  # (nk, N d R)
        Ub = U.reshape(R, N, N, d, R)  # [r', i', t, k, s]
        # 2 tr(U_a[t_b] U_b[t_a])
        T = 2.0 * np.einsum("rbaks,sablr->akbl", Ub, Ub)
        # 2 tr(A_{t_b t_a} G_a^T A G_b)
        S = (Gm.T @ U).reshape(N, d, R, N, d, R)  # [ta, ka, y, tb, kb, x]
        Ab = A.reshape(R, N, R, N)
        T += 2.0 * np.einsum("xbya,akyblx->akbl", Ab, S)
        out = np.zeros((N * d + 1, N * d + 1))
        out[: N * d, : N * d] = T.reshape(N * d, N * d)
        Zl = A @ Cl @ A
        Zb = Zl.reshape(R, N, R, N)
        tl = 2.0 * np.einsum("irtks,rist->tk", G, Zb).reshape(N * d)
        out[: N * d, N * d] = out[N * d, : N * d] = tl
        ACl = A @ Cl
        out[N * d, N * d] = float(np.sum(ACl * ACl.T))
        return out


_THREADS: ThreadpoolController | None = None


def _single_threaded() -> Any:
    """BLAS limited to one thread: the matrices here are small (N x N for a few hundred
    samples), and on a loaded 2-core machine two BLAS threads contend. Measured on the
    100-sample walk while other jobs ran: 41.7 s for 73 iterations with the default
    threads, 6.2 s with one."""
    global _THREADS
    if _THREADS is None:
        _THREADS = ThreadpoolController()
    return _THREADS.limit(limits=1, user_api="blas")


def _inverse_square(log_sigma: float) -> float:
    """1 / sigma^2 from log sigma; inf (not a warning) when IPOPT tries a far step, which
    makes it shorten the step."""
    with np.errstate(over="ignore"):
        return float(np.exp(-2.0 * log_sigma))


def _inverse(cf: tuple[np.ndarray, bool]) -> np.ndarray:
    """C^-1 from its Cholesky factor (LAPACK potri), both triangles."""
    inv, info = sla.lapack.dpotri(cf[0], lower=cf[1])
    if info != 0:
        raise np.linalg.LinAlgError(f"potri failed ({info})")
    return np.triu(inv) + np.triu(inv, 1).T if not cf[1] else np.tril(inv) + np.tril(inv, -1).T


# --------------------------------------------------------------------------- CasADi blocks
class ExactPriorCost(NumpyCost):
    """One of the two prior blocks (``part`` 0: the quadratic, 1: the log-determinant) as
    a numpy cost of the stacked NLP vectors, BLAS single-threaded."""

    def __init__(self, name: str, model: ExactPriorModel, part: int):
        self.model, self.part = model, part
        lay = model.lay
        super().__init__(name, lay.n_x, lay.n_p, self._value, self._gradient)

    def _value(self, x: np.ndarray, p: np.ndarray) -> float:
        with _single_threaded():
            return self.model.values(x, p)[self.part]

    def _gradient(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        with _single_threaded():
            return self.model.gradient(x, p)[self.part]


class ExactPriorHessian(HessianCallback):
    """Upper triangle of the exact Hessian of both prior blocks over the knots, the field
    values and the estimated hyperparameters, for IPOPT's ``hess_lag`` (not scaled by
    lam_f). The pattern is dense over those unknowns except between different field
    components of m when one correlation matrix serves all three (``se``)."""

    def __init__(self, name: str, model: ExactPriorModel, n_g: int = 0):
        ca.Callback.__init__(self)
        self.model, self.n_g = model, n_g
        m, lay, kn = model, model.lay, model.knots
        N, d = m.N, m.dim
        nm = m.n_k * m.ncol
        # local index -> x index, for the local Hessian's order (theta, m, log sigma_f)
        self._T = sps.kron(sps.eye(d), kn.matrix, format="csr")  # (d N, d K): axis-major
        # local theta order is t-major (t d + k); reorder to axis-major (k N + t)
        self._perm_theta = (np.arange(N)[None, :] * d + np.arange(d)[:, None]).ravel()
        xi = [lay.C + np.arange(kn.count * d)]
        if m.est_l:
            xi.append(np.array([lay.lengthscale[1]]))
        xi.append(lay.M + np.arange(nm))
        if m.est_sf:
            xi.append(np.array([lay.sigma_f[1]]))
        self._xidx = np.concatenate(xi)
        n = self._xidx.size
        keep = np.ones((n, n), dtype=bool)
        if m.ncol > 1:
            off = kn.count * d + int(m.est_l)
            comp = np.full(n, -1)
            comp[off : off + nm] = np.repeat(np.arange(m.ncol), m.n_k)
            both = (comp[:, None] >= 0) & (comp[None, :] >= 0)
            keep &= ~both | (comp[:, None] == comp[None, :])
        r, cidx = np.nonzero(np.triu(keep))
        self._lr, self._lc = r, cidx
        xr, xc = self._xidx[r], self._xidx[cidx]
        self._set_pattern(np.minimum(xr, xc), np.maximum(xr, xc), lay.n_x, lay.n_p)
        self.construct(name, {})

    def values(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        with _single_threaded():
            return self._values(x.copy(), p.copy())

    def _values(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        m = self.model
        N, d = m.N, m.dim
        if m._factor(x, p)["cf"] is None:  # not positive definite: no Hessian either
            return np.full(self._lr.size, np.nan)
        H = m.local_hessian(x, p)
        # theta (t-major positions, log l) -> (knots axis-major, [log l])
        Hpp = H[: N * d, : N * d][np.ix_(self._perm_theta, self._perm_theta)]
        T = self._T
        pos = T.T @ (T.T @ Hpp).T  # (dK, dK): T^T H T (symmetric)
        rest_idx = list(range(N * d, H.shape[0]))
        if not m.est_l:
            rest_idx.remove(N * d)
        if not m.est_sf:
            rest_idx.remove(H.shape[0] - 1)
        Hpr = T.T @ H[: N * d, rest_idx][self._perm_theta, :]  # (dK, rest)
        Hrr = H[np.ix_(rest_idx, rest_idx)]
        n = self._xidx.size
        L = np.empty((n, n))
        k = pos.shape[0]
        L[:k, :k] = pos
        L[:k, k:] = Hpr
        L[k:, :k] = Hpr.T
        L[k:, k:] = Hrr
        return L[self._lr, self._lc]


def add_exact_prior(
    b: Any,
    kernel: Kernel,
    knots: Knots,
    dim: int,
    jitter: float,
    estimate: tuple[str, ...] = (),
    logdet: bool = False,
    positions: str = "C",
    dead_reckoning: str | None = "Q",
) -> tuple[str | tuple[str, ...], ExactPriorHessian]:
    """Add the exact GP prior to a builder (casmag.nlp.NLPBuilder) as cost ``gp_prior``
    (and ``gp_logdet`` when ``logdet``), reading the field ``M`` (N, 3), the positions
    (variable ``positions``: knot corrections added to the parameter ``dead_reckoning``, or
    the positions themselves when that is None) and sigma_f, lengthscale (variables
    ``log_<name>`` when in ``estimate``, else parameters ``<name>``). Declare every symbol
    first. Returns the block names and the Hessian callback for ``hess_lag``."""
    n_x, n_p = b.sizes

    def where(h: str) -> tuple[str, int]:
        return ("x", b.offset(f"log_{h}")) if h in estimate else ("p", b.offset(h, "p"))

    layout = ExactLayout(
        n_x=n_x,
        n_p=n_p,
        C=b.offset(positions),
        M=b.offset("M"),
        Q=None if dead_reckoning is None else b.offset(dead_reckoning, "p"),
        sigma_f=where("sigma_f"),
        lengthscale=where("lengthscale"),
    )
    model = ExactPriorModel(kernel, knots, dim, jitter, layout, logdet)
    x, p = b.x_vector(), b.p_vector()
    quad = b.retain(ExactPriorCost("gp_prior_cb", model, 0))
    b.cost("gp_prior", quad(x, p))
    if logdet:
        det = b.retain(ExactPriorCost("gp_logdet_cb", model, 1))
        b.cost("gp_logdet", det(x, p))
    hess = b.retain(ExactPriorHessian("gp_prior_hessian", model))
    return (("gp_prior", "gp_logdet") if logdet else "gp_prior"), hess
