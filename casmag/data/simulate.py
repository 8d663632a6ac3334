"""Simulated data for the planar GP-SLAM problem (paper Section 3.1).

The world: a planar Archimedean spiral walked at constant speed, one magnetometer sample per
pose; a 3-component field drawn from the GP prior at the true positions; odometry increments
with a constant bias and white noise; a magnetometer with white noise. The assumptions the
paper's text left open are documented in problems/README.md.

Random streams: one seed gives independent streams (field, odometry, magnetometer, path), so
changing, say, the odometry noise level leaves the drawn field unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from casmag.data.dipoles import Dipole, DipoleField, moment_for
from casmag.gp.kernels import FIELD_DIM, field_covariance, get_kernel
from casmag.problem.spec import Problem, SimulationSpec, TrajectorySpec


@dataclass(frozen=True)
class Dataset:
    """One data set for a translational GP-SLAM problem.

    U: (N-1, d) odometry increments [m]; Y: (N, 3) magnetometer samples (field units);
    anchor: (d,) known first position [m]. Truth (None for real recordings without it):
    P_true (N, d) positions [m], M_true (N, 3) field at the true positions, bias_true (d,)
    per-step odometry bias [m].

    Several sessions (recordings of the same field, casmag.solver.multisession) are stacked: starts
    (S,) is the first sample of each session, anchor is then (S, d), one known first position
    per session, and bias_true (S, d); the step from a session's last sample to the next
    session's first, U[starts[s] - 1], is not odometry and is ignored.
    """

    U: np.ndarray
    Y: np.ndarray
    anchor: np.ndarray
    P_true: np.ndarray | None = None
    M_true: np.ndarray | None = None
    bias_true: np.ndarray | None = None
    starts: tuple[int, ...] = (0,)

    @property
    def n_samples(self) -> int:
        return self.Y.shape[0]

    @property
    def n_sessions(self) -> int:
        return len(self.starts)

    @property
    def session_bounds(self) -> list[tuple[int, int]]:
        """(first, end) sample range of each session."""
        ends = [*self.starts[1:], self.n_samples]
        return list(zip(self.starts, ends, strict=True))

    @property
    def dim(self) -> int:
        return self.U.shape[1]

    def dead_reckoning(self) -> np.ndarray:
        """(N, d) positions from integrating the odometry from the anchor (bias not removed);
        each session from its own anchor."""
        if self.n_sessions == 1:
            return np.vstack([self.anchor, self.anchor + np.cumsum(self.U, axis=0)])
        anchors = np.asarray(self.anchor, dtype=float).reshape(self.n_sessions, -1)
        parts = [
            np.vstack([a, a + np.cumsum(self.U[i : j - 1], axis=0)])
            for a, (i, j) in zip(anchors, self.session_bounds, strict=True)
        ]
        return np.vstack(parts)

    def prefix(self, n: int) -> Dataset:
        """The first n samples (and their n - 1 odometry steps); of stacked sessions, the
        sessions the first n samples reach (the last one cut at n), each its anchor and
        true bias."""
        if not 2 <= n <= self.n_samples:
            raise ValueError(f"prefix length {n} outside [2, {self.n_samples}]")
        reached = sum(1 for a in self.starts if a < n)
        rows = slice(0, reached)
        several = self.n_sessions > 1
        return replace(
            self,
            U=self.U[: n - 1],
            Y=self.Y[:n],
            P_true=None if self.P_true is None else self.P_true[:n],
            M_true=None if self.M_true is None else self.M_true[:n],
            anchor=np.asarray(self.anchor)[rows] if several else self.anchor,
            bias_true=np.asarray(self.bias_true)[rows]
            if several and self.bias_true is not None
            else self.bias_true,
            starts=self.starts[:reached],
        )

    def debiased(self, bias: np.ndarray) -> Dataset:
        """The same data with a per-step bias subtracted from every odometry increment (the
        true bias, when known, is reduced by the same amount); of stacked sessions, one bias
        row per session ((S, d)), each subtracted from its own session's steps."""
        bias = np.asarray(bias, dtype=float)
        if self.n_sessions == 1:
            bias = bias.ravel()
            return replace(
                self,
                U=self.U - bias,
                bias_true=None if self.bias_true is None else self.bias_true - bias,
            )
        bias = bias.reshape(self.n_sessions, self.dim)
        U = self.U.copy()
        for b, (i, j) in zip(bias, self.session_bounds, strict=True):
            U[i : j - 1] -= b
        return replace(
            self,
            U=U,
            bias_true=None
            if self.bias_true is None
            else np.reshape(self.bias_true, bias.shape) - bias,
        )


