"""Several sessions of one field with one map for the IMU model (casmag.model.imu ``starts``,
casmag.data.imusim.stack_sessions, casmag.solver.imu through
casmag.solver.staged.solve_sessions): a simulated recording cut in two sessions, each
from its own known initial state."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from small_problems import tiny_imu

from casmag.data.imusim import ImuData, Truth, simulate_imu, stack_sessions
from casmag.data.recording import write_recording
from casmag.errors import DataError
from casmag.model.imu import keyframes
from casmag.problem.imu import load_imu_problem
from casmag.solver.imu import extend_states, solve_imu, solve_imu_stages
from casmag.solver.recslam import slam_sessions

ROOT = Path(__file__).resolve().parents[2]

#: The tiny desk rectangle, two loops, given hyperparameters and constant biases.
GP = {"sigma_f": 0.3, "lengthscale": 0.2, "num_basis": 200}


def _problem() -> dict:
    d = tiny_imu(gp=GP, imu={"bias": "constant"})
    d["simulation"]["scenario"]["loops"] = 2
    return d


def _cut(data: ImuData, a: int, e: int) -> ImuData:
    """Samples [a, e) of a simulation as a recording of its own, from its true state at a."""
    tr = data.truth
    return ImuData(
        T=data.T, dq=data.dq[a : e - 1], dv=data.dv[a : e - 1], Y=data.Y[a:e],
        p0=tr.P[a].copy(), v0=tr.V[a].copy(), q0=tr.Q[a].copy(),
        truth=Truth(t=tr.t[a:e], P=tr.P[a:e], V=tr.V[a:e], Q=tr.Q[a:e]),
        b_w=data.b_w[a:e], b_a=data.b_a[a:e], M=data.M[a:e],
    )  # fmt: skip


@pytest.fixture(scope="module")
def sessions():
    """The problem, its data, and the data cut at a keyframe into two sessions."""
    prob = load_imu_problem(_problem())
    data = simulate_imu(prob)
    n = prob.substeps
    cut = n * ((data.n_samples // 2) // n)
    parts = [_cut(data, 0, cut), _cut(data, cut, data.n_samples)]
    return prob, data, parts, stack_sessions(parts)


def test_stacked_sessions_keep_each_sessions_keyframes_and_initial_state(sessions):
    """The stacked data: one stand-in increment between the sessions, each session's
    keyframes from its own first sample, its initial state the true one there."""
    prob, data, parts, both = sessions
    cut = parts[0].n_samples
    assert both.starts == (0, cut) and both.n_samples == data.n_samples
    np.testing.assert_array_equal(both.dq[cut - 1], [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(np.delete(both.dq, cut - 1, 0), np.delete(data.dq, cut - 1, 0))
    P0, V0, Q0 = both.initial_states()
    np.testing.assert_array_equal(P0[1], data.truth.P[cut])
    np.testing.assert_array_equal(V0[1], data.truth.V[cut])
    np.testing.assert_array_equal(Q0[1], data.truth.Q[cut])
    kf = keyframes(both, prob.substeps, 1e-3, 1e-2)
    whole = keyframes(data, prob.substeps, 1e-3, 1e-2)
    k = kf.starts[1]
    assert kf.idx[k] == cut and np.array_equal(kf.idx, whole.idx)
    # every interval but the one into the second session is the single recording's
    keep = np.arange(kf.idx.size - 1) != k - 1
    np.testing.assert_array_equal(kf.DQ[keep], whole.DQ[keep])
    np.testing.assert_allclose(kf.LINV[keep], whole.LINV[keep], rtol=1e-12)
    with pytest.raises(ValueError, match="one IMU interval"):
        stack_sessions([parts[0], dataclasses.replace(parts[1], T=2 * data.T)])


def test_the_step_between_sessions_is_not_read(sessions):
    """The IMU-only adjustment of two sessions does not read the increments between them:
    a wild stand-in row there changes nothing; each session keeps its own biases."""
    both = sessions[3]
    cut = both.starts[1]
    wild = dataclasses.replace(
        both,
        dq=both.dq.copy(),
        dv=both.dv.copy(),
    )
    wild.dq[cut - 1] = [0.0, 1.0, 0.0, 0.0]
    wild.dv[cut - 1] = [5.0, -3.0, 9.0]
    spec = {**_problem(), "model": {**_problem()["model"], "gp": {"form": "none"}}}
    p = load_imu_problem(spec)
    a, b = solve_imu_stages(p, both), solve_imu_stages(p, wild)
    assert a.imu_only.solution.success
    np.testing.assert_allclose(a.imu_only.P, b.imu_only.P, atol=1e-12)
    assert a.imu_only.solution.x["BW"].shape == (2, 3)


def test_extending_into_a_session_not_reached_takes_its_reference():
    """A prefix continued past a session's start: its own last session shifted to join it,
    the new session the reference's own (positions, orientations, biases)."""
    K, starts = 10, (0, 6)
    rng = np.random.default_rng(3)
    ref = type("Ref", (), {})()
    ref.P, ref.V = rng.normal(size=(K, 3)), rng.normal(size=(K, 3))
    ref.Q = np.tile([1.0, 0.0, 0.0, 0.0], (K, 1))
    ref.b_w, ref.b_a = np.repeat([[1.0] * 3, [2.0] * 3], (6, 4), 0), np.zeros((K, 3))
    states = {
        "P": ref.P[:4] + 1.0, "V": ref.V[:4], "Q": ref.Q[:4],
        "BW": np.array([[0.5] * 3]), "BA": np.zeros((1, 3)), "zero_centre": np.zeros((1, 3)),
    }  # fmt: skip
    out = extend_states(states, ref, K, starts=starts)
    np.testing.assert_allclose(out["P"][4:6], ref.P[4:6] + 1.0)  # joined to the prefix
    np.testing.assert_allclose(out["P"][6:], ref.P[6:])  # the second session's own
    np.testing.assert_allclose(out["BW"], [[0.5] * 3, [2.0] * 3])


