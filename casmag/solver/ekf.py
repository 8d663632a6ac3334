"""The filter baseline: an extended Kalman filter with the reduced-rank GP map in its state.

The published magnetic-SLAM systems are filters of this kind (Viset, Helmons & Kok, Sensors
2022; Kok & Solin 2018): the state is the pose and the map's basis-function weights, the
odometry predicts the pose, and each magnetometer sample updates pose and map together
through y = R^T (m(p; w) + c) + e, e ~ N(0, sigma_m^2 I). Here the map is casmag's own
(casmag.gp.reduced_rank: the same basis box, kernel, hyperparameters, constant field and
noise as the batch MAP of the same problem), so the two differ only in the estimator: one
forward pass, each sample's linearisation fixed once it is made, against the MAP over the
whole recording.

State: x = [nav, w, c], nav the motion model's states first (:class:`TranslationalNav`:
position and, when estimated, the constant per-step odometry bias; :class:`PlanarNav`:
position, heading and the heading-rate bias), w the weights (SE: (M, 3) column-major, one
column per field component; curl-free: (M,) of the scalar potential) with their prior
variances S(sqrt(lambda_j)), c the constant field with N(0, sigma_lin^2 I).

Cost: the covariance is dense, n = n_nav + n_w + 3 unknowns; each step reads and writes it
once: O(n^2) per sample (the peers' "O(m^2) per step"). Only its upper triangle is kept
(BLAS dsymm and dsyrk), which halves the memory traffic.

:func:`run_filter` is the whole filter; :func:`filter_result` runs it and returns a
:class:`casmag.result.Result` (its covariance scaled for correlated magnetometer residuals),
for a translational problem of ``casmag slam`` (:func:`translational_filter_result`), a
planar one (casmag.solver.planar.solve_planar with ``method="ekf"``) or a recording located
against a saved map, which the filter updates (:func:`localise_filter`). ``casmag slam
REC --method ekf|both`` is the command line (casmag.report.methods: both side by side).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
from scipy.linalg import blas

from casmag import strapdown as sd
from casmag.gp.kernels import FIELD_DIM
from casmag.gp.reduced_rank import HilbertBasis
from casmag.model.rrmap import field_and_jacobians


class NavModel(Protocol):
    """A motion model's part of the filter: its states come first in the state vector."""

    n_nav: int
    dim: int  # position dimension
    bias_states: slice  # where the estimated biases sit among the states (empty: none)

    def initial(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean (n_nav,) and covariance (n_nav, n_nav) of the first sample's states."""
        ...

    def predict(self, x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """States at sample k + 1 from those at k: mean, Jacobian F, process noise Q."""
        ...

    def position(self, x: np.ndarray) -> np.ndarray:
        """The position the map is read at (its first ``dim`` or fewer states); its Jacobian
        in x is [I, 0]."""
        ...

    def rotation(self, x: np.ndarray) -> tuple[np.ndarray, list[tuple[int, np.ndarray]]]:
        """R^T (3, 3), world to sensor frame, and [(state index, d R^T / d x_i)]."""
        ...

    # Optional: ``pseudo_measurement(x) -> (r, H_nav, var) | None``, a linear measurement of
    # the nav states applied after each magnetometer update (PoseNav's height prior).


@dataclass
class TranslationalNav:
    """p_{k+1} = p_k + u_k - b + e_k, e_k ~ N(0, sigma^2 I) (casmag.model.translational);
    b the constant per-step bias of the odometry (estimated when ``bias_sigma`` is given:
    its prior's standard deviation), p_0 ~ N(anchor, anchor_sigma^2 I). The field is read in
    the world frame."""

    U: np.ndarray  # (N - 1, d) increments
    anchor: np.ndarray
    sigma: float
    anchor_sigma: float
    bias_sigma: float | None = None

    def __post_init__(self) -> None:
        self.dim = self.U.shape[1]
        self.n_nav = 2 * self.dim if self.bias_sigma is not None else self.dim
        self.bias_states = slice(self.dim, self.n_nav)
        d = self.dim
        self._F = np.eye(self.n_nav)
        if self.bias_sigma is not None:
            self._F[:d, d:] = -np.eye(d)
        self._Q = np.zeros((self.n_nav, self.n_nav))
        self._Q[:d, :d] = self.sigma**2 * np.eye(d)

    def initial(self) -> tuple[np.ndarray, np.ndarray]:
        x = np.zeros(self.n_nav)
        x[: self.dim] = np.ravel(self.anchor)[: self.dim]
        var = np.full(self.n_nav, self.anchor_sigma**2)
        if self.bias_sigma is not None:
            var[self.dim :] = self.bias_sigma**2
        return x, np.diag(var)

    def predict(self, x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = x.copy()
        x[: self.dim] += self.U[k]
        if self.bias_sigma is not None:
            x[: self.dim] -= x[self.dim :]
        return x, self._F, self._Q

    def position(self, x: np.ndarray) -> np.ndarray:
        return x[: self.dim]

    def rotation(self, x: np.ndarray) -> tuple[np.ndarray, list[tuple[int, np.ndarray]]]:
        return np.eye(FIELD_DIM), []


@dataclass
class PlanarNav:
    """States (x, y, psi, b) (casmag.model.planar): psi_{k+1} = psi_k + dyaw_k - b dt_k +
    e_psi, p_{k+1} = p_k + Rz(psi_k) (dfwd_k, dleft_k) + e_p; the field is read in the body
    frame, y = Rz(psi)^T (m(p) + c). ``bias_walk`` [rad/s/sqrt(s)]: the bias's random walk
    (0: constant)."""

    U: np.ndarray  # (N - 1, 3): dfwd, dleft, dyaw
    dt: np.ndarray  # (N - 1,)
    anchor: np.ndarray  # (3,): x, y, psi
    sigma_disp: float
    sigma_dyaw: float
    sigma_anchor: float
    sigma_psi0: float
    bias_sigma: float
    bias_walk: float = 0.0

    def __post_init__(self) -> None:
        self.dim = 2
        self.n_nav = 4
        self.bias_states = slice(3, 4)

    def initial(self) -> tuple[np.ndarray, np.ndarray]:
        x = np.array([*np.ravel(self.anchor)[:3], 0.0])
        var = [self.sigma_anchor**2] * 2 + [self.sigma_psi0**2, self.bias_sigma**2]
        return x, np.diag(var)

    def predict(self, x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        fwd, left, dyaw = self.U[k]
        h = float(self.dt[k])
        c, s = math.cos(x[2]), math.sin(x[2])
        out = x.copy()
        out[0] += c * fwd - s * left
        out[1] += s * fwd + c * left
        out[2] += dyaw - x[3] * h
        F = np.eye(4)
        F[0, 2] = -s * fwd - c * left
        F[1, 2] = c * fwd - s * left
        F[2, 3] = -h
        Q = np.diag(
            [self.sigma_disp**2, self.sigma_disp**2, self.sigma_dyaw**2, self.bias_walk**2 * h]
        )
        return out, F, Q

    def position(self, x: np.ndarray) -> np.ndarray:
        return x[:2]

    def rotation(self, x: np.ndarray) -> tuple[np.ndarray, list[tuple[int, np.ndarray]]]:
        c, s = math.cos(x[2]), math.sin(x[2])
        Rt = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        dRt = np.array([[-s, c, 0.0], [-c, -s, 0.0], [0.0, 0.0, 0.0]])
        return Rt, [(2, dRt)]


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@dataclass
class PoseNav:
    """States (p (3), theta (3), b_w (3)[, b_p (3)]) of the pose-odometry model
    (casmag.model.pose): the orientation is a nominal quaternion kept by this object, one
    per sample (``nominal``), times the error state theta (a body-frame rotation vector),
    folded into the nominal at each prediction (an error-state, or multiplicative, EKF):
    q_{k+1} = q_k exp(theta) dq_k exp(-b_w dt_k), p_{k+1} = p_k + R(q_k exp(theta))
    (dp_k - b_p); the field is read in the body frame, y = R^T (m(p) + c). b_p is a state
    when ``bias_p_sigma`` is given, else held at zero. ``height_sigma``: every sample's
    height measured as the first's with that standard deviation (the MAP's ``height``
    block)."""

    U: np.ndarray  # (N - 1, 7): dp, dq
    dt: np.ndarray  # (N - 1,)
    p0: np.ndarray
    q0: np.ndarray
    sigma_p: float
    sigma_r: float
    sigma_anchor: float
    sigma_att0: float
    bias_w_sigma: float
    bias_p_sigma: float | None = None
    position_dim: int = 3  # the map's: 2 reads the field at (x, y)
    height_sigma: float | None = None  # the pose model's ``height`` block, as a measurement

    def __post_init__(self) -> None:
        self.dim = 3
        self.n_nav = 9 if self.bias_p_sigma is None else 12
        self.bias_states = slice(6, self.n_nav)
        n = self.U.shape[0] + 1
        self.nominal = np.empty((n, 4))
        self._current = 0

    def initial(self) -> tuple[np.ndarray, np.ndarray]:
        self.nominal[0] = sd.quat_normalize(np.asarray(self.q0, dtype=float))
        self._current = 0
        x = np.zeros(self.n_nav)
        x[:3] = self.p0
        var = [self.sigma_anchor**2] * 3 + [self.sigma_att0**2] * 3 + [self.bias_w_sigma**2] * 3
        if self.bias_p_sigma is not None:
            var += [self.bias_p_sigma**2] * 3
        return x, np.diag(var)

    def predict(self, x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        h = float(self.dt[k])
        q = sd.quat_mul(self.nominal[k], sd.quat_exp(x[3:6]))  # the update folded in
        R = sd.quat_to_rotmat(q)
        b_p = x[9:12] if self.bias_p_sigma is not None else np.zeros(3)
        u = self.U[k, :3] - b_p
        dq = sd.quat_mul(sd.quat_normalize(self.U[k, 3:7]), sd.quat_exp(-h * x[6:9]))
        self.nominal[k + 1] = sd.quat_normalize(sd.quat_mul(q, dq))
        self._current = k + 1
        out = x.copy()
        out[:3] = x[:3] + R @ u
        out[3:6] = 0.0
        F = np.eye(self.n_nav)
        F[:3, 3:6] = -R @ _skew(u)
        F[3:6, 3:6] = sd.quat_to_rotmat(dq).T
        F[3:6, 6:9] = -h * np.eye(3)
        if self.bias_p_sigma is not None:
            F[:3, 9:12] = -R
        Q = np.zeros((self.n_nav, self.n_nav))
        Q[:3, :3] = self.sigma_p**2 * np.eye(3)
        Q[3:6, 3:6] = self.sigma_r**2 * np.eye(3)
        return out, F, Q

    def position(self, x: np.ndarray) -> np.ndarray:
        return x[: self.position_dim]

    def _rt(self, x: np.ndarray, k: int) -> np.ndarray:
        return sd.quat_to_rotmat(sd.quat_mul(self.nominal[k], sd.quat_exp(x[3:6]))).T

    def rotation(self, x: np.ndarray) -> tuple[np.ndarray, list[tuple[int, np.ndarray]]]:
        Rt = self._rt(x, self._current)
        # R = Rnom exp(theta): d(R^T) / d theta_i = -[e_i]x R^T to first order in theta.
        return Rt, [(3 + i, -_skew(np.eye(3)[i]) @ Rt) for i in range(3)]

    def pseudo_measurement(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The height prior of the MAP's ``height`` block as a measurement z = z_0 at every
        sample (None without it)."""
        if self.height_sigma is None:
            return None
        H = np.zeros((1, self.n_nav))
        H[0, 2] = 1.0
        return np.array([self.p0[2] - x[2]]), H, np.array([self.height_sigma**2])

    def orientations(self, states: np.ndarray) -> np.ndarray:
        """(N, 4) filtered orientations of the states of a run."""
        return sd.quat_normalize(sd.quat_mul(self.nominal, sd.quat_exp(states[:, 3:6])))

    def sensor_rotations(self, states: np.ndarray) -> np.ndarray:
        """(N, 3, 3) R^T of each filtered state."""
        return sd.quat_to_rotmat(self.orientations(states)).transpose(0, 2, 1)


def sensor_rotations(nav: NavModel, states: np.ndarray) -> np.ndarray:
    """(N, 3, 3) R^T of a run's filtered states: the nav model's own when it keeps its
    orientation outside the state (:class:`PoseNav`), else from :meth:`NavModel.rotation`."""
    own = getattr(nav, "sensor_rotations", None)
    if own is not None:
        return own(states)
    return np.stack([nav.rotation(x)[0] for x in states])


@dataclass
class FilterMap:
    """The map in the state: basis, kernel, hyperparameters, the constant field's prior."""

    basis: HilbertBasis
    kernel: str  # "se" or "curl_free"
    sigma_f: float
    lengthscale: float
    sigma_m: float
    sigma_lin: float
    weights_mean: np.ndarray | None = None  # prior mean of w (default 0)
    constant_mean: np.ndarray | None = None  # prior mean of c (default 0)
    # prior covariance of [w, c] (default: diagonal, the prior variances and sigma_lin^2)
    prior_cov: np.ndarray | None = None

    @property
    def n_w(self) -> int:
        m = self.basis.num_basis
        return FIELD_DIM * m if self.kernel == "se" else m

    def prior_variances(self) -> np.ndarray:
        S = self.basis.prior_variances(self.kernel, self.sigma_f, self.lengthscale)
        return np.tile(S, FIELD_DIM) if self.kernel == "se" else S


@dataclass
class FilterRun:
    """A filter's output. ``states`` (N, n_nav) filtered means; ``position_cov`` (N, d, d);
    ``weights`` and ``constant``: the map at the end; ``nis`` (N,): each sample's
    normalised innovation squared (chi-square with 3 degrees of freedom when the filter is
    consistent); ``seconds``: the filter's wall time."""

    states: np.ndarray
    position_cov: np.ndarray
    weights: np.ndarray
    constant: np.ndarray
    nis: np.ndarray
    seconds: float
    n_state: int
    dim: int
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def positions(self) -> np.ndarray:
        return self.states[:, : self.dim]

    @property
    def mean_nis(self) -> float:
        return float(np.mean(self.nis))


def _measurement(
    nav: NavModel, fmap: FilterMap, x: np.ndarray, n_nav: int
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted magnetometer (3,) and its Jacobian H (3, n) at the state x."""
    n_w = fmap.n_w
    w = x[n_nav : n_nav + n_w]
    c = x[n_nav + n_w :]
    p = nav.position(x[:n_nav])
    f, rows, D = field_and_jacobians(fmap.basis, fmap.kernel, p[None, :], w)
    world = f[0] + c
    Rt, dRt = nav.rotation(x[:n_nav])
    H = np.zeros((FIELD_DIM, x.shape[0]))
    H[:, : p.shape[0]] = Rt @ D[0]  # the map's coordinates (the first ones of the position)
    for i, dR in dRt:
        H[:, i] += dR @ world
    if fmap.kernel == "se":
        phi = rows[0][0]
        m = phi.shape[0]
        for j in range(FIELD_DIM):
            H[:, n_nav + j * m : n_nav + (j + 1) * m] = np.outer(Rt[:, j], phi)
    else:
        G = np.vstack([r[0] for r in rows])  # (3, M)
        H[:, n_nav : n_nav + n_w] = Rt @ G
    H[:, n_nav + n_w :] = Rt
    return Rt @ world, H


def _pseudo_update(
    x: np.ndarray, P: np.ndarray, r: np.ndarray, H_nav: np.ndarray, var: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A linear update of the state by a motion model's pseudo-measurement (residual r (m,),
    its Jacobian in the nav states H_nav (m, n_nav), variances var (m,)), on the upper
    triangle of P as the magnetometer's update."""
    H = np.zeros((r.shape[0], x.shape[0]))
    H[:, : H_nav.shape[1]] = H_nav
    PHt = blas.dsymm(1.0, P, np.asfortranarray(H.T), side=0, lower=0)
    S = H @ PHt + np.diag(var)
    L = np.linalg.cholesky(0.5 * (S + S.T))
    B = np.linalg.solve(L, PHt.T).T
    x = x + B @ np.linalg.solve(L, r)
    P = blas.dsyrk(-1.0, np.asfortranarray(B), beta=1.0, c=P, trans=0, lower=0, overwrite_c=1)
    return x, P


def run_filter(
    nav: NavModel, fmap: FilterMap, Y: np.ndarray, iterations: int = 1, map_cov: bool = False
) -> FilterRun:
    """The EKF over every sample: update with Y[0] at the first state, then predict and
    update for each later sample. Y: (N, 3) magnetometer samples in the sensor frame.
    iterations: relinearisations per update (1: the EKF; more: the iterated EKF).
    map_cov: keep the final covariance of [w, c] (``extra["map_cov"]``)."""
    t0 = time.perf_counter()
    N = Y.shape[0]
    n_nav, n_w = nav.n_nav, fmap.n_w
    n = n_nav + n_w + FIELD_DIM
    x = np.zeros(n)
    x0, P0 = nav.initial()
    x[:n_nav] = x0
    if fmap.weights_mean is not None:
        x[n_nav : n_nav + n_w] = fmap.weights_mean
    if fmap.constant_mean is not None:
        x[n_nav + n_w :] = fmap.constant_mean
    # Upper triangle only, Fortran order so that BLAS updates it in place.
    P = np.zeros((n, n), order="F")
    P[:n_nav, :n_nav] = P0
    if fmap.prior_cov is not None:
        P[n_nav:, n_nav:] = fmap.prior_cov
    else:
        diag = np.concatenate([fmap.prior_variances(), np.full(FIELD_DIM, fmap.sigma_lin**2)])
        P[np.arange(n_nav, n), np.arange(n_nav, n)] = diag
    R = fmap.sigma_m**2 * np.eye(FIELD_DIM)
    pseudo = getattr(nav, "pseudo_measurement", None)
    states = np.empty((N, n_nav))
    cov = np.empty((N, nav.dim, nav.dim))
    nis = np.empty(N)
    for k in range(N):
        if k > 0:
            xn, F, Q = nav.predict(x[:n_nav], k - 1)
            Pnn = np.triu(P[:n_nav, :n_nav])
            Pnn = Pnn + np.triu(Pnn, 1).T
            P[:n_nav, n_nav:] = F @ P[:n_nav, n_nav:]
            P[:n_nav, :n_nav] = F @ Pnn @ F.T + Q
            x[:n_nav] = xn
        x_pred = x.copy()
        for it in range(iterations):
            h, H = _measurement(nav, fmap, x, n_nav)
            PHt = blas.dsymm(1.0, P, np.asfortranarray(H.T), side=0, lower=0)  # (n, 3)
            S = H @ PHt + R
            S = 0.5 * (S + S.T)
            L = np.linalg.cholesky(S)
            r = Y[k] - h - H @ (x_pred - x)
            z = np.linalg.solve(L, r)
            if it == 0:
                nis[k] = float(z @ z)
            # K = PHt S^-1; P -= K S K^T = (PHt L^-T)(PHt L^-T)^T.
            B = np.linalg.solve(L, PHt.T).T  # (n, 3) = PHt L^-T
            x = x_pred + B @ z
        P = blas.dsyrk(-1.0, np.asfortranarray(B), beta=1.0, c=P, trans=0, lower=0, overwrite_c=1)
        measured = None if pseudo is None else pseudo(x[:n_nav])
        if measured is not None:
            x, P = _pseudo_update(x, P, *measured)
        states[k] = x[:n_nav]
        pc = np.triu(P[: nav.dim, : nav.dim])
        cov[k] = pc + np.triu(pc, 1).T
    extra: dict[str, Any] = {}
    if map_cov:
        Pm = np.triu(P[n_nav:, n_nav:])
        extra["map_cov"] = Pm + np.triu(Pm, 1).T
    return FilterRun(
        extra=extra,
        states=states,
        position_cov=cov,
        weights=x[n_nav : n_nav + n_w].copy(),
        constant=x[n_nav + n_w :].copy(),
        nis=nis,
        seconds=time.perf_counter() - t0,
        n_state=n,
        dim=nav.dim,
    )


#: Status of a filter that ran over every sample (a filter has no convergence to report).
FILTERED = "Filter_Completed"
#: Status of a filter whose innovation covariance stopped being positive definite.
DIVERGED = "Filter_Diverged"
#: The odometry bias prior of the filter when the problem gives none, as a fraction of the
#: median step: the batch needs no prior (all samples fix the bias together), a filter does
#: (see :func:`translational_filter`).
BIAS_PRIOR_STEP_FRACTION = 0.01


def translational_nav(problem: Any, data: Any) -> TranslationalNav:
    """The translational motion model of a problem (casmag.problem.spec.Problem) in the
    filter: its odometry noise and anchor; the constant per-step odometry bias in the state
    when the problem estimates it, with the problem's prior, else
    BIAS_PRIOR_STEP_FRACTION of the median step."""
    from casmag.errors import ProblemError

    if data.n_sessions > 1:
        raise ProblemError(problem.source, "", "the filter runs one recording at a time")
    m = problem.spec.model
    bias_sigma = None
    if m.odometry.estimate_bias:
        step = float(np.median(np.linalg.norm(data.U, axis=1)))
        bias_sigma = m.odometry.bias_prior_sigma or max(BIAS_PRIOR_STEP_FRACTION * step, 1e-9)
    return TranslationalNav(
        np.asarray(data.U, dtype=float),
        np.asarray(data.anchor, dtype=float),
        float(problem.assumed_sigma_odometry),
        float(m.anchor.sigma),
        bias_sigma,
    )


def translational_filter(problem: Any, data: Any) -> tuple[TranslationalNav, FilterMap]:
    """The filter of a translational problem (with a reduced-rank map, its hyperparameters
    set or estimated already, as ``casmag slam`` makes them): :func:`translational_nav` and
    the batch's map box around the dead reckoning (casmag.model.translational.Structure),
    kernel, sigma_f, lengthscale, sigma_m and constant-field prior sigma_lin."""
    from casmag.errors import ProblemError
    from casmag.gp.reduced_rank import cached_basis
    from casmag.model.translational import Structure

    m = problem.spec.model
    if m.gp.form != "reduced_rank":
        raise ProblemError(problem.source, "model.gp.form", "the filter needs reduced_rank")
    nav = translational_nav(problem, data)
    s = Structure.of(problem, data)
    hyper = problem.assumed_hyperparameters
    sigma_lin = m.gp.sigma_lin if m.gp.sigma_lin is not None else float(np.abs(data.Y).max())
    fmap = FilterMap(
        cached_basis(s.basis),
        problem.assumed_kernel,
        float(hyper["sigma_f"]),
        float(hyper["lengthscale"]),
        float(hyper["sigma_m"]),
        float(sigma_lin),
    )
    return nav, fmap


def run_safely(
    nav: NavModel, fmap: FilterMap, Y: np.ndarray, iterations: int = 1, map_cov: bool = False
) -> FilterRun | None:
    """:func:`run_filter`, or None when it diverged: the innovation covariance stopped being
    positive definite, or a state is not finite."""
    try:
        with np.errstate(invalid="raise", over="raise"):
            run = run_filter(nav, fmap, np.asarray(Y, dtype=float), iterations, map_cov)
    except (np.linalg.LinAlgError, FloatingPointError):
        return None
    return run if np.all(np.isfinite(run.states)) else None


def filter_result(
    nav: NavModel,
    fmap: FilterMap,
    Y: np.ndarray,
    P_odometry: np.ndarray,
    P_true: np.ndarray | None,
    info: dict[str, Any],
    motion: str = "translational",
    iterations: int = 1,
    run: FilterRun | None = None,
    duration: float | None = None,
    **fields: Any,
) -> Any:
    """Run the filter on the magnetometer samples Y and return it as a
    :class:`casmag.result.Result` of the given motion model (``info.method`` ``ekf``;
    ``info.filter``: state size, wall time, mean NIS). P_odometry: the dead reckoning;
    P_true: the truth, for the errors only; ``fields``: further Result fields (e.g.
    ``odometry_bias_true``); ``run``: the filter already run (:func:`run_safely`; None: run
    here); ``duration``: the recording's length [s], for the real-time factor
    (``info.filter.real_time_factor``: recording time per second of filter time). A filter
    whose innovation covariance stopped being positive definite, or whose state is not
    finite, is a failure (status DIVERGED), no errors reported. ``P_cov`` is the filter's
    covariance of each position given the samples up to it, scaled by the long-run
    inflation of its magnetometer residuals (``uncertainty.inflation``;
    ``P_cov_uninflated`` the filter's own). Motion-model figures (the planar headings) are
    the caller's."""
    from casmag.result import Result
    from casmag.result.metrics import rmse_and_max
    from casmag.solver.uncertainty import PositionUncertainty, residual_inflation
    from casmag.versions import __version__, versions

    Y = np.asarray(Y, dtype=float)
    if run is None:
        run = run_safely(nav, fmap, Y, iterations)
    before = after = (None, None)
    if P_true is not None:
        before = rmse_and_max(P_odometry, P_true)
    info = {
        **info,
        "method": "ekf",
        "n_samples": int(Y.shape[0]),
        "kernel": fmap.kernel,
        "gp_form": "reduced_rank",
        "num_basis": fmap.basis.num_basis,
        "casmag": __version__,
        "versions": versions(),
    }
    common = {
        "motion": motion,
        "iterations": 0,
        "build_seconds": 0.0,
        "rmse_before": before[0],
        "max_before": before[1],
        "hyperparameters": {
            "sigma_f": fmap.sigma_f,
            "lengthscale": fmap.lengthscale,
            "sigma_m": fmap.sigma_m,
        },
        "cost_per_iteration": [],
        **fields,
    }
    if run is None:
        info["filter"] = {"reason": "the innovation covariance stopped being positive definite"}
        return Result(
            info=info,
            status=DIVERGED,
            success=False,
            solve_seconds=0.0,
            rmse_after=None,
            max_after=None,
            cost_blocks={},
            arrays={"P_odometry": P_odometry, "P_estimate": P_odometry, "P_true": P_true},
            **common,
        )
    P_est = run.positions
    if P_true is not None:
        after = rmse_and_max(P_est, P_true)
    # The final map at the filtered path, read in the sensor frame.
    f, _, _ = field_and_jacobians(fmap.basis, fmap.kernel, P_est, run.weights)
    M_est = np.einsum("nij,nj->ni", sensor_rotations(nav, run.states), f + run.constant)
    misfit = 0.5 * float(np.sum(((Y - M_est) / fmap.sigma_m) ** 2))
    # Correlated magnetometer residuals carry less information than white ones: the
    # position covariance is scaled by the largest long-run inflation factor of the
    # residuals (casmag.solver.uncertainty.residual_inflation, the MAP's sandwich as one
    # scalar): on the real robot sequences located against a saved map it took the mean
    # NEES from 36-67 to 2.2-4.5 (expected 2).
    inflation = residual_inflation(Y - M_est, [(0, Y.shape[0])], fmap.sigma_m, "long-run")
    factor = float(np.max(inflation.lam))
    cov = run.position_cov * factor
    uncertainty = PositionUncertainty(cov).summary(P_est, P_true)
    uncertainty["inflation"] = {**inflation.to_dict(), "active": factor > 1.0, "scale": factor}
    uncertainty["uninflated"] = PositionUncertainty(run.position_cov).summary(P_est, P_true)
    info["filter"] = {
        "state_size": run.n_state,
        "iterations_per_update": iterations,
        "seconds": run.seconds,
        "mean_nis": run.mean_nis,
        "nis_expected": float(FIELD_DIM),
        "real_time_factor": None if duration is None else float(duration / max(run.seconds, 1e-9)),
    }
    arrays: dict[str, Any] = {
        "P_cov": cov,
        "P_cov_uninflated": run.position_cov,
        "P_odometry": P_odometry,
        "P_estimate": P_est,
        "P_true": P_true,
        "M_estimate": M_est,
        "Y": Y,
    }
    bias = run.states[-1, nav.bias_states]
    return Result(
        info=info,
        status=FILTERED,
        success=True,
        solve_seconds=run.seconds,
        rmse_after=after[0],
        max_after=after[1],
        odometry_bias=[float(v) for v in bias] if bias.size else None,
        cost_blocks={"magnetometer": {"after": misfit}},
        uncertainty=uncertainty,
        arrays=arrays,
        **common,
    )


def translational_filter_result(problem: Any, data: Any, duration: float | None = None) -> Any:
    """:func:`filter_result` of a translational problem on its data set
    (:func:`translational_filter`); duration: the recording's length [s]."""
    nav, fmap = translational_filter(problem, data)
    info, fields = _translational_info(problem, data, nav)
    return filter_result(
        nav, fmap, data.Y, data.dead_reckoning(), data.P_true, info, duration=duration, **fields
    )


def _translational_info(
    problem: Any, data: Any, nav: TranslationalNav
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The info entries and Result fields of a translational filter result."""
    bias_true = getattr(data, "bias_true", None)
    info = {
        "name": problem.name,
        "source": problem.source,
        "estimate_bias": nav.bias_sigma is not None,
        "bias_prior_sigma": nav.bias_sigma,
    }
    truth = None if bias_true is None else [float(v) for v in np.ravel(bias_true)]
    return info, {"odometry_bias_true": truth}


def localise_filter(
    problem: Any, data: Any, saved: Any, map_source: str = "", duration: float | None = None
) -> Any:
    """A translational recording located against a saved map (casmag.gp.savedmap) by the
    filter, which updates the map as it goes: the map block of the state starts at the
    saved posterior (mean, and the inverse of its precision as covariance), so the map's
    own uncertainty is in every update and the recording's data refine it. The result's
    ``field_map`` is the updated map (written as map.npz: mean and precision of the
    filter's final map block, marginal over the path); ``info.localisation`` has the share
    of the path on mapped ground (casmag.solver.localize.covered), flagged ``off_map`` below
    casmag.solver.localize.MIN_COVERED, as for the MAP localisation."""
    import scipy.linalg as sla

    from casmag.errors import DataError
    from casmag.solver.localize import covered, off_map_flag

    where = map_source or "map"
    saved.require_box(where)
    saved.require_posterior(where)
    if saved.dim != data.dim:
        raise DataError(f"{where}: a {saved.dim}-D map cannot locate a {data.dim}-D recording")
    if data.n_sessions > 1:
        raise DataError(f"{where}: localises one recording at a time")
    nav = translational_nav(problem, data)
    n_w = saved.num_weights
    cov_z = sla.cho_solve((saved.cholesky(), True), np.eye(saved.size))
    prior_cov = np.zeros((n_w + FIELD_DIM, n_w + FIELD_DIM))
    prior_cov[: saved.size, : saved.size] = cov_z
    c_mean = saved.mean[n_w:] if saved.constant_field else np.zeros(FIELD_DIM)
    if not saved.constant_field:  # the map has no constant: hold it at zero
        prior_cov[n_w:, n_w:] = np.eye(FIELD_DIM) * (1e-9 * saved.sigma_m) ** 2
    fmap = FilterMap(
        saved.basis(),
        saved.kernel,
        saved.sigma_f,
        saved.lengthscale,
        saved.sigma_m,
        sigma_lin=1.0,
        weights_mean=saved.mean[:n_w],
        constant_mean=c_mean,
        prior_cov=prior_cov,
    )
    run = run_safely(nav, fmap, data.Y, map_cov=True)
    info, fields = _translational_info(problem, data, nav)
    info["localisation"] = {"map": map_source, "frame": saved.frame, "map_unknowns": saved.size}
    result = filter_result(
        nav,
        fmap,
        data.Y,
        data.dead_reckoning(),
        data.P_true,
        info,
        run=run,
        duration=duration,
        **fields,
    )
    if run is None:
        return result
    on_map = float(covered(saved, run.positions).mean())
    result.info["localisation"]["covered"] = on_map
    flag = off_map_flag(on_map)
    if flag is not None:
        result.flags.append(flag)
        result.judge()
    keep = np.r_[np.arange(n_w), n_w + np.arange(FIELD_DIM if saved.constant_field else 0)]
    cov = run.extra["map_cov"][np.ix_(keep, keep)]
    mean = np.concatenate([run.weights, run.constant])[keep]
    L = np.linalg.cholesky(0.5 * (cov + cov.T))
    precision = sla.cho_solve((L, True), np.eye(keep.size))
    result.field_map = replace(saved, mean=mean, precision=0.5 * (precision + precision.T))
    result.info["map"] = {"saved": True, "updated_from": map_source}
    return result
