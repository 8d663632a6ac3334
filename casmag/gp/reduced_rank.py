"""Hilbert-space reduced-rank GP basis for the field map.

Solin & Särkkä (2020), "Hilbert space methods for reduced-rank Gaussian process regression",
and Solin et al. (2018), "Modeling and interpolation of the ambient magnetic field by Gaussian
processes".

On a box Omega = prod_k [c_k - L_k, c_k + L_k] (``Domain``) the Dirichlet eigenfunctions of
the negative Laplacian are

    phi_j(x)  = prod_k L_k^(-1/2) sin(pi j_k (x_k - c_k + L_k) / (2 L_k)),   j_k = 1, 2, ...
    lambda_j  = sum_k (pi j_k / (2 L_k))^2,

orthonormal on Omega and zero on its boundary. A stationary kernel with spectral density S is
approximated inside the box by

    k(x, x') ~= sum_j S(sqrt(lambda_j)) phi_j(x) phi_j(x'),

so a GP becomes a linear model with M weights w_j ~ N(0, S(sqrt(lambda_j))).

Field models (``kernel_name`` as in ``casmag.gp.kernels``):

* ``se``: each field component independently, m_c(x) = phi(x)^T w_c, weights (M, 3).
* ``curl_free``: m(x) = grad phi(x)^T w, one weight vector (M,) for the scalar potential with
  SE covariance. Note ``Cov(d_a Phi(x), d_b Phi(x')) = -d_a d_b k(r)|_{r = x - x'}
  = (1/l^2)(delta_ab - r_a r_b / l^2) k(r)``, exactly casmag's ``CurlFree`` K_H, so the field is
  the gradient itself (m = -grad Phi has the same covariance; we use + grad Phi).
* optionally a constant field m(x) += c, c ~ N(0, sigma_lin^2 I_3) (the "linear potential"
  Phi_lin(x) = c^T x of Solin et al. 2018), three extra weights.

Planar data and the curl-free field: the field of a potential has a z component even when the
positions lie in the plane z = 0, and that component is the z-derivative of the potential, which
needs the potential as a function of 3-D position. ``casmag.gp.kernels.CurlFree`` likewise embeds
2-D points at z = 0 and keeps all three components. The basis for planar curl-free data is
therefore built on a 3-D box whose z-extent is [-L_z, L_z] around z = 0, with L_z equal to the
horizontal margin (``Domain.extended_to_3d``, ``domain_for``) and evaluated at z = 0 (2-D
positions are padded with z = 0 by every evaluation function here). The box only has to be as
thick as the boundary margin: the Dirichlet condition acts like mirror images of the
covariance across each face, so a face at distance L_z >= 3 l from the data plane contributes
errors of order (2 L_z / l)^2 exp(-(2 L_z / l)^2 / 2) < 1e-6 relative. Measured on a 6 m x 6 m
area with l = 0.35 m (50 points, default basis): max error of the curl-free covariance relative
to sigma_f^2 / l^2 is 0.83 for L_z = l, 0.016 for L_z = 2 l and 0.0074 for L_z = 3 l (the last
is the spectral truncation, see ``default_num_basis``). At z = 0 the basis
functions with even j_z vanish, but their z-derivatives do not, and they carry the z component.

Memory: ``phi`` returns an (N, M) float64 array, 8 N M bytes (N = 100,000, M = 1,000 is 800 MB);
it is computed in row chunks so temporaries stay small, but the output is dense. ``grad_phi``
returns (N, d, M), d times more; use it for modest N (tests, covariances). To evaluate a map at
many points use ``evaluate_field``, which chunks and never holds the full basis matrix. The NLP
should use the per-point CasADi functions ``phi_sx`` / ``grad_phi_sx`` / ``field_sx`` and
``map`` them over samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import casadi as ca
import numpy as np

from casmag.gp.kernels import FIELD_DIM, get_kernel

#: Boundary margin in lengthscales (see ``default_margin``).
MARGIN_LENGTHSCALES = 3.0
#: Highest included frequency in units of 1 / lengthscale (see ``default_num_basis``).
OMEGA_MAX_LENGTHSCALES = 4.0
#: Largest default number of basis functions (see ``default_num_basis``).
MAX_NUM_BASIS = 4000
#: Target number of (point, basis function) entries per chunk in the numpy evaluations, so
#: temporaries stay at a few MB each whatever N and M.
CHUNK_ENTRIES = 1 << 18

# Kernels whose (generating) spectral density is the SE density, so the CasADi form below holds.
_SE_DENSITY_KERNELS = frozenset({"se", "curl_free"})


# --------------------------------------------------------------------------- domain
@dataclass(frozen=True)
class Domain:
    """The box prod_k [center_k - half_width_k, center_k + half_width_k]."""

    center: np.ndarray  # (d,)
    half_width: np.ndarray  # (d,) L_k

    def __post_init__(self) -> None:
        center = np.atleast_1d(np.asarray(self.center, dtype=float)).copy()
        half = np.atleast_1d(np.asarray(self.half_width, dtype=float)).copy()
        if center.ndim != 1 or center.shape != half.shape:
            raise ValueError(
                f"center and half_width must be 1-D of equal length, got {center.shape} and "
                f"{half.shape}"
            )
        if not (np.all(np.isfinite(center)) and np.all(np.isfinite(half)) and np.all(half > 0)):
            raise ValueError(f"half_width must be finite and positive, got {half}")
        center.flags.writeable = False
        half.flags.writeable = False
        object.__setattr__(self, "center", center)
        object.__setattr__(self, "half_width", half)

    @property
    def dim(self) -> int:
        return int(self.center.shape[0])

    @property
    def lower(self) -> np.ndarray:
        return self.center - self.half_width

    @property
    def upper(self) -> np.ndarray:
        return self.center + self.half_width

    @classmethod
    def around(cls, X: np.ndarray, margin: float) -> Domain:
        """Bounding box of the points X (N, d) grown by ``margin`` on every side."""
        X = np.asarray(X, dtype=float)
        if X.ndim != 2 or X.shape[0] == 0:
            raise ValueError(f"X must be a non-empty (N, d) array, got shape {X.shape}")
        if not margin > 0:
            raise ValueError(f"margin must be positive, got {margin}")
        lo = X.min(axis=0) - margin
        hi = X.max(axis=0) + margin
        return cls(center=0.5 * (lo + hi), half_width=0.5 * (hi - lo))

    def extended_to_3d(self, half_width_z: float) -> Domain:
        """This 2-D box times [-half_width_z, half_width_z] in z (planar data, see module doc)."""
        if self.dim != 2:
            raise ValueError(f"only a 2-D domain can be extended to 3-D, this one is {self.dim}-D")
        return Domain(
            center=np.append(self.center, 0.0),
            half_width=np.append(self.half_width, float(half_width_z)),
        )

    def contains(self, X: np.ndarray) -> np.ndarray:
        """(N,) bool: which points (padded with zeros to d coordinates) lie inside the box."""
        Xp = _pad(np.asarray(X, dtype=float), self.dim)
        return np.all((Xp >= self.lower) & (Xp <= self.upper), axis=1)


def default_margin(lengthscale: float) -> float:
    """Boundary margin around the data: 3 lengthscales.

    The Dirichlet condition makes the approximation equal to the kernel minus mirror images of
    it across each face (plus more distant images), so at a point a distance delta from the
    boundary the error is about k(2 delta) / k(0) = exp(-2 delta^2 / l^2); for the curl-free
    kernel it gains a factor up to (2 delta / l)^2. With delta = 3 l this is 1.5e-8 (SE) and
    5e-7 (curl-free), negligible next to the spectral truncation error, while a wider margin
    would only increase the number of basis functions needed (Solin & Särkkä 2020, Sec. 4:
    boundary effects decay within a few lengthscales).
    """
    if not lengthscale > 0:
        raise ValueError(f"lengthscale must be positive, got {lengthscale}")
    return MARGIN_LENGTHSCALES * float(lengthscale)


def domain_for(
    kernel_name: str, X: np.ndarray, lengthscale: float, margin: float | None = None
) -> Domain:
    """The box for a kernel's basis around positions X (N, 2 or 3).

    For ``curl_free`` with planar X (N, 2) this is the 3-D box [data extent + margin] x
    [-margin, margin] for the potential (see the module docstring); otherwise the bounding box.
    """
    X = np.asarray(X, dtype=float)
    margin = default_margin(lengthscale) if margin is None else float(margin)
    domain = Domain.around(X, margin)
    if get_kernel(kernel_name).input_dim == 3 and domain.dim == 2:
        domain = domain.extended_to_3d(margin)
    return domain


# --------------------------------------------------------------------------- basis size
def _ball_indices(
    half_width: np.ndarray, omega_max: float, limit: int | None = None
) -> tuple[np.ndarray, np.ndarray] | None:
    """All multi-indices j >= 1 with sqrt(lambda_j) <= omega_max, as ((K, d) ints, (K,) lambda),
    in lexicographic order; None if there are more than ``limit``.

    Built axis by axis, keeping only prefixes that still extend to a point inside the ball
    (partial sum plus the smallest possible remaining terms), so every stage has at most as
    many entries as the result and the work is proportional to it, not to the enclosing cube.
    """
    r2 = omega_max**2 * (1 + 1e-12)  # include eigenvalues on the sphere despite rounding
    steps2 = (math.pi / (2 * np.asarray(half_width, dtype=float))) ** 2
    d = steps2.size
    idx = np.zeros((1, 0), dtype=np.int64)
    lam = np.zeros(1)
    for k in range(d):
        budget = r2 - steps2[k + 1 :].sum() - lam  # room left for axis k's term
        nj = np.floor(np.sqrt(np.maximum(budget, 0.0) / steps2[k])).astype(np.int64)
        # Fix rounding at the edge with the exact comparison.
        nj += steps2[k] * (nj + 1) ** 2 <= budget
        nj -= (nj > 0) & (steps2[k] * nj**2 > budget)
        total = int(nj.sum())
        if limit is not None and total > limit:
            return None
        rows = np.repeat(np.arange(lam.size), nj)
        starts = np.repeat(np.cumsum(nj) - nj, nj)
        j = np.arange(total) - starts + 1
        idx = np.column_stack([idx[rows], j])
        lam = lam[rows] + steps2[k] * j**2
    return idx.reshape(-1, d), lam


def default_num_basis(
    domain: Domain,
    lengthscale: float,
    d: int | None = None,
    *,
    omega_factor: float = OMEGA_MAX_LENGTHSCALES,
    max_basis: int = MAX_NUM_BASIS,
) -> int:
    """Number of basis functions with sqrt(lambda_j) <= omega_max = omega_factor / lengthscale.

    The SE spectral density falls to exp(-c^2 / 2) of S(0) at omega = c / l: 3.4e-4 at the
    default c = 4. What matters for the kernel is the truncated spectral mass: for the SE
    kernel in d = 2 it is P(chi^2_2 > c^2) = exp(-c^2/2) = 3.4e-4 of k(0); in d = 3 it is
    P(chi^2_3 > c^2) = 1.1e-3; and for the curl-free field (the gradient weights S by omega^2)
    it is P(chi^2_5 > c^2) = 6.8e-3 of the component variance sigma_f^2 / l^2. c = 3.5 would
    leave 3.2e-2 on the curl-free variance, c = 4.5 would need 40 % more functions in 3-D.

    The count is that of a quarter/eighth ball of radius omega_max on the eigenvalue lattice
    (spacing pi / (2 L_k)), about (omega_max^d vol(unit ball) / 2^d) prod_k (2 L_k / pi). It is
    capped at ``max_basis`` (default 4000, which covers the curl-free case on a 6 m x 6 m area
    with l = 0.35 m: 2987 functions, versus 654 for the 2-D SE basis). Beyond that the dense
    per-sample basis dominates the cost of the NLP and the user should choose the number (or a
    larger lengthscale) explicitly. Capping is silent.
    """
    d = domain.dim if d is None else int(d)
    if d != domain.dim:
        raise ValueError(f"d = {d} does not match the {domain.dim}-D domain")
    if not lengthscale > 0:
        raise ValueError(f"lengthscale must be positive, got {lengthscale}")
    ball = _ball_indices(domain.half_width, omega_factor / float(lengthscale), limit=max_basis)
    return max_basis if ball is None else max(ball[1].size, 1)


# --------------------------------------------------------------------------- helpers
def _pad(X: np.ndarray, d: int) -> np.ndarray:
    """(N, p) points with p <= d as (N, d), missing coordinates zero (the plane z = 0)."""
    X = np.atleast_2d(X)
    if X.shape[1] > d:
        raise ValueError(f"points have {X.shape[1]} coordinates, the basis only {d}")
    if X.shape[1] == d:
        return X
    out = np.zeros((X.shape[0], d))
    out[:, : X.shape[1]] = X
    return out


def _is_casadi(*values: Any) -> bool:
    return any(isinstance(v, ca.SX | ca.MX | ca.DM) for v in values)


# --------------------------------------------------------------------------- basis
class HilbertBasis:
    """The M Dirichlet Laplace eigenfunctions of a box with the smallest eigenvalues.

    domain: the box; num_basis: M, or None for ``default_num_basis(domain,
    lengthscale_for_default)``. input_dim: dimension of the basis' input space; None means the
    domain's. ``input_dim=3`` with a 2-D domain extends it to the 3-D box for planar curl-free
    data with z half-width ``default_margin(lengthscale_for_default)`` (module docstring).

    Evaluation accepts positions with fewer coordinates than the basis (padded with zeros, i.e.
    the plane z = 0). Points outside the box are evaluated without complaint but the
    approximation only holds well inside (a margin from the faces).
    """

    def __init__(
        self,
        domain: Domain,
        num_basis: int | None = None,
        *,
        lengthscale_for_default: float | None = None,
        input_dim: int | None = None,
    ) -> None:
        if input_dim is not None and input_dim != domain.dim:
            if input_dim == 3 and domain.dim == 2:
                if lengthscale_for_default is None:
                    raise ValueError(
                        "extending a 2-D domain to 3-D needs lengthscale_for_default (for the "
                        "z half-width); or pass Domain.extended_to_3d(...) directly"
                    )
                domain = domain.extended_to_3d(default_margin(lengthscale_for_default))
            else:
                raise ValueError(f"input_dim {input_dim} does not fit a {domain.dim}-D domain")
        if num_basis is None:
            if lengthscale_for_default is None:
                raise ValueError("give num_basis or lengthscale_for_default")
            num_basis = default_num_basis(domain, lengthscale_for_default)
        num_basis = int(num_basis)
        if num_basis < 1:
            raise ValueError(f"num_basis must be >= 1, got {num_basis}")
        self.domain = domain
        self.indices, lam = self._smallest(domain.half_width, num_basis)
        self.eigenvalues = lam
        self.sqrt_eigenvalues = np.sqrt(lam)
        self.indices.flags.writeable = False
        self.eigenvalues.flags.writeable = False
        self.sqrt_eigenvalues.flags.writeable = False
        # Per-axis angular frequencies pi j / (2 L) of the distinct j values, and the column
        # of each basis function in the per-axis tables.
        self._jmax = self.indices.max(axis=0)
        self._axis_freq = [
            math.pi * np.arange(1, jm + 1) / (2 * L)
            for jm, L in zip(self._jmax, domain.half_width, strict=True)
        ]
        self._scale = float(np.prod(domain.half_width ** (-0.5)))

    @staticmethod
    def _smallest(half_width: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
        # Grow a ball until it holds m multi-indices, then take the m smallest eigenvalues
        # (ties broken lexicographically on the indices, so the choice is deterministic).
        d = half_width.size
        step_min = math.pi / (2 * half_width.max())
        # Radius of a ball with ~m lattice points in the positive orthant, then grow.
        vol_unit = math.pi ** (d / 2) / math.gamma(d / 2 + 1)
        cell = float(np.prod(math.pi / (2 * half_width)))
        omega = max((m * cell * 2**d / vol_unit) ** (1 / d), step_min * math.sqrt(d))
        while True:
            ball = _ball_indices(half_width, omega)
            assert ball is not None  # no limit given
            idx, lam = ball
            if lam.size >= m:
                break
            omega *= 1.25
        order = np.lexsort((*idx.T[::-1], lam))[:m]
        return np.ascontiguousarray(idx[order]), lam[order]

    @property
    def num_basis(self) -> int:
        return int(self.indices.shape[0])

    @property
    def input_dim(self) -> int:
        return self.domain.dim

    # ------------------------------------------------------------------ numpy
    def _chunks(self, X: np.ndarray, chunk_rows: int | None) -> tuple[np.ndarray, list[slice]]:
        """Padded points (N, d) and the row slices of the chunks."""
        Xp = _pad(np.asarray(X, dtype=float), self.input_dim)
        rows = chunk_rows or max(1, CHUNK_ENTRIES // self.num_basis)
        return Xp, [slice(i, i + rows) for i in range(0, Xp.shape[0], rows)]

    def _phi_block(self, Xp: np.ndarray) -> np.ndarray:
        """(n, M) basis functions at the padded points Xp (n, d)."""
        out = np.full((Xp.shape[0], self.num_basis), self._scale)
        for k in range(self.input_dim):
            arg = (Xp[:, k] - self.domain.lower[k])[:, None] * self._axis_freq[k][None, :]
            out *= np.take(np.sin(arg), self.indices[:, k] - 1, axis=1)
        return out

    def _grad_block(self, Xp: np.ndarray) -> list[np.ndarray]:
        """d arrays (n, M): the derivative along each axis at the padded points Xp (n, d)."""
        S, C = [], []
        for k in range(self.input_dim):
            arg = (Xp[:, k] - self.domain.lower[k])[:, None] * self._axis_freq[k][None, :]
            col = self.indices[:, k] - 1
            S.append(np.take(np.sin(arg), col, axis=1))
            C.append(np.take(np.cos(arg) * self._axis_freq[k], col, axis=1))
        grads = []
        for a in range(self.input_dim):
            g = self._scale * (C[0] if a == 0 else S[0])
            for k in range(1, self.input_dim):
                g *= C[k] if k == a else S[k]
            grads.append(g)
        return grads

    def phi(self, X: np.ndarray, chunk_rows: int | None = None) -> np.ndarray:
        """(N, M) basis functions at the points X (N, p), p <= d (8 N M bytes, see module).

        Computed in chunks of ``chunk_rows`` points (default: about CHUNK_ENTRIES / M).
        """
        Xp, chunks = self._chunks(X, chunk_rows)
        out = np.empty((Xp.shape[0], self.num_basis))
        for sl in chunks:
            out[sl] = self._phi_block(Xp[sl])
        return out

    def grad_phi(self, X: np.ndarray, chunk_rows: int | None = None) -> np.ndarray:
        """(N, d, M) gradient of each basis function at X (N, p), p <= d.

        Includes the derivatives along padded axes (the z-derivative for planar points).
        """
        Xp, chunks = self._chunks(X, chunk_rows)
        out = np.empty((Xp.shape[0], self.input_dim, self.num_basis))
        for sl in chunks:
            for a, g in enumerate(self._grad_block(Xp[sl])):
                out[sl, a] = g
        return out

    def second_derivatives(self, X: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
        """d^2 phi / dx_a dx_b at X (N, p), p <= d (padded with zeros), for a <= b: each
        (N, M). Used for the Jacobian of a curl-free field with respect to position."""
        Xp = _pad(np.asarray(X, dtype=float), self.input_dim)
        S, C, F = [], [], []
        for k in range(self.input_dim):
            freq = self._axis_freq[k]
            arg = (Xp[:, k] - self.domain.lower[k])[:, None] * freq[None, :]
            col = self.indices[:, k] - 1
            S.append(np.take(np.sin(arg), col, axis=1))
            C.append(np.take(np.cos(arg), col, axis=1))
            F.append(freq[col])
        out = {}
        for a in range(self.input_dim):
            for b in range(a, self.input_dim):
                g = np.full(S[0].shape, self._scale)
                for k in range(self.input_dim):
                    if k == a == b:
                        g = g * (-(F[k] ** 2) * S[k])
                    elif k in (a, b):
                        g = g * (F[k] * C[k])
                    else:
                        g = g * S[k]
                out[(a, b)] = g
        return out

    def derivatives(
        self, X: np.ndarray, orders: list[tuple[int, ...]]
    ) -> dict[tuple[int, ...], np.ndarray]:
        """Partial derivatives of every basis function at X (N, p), p <= d (padded with zeros).

        orders: multi-indices (o_1, ..., o_d) of derivative orders per axis; returns each as
        (N, M). Uses d^o/dx^o sin(f x) = f^o sin(f x + o pi / 2), so any order costs one
        product over the axes.
        """
        Xp = _pad(np.asarray(X, dtype=float), self.input_dim)
        tables: dict[tuple[int, int], np.ndarray] = {}
        out = {}
        for order in orders:
            if len(order) != self.input_dim or min(order) < 0:
                raise ValueError(f"derivative orders {order} do not fit a {self.input_dim}-D basis")
            g = None
            for k, o in enumerate(order):
                if (k, o) not in tables:
                    freq = self._axis_freq[k]
                    arg = (Xp[:, k] - self.domain.lower[k])[:, None] * freq[None, :]
                    vals = freq[None, :] ** o * np.sin(arg + o * math.pi / 2)
                    tables[k, o] = np.take(vals, self.indices[:, k] - 1, axis=1)
                if g is None:  # one new (N, M) array per order, the products in place
                    g = tables[k, o] * self._scale
                else:
                    g *= tables[k, o]
            out[tuple(order)] = g
        return out

    # ------------------------------------------------------------------ casadi
    def _sx_factors(self, x: ca.SX, cos: bool) -> tuple[list[Any], list[Any]]:
        S, C = [], []
        for k in range(self.input_dim):
            freq = ca.DM(self._axis_freq[k])
            arg = (x[k] - self.domain.lower[k]) * freq  # (J_k, 1)
            col = [int(c) for c in self.indices[:, k] - 1]
            S.append(ca.sin(arg)[col])
            if cos:
                C.append((ca.cos(arg) * freq)[col])
        return S, C

    def _sx_input(self, position_dim: int | None) -> tuple[ca.SX, ca.SX]:
        p = self.input_dim if position_dim is None else int(position_dim)
        if not 1 <= p <= self.input_dim:
            raise ValueError(f"position_dim must be in 1..{self.input_dim}, got {p}")
        x = ca.SX.sym("x", p)
        xp = ca.vertcat(x, ca.SX.zeros(self.input_dim - p)) if p < self.input_dim else x
        return x, xp

    def phi_sx(self, position_dim: int | None = None) -> ca.Function:
        """SX function x (p, 1) -> phi (M, 1); p = position_dim (default d), padded with 0."""
        x, xp = self._sx_input(position_dim)
        S, _ = self._sx_factors(xp, cos=False)
        out = self._scale * S[0]
        for s in S[1:]:
            out = out * s
        return ca.Function("hilbert_phi", [x], [out], ["x"], ["phi"])

    def grad_phi_sx(self, position_dim: int | None = None) -> ca.Function:
        """SX function x (p, 1) -> grad phi (d, M): row a is d/dx_a of every basis function."""
        x, xp = self._sx_input(position_dim)
        S, C = self._sx_factors(xp, cos=True)
        rows = []
        for a in range(self.input_dim):
            g = self._scale * (C[0] if a == 0 else S[0])
            for k in range(1, self.input_dim):
                g = g * (C[k] if k == a else S[k])
            rows.append(g.T)
        return ca.Function("hilbert_grad_phi", [x], [ca.vertcat(*rows)], ["x"], ["grad_phi"])

    def field_sx(self, kernel_name: str, position_dim: int | None = None) -> ca.Function:
        """SX function (x (p, 1), w, c (3, 1)) -> field m (3, 1) at one position.

        ``se``: w is (M, 3), m = W^T phi(x) + c. ``curl_free``: w is (M, 1), m = grad phi(x) w
        + c (3-D basis required). c is the constant field (pass zeros without that term).
        """
        kernel_name = _check_kernel(self, kernel_name)
        x, _ = self._sx_input(position_dim)
        c = ca.SX.sym("c", FIELD_DIM)
        if kernel_name == "se":
            w = ca.SX.sym("w", self.num_basis, FIELD_DIM)
            m = ca.mtimes(w.T, self.phi_sx(position_dim)(x)) + c
        else:
            w = ca.SX.sym("w", self.num_basis)
            m = ca.mtimes(self.grad_phi_sx(position_dim)(x), w) + c
        return ca.Function("hilbert_field", [x, w, c], [m], ["x", "w", "c"], ["m"])

    # ------------------------------------------------------------------ prior
    def prior_variances(
        self, kernel_name: str, sigma_f: Any, lengthscale: Any, d: int | None = None
    ) -> Any:
        """S(sqrt(lambda_j)) for the kernel's (generating) spectral density in d dims.

        d defaults to the basis dimension (3 for the curl-free potential). numpy (M,) for
        numeric hyperparameters, a CasADi (M, 1) column when either is a CasADi symbol.
        """
        d = self.input_dim if d is None else int(d)
        kernel = get_kernel(kernel_name)
        if not _is_casadi(sigma_f, lengthscale):
            return np.asarray(
                kernel.spectral_density(self.sqrt_eigenvalues, sigma_f, lengthscale, d),
                dtype=float,
            )
        if kernel.name not in _SE_DENSITY_KERNELS:
            raise NotImplementedError(f"no CasADi spectral density for kernel {kernel.name!r}")
        omega2 = ca.DM(self.eigenvalues)
        return (
            sigma_f**2
            * (2 * math.pi * lengthscale**2) ** (d / 2)
            * ca.exp(-0.5 * lengthscale**2 * omega2)
        )

    def prior_std(
        self, kernel_name: str, sigma_f: Any, lengthscale: Any, d: int | None = None
    ) -> Any:
        """sqrt(S(sqrt(lambda_j))), written without a square root of tiny numbers (for a
        whitened parametrisation w = prior_std * v, v ~ N(0, I)). numpy or CasADi like
        ``prior_variances``; SE-density kernels only."""
        d = self.input_dim if d is None else int(d)
        if get_kernel(kernel_name).name not in _SE_DENSITY_KERNELS:
            raise NotImplementedError(f"no spectral density for kernel {kernel_name!r}")
        if _is_casadi(sigma_f, lengthscale):
            omega2: Any = ca.DM(self.eigenvalues)
            exp: Any = ca.exp
        else:
            omega2, exp = self.eigenvalues, np.exp
        return (
            sigma_f
            * (2 * math.pi * lengthscale**2) ** (d / 4)
            * exp(-0.25 * lengthscale**2 * omega2)
        )


def _check_kernel(basis: HilbertBasis, kernel_name: str) -> str:
    name = get_kernel(kernel_name).name
    if name not in _SE_DENSITY_KERNELS:
        raise NotImplementedError(f"no reduced-rank form for kernel {name!r} (se, curl_free)")
    if name == "curl_free" and basis.input_dim != 3:
        raise ValueError(
            "the curl-free field needs the potential over 3-D positions: build the basis on a "
            "3-D box (Domain.extended_to_3d / domain_for / input_dim=3), see the module doc"
        )
    return name


# --------------------------------------------------------------------------- users / tests
def approx_kernel_matrix(
    basis: HilbertBasis,
    kernel_name: str,
    X1: np.ndarray,
    X2: np.ndarray,
    sigma_f: float,
    lengthscale: float,
    sigma_lin: float = 0.0,
) -> np.ndarray:
    """Reduced-rank approximation of ``get_kernel(kernel_name).matrix(X1, X2, ...)``.

    Same shape and ordering: (N1, N2) per component for ``se``, (3 N1, 3 N2) component-major
    for ``curl_free``. sigma_lin adds the covariance sigma_lin^2 of the constant-field term to
    every same-component entry.
    """
    name = _check_kernel(basis, kernel_name)
    S = basis.prior_variances(name, sigma_f, lengthscale)
    lin = float(sigma_lin) ** 2
    if name == "se":
        P1, P2 = basis.phi(X1), basis.phi(X2)
        return (P1 * S) @ P2.T + lin
    G1, G2 = basis.grad_phi(X1), basis.grad_phi(X2)
    rows = []
    for a in range(FIELD_DIM):
        row = []
        for b in range(FIELD_DIM):
            block = (G1[:, a] * S) @ G2[:, b].T
            row.append(block + lin if a == b else block)
        rows.append(row)
    return np.block(rows)


def evaluate_field(
    basis: HilbertBasis,
    kernel_name: str,
    X: np.ndarray,
    weights: np.ndarray,
    constant: np.ndarray | None = None,
    chunk_rows: int | None = None,
) -> np.ndarray:
    """(N, 3) field at X (N, p) from the weights: (M, 3) for ``se``, (M,) for ``curl_free``.

    Chunked, so memory stays at a few chunk_rows x M arrays whatever N.
    """
    name = _check_kernel(basis, kernel_name)
    X = np.atleast_2d(np.asarray(X, dtype=float))
    w = np.asarray(weights, dtype=float)
    expected = (basis.num_basis, FIELD_DIM) if name == "se" else (basis.num_basis,)
    if w.shape != expected:
        raise ValueError(f"weights must have shape {expected} for {name!r}, got {w.shape}")
    Xp, chunks = basis._chunks(X, chunk_rows)
    out = np.empty((Xp.shape[0], FIELD_DIM))
    for sl in chunks:
        if name == "se":
            out[sl] = basis._phi_block(Xp[sl]) @ w
        else:
            out[sl] = np.column_stack([g @ w for g in basis._grad_block(Xp[sl])])
    if constant is not None:
        out += np.asarray(constant, dtype=float).reshape(1, FIELD_DIM)
    return out


@lru_cache(maxsize=8)
def cached_basis(key: tuple) -> HilbertBasis:
    """The basis of a problem structure's key ``(center, half_width, num_basis)`` (tuples),
    built once: the translational, IMU, planar and sliding-window NLPs share this cache."""
    center, half_width, num_basis = key
    return HilbertBasis(Domain(np.array(center), np.array(half_width)), num_basis)
