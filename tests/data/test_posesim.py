"""Simulated planar and pose recordings (casmag.data.posesim): without noise and biases the
odometry integrates back to the true path, and the magnetometer turned by the true heading
or orientation is the simulation's field."""

import numpy as np
import pytest

from casmag import strapdown as sd
from casmag.data.posesim import simulate_planar, simulate_pose
from casmag.data.simulate import simulate
from casmag.model.planar import dead_reckon_planar
from casmag.problem.spec import SimulationSpec

SPEC = SimulationSpec.model_validate(
    {
        "trajectory": {"kind": "walk", "samples": 60, "step": 0.5, "area": [6.0, 3.0]},
        "field": {"kernel": "curl_free", "sigma_f": 1.0, "lengthscale": 1.0, "method": "dipoles"},
        "odometry": {"noise": 0.0, "bias": [0.0, 0.0]},
        "magnetometer": {"noise": 0.0},
    }
)


def test_noise_free_planar_odometry_integrates_to_the_path():
    sim = simulate_planar(SPEC, 3, heading_noise=0.0)
    truth = simulate(SPEC, 3)
    P, psi = dead_reckon_planar(sim.U, sim.P_true[0], float(sim.psi_true[0]))
    np.testing.assert_allclose(P, truth.P_true, atol=1e-9)
    np.testing.assert_allclose(psi, sim.psi_true, atol=1e-12)
    c, s = np.cos(sim.psi_true), np.sin(sim.psi_true)
    Y = sim.Y
    world = np.column_stack([c * Y[:, 0] - s * Y[:, 1], s * Y[:, 0] + c * Y[:, 1], Y[:, 2]])
    np.testing.assert_allclose(world, truth.M_true, atol=1e-12)


def test_noise_free_pose_odometry_integrates_to_the_path():
    sim = simulate_pose(SPEC, 3, rotation_noise=0.0, bias_p=(0.0, 0.0, 0.0))
    P, Q = sd.dead_reckon_pose(sim.U, sim.P_true[0], sim.q_true[0])
    np.testing.assert_allclose(P, sim.P_true, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(Q * sim.q_true, axis=1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(sd.rotate(sim.q_true, sim.Y), simulate(SPEC, 3).M_true, atol=1e-12)


def test_the_planar_biases_are_where_the_arguments_say():
    spec = SPEC.model_copy(
        update={"odometry": SPEC.odometry.model_copy(update={"bias": [0.01, -0.02]})}
    )
    quiet = simulate_planar(spec, 3, heading_noise=0.0, heading_bias=0.0)
    biased = simulate_planar(spec, 3, rate_hz=4.0, heading_noise=0.0, heading_bias=0.05)
    exact = simulate_planar(SPEC, 3, heading_noise=0.0)
    np.testing.assert_allclose(quiet.U[:, :2] - exact.U[:, :2], np.tile([0.01, -0.02], (59, 1)))
    # the heading-rate bias is per second: 0.05 rad/s at 4 Hz is 0.0125 rad per step
    np.testing.assert_allclose(biased.U[:, 2] - exact.U[:, 2], 0.0125, atol=1e-15)
    np.testing.assert_allclose(biased.t[1] - biased.t[0], 0.25)


def test_the_recordings_carry_their_motion_and_truth():
    planar = simulate_planar(SPEC, 1).recording("p")
    pose = simulate_pose(SPEC, 1).recording("q")
    assert (planar.motion, planar.increment_names) == ("planar", ("dfwd", "dleft", "dyaw"))
    assert pose.motion == "pose" and pose.increments.shape == (59, 7)
    assert planar.yaw_true is not None and pose.q_true is not None
    with pytest.raises(ValueError, match="displacement bias of 3 axes"):
        simulate_planar(SPEC, 1, bias_p=(0.0, 0.0, 0.0))