def spiral(spec: TrajectorySpec) -> np.ndarray:
    """(N, 2) positions [m] on r = r0 + pitch * theta / (2 pi), spaced ``step`` along the arc."""
    length = (spec.samples - 1) * spec.step
    b = spec.pitch / (2 * np.pi)
    # Arc length s(theta) >= r0 theta and >= b theta^2 / 2, so this theta range is long enough.
    bound = np.sqrt(2 * length / b)
    if spec.start_radius > 0:
        bound = min(bound, length / spec.start_radius)
    theta_max = 1.01 * bound + 1.0
    n_fine = int(min(max(2e5, theta_max * 2e3), 5e6))
    theta = np.linspace(0.0, theta_max, n_fine)
    r = spec.start_radius + b * theta
    xy = np.column_stack([r * np.cos(theta), r * np.sin(theta)])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    if s[-1] < length:
        raise ValueError("spiral grid too short; increase start_radius or pitch")
    target = np.arange(spec.samples) * spec.step
    return np.column_stack([np.interp(target, s, xy[:, 0]), np.interp(target, s, xy[:, 1])])


def walk(spec: TrajectorySpec, rng: np.random.Generator) -> np.ndarray:
    """(N, 2) positions [m] of a smooth random walk looping inside ``spec.area``.

    The heading is a random walk (``heading_noise`` rad per square-root metre); within
    ``wall_margin`` of an edge it turns towards the centre, at most 0.5 rad per step.
    """
    half = np.asarray(spec.area, dtype=float) / 2.0
    inner = np.maximum(half - spec.wall_margin, 1e-9)
    n, step = spec.samples, spec.step
    kicks = spec.heading_noise * np.sqrt(step) * rng.standard_normal(n)
    P = np.empty((n, 2))
    p = np.zeros(2)
    psi = rng.uniform(-np.pi, np.pi)
    for i in range(n):
        P[i] = p
        psi += kicks[i]
        if np.any(np.abs(p) > inner):
            home = np.arctan2(-p[1], -p[0])
            turn = np.angle(np.exp(1j * (home - psi)))
            psi += np.clip(turn, -0.5, 0.5)
        p = p + step * np.array([np.cos(psi), np.sin(psi)])
    return P