@pytest.mark.slow
def test_two_recordings_of_the_rectangle_share_one_map():
    """The rectangle scenario (problems/imu) simulated twice, seeds 1 and 2, as two
    sessions of one field: the IMU problem's ladder on both together succeeds, trusted,
    each session within a tenth of its IMU-only adjustment's error (measured: 3.8 and 3.9
    mm from 127 and 126 mm; each solved alone, 4.5 and 10.4 mm)."""
    probs = [load_imu_problem(ROOT / "problems/imu/rectangle.yaml", [f"seed={s}"]) for s in (1, 2)]
    datas = [simulate_imu(p) for p in probs]
    r = solve_imu(probs[0], stack_sessions(datas))
    assert r.success, r.status
    assert r.verdict["trusted"], r.verdict
    rows = r.info["sessions"]
    assert [row["keyframes"] for row in rows] == [(d.n_samples - 1) // 20 + 1 for d in datas]
    for row in rows:
        assert row["rmse_after"] < 0.1 * row["rmse_before"], row


def test_several_imu_recordings_need_their_first_poses_and_one_rate(tmp_path):
    """``casmag slam A B`` with IMU recordings: one without its truth's orientation, or at
    another rate, is refused in one line naming it."""
    prob = load_imu_problem(_problem())
    data = simulate_imu(prob)
    tr = data.truth
    imu = np.hstack([data.dq, data.dv])
    a, b, c = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "c.csv"
    write_recording(a, tr.t, data.Y, imu=imu, P_true=tr.P, q_true=tr.Q)
    write_recording(b, tr.t, data.Y, imu=imu, P_true=tr.P)
    write_recording(c, 2 * tr.t, data.Y, imu=imu, P_true=tr.P, q_true=tr.Q)
    with pytest.raises(DataError, match=r"b\.csv: several sessions need .* truth columns"):
        slam_sessions([a, b])
    with pytest.raises(DataError, match=r"c\.csv: t: sample interval .* one IMU rate") as err:
        slam_sessions([a, c])
    assert "\n" not in str(err.value)


def test_with_a_strategy_the_sessions_are_added_one_at_a_time():
    """``solver.warm_start.strategy: none`` on two sessions (the tiny rectangle, seeds 11
    and 12): casmag.solver.staged.solve_sessions solves the first session alone, then both
    from the first's estimate continued by the second's IMU-only adjustment; every solve is
    recorded with its session, the last one kept."""
    d = _problem()
    d["simulation"]["scenario"]["loops"] = 1
    d["solver"]["warm_start"] = {"strategy": "none"}
    probs = [load_imu_problem({**d, "seed": s}) for s in (11, 12)]
    both = stack_sessions([simulate_imu(p) for p in probs])
    r = solve_imu(probs[0], both)
    assert r.info["warm_start"] == "sessions"
    k1 = r.info["sessions"][1]["first_keyframe"]
    grow = r.stages[-1]["grow"]
    assert [(g["session"], g["keyframes"], g.get("start")) for g in grow] == [
        (0, k1, None),
        (1, r.info["keyframes"], "dead reckoning"),
    ]
    assert grow[1]["chosen"] and r.iterations == grow[1]["iterations"]
