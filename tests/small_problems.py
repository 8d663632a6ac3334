"""Small seeded problems and fields shared by several test files."""

from pathlib import Path

import casmag
from casmag.data.imusim import dipole_field

ROOT = Path(__file__).resolve().parents[1]


def tiny_walk(overrides=()):
    """problems/bench/walk.yaml shrunk to 120 samples in a 1.5 m room, a knot every 3
    samples, solved as one batch (seed 2)."""
    return casmag.load_problem(
        ROOT / "problems/bench/walk.yaml",
        [
            "seed=2",
            "simulation.trajectory.samples=120",
            "simulation.trajectory.area=[1.5, 1.5]",
            "model.trajectory.knot_every=3",
            "solver.warm_start.strategy=none",
            *overrides,
        ],
    )


def planar_room_field():
    """Earth's field plus four dipoles around a 2 m x 1.5 m walk (the planar tests)."""
    return dipole_field(
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


def tiny_imu(**model):
    """A 4-second rectangle on a desk with one dipole: a few dozen keyframes."""
    data = {
        "seed": 11,
        "simulation": {
            "scenario": {
                "kind": "rectangle",
                "size": [0.12, 0.08],
                "loops": 1,
                "static": 0.5,
                "speed": 0.12,
            },
            "field": {"dipoles": [{"position": [0.25, 0.0, -0.1], "moment": [2e-3, 1e-3, -3e-3]}]},
        },
        "model": {"keyframe_rate": 5.0, **model},
        "solver": {"max_iter": 100, "tol": 1e-5},
    }
    return data


def imu_noise_free(data, biases=True):
    """The IMU problem dictionary ``data`` made noise-free (sensors and magnetometer), with
    small model noises; ``biases`` False also zeroes the simulated biases."""
    imu = {
        "gyro_noise_density": 0.0,
        "acc_noise_density": 0.0,
        "gyro_bias_walk": 0.0,
        "acc_bias_walk": 0.0,
    }
    if not biases:
        imu.update(gyro_bias=[0.0, 0.0, 0.0], acc_bias=[0.0, 0.0, 0.0])
    data["simulation"]["imu"] = imu
    data["simulation"]["magnetometer"] = {"noise": 0.0}
    data["model"]["imu"] = {
        "gyro_noise_density": 1e-3,
        "acc_noise_density": 1e-4,
        "gyro_bias_walk": 1e-5,
        "acc_bias_walk": 1e-6,
    }
    # One sample per keyframe: averaging has an error of its own (the field's variation over
    # the window, the gyro bias), so only the keyframe's own sample makes the truth the optimum.
    data["model"]["magnetometer"] = {"sigma_m": 1e-3, "samples": 1}
    data["model"]["zero_position"] = {"sigma": None}
    return data
