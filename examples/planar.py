"""The planar odometry-with-heading model (dfwd, dleft, dyaw and a heading-rate bias) from
arrays: a simulated walk in a room with four magnetic dipoles, solved with three starts
(the dead reckoning and two opposite heading-rate biases, the lowest MAP cost kept).

    python examples/planar.py
"""

import numpy as np

from casmag.data.imusim import dipole_field, simulate_planar
from casmag.problem.imu import load_planar_options
from casmag.solver.planar import solve_planar

# Earth's field (1 a.u., inclination 67 deg, declination 2 deg) and four dipoles [m, a.u. m^3]
field = dipole_field(
    1.0,
    67.0,
    2.0,
    [
        ("radiator", [1.9, 0.3, 0.2], [0.08, -0.04, 0.05]),
        ("cabinet", [-0.4, 1.5, 0.3], [-0.05, 0.08, 0.06]),
        ("rebar", [0.3, -0.3, -0.5], [0.03, 0.05, -0.12]),
        ("rebar", [-1.0, -0.6, -0.5], [-0.06, 0.02, -0.1]),
    ],
)
d = simulate_planar(1, field, size=(2.0, 1.5), loops=2, heading_bias_deg=0.5, disp_noise=0.002)
options = load_planar_options(
    None, ["model.sigma_disp=0.002", f"model.sigma_dyaw={np.radians(0.05)}", "model.starts=3"]
)
r = solve_planar(*d.U.T, d.Y, options, truth={"P": d.P, "psi": d.psi}, t=d.t)
print(f"{r.status}: RMSE {r.rmse_before:.3f} m -> {r.rmse_after:.3f} m")
h = r.details
print(f"heading RMS {h['heading_rms_deg_before']:.2f} -> {h['heading_rms_deg_after']:.2f} deg")
bias = np.degrees(r.odometry_bias[0])
print(f"heading-rate bias {bias:.3f} deg/s (true {np.degrees(d.bias):.3f})")
