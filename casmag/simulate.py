"""Simulated data for the planar GP-SLAM problem (paper Section 3.1).

The world: a planar Archimedean spiral walked at constant speed, one magnetometer sample per
pose; a 3-component field drawn from the GP prior at the true positions; odometry increments
with a constant bias and white noise; a magnetometer with white noise. The assumptions the
paper's text left open are documented in problems/README.md.

Random streams: one seed gives three independent streams (field, odometry, magnetometer), so
changing, say, the odometry noise level leaves the drawn field unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from casmag.config import Problem, SimulationSpec, TrajectorySpec
from casmag.kernels import FIELD_DIM, field_covariance, get_kernel


@dataclass(frozen=True)
class Dataset:
    """One data set for a translational GP-SLAM problem.

    U: (N-1, d) odometry increments [m]; Y: (N, 3) magnetometer samples (field units);
    anchor: (d,) known first position [m]. Truth (None for real recordings without it):
    P_true (N, d) positions [m], M_true (N, 3) field at the true positions, bias_true (d,)
    per-step odometry bias [m].
    """

    U: np.ndarray
    Y: np.ndarray
    anchor: np.ndarray
    P_true: np.ndarray | None = None
    M_true: np.ndarray | None = None
    bias_true: np.ndarray | None = None

    @property
    def n_samples(self) -> int:
        return self.Y.shape[0]

    @property
    def dim(self) -> int:
        return self.U.shape[1]

    def dead_reckoning(self) -> np.ndarray:
        """(N, d) positions from integrating the odometry from the anchor (bias not removed)."""
        return np.vstack([self.anchor, self.anchor + np.cumsum(self.U, axis=0)])


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
    P = spiral(spec.trajectory)
    M = draw_field(P, spec.field.kernel, spec.field.sigma_f, spec.field.lengthscale, rng_field)
    bias = np.asarray(spec.odometry.bias, dtype=float)
    dP = np.diff(P, axis=0)
    U = dP + bias + spec.odometry.noise * rng_odo.standard_normal(dP.shape)
    Y = M + spec.magnetometer.noise * rng_mag.standard_normal(M.shape)
    return Dataset(U=U, Y=Y, anchor=P[0].copy(), P_true=P, M_true=M, bias_true=bias)


def simulate_problem(problem: Problem) -> Dataset:
    """The data set a problem describes, with the problem's seed."""
    return simulate(problem.spec.simulation, problem.spec.seed)
