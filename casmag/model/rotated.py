"""The reduced-rank map read through a rotation, y = R(o)^T (m(p) + c): the field block of
every motion model whose magnetometer turns with the body (planar with heading, IMU).

:func:`add_rotated_map` declares the whitened weights, the constant field and the blocks
``magnetometer``, ``gp_prior`` and ``constant_field_prior`` (the residual symbolic per
sample); :func:`rotated_gauss_newton` gives the block's Gauss-Newton Hessian
(:class:`RotatedFieldGaussNewton`, numpy, optionally with its second-order terms). A motion
model supplies the positions, the orientation unknowns and a rotation function
(:func:`imu_rotation_function`, :func:`planar_rotation_function`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from casmag import strapdown as sd
from casmag.gp.kernels import FIELD_DIM
from casmag.gp.reduced_rank import HilbertBasis
from casmag.model.builder import Pose
from casmag.model.rrmap import HessianCallback, curvature_terms, field_and_jacobians
from casmag.nlp import NLPBuilder


# --------------------------------------------------------------------------- rotations
def imu_rotation_function() -> ca.Function:
    """SX (d (3), rnom (9, column-major 3x3)) -> R = Rnom R(1, d / 2) (3, 3)."""
    d, rnom = ca.SX.sym("d", 3), ca.SX.sym("rnom", 9)
    R = ca.mtimes(ca.reshape(rnom, 3, 3), sd.ca_rotmat(sd.ca_gibbs(d)))
    return ca.Function("imu_rotation", [d, rnom], [R])


def planar_rotation_function() -> ca.Function:
    """SX (psi (1), empty (0)) -> Rz(psi) (3, 3)."""
    psi, aux = ca.SX.sym("psi"), ca.SX.sym("aux", 0)
    c, s = ca.cos(psi), ca.sin(psi)
    R = ca.vertcat(ca.horzcat(c, -s, 0), ca.horzcat(s, c, 0), ca.horzcat(0, 0, 1))
    return ca.Function("planar_rotation", [psi, aux], [R])


# --------------------------------------------------------------------------- Gauss-Newton
@dataclass(frozen=True)
class RotatedMapLayout:
    """Where the magnetometer block's unknowns and data sit in the NLP's x and p vectors.

    pos: (n, d) indices in x of each sample's position; rot: (n, r) indices in x of its
    orientation unknowns; aux: (n, a) indices in p of its orientation parameters (the
    nominal rotation), a may be 0; W, c: offsets of the map weights and the constant field
    (None without one) in x; sigma_m: offset in p."""

    n_x: int
    n_p: int
    pos: np.ndarray
    pos_nominal: np.ndarray | None  # (n, d) indices in p added to x[pos] (error state)
    rot: np.ndarray
    aux: np.ndarray
    W: int
    c: int | None
    sigma_m: int
    Y: int | None = None
    sigma_f: int | None = None  # with lengthscale: offsets in p; the x entries at W are then
    lengthscale: int | None = None  # whitened weights V, map weights sqrt(S) V


class RotatedFieldGaussNewton(HessianCallback):
    """Gauss-Newton Hessian (upper triangle, not scaled by lam_f) of

        0.5 sum_k |(y_k - R(o_k)^T (m(p_k) + c)) / sigma_m|^2

    for a reduced-rank map m (``se`` or ``curl_free``). Per sample, the residual's Jacobian
    with respect to its local unknowns (position and orientation) is L_k = -[R^T dm/dp,
    d(R^T u)/do] / sigma_m; the weight block is that of the unrotated map (R R^T = I); the
    sparsity pattern is fixed at construction and values are filled with numpy.

    In mode ``exact``, and in mode ``hybrid`` once the block's cost stalls
    (:class:`casmag.model.rrmap.HessianCallback`), the second-order terms are added: with
    lam = -(y - R^T u) / sigma_m^2 and F(o, u) = lam . (R(o)^T u), the blocks F_oo, F_ou,
    F_ou dm/dp and F_ou dm/dw (u = m + c is linear in w and c), the position-weight block
    sum_b (R lam)_b d^2 m_b / dp dw and the field's own curvature in position
    sum_b (R lam)_b d^2 m_b / dp dp (third derivatives of the basis for curl-free): the
    block's exact Hessian. Measured on the homogeneous outdoor problem (one loop): 59
    iterations without these terms (linear convergence along the accelerometer-bias/tilt
    direction), 12 with CasADi's exact Hessian. In a strongly varying field the terms slow
    the first iterations (rectangle: over 90 iterations with them from the start) but
    Gauss-Newton alone converges only linearly near the solution (spiral seed 3: 150
    iterations at a 3-5 % fall of the dual infeasibility per iteration), hence ``hybrid``
    Hessian."""

    #: hybrid: the exact terms once the block's cost falls by less than 1 % between
    #: evaluations. At 20 % (the translational map's switch) they came in while still far
    #: from the solution on weakly determined problems: handwriting seed 1, first prefix (31
    #: keyframes, no revisit), 133 iterations against 16 at 1 % (every solve of that run
    #: at most 37, 73 s against 138 s); spiral seed 3 11 + 16 against 13 + 28 iterations.
    SWITCH = 0.01

    def __init__(
        self,
        name: str,
        basis: HilbertBasis,
        kernel: str,
        rotation: ca.Function,
        layout: RotatedMapLayout,
        mode: str = "hybrid",
    ):
        ca.Callback.__init__(self)
        self.set_mode(mode)
        self.basis, self.kernel, self.lay = basis, kernel, layout
        self.n, self.d = layout.pos.shape
        self.r = layout.rot.shape[1]
        M = basis.num_basis
        self.n_w = M * FIELD_DIM if kernel == "se" else M
        o = ca.SX.sym("o", self.r)
        aux = ca.SX.sym("aux", layout.aux.shape[1])
        u = ca.SX.sym("u", 3)
        R = rotation(o, aux)
        Rtu = ca.mtimes(R.T, u)
        self._rot = ca.Function("rot_jac", [o, aux, u], [ca.vec(R), ca.vec(ca.jacobian(Rtu, o))])
        self._rot_map = self._rot.map(self.n)
        lam = ca.SX.sym("lam", 3)
        Hf = ca.hessian(ca.dot(lam, Rtu), ca.vertcat(o, u))[0]
        r = self.r
        self._curv = ca.Function(
            "rot_curvature", [o, aux, u, lam], [ca.vec(Hf[:r, :r]), ca.vec(Hf[:r, r:])]
        ).map(self.n)
        self._pattern()
        self.construct(name, {})

    def _pattern(self) -> None:
        lay, _n, M = self.lay, self.n, self.basis.num_basis
        local = np.hstack([lay.pos, lay.rot])  # (n, nl)
        nl = local.shape[1]
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []

        def add(r: Any, c: Any) -> None:
            r, c = np.broadcast_arrays(np.asarray(r), np.asarray(c))
            rows.append(np.minimum(r, c).ravel())
            cols.append(np.maximum(r, c).ravel())

        for i in range(nl):
            for j in range(i, nl):
                add(local[:, i], local[:, j])
        widx = lay.W + np.arange(self.n_w)
        for i in range(nl):
            add(local[:, i][:, None], widx[None, :])
        iu = np.triu_indices(M)
        if self.kernel == "se":
            for b in range(FIELD_DIM):
                add(lay.W + b * M + iu[0], lay.W + b * M + iu[1])
        else:
            add(lay.W + iu[0], lay.W + iu[1])
        if lay.c is not None:
            for b in range(FIELD_DIM):
                for i in range(nl):
                    add(local[:, i], lay.c + b)
                add(widx, lay.c + b)
                add(np.array([lay.c + b]), np.array([lay.c + b]))
        self._set_pattern(np.concatenate(rows), np.concatenate(cols), lay.n_x, lay.n_p)
        self._nl = nl

    def _position_weight_curvature(
        self, P: np.ndarray, mu: np.ndarray, w: np.ndarray
    ) -> list[np.ndarray]:
        """sum_b mu_b d^2 m_b / dp_j dw for each position axis j: (n, n_w) each."""
        n, d = P.shape
        if self.kernel == "se":
            grads = self.basis.grad_phi(P)  # (n, D, M)
            return [(mu[:, :, None] * grads[:, j, :][:, None, :]).reshape(n, -1) for j in range(d)]
        H = self.basis.second_derivatives(P)
        return [
            sum(mu[:, b][:, None] * H[(min(b, j), max(b, j))] for b in range(FIELD_DIM))
            for j in range(d)
        ]

    def _linearised(self, x: np.ndarray, p: np.ndarray) -> tuple[Any, ...]:
        """The block at x: positions P, orientation unknowns o, their parameters aux, the
        weights w (dW/dV ``scale``), constant field c, 1 / sigma_m, the field m and its
        Jacobians A (weights) and D (position), the rotations R (n, 3, 3) and the
        residuals' Jacobian L (n, 3, nl) with respect to each sample's local unknowns."""
        lay, n, M = self.lay, self.n, self.basis.num_basis
        P = x[lay.pos] if lay.pos_nominal is None else x[lay.pos] + p[lay.pos_nominal]
        o = x[lay.rot]
        aux = p[lay.aux] if lay.aux.shape[1] else np.zeros((n, 0))
        w = x[lay.W : lay.W + self.n_w]
        scale = np.ones(self.n_w)  # dW/dV per weight entry
        if lay.sigma_f is not None and lay.lengthscale is not None:
            S = self.basis.prior_variances(
                self.kernel, float(p[lay.sigma_f]), float(p[lay.lengthscale])
            )
            scale = np.tile(np.sqrt(S), self.n_w // M)
            w = w * scale
        c = x[lay.c : lay.c + 3] if lay.c is not None else np.zeros(3)
        inv = 1.0 / float(p[lay.sigma_m])
        m, A, D = field_and_jacobians(self.basis, self.kernel, P, w)
        Rv, Jv = self._rot_map(o.T, aux.T, (m + c).T)
        R = np.asarray(Rv).T.reshape(n, 3, 3, order="F")  # R[k] = R_k
        Jo = np.asarray(Jv).T.reshape(n, 3, self.r, order="F")
        Jp = np.einsum("kba,kbj->kaj", R, D)  # R^T dm/dp
        L = -inv * np.concatenate([Jp, Jo], axis=2)  # (n, 3, nl)
        return P, o, aux, w, scale, c, inv, m, A, D, R, L

    def residual_jacobian(self, x: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, Any]:
        """The block's whitened residuals e = (y - R^T (m + c)) / sigma_m (n, 3) at x and
        their Jacobian (3n, n_x) with respect to x, a scipy CSR matrix whose rows are the
        residuals sample by sample (e_k's three components together); J^T J is the
        Gauss-Newton Hessian :meth:`values` gives (casmag.solver.uncertainty's correction
        for correlated residuals)."""
        import scipy.sparse as sp

        lay, n = self.lay, self.n
        _, _, _, _, scale, c, inv, m, A, _, R, L = self._linearised(x, p)
        Y = p[lay.Y : lay.Y + 3 * n].reshape(n, 3, order="F")
        e = (Y - np.einsum("kba,kb->ka", R, m + c)) * inv
        local = np.hstack([lay.pos, lay.rot])  # (n, nl)
        nl = local.shape[1]
        rows = np.arange(3 * n).reshape(n, 3)
        # de_a / du_b = -R[b, a] / sigma_m, u = m + c; m linear in the weights (A)
        Ru = -inv * np.transpose(R, (0, 2, 1))  # (n, 3 [a], 3 [b])
        if self.kernel == "se":  # m_b = A0 w_b: column W + b M + j
            Jw = (Ru[:, :, :, None] * A[0][:, None, None, :]).reshape(n, 3, self.n_w)
        else:  # m_b = A_b w
            Jw = np.einsum("kab,bkj->kaj", Ru, np.stack(A))
        parts = [
            sp.csr_matrix(
                (L.ravel(), (np.repeat(rows.ravel(), nl), np.repeat(local, 3, axis=0).ravel())),
                shape=(3 * n, lay.n_x),
            ),
            sp.csr_matrix(
                (
                    (Jw * scale).ravel(),
                    (
                        np.repeat(rows.ravel(), self.n_w),
                        np.tile(lay.W + np.arange(self.n_w), 3 * n),
                    ),
                ),
                shape=(3 * n, lay.n_x),
            ),
        ]
        if lay.c is not None:
            parts.append(
                sp.csr_matrix(
                    (
                        Ru.ravel(),
                        (np.repeat(rows.ravel(), 3), np.tile(lay.c + np.arange(3), 3 * n)),
                    ),
                    shape=(3 * n, lay.n_x),
                )
            )
        return e, sum(parts[1:], parts[0]).tocsr()

    def values(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The Hessian entries in the order of the pattern's triplets."""
        lay, n, d, M = self.lay, self.n, self.d, self.basis.num_basis
        P, o, aux, w, scale, c, inv, m, A, D, R, L = self._linearised(x, p)
        # Coefficients of du/d(w, c) in the local-map blocks: -R L / sigma (Gauss-Newton)
        # plus F_ou (second order, orientation rows only).
        G = -inv * np.einsum("kab,kbl->kal", R, L)
        nl = self._nl
        S = np.zeros((n, nl, nl))
        exact = False
        if self.mode != "gauss-newton":
            Y = p[lay.Y : lay.Y + 3 * n].reshape(n, 3, order="F")
            e = Y - np.einsum("kba,kb->ka", R, m + c)
            exact = self._use_exact(0.5 * float(np.sum(e**2)) * inv * inv)
            lam = -e * inv * inv
        else:
            self._use_exact(0.0)
        if exact:
            Foo, Fou = self._curv(o.T, aux.T, (m + c).T, lam.T)
            Foo = np.asarray(Foo).T.reshape(n, self.r, self.r, order="F")
            Fou = np.asarray(Fou).T.reshape(n, self.r, 3, order="F")
            S[:, d:, d:] = Foo
            S[:, d:, :d] = np.einsum("kib,kbj->kij", Fou, D)
            S[:, :d, d:] = np.transpose(S[:, d:, :d], (0, 2, 1))
            G[:, :, d:] += np.transpose(Fou, (0, 2, 1))
            mu = np.einsum("kab,kb->ka", R, lam)  # dF/du = R lam
            cross = self._position_weight_curvature(P, mu, w)
            # The field's own curvature in position: sum_b mu_b d^2 m_b / dp dp (third
            # derivatives of the basis for curl-free).
            s2, _ = curvature_terms(self.basis, self.kernel, P, w, mu)
            for (a, b), v in s2.items():
                S[:, a, b] += v
                if a != b:
                    S[:, b, a] += v
        out = []
        for i in range(nl):
            for j in range(i, nl):
                out.append(np.einsum("ka,ka->k", L[:, :, i], L[:, :, j]) + S[:, i, j])
        for i in range(nl):
            if self.kernel == "se":
                blk = G[:, :, i][:, :, None] * A[0][:, None, :]  # (n, 3, M): column b M + j
                blk = blk.reshape(n, -1)
            else:
                blk = sum(G[:, b, i][:, None] * A[b] for b in range(FIELD_DIM))
            if exact and i < d:
                blk = blk + cross[i]
            out.append(blk * scale)
        iu = np.triu_indices(M)
        inv2 = inv * inv
        sm = scale[:M]  # the same per basis function for every field component
        if self.kernel == "se":
            H = (A[0].T @ A[0]) * inv2 * np.outer(sm, sm)
            out.extend([H[iu]] * FIELD_DIM)
        else:
            H = sum(a.T @ a for a in A) * inv2 * np.outer(sm, sm)
            out.append(H[iu])
        if lay.c is not None:
            for b in range(FIELD_DIM):
                for i in range(nl):
                    out.append(G[:, b, i])
                if self.kernel == "se":
                    v = np.zeros(self.n_w)
                    v[b * M : (b + 1) * M] = A[0].sum(axis=0) * inv2
                else:
                    v = A[b].sum(axis=0) * inv2
                out.append(v * scale)
                out.append(np.array([n * inv2]))
        return np.concatenate([np.ravel(v) for v in out])


# --------------------------------------------------------------------------- map blocks
def add_rotated_map(
    b: NLPBuilder, basis: HilbertBasis, kernel: str, pose: Pose, window: bool = False
) -> tuple[ca.MX, ca.MX]:
    """Weights, constant field and the blocks ``magnetometer``, ``gp_prior``,
    ``constant_field_prior`` for a magnetometer read through the pose's rotation. The unknown
    named ``W`` holds the whitened weights V (map weights sqrt(S) V, S the prior variances).
    With ``window`` (a window of the sliding windows, casmag.solver.staged) the two prior
    blocks are replaced by ``map_prior``, 0.5 (z - mu)^T Lambda (z - mu) on z = [vec(V); c]
    (:func:`rotated_design`), its mean ``map_mean`` and precision ``map_precision``
    parameters carried from the earlier windows (casmag.nlp.NLPBuilder.quadratic). Returns
    (W, c) with W the map weights (an expression)."""
    assert pose.rotation is not None
    M, n, dim, rot = basis.num_basis, pose.n, pose.dim, pose.rotation
    # Whitened weights V (the unknowns): W = sqrt(S) V, so the GP prior is 0.5 |V|^2. With
    # W itself, the prior variances S span 6 orders of magnitude and IPOPT's gradient test
    # stalls on the high-frequency weights (handwriting: max |dJ/dW| 0.026 at S = 1.4e-8,
    # 3.9e-6 in whitened units) while the solution no longer moves.
    V = b.variable("W", (M, FIELD_DIM) if kernel == "se" else (M, 1))
    c = b.variable("c", (FIELD_DIM, 1))
    Y = b.parameter("Y", (n, FIELD_DIM))
    sigma_m = b.parameter("sigma_m", (1, 1))
    sigma_f = b.parameter("sigma_f", (1, 1))
    ell = b.parameter("lengthscale", (1, 1))
    sigma_lin = None if window else b.parameter("sigma_lin", (1, 1))
    fieldf = basis.field_sx(kernel, position_dim=dim)
    x, y, sig = ca.SX.sym("x", dim), ca.SX.sym("y", FIELD_DIM), ca.SX.sym("sigma_m")
    o = ca.SX.sym("o", rot.unknowns.shape[1])
    aux = ca.SX.sym("aux", 0 if rot.aux is None else rot.aux.shape[1])
    S = basis.prior_variances(kernel, sigma_f, ell)
    W = V * ca.repmat(ca.sqrt(S), 1, V.shape[1])
    w_sx, c_sx = ca.SX.sym("w", *W.shape), ca.SX.sym("c", FIELD_DIM)
    R = rot.function(o, aux)
    e = (y - ca.mtimes(R.T, fieldf(x, w_sx, c_sx))) / sig
    resid = ca.Function("rotated_mag_residual", [x, o, aux, y, w_sx, c_sx, sig], [e])
    aux_arg = rot.aux.T if rot.aux is not None else ca.MX(0, n)
    E = resid.map(n, "serial")(pose.positions.T, rot.unknowns.T, aux_arg, Y.T, W, c, sigma_m)
    b.cost("magnetometer", 0.5 * ca.sumsqr(E))
    if window:
        nz = V.numel() + FIELD_DIM
        mu = b.parameter("map_mean", (nz, 1))
        Lam = b.parameter("map_precision", (nz, nz))
        b.quadratic("map_prior", "W", ca.vertcat(ca.vec(V), c), mu, Lam)
        return W, c
    b.cost("gp_prior", 0.5 * ca.sumsqr(V))
    b.cost("constant_field_prior", 0.5 * ca.sumsqr(c / sigma_lin))
    return W, c


def window_unknowns(basis: HilbertBasis, kernel: str) -> int:
    """Length of z = [vec(V); c], the unknowns of a rotated window map's prior."""
    return basis.num_basis * (FIELD_DIM if kernel == "se" else 1) + FIELD_DIM


def rotated_design(
    basis: HilbertBasis,
    kernel: str,
    P: np.ndarray,
    R: np.ndarray,
    sigma_f: float,
    lengthscale: float,
) -> np.ndarray:
    """(3N, nz) matrix J with the magnetometer readings y_k = R_k^T (m(p_k) + c) stacked as
    J z, z = [vec(V); c] (V the whitened weights, column-major as CasADi's vec), at
    positions P (N, d) with body-to-map rotations R (N, 3, 3): the reading is linear in the
    map for a known pose, so a committed window's samples enter the map prior exactly as
    linear-Gaussian observations."""
    P = np.asarray(P, dtype=float)
    N, M = P.shape[0], basis.num_basis
    sqrt_s = np.sqrt(basis.prior_variances(kernel, sigma_f, lengthscale))
    zero = np.zeros(M * FIELD_DIM if kernel == "se" else M)
    _, A, _ = field_and_jacobians(basis, kernel, P, zero)
    nv = window_unknowns(basis, kernel) - FIELD_DIM
    G = np.zeros((N, FIELD_DIM, nv + FIELD_DIM))
    for q in range(FIELD_DIM):
        if kernel == "se":
            G[:, q, q * M : (q + 1) * M] = A[0] * sqrt_s
        else:
            G[:, q, :M] = A[q] * sqrt_s
        G[:, q, nv + q] = 1.0
    J = np.einsum("kji,kjz->kiz", R, G)
    return J.reshape(N * FIELD_DIM, nv + FIELD_DIM)


def rotated_gauss_newton(
    b: NLPBuilder, basis: HilbertBasis, kernel: str, pose: Pose, mode: str = "hybrid"
) -> tuple[str, RotatedFieldGaussNewton]:
    """The ``magnetometer`` block's Hessian callback of :func:`add_rotated_map` on a pose
    (declare every symbol first)."""
    layout = rotated_layout(b, pose, whitened=True)
    return "magnetometer", RotatedFieldGaussNewton(
        "rotated_mag_gauss_newton", basis, kernel, pose.rotation.function, layout, mode
    )


def rotated_layout(b: NLPBuilder, pose: Pose, whitened: bool) -> RotatedMapLayout:
    """Where a rotated magnetometer block's unknowns and data sit in x and p (every symbol
    declared first: ``W``, ``c``, ``Y``, ``sigma_m`` and, with ``whitened`` weights,
    ``sigma_f`` and ``lengthscale``). One row per sample: the pose's knots are the samples."""
    assert pose.rotation is not None
    if pose.knots.count != pose.n:
        raise ValueError("a rotated magnetometer block needs one pose unknown per sample")
    n_x, n_p = b.sizes
    n, dim, rot = pose.n, pose.dim, pose.rotation
    k = np.arange(n)

    def columns(name: str, width: int, of: str = "x") -> np.ndarray:
        return np.column_stack([b.offset(name, of) + a * n + k for a in range(width)])

    pos_nominal = None if pose.nominal is None else columns(pose.nominal, dim, "p")
    if rot.aux_name is None:
        aux = np.zeros((n, 0), dtype=np.int64)
    else:
        aux = columns(rot.aux_name, rot.aux.shape[1], "p")
    return RotatedMapLayout(
        n_x=n_x,
        n_p=n_p,
        pos=columns(pose.variable, dim),
        pos_nominal=pos_nominal,
        rot=columns(rot.variable, rot.unknowns.shape[1]),
        aux=aux,
        W=b.offset("W"),
        c=b.offset("c"),
        sigma_m=b.offset("sigma_m", "p"),
        Y=b.offset("Y", "p"),
        sigma_f=b.offset("sigma_f", "p") if whitened else None,
        lengthscale=b.offset("lengthscale", "p") if whitened else None,
    )


def ridge_weights(
    basis: HilbertBasis,
    kernel: str,
    P: np.ndarray,
    M_local: np.ndarray,
    c0: np.ndarray,
    sigma_m: float,
    sigma_f: float,
    lengthscale: float,
) -> np.ndarray:
    """Posterior mean of the map weights given the field samples M_local (N, 3) in the
    local frame at positions P (N, d), with the constant c0 removed."""
    S = basis.prior_variances(kernel, sigma_f, lengthscale)
    Mb = basis.num_basis
    zero = np.zeros(Mb * FIELD_DIM if kernel == "se" else Mb)
    _, A, _ = field_and_jacobians(basis, kernel, P, zero)
    Rr = M_local - c0
    if kernel == "se":
        G = A[0].T @ A[0] / sigma_m**2 + np.diag(1.0 / S)
        return np.linalg.solve(G, A[0].T @ Rr / sigma_m**2)
    G = sum(a.T @ a for a in A) / sigma_m**2 + np.diag(1.0 / S)
    rhs = sum(A[q].T @ Rr[:, q] for q in range(FIELD_DIM)) / sigma_m**2
    return np.linalg.solve(G, rhs).reshape(-1, 1)


def whiten(
    basis: HilbertBasis, kernel: str, sigma_f: float, lengthscale: float, W: np.ndarray
) -> np.ndarray:
    """Map weights W (M, k) -> the NLP's whitened weights V = W / sqrt(S) (same shape)."""
    S = basis.prior_variances(kernel, sigma_f, lengthscale)
    return W / np.sqrt(S)[:, None]