def fourier_field(
    X: np.ndarray,
    kernel_name: str,
    sigma_f: float,
    lengthscale: float,
    features: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """(N, 3) field from random Fourier features, a draw that approximates the GP prior.

    se: each component sigma_f sqrt(2 / F) sum_k a_k cos(omega_k . x + b_k) with omega_k ~
    N(0, I / l^2), a_k ~ N(0, 1), b_k ~ U(0, 2 pi). curl_free: l times the gradient of such a
    scalar potential drawn over three dimensions (planar X lie at z = 0), whose covariance is
    the curl-free kernel sigma_f^2 (I - r r^T / l^2) exp(-|r|^2 / (2 l^2)).
    """
    N, d = X.shape
    X3 = np.column_stack([X, np.zeros((N, 3 - d))]) if d < 3 else X
    scale = sigma_f * np.sqrt(2.0 / features)
    out = np.zeros((N, FIELD_DIM))
    chunk = 8192
    if kernel_name == "se":
        omega = rng.standard_normal((FIELD_DIM, features, 3)) / lengthscale
        b = rng.uniform(0, 2 * np.pi, (FIELD_DIM, features))
        a = rng.standard_normal((FIELD_DIM, features))
        for s in range(0, N, chunk):
            xs = X3[s : s + chunk]
            for c in range(FIELD_DIM):
                out[s : s + chunk, c] = scale * np.cos(xs @ omega[c].T + b[c]) @ a[c]
        return out
    if kernel_name == "curl_free":
        omega = rng.standard_normal((features, 3)) / lengthscale
        b = rng.uniform(0, 2 * np.pi, features)
        a = rng.standard_normal(features)
        for s in range(0, N, chunk):
            xs = X3[s : s + chunk]
            # grad of cos(omega . x + b) is -omega sin(omega . x + b)
            out[s : s + chunk] = -lengthscale * scale * (np.sin(xs @ omega.T + b) * a) @ omega
        return out
    raise ValueError(f"fourier fields support se and curl_free, not {kernel_name!r}")


def dipole_floor_field(
    X: np.ndarray,
    kernel_name: str,
    sigma_f: float,
    lengthscale: float,
    density: float,
    depth: tuple[float, float] | None,
    rng: np.random.Generator,
) -> np.ndarray:
    """(N, 3) field of magnetic dipoles under the floor at positions X (N, 2 or 3; planar
    X lie at z = 0): ``density`` dipoles per square metre over the positions' bounding box
    grown by the deepest depth, each at a depth uniform in ``depth`` [m] (None: 1.5 to 3
    lengthscales) below z = 0 with a moment in a uniformly random direction and a
    log-uniform strength over a decade, all scaled so that each component's standard
    deviation along X is the GP's (sigma_f; curl_free: sigma_f / l). Curl-free and
    divergence-free (casmag.data.dipoles), not a draw from the GP prior."""
    N, d = X.shape
    X3 = np.column_stack([X, np.zeros((N, 3 - d))]) if d < 3 else X
    lo_d, hi_d = depth if depth is not None else (1.5 * lengthscale, 3.0 * lengthscale)
    lo = X3[:, :2].min(axis=0) - hi_d
    hi = X3[:, :2].max(axis=0) + hi_d
    count = max(1, int(rng.poisson(density * float(np.prod(hi - lo)))))
    pos = np.column_stack(
        [rng.uniform(lo[0], hi[0], count), rng.uniform(lo[1], hi[1], count), np.zeros(count)]
    )
    pos[:, 2] = X3[:, 2].min() - rng.uniform(lo_d, hi_d, count)
    direction = rng.standard_normal((count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    strength = 10.0 ** rng.uniform(0.0, 1.0, count)
    moments = [
        moment_for(s, float(X3[:, 2].min() - z), u)
        for s, z, u in zip(strength, pos[:, 2], direction, strict=True)
    ]
    field = DipoleField(np.zeros(3), [Dipole(p, m) for p, m in zip(pos, moments, strict=True)])
    M = np.empty((N, FIELD_DIM))
    for s in range(0, N, 4096):
        M[s : s + 4096] = field(X3[s : s + 4096])
    target = sigma_f / (lengthscale if kernel_name == "curl_free" else 1.0)
    return M * (target / float(np.sqrt(np.mean(np.var(M, axis=0)))))


def draw_field(
    X: np.ndarray, kernel_name: str, sigma_f: float, lengthscale: float, rng: np.random.Generator
) -> np.ndarray:
    """(N, 3) field drawn from the GP prior at points X (N, d)."""
    kernel = get_kernel(kernel_name)
    K = field_covariance(kernel, X, sigma_f, lengthscale)
    # A small relative jitter keeps the Cholesky factor real for nearly coincident points.
    jitter = 1e-9 * kernel.variance(sigma_f, lengthscale)
    L = np.linalg.cholesky(K + jitter * np.eye(K.shape[0]))
    m = L @ rng.standard_normal(K.shape[0])
    return m.reshape(FIELD_DIM, X.shape[0]).T


def simulate(spec: SimulationSpec, seed: int) -> Dataset:
    """Simulate one data set from a simulation spec and a seed."""
    rng_field, rng_odo, rng_mag = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3)
    )
    rng_path = np.random.default_rng(np.random.SeedSequence(seed).spawn(4)[3])
    P = (
        spiral(spec.trajectory)
        if spec.trajectory.kind == "spiral"
        else walk(spec.trajectory, rng_path)
    )
    f = spec.field
    if f.method == "fourier":
        M = fourier_field(P, f.kernel, f.sigma_f, f.lengthscale, f.features, rng_field)
    elif f.method == "dipoles":
        depth = None if f.dipole_depth is None else (f.dipole_depth[0], f.dipole_depth[1])
        M = dipole_floor_field(
            P, f.kernel, f.sigma_f, f.lengthscale, f.dipole_density, depth, rng_field
        )
    else:
        M = draw_field(P, f.kernel, f.sigma_f, f.lengthscale, rng_field)
    bias = np.asarray(spec.odometry.bias, dtype=float)
    dP = np.diff(P, axis=0)
    U = dP + bias + spec.odometry.noise * rng_odo.standard_normal(dP.shape)
    Y = M + spec.magnetometer.noise * rng_mag.standard_normal(M.shape)
    return Dataset(U=U, Y=Y, anchor=P[0].copy(), P_true=P, M_true=M, bias_true=bias)


def simulate_problem(problem: Problem) -> Dataset:
    """The data set a problem describes, with the problem's seed."""
    return simulate(problem.spec.simulation, problem.spec.seed)
