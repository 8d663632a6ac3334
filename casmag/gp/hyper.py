"""Hyperparameters from data by the GP marginal likelihood (paper Eq. 5).

The joint MAP over the field and sigma_m (or, with the reduced-rank map, over the weights and
sigma_f, l) is unbounded, so hyperparameters that the MAP cannot estimate are estimated here,
with the field integrated out:

    -log p(y | X, theta) = 0.5 y^T (K + C + sigma_m^2 I)^-1 y + 0.5 log|K + C + sigma_m^2 I|
                           + 0.5 n log(2 pi),

K the field kernel matrix at the positions X and C = sigma_lin^2 (I_3 kron 1 1^T) a constant
field per window. The sum runs over short windows of consecutive samples, which keeps each
Cholesky factor small and, with drifting positions, keeps the drift inside a window small.
Everything starts from the data (field spread, window extent), not from constants tuned to
one data set; a few lengthscale starts guard against local minima.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import scipy.optimize
from threadpoolctl import threadpool_limits

from casmag.gp.kernels import FIELD_DIM, field_covariance, get_kernel


@dataclass(frozen=True)
class HyperEstimate:
    """Estimated sigma_f, lengthscale [m], sigma_m (field units), the negative log marginal
    likelihood at the estimate, and the number of windows and samples used."""

    sigma_f: float
    lengthscale: float
    sigma_m: float
    neg_log_marginal: float
    n_windows: int
    n_samples: int
    converged: bool


def select_windows(X: np.ndarray, Y: np.ndarray, window: int, max_windows: int) -> list[tuple]:
    """Up to max_windows blocks of ``window`` consecutive samples, evenly spread."""
    n = len(X)
    if n < 2:
        raise ValueError("need at least 2 samples")
    window = min(window, n)
    count = max(1, min(max_windows, n // window))
    starts = np.linspace(0, n - window, count).astype(int)
    return [(X[s : s + window], Y[s : s + window]) for s in starts]


def negative_log_marginal(
    log_theta: np.ndarray, windows: list[tuple], kernel_name: str, sigma_lin: float
) -> float:
    """Sum over windows of -log p(y | X, theta); log_theta = log (sigma_f, l, sigma_m)."""
    sigma_f, ell, sigma_m = np.exp(log_theta)
    kernel = get_kernel(kernel_name)
    total = 0.0
    for Xw, Yw in windows:
        n = len(Xw)
        K = field_covariance(kernel, Xw, sigma_f, ell)
        K += sigma_lin**2 * np.kron(np.eye(FIELD_DIM), np.ones((n, n)))
        K[np.diag_indices_from(K)] += sigma_m**2
        y = Yw.ravel(order="F")  # component-major, as the kernel matrix
        try:
            L = np.linalg.cholesky(K)
        except np.linalg.LinAlgError:
            return np.inf
        a = np.linalg.solve(L, y)
        total += 0.5 * a @ a + np.log(np.diag(L)).sum() + 0.5 * y.size * np.log(2 * np.pi)
    return float(total)


def negative_log_marginal_and_gradient(
    log_theta: np.ndarray, windows: list[tuple], kernel_name: str, sigma_lin: float
) -> tuple[float, np.ndarray]:
    """:func:`negative_log_marginal` and its exact gradient in log (sigma_f, l, sigma_m):
    per window 0.5 tr((K^-1 - a a^T) dK), a = K^-1 y, with dK/dlog sigma_f = 2 K_f,
    dK/dlog sigma_m = 2 sigma_m^2 I and dK/dlog l by a complex step (exact to rounding:
    no difference is taken). With finite differences of the marginal likelihood, L-BFGS-B
    ended in a failed line search on some machines and not on others (the estimate good,
    ``converged`` false)."""
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # overflow: inf cost
        return _nlml_and_gradient(log_theta, windows, kernel_name, sigma_lin)


def _nlml_and_gradient(
    log_theta: np.ndarray, windows: list[tuple], kernel_name: str, sigma_lin: float
) -> tuple[float, np.ndarray]:
    sigma_f, ell, sigma_m = np.exp(log_theta)
    kernel = get_kernel(kernel_name)
    total, grad = 0.0, np.zeros(3)
    h = 1e-30
    for Xw, Yw in windows:
        n = len(Xw)
        Kf = field_covariance(kernel, Xw, sigma_f, ell)
        dK_ell = field_covariance(kernel, Xw, sigma_f, ell * complex(1.0, h)).imag / h
        K = Kf + sigma_lin**2 * np.kron(np.eye(FIELD_DIM), np.ones((n, n)))
        K[np.diag_indices_from(K)] += sigma_m**2
        y = Yw.ravel(order="F")
        if not (np.isfinite(K).all() and np.isfinite(dK_ell).all()):
            return np.inf, np.zeros(3)  # overflow at an extreme trial point of the search
        try:
            cho = scipy.linalg.cho_factor(K, lower=True)
        except np.linalg.LinAlgError:
            return np.inf, np.zeros(3)
        a = scipy.linalg.cho_solve(cho, y)
        Kinv = scipy.linalg.cho_solve(cho, np.eye(y.size))
        total += 0.5 * y @ a + np.log(np.diag(cho[0])).sum() + 0.5 * y.size * np.log(2 * np.pi)
        W = Kinv - np.outer(a, a)
        grad[0] += np.sum(W * Kf)  # 0.5 tr(W 2 K_f)
        grad[1] += 0.5 * np.sum(W * dK_ell)
        grad[2] += sigma_m**2 * np.trace(W)
    return float(total), grad


def estimate_hyperparameters(
    X: np.ndarray,
    Y: np.ndarray,
    kernel: str = "curl_free",
    window: int = 150,
    max_windows: int = 8,
    starts: tuple[float, ...] = (0.05, 0.1, 0.2),
) -> HyperEstimate:
    """Maximise the windowed marginal likelihood of magnetometer data Y (N, 3) at positions
    X (N, d) over log sigma_f, log l and log sigma_m.

    starts: initial lengthscales as fractions of the median window extent. Initial sigma_f
    from the field's spread within windows (per-component variance sigma_f^2 for ``se``,
    sigma_f^2 / l^2 for ``curl_free``); initial sigma_m one tenth of that spread. The
    constant-field prior sigma_lin is the largest mean component plus the overall spread.
    """
    X, Y = np.asarray(X, dtype=float), np.asarray(Y, dtype=float)
    if X.ndim != 2 or Y.shape != (X.shape[0], FIELD_DIM):
        raise ValueError(f"expected X (N, d) and Y (N, 3), got {X.shape} and {Y.shape}")
    with threadpool_limits(1):
        # Windows of a few hundred rows: BLAS threads only contend (measured: a 450 x 450
        # Cholesky took 2 ms on one thread, 30 ms on two threads of a busy 2-core machine).
        return _estimate(X, Y, kernel, window, max_windows, starts)


def _estimate(
    X: np.ndarray,
    Y: np.ndarray,
    kernel: str,
    window: int,
    max_windows: int,
    starts: tuple[float, ...],
) -> HyperEstimate:
    wins = select_windows(X, Y, window, max_windows)
    spread = float(np.mean([Yw.std(axis=0).mean() for _, Yw in wins]))
    extent = float(np.median([np.ptp(Xw, axis=0).max() for Xw, _ in wins]))
    if spread <= 0 or extent <= 0:
        raise ValueError("the data have no spread in field or position")
    sigma_lin = float(np.abs(Y.mean(axis=0)).max() + Y.std())
    name = get_kernel(kernel).name
    best = None
    for frac in starts:
        ell0 = frac * extent
        sigma_f0 = spread if name == "se" else spread * ell0
        x0 = np.log([sigma_f0, ell0, 0.1 * spread])
        res = scipy.optimize.minimize(
            negative_log_marginal_and_gradient,
            x0,
            args=(wins, name, sigma_lin),
            jac=True,
            method="L-BFGS-B",
        )
        if best is None or res.fun < best.fun:
            best = res
    sigma_f, ell, sigma_m = np.exp(best.x)
    return HyperEstimate(
        sigma_f=float(sigma_f),
        lengthscale=float(ell),
        sigma_m=float(sigma_m),
        neg_log_marginal=float(best.fun),
        n_windows=len(wins),
        n_samples=sum(len(w[0]) for w in wins),
        converged=bool(best.success),
    )


@dataclass(frozen=True)
class FieldEvidence:
    """Does the field along a trajectory carry position information? Windowed marginal
    likelihoods (paper Eq. 5, ``casmag.gp.hyper``) of the magnetometer rotated into the local
    frame, under the GP map (sigma_f, lengthscale [m], sigma_m estimated) and under a
    homogeneous field (a constant per window plus white noise sigma_m_homogeneous, the only
    hyperparameter): neg_log_marginal_* [nats] over n scalar observations. The map's two
    extra hyperparameters cost the BIC penalty ln(n) (0.5 k ln n, k = 2);
    log_bayes_factor = neg_log_marginal_homogeneous - neg_log_marginal_map - penalty, and the
    field is ``homogeneous`` when it is not positive."""

    sigma_f: float
    lengthscale: float
    sigma_m: float
    sigma_m_homogeneous: float
    neg_log_marginal_map: float
    neg_log_marginal_homogeneous: float
    n: int
    penalty: float
    log_bayes_factor: float
    homogeneous: bool

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def field_evidence(
    P: np.ndarray,
    Y_local: np.ndarray,
    kernel: str,
    est: HyperEstimate | None = None,
    window: int = 150,
    max_windows: int = 8,
) -> FieldEvidence:
    """Compare a spatially varying field with a homogeneous one along positions P (K, 3)
    with the magnetometer Y_local (K, 3) in the local frame (same windows as the
    hyperparameter estimate, which is reused when given as ``est``, with the same
    ``window`` and ``max_windows``)."""
    if est is None:
        est = estimate_hyperparameters(
            P, Y_local, kernel=kernel, window=window, max_windows=max_windows
        )
    wins = select_windows(P, Y_local, window, max_windows)
    # As casmag.gp.hyper: the constant-field prior from the data's mean and spread.
    sigma_lin = float(np.abs(Y_local.mean(axis=0)).max() + Y_local.std())
    name = get_kernel(kernel).name
    # sigma_f -> 0 switches the map off (1e-12 of the field: below rounding).
    log_sf0 = np.log(1e-12 * max(sigma_lin, 1e-300))

    def homogeneous(log_sm: float) -> float:
        return negative_log_marginal(np.array([log_sf0, 0.0, log_sm]), wins, name, sigma_lin)

    spread = max(float(np.mean([Yw.std(axis=0).mean() for _, Yw in wins])), 1e-12)
    res = scipy.optimize.minimize_scalar(
        homogeneous, bounds=(np.log(spread) - 12.0, np.log(spread) + 2.0), method="bounded"
    )
    n = FIELD_DIM * sum(len(Xw) for Xw, _ in wins)
    penalty = float(np.log(n))
    lbf = float(res.fun) - est.neg_log_marginal - penalty
    return FieldEvidence(
        sigma_f=est.sigma_f,
        lengthscale=est.lengthscale,
        sigma_m=est.sigma_m,
        sigma_m_homogeneous=float(np.exp(res.x)),
        neg_log_marginal_map=est.neg_log_marginal,
        neg_log_marginal_homogeneous=float(res.fun),
        n=n,
        penalty=penalty,
        log_bayes_factor=lbf,
        homogeneous=bool(lbf <= 0.0),
    )


def noise_correlation_time(
    X: np.ndarray,
    Y: np.ndarray,
    kernel: str,
    est: HyperEstimate,
    window: int = 150,
    max_windows: int = 8,
    max_lag: int = 50,
) -> float:
    """Integrated autocorrelation time (in samples) of the magnetometer residuals along
    time: tau = 1 + 2 sum_k rho_k over lags k until the first non-positive average
    autocorrelation (Geyer's initial positive sequence). The residuals are the GP's
    leave-one-out residuals within each window at the estimate. White noise gives tau near
    1; noise correlated over tau samples carries the information of N / tau independent
    samples, so a white-noise model needs its sigma_m inflated by sqrt(tau) to stay honest.
    """
    name = get_kernel(kernel).name
    sigma_lin = float(np.abs(Y.mean(axis=0)).max() + Y.std())
    rho_sum = np.zeros(max_lag + 1)
    counts = np.zeros(max_lag + 1)
    with threadpool_limits(1):
        for Xw, Yw in select_windows(X, Y, window, max_windows):
            n = len(Xw)
            K = field_covariance(get_kernel(name), Xw, est.sigma_f, est.lengthscale)
            K += sigma_lin**2 * np.kron(np.eye(FIELD_DIM), np.ones((n, n)))
            K[np.diag_indices_from(K)] += est.sigma_m**2
            Ki = np.linalg.inv(K)
            r = (Ki @ Yw.ravel(order="F")) / np.diag(Ki)
            R = r.reshape(FIELD_DIM, n)
            R = R - R.mean(axis=1, keepdims=True)
            var = np.mean(R**2, axis=1)
            for k in range(min(max_lag, n - 2) + 1):
                rho_sum[k] += np.mean(np.mean(R[:, : n - k] * R[:, k:], axis=1) / var)
                counts[k] += 1
    rho = rho_sum / np.maximum(counts, 1)
    tau = 1.0
    for k in range(1, max_lag + 1):
        if counts[k] == 0 or rho[k] <= 0:
            break
        tau += 2.0 * rho[k]
    return float(tau)


HYPER_ORDER = ("sigma_f", "lengthscale", "sigma_m")
MAX_ROUNDS = 30  # of the step-limited search in estimate_conditional (a factor e each)
EDGE_TOL = 1e-3  # a search round that ends this close (log) to its box's edge goes on


@dataclass(frozen=True)
class ConditionalEstimate:
    """The marginal-likelihood estimate of some hyperparameters with the others fixed:
    ``values`` holds all three (estimated and fixed), ``free`` the estimated names,
    ``start`` the values the search started from."""

    values: dict[str, float]
    free: tuple[str, ...]
    start: dict[str, float]
    neg_log_marginal: float
    n_windows: int
    n_samples: int
    converged: bool
    iterations: int

    def to_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d["free"] = list(self.free)
        return d


def estimate_conditional(
    X: np.ndarray,
    Y: np.ndarray,
    kernel: str,
    values: dict[str, float],
    free: tuple[str, ...] | list[str],
    sigma_lin: float = 0.0,
    window: int = 150,
    max_windows: int = 8,
) -> ConditionalEstimate:
    """Maximise the windowed marginal likelihood of Y (N, 3) at positions X (N, d) over the
    hyperparameters named in ``free`` (log-parameterised, L-BFGS-B), starting from
    ``values`` (sigma_f, lengthscale, sigma_m), which also hold the fixed ones.

    sigma_lin: prior standard deviation of a constant field per window (0: a zero-mean
    field, as the exact GP map assumes). The search is bounded to 1e-4 ... 1e4 times the
    data's scale (sigma_f: the field's spread within windows, times l for the curl- and
    divergence-free kernels; l: the median window extent; sigma_m: the spread), which keeps
    the kernel matrix representable when the data favour a degenerate value.
    """
    X, Y = np.asarray(X, dtype=float), np.asarray(Y, dtype=float)
    if X.ndim != 2 or Y.shape != (X.shape[0], FIELD_DIM):
        raise ValueError(f"expected X (N, d) and Y (N, 3), got {X.shape} and {Y.shape}")
    unknown = [h for h in free if h not in HYPER_ORDER]
    if unknown or len(set(free)) != len(free) or not free:
        raise ValueError(f"free must name some of {HYPER_ORDER} once each, got {list(free)}")
    if any(not (values[h] > 0) for h in HYPER_ORDER):
        raise ValueError(f"hyperparameters must be positive, got {values}")
    with threadpool_limits(1):
        wins = select_windows(X, Y, window, max_windows)
        spread = float(np.mean([Yw.std(axis=0).mean() for _, Yw in wins]))
        extent = float(np.median([np.ptp(Xw, axis=0).max() for Xw, _ in wins]))
        if spread <= 0 or extent <= 0:
            raise ValueError("the data have no spread in field or position")
        name = get_kernel(kernel).name
        scale = {
            "sigma_f": spread if name == "se" else spread * values["lengthscale"],
            "lengthscale": extent,
            "sigma_m": spread,
        }
        full = np.log([values[h] for h in HYPER_ORDER])
        index = [HYPER_ORDER.index(h) for h in free]

        def objective(z: np.ndarray) -> float:
            theta = full.copy()
            theta[index] = z
            return negative_log_marginal(theta, wins, name, sigma_lin)

        def objective_and_gradient(z: np.ndarray) -> tuple[float, np.ndarray]:
            theta = full.copy()
            theta[index] = z
            f, g = negative_log_marginal_and_gradient(theta, wins, name, sigma_lin)
            return f, g[index]

        lo = np.log([scale[h] for h in free]) - np.log(1e4)
        hi = np.log([scale[h] for h in free]) + np.log(1e4)
        z = np.clip(full[index], lo, hi)
        f = objective(z)
        converged, iterations = False, 0
        # A local search from the start, at most a factor e per round: the marginal
        # likelihood at drifted positions can fall steeply towards a minimum and then stay
        # flat beyond it (l -> 0: white noise), where one unbounded line search would land
        # (measured on the paper's base case from l = 0.15 m: l = 4e-5 m instead of 0.029 m).
        for _ in range(MAX_ROUNDS):
            box_lo, box_hi = np.maximum(z - 1.0, lo), np.minimum(z + 1.0, hi)
            if len(z) == 1:
                # One hyperparameter: Brent's bounded search needs no gradient (finite
                # differences of the marginal likelihood drown in rounding when K is
                # ill-conditioned, as with sigma_f >> sigma_m).
                res = scipy.optimize.minimize_scalar(
                    lambda t: objective(np.array([t])),
                    bounds=(box_lo[0], box_hi[0]),
                    method="bounded",
                    options={"xatol": EDGE_TOL / 10},
                )
                x_new, f_new, nit = np.array([res.x]), float(res.fun), int(res.nfev)
            else:
                res = scipy.optimize.minimize(
                    objective_and_gradient,
                    z,
                    jac=True,
                    method="L-BFGS-B",
                    bounds=list(zip(box_lo, box_hi, strict=True)),
                )
                x_new, f_new, nit = res.x, float(res.fun), int(res.nit)
            iterations += nit
            if not f_new < f:
                converged = bool(res.success)
                break
            z, f = x_new, f_new
            at_edge = ((z - box_lo < EDGE_TOL) & (box_lo > lo)) | (
                (box_hi - z < EDGE_TOL) & (box_hi < hi)
            )
            if not at_edge.any():
                converged = bool(res.success)
                break
    out = dict(values)
    for h, v in zip(free, np.exp(z), strict=True):
        out[h] = float(v)
    return ConditionalEstimate(
        values={h: float(out[h]) for h in HYPER_ORDER},
        free=tuple(free),
        start={h: float(values[h]) for h in HYPER_ORDER},
        neg_log_marginal=float(f),
        n_windows=len(wins),
        n_samples=sum(len(w[0]) for w in wins),
        converged=converged,
        iterations=iterations,
    )
