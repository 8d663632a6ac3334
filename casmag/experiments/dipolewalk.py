"""A recording of the kind a user brings, to measure ``casmag slam`` on: a translational
walk in a physical field, written as a recording CSV with its truth.

The path is casmag.data.simulate.walk (a smooth random walk looping inside a square at
0.5 m/s, 10 Hz, 5 cm a sample). The field is Earth's (50 uT, inclination 67 deg) plus
``dipoles`` magnetic dipoles 0.3-1.2 m below the floor, spread over the square grown by
1 m, each in a random direction with an on-axis strength at the floor log-uniform over
3-30 uT (casmag.data.dipoles): not a draw from any GP prior, and in microtesla, as a
magnetometer writes it. The magnetometer adds white noise of ``noise`` uT; the odometry
adds 2 mm per step of white noise and a constant bias in a random direction sized so that
the linear drift alone has an RMSE of ``drift`` metres over the walk::

    python -m casmag.experiments.dipolewalk walk.csv --samples 16000 --area 6 --seed 1
    casmag slam walk.csv --out results/walk
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from casmag.data.dipoles import Dipole, DipoleField, earth_field, moment_for
from casmag.data.recording import write_recording
from casmag.data.simulate import walk
from casmag.problem.spec import TrajectorySpec

STEP = 0.05
RATE = 10.0
EARTH_UT = 50.0
ODOMETRY_NOISE = 2e-3


def dipole_walk(
    samples: int,
    area: float,
    seed: int,
    drift: float = 0.5,
    dipoles: int = 40,
    noise: float = 0.3,
) -> dict[str, np.ndarray]:
    """The recording's arrays: t (N,), Y (N, 3) [uT], dxy (N-1, 2) [m], P_true (N, 2)."""
    rng = np.random.default_rng(seed)
    spec = TrajectorySpec(
        kind="walk",
        samples=samples,
        step=STEP,
        area=[area, area],
        heading_noise=0.6,
        wall_margin=0.5,
    )
    P = walk(spec, rng)
    half = area / 2 + 1.0
    sources = []
    for _ in range(dipoles):
        centre = np.array(
            [rng.uniform(-half, half), rng.uniform(-half, half), -rng.uniform(0.3, 1.2)]
        )
        direction = rng.standard_normal(3)
        strength = 10.0 ** rng.uniform(0.5, 1.5)
        sources.append(Dipole(centre, moment_for(strength, -centre[2], direction)))
    field = DipoleField(EARTH_UT * earth_field(), sources)
    X = np.column_stack([P, np.zeros(samples)])
    M = np.vstack([field(X[s : s + 4096]) for s in range(0, samples, 4096)])
    Y = M + noise * rng.standard_normal(M.shape)
    bias = rng.standard_normal(2)
    bias *= drift * np.sqrt(3.0) / samples / np.linalg.norm(bias)  # linear drift's RMSE
    U = np.diff(P, axis=0) + bias + ODOMETRY_NOISE * rng.standard_normal((samples - 1, 2))
    return {"t": np.arange(samples) * (1.0 / RATE), "Y": Y, "dxy": U, "P_true": P}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="recording CSV to write")
    parser.add_argument("--samples", type=int, default=16_000)
    parser.add_argument("--area", type=float, default=6.0, help="side of the square [m]")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--drift", type=float, default=0.5, help="RMSE of the bias drift [m]")
    parser.add_argument("--dipoles", type=int, default=40)
    parser.add_argument("--noise", type=float, default=0.3, help="magnetometer noise [uT]")
    a = parser.parse_args()
    rec = dipole_walk(a.samples, a.area, a.seed, a.drift, a.dipoles, a.noise)
    write_recording(a.out, rec["t"], rec["Y"], dxy=rec["dxy"], P_true=rec["P_true"])
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
