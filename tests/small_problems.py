"""Small seeded problems and fields shared by several test files."""

from pathlib import Path

import casmag
from casmag.imusim import dipole_field

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
