"""The filter baseline from the library: casmag's EKF with a motion model of your own.

Wheel odometry whose scale is off by an unknown factor (tyre wear, a wrong wheel radius):
the states are the position and the scale s, p_{k+1} = p_k + s u_k + e_k. That model is
not one of casmag's; as a NavModel of four methods (initial, predict, position, rotation)
it runs in casmag's EKF with the reduced-rank GP map in the state. A walk of two laps
through a field drawn from the map's own prior is simulated and filtered. Run from the
repository's root: python examples/filter.py
"""

import math

import numpy as np

from casmag.gp.reduced_rank import Domain, HilbertBasis
from casmag.model.rrmap import field_and_jacobians
from casmag.solver.ekf import FilterMap, run_filter


class ScaledOdometry:
    """States (x, y, s): the odometry increments u_k scaled by s, noise ``sigma`` [m]."""

    dim, n_nav = 2, 3
    bias_states = slice(2, 3)  # the scale: the odometry's error the filter estimates

    def __init__(self, U, p0, sigma, scale_sigma):
        self.U, self.p0, self.sigma, self.scale_sigma = U, np.asarray(p0), sigma, scale_sigma

    def initial(self):
        return np.r_[self.p0, 1.0], np.diag([1e-6, 1e-6, self.scale_sigma**2])

    def predict(self, x, k):
        u = self.U[k]
        F = np.eye(3)
        F[:2, 2] = u
        return np.r_[x[:2] + x[2] * u, x[2]], F, np.diag([self.sigma**2] * 2 + [0.0])

    def position(self, x):
        return x[:2]

    def rotation(self, x):  # the magnetometer is read in the map frame
        return np.eye(3), []


rng = np.random.default_rng(1)
n = 400
t = np.linspace(0.0, 4.0 * math.pi, n)  # two laps of a 3 m x 2 m ellipse
P = np.column_stack([1.5 * np.cos(t), np.sin(t)])
U = np.diff(P, axis=0) / 0.93 + 0.002 * rng.standard_normal((n - 1, 2))  # 7 % too long
basis = HilbertBasis(Domain(np.zeros(2), np.array([3.0, 2.5])), 200)
fmap = FilterMap(basis, "se", sigma_f=1.0, lengthscale=0.5, sigma_m=0.05, sigma_lin=2.0)
w = rng.standard_normal(fmap.n_w) * np.sqrt(fmap.prior_variances())
Y = field_and_jacobians(basis, "se", P, w)[0] + [0.4, -0.2, 0.9]
Y += 0.05 * rng.standard_normal(Y.shape)

run = run_filter(ScaledOdometry(U, P[0], sigma=0.002, scale_sigma=0.1), fmap, Y)
dead = np.vstack([P[0], P[0] + np.cumsum(U, axis=0)])
err = np.sqrt(np.mean(np.sum((run.positions - P) ** 2, axis=1)))
err0 = np.sqrt(np.mean(np.sum((dead - P) ** 2, axis=1)))
print(f"filter RMSE {err:.3f} m (dead reckoning {err0:.3f} m)")
print(f"odometry scale {run.states[-1, 2]:.3f} (true 0.930)")
print(f"mean NIS {run.mean_nis:.2f} (3 when consistent), {run.n_state} states, {run.seconds:.2f} s")
