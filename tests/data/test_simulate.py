"""The translational simulator's physical field (casmag.data.simulate.dipole_floor_field)."""

import numpy as np
import pytest
from small_problems import ROOT

import casmag
from casmag.data.dipoles import Dipole
from casmag.data.simulate import dipole_floor_field, simulate_problem

WALK = ROOT / "problems/bench/walk.yaml"


@pytest.mark.parametrize(("kernel", "target"), [("se", 1.0), ("curl_free", 1.0 / 0.35)])
def test_dipole_field_has_the_gp_component_scale(kernel, target):
    """simulation.field.method: dipoles: the same seed gives the same field, each
    component's variance averages to the GP's (sigma_f^2, or sigma_f^2 / l^2 curl-free),
    and the field is not a constant (dipoles under the whole walk)."""
    overrides = [
        "simulation.field.method=dipoles",
        f"simulation.field.kernel={kernel}",
        "simulation.trajectory.samples=1500",
    ]
    a = simulate_problem(casmag.load_problem(WALK, overrides))
    b = simulate_problem(casmag.load_problem(WALK, overrides))
    assert np.array_equal(a.M_true, b.M_true)
    assert np.sqrt(np.mean(np.var(a.M_true, axis=0))) == pytest.approx(target, rel=1e-12)
    assert np.all(np.std(a.M_true, axis=0) > 0.2 * target)


def test_dipoles_sit_under_the_floor_and_the_field_is_theirs():
    """A single dipole's field reproduced: the function's field is a scaled sum of
    casmag.data.dipoles fields of dipoles below the plane of the path."""
    rng = np.random.default_rng(0)
    X = rng.uniform(0.0, 1.0, size=(50, 2))
    M = dipole_floor_field(X, "se", 1.0, 0.3, 1e-9, (0.5, 0.5), np.random.default_rng(1))
    # density ~0 still places one dipole (at least one), 0.5 m below z = 0
    r = np.random.default_rng(1)
    r.poisson(1e-9 * 4.0)  # the same draws in the same order
    lo, hi = X.min(axis=0) - 0.5, X.max(axis=0) + 0.5
    pos = np.array([r.uniform(lo[0], hi[0]), r.uniform(lo[1], hi[1]), 0.0])
    pos[2] = -r.uniform(0.5, 0.5)
    u = r.standard_normal(3)
    u /= np.linalg.norm(u)
    s = 10.0 ** r.uniform(0.0, 1.0)
    B = Dipole(pos, 0.5 * s * 0.5**3 * u).field(np.column_stack([X, np.zeros(50)]))
    scale = M[0, 0] / B[0, 0]
    assert np.allclose(M, scale * B, rtol=1e-10) and scale > 0


@pytest.mark.parametrize(
    ("override", "reason"),
    [
        ("simulation.field.dipole_depth=[1.0, 0.5]", "shallowest, deepest"),
        ("simulation.field.kernel=div_free", "dipoles gives a curl-free field"),
    ],
)
def test_dipole_settings_refused(override, reason):
    with pytest.raises(casmag.ProblemError, match=reason):
        casmag.load_problem(WALK, ["simulation.field.method=dipoles", override])
