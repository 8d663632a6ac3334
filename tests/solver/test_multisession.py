"""Multi-session GP-SLAM (casmag.solver.multisession): one chain of knots, one bias and one anchor
per session, one shared map."""

from __future__ import annotations

import json
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from click.testing import CliRunner

from casmag.cli.main import main
from casmag.data.recording import write_recording
from casmag.data.simulate import Dataset, simulate_problem
from casmag.gp.kernels import field_covariance, get_kernel
from casmag.model.knots import Knots
from casmag.problem.spec import load_problem
from casmag.result.metrics import rmse_and_max
from casmag.solver.multisession import session_order, solve_sessions, split, stack
from casmag.solver.sessions import revisit_fraction
from casmag.solver.translational import TranslationalStaged

ROOT = Path(__file__).resolve().parents[2]


def test_knots_keep_one_chain_per_session():
    k = Knots(12, 3, starts=(0, 5))
    np.testing.assert_array_equal(k.samples, [0, 3, 4, 5, 8, 11])
    np.testing.assert_array_equal(k.session_of_interval, [0, 0, -1, 1, 1])
    # No sample is interpolated across the gap: the last sample of session 0 is a knot.
    A = k.matrix.toarray()
    assert A[4, 2] == 1.0 and A[5, 3] == 1.0
    with pytest.raises(ValueError, match="sessions"):
        Knots(10, 2, starts=(0, 9))


def test_odometry_cost_is_the_sum_of_the_sessions():
    rng = np.random.default_rng(3)
    n1, n2 = 9, 7
    both = Knots(n1 + n2, 2, starts=(0, n1))
    C = rng.standard_normal((both.count, 2))
    b = rng.standard_normal((2, 2))
    Cs, bs = ca.MX.sym("C", both.count, 2), ca.MX.sym("b", 2, 2)
    f = ca.Function("f", [Cs, bs], [both.odometry_cost(Cs, bs, 0.5)])
    total = float(f(C, b))
    parts = 0.0
    for k, (rows, bias) in zip(
        (Knots(n1, 2), Knots(n2, 2)), ((slice(0, 5), b[0:1]), (slice(5, None), b[1:2])), strict=True
    ):
        Ck = ca.MX.sym("C", k.count, 2)
        g = ca.Function("g", [Ck], [k.odometry_cost(Ck, ca.DM(bias), 0.5)])
        parts += float(g(C[rows]))
    assert total == pytest.approx(parts, rel=1e-12)


def _pair(seed: int = 7):
    """Session A: the paper's spiral (loops, 2 % bias); session B: a straight line across
    it (no loop of its own) with a larger bias. One field drawn from the GP prior at both."""
    base = load_problem(ROOT / "problems/paper/base.yaml", ["model.gp.form=reduced_rank"])
    PA = simulate_problem(base).P_true
    # The data below are not the problem's simulation: its model settings are given (the
    # values its nulls stand for), as casmag.solve requires for such data.
    base = base.with_overrides(
        {
            "model.gp.sigma_f": base.assumed_sigma_f,
            "model.gp.lengthscale": base.assumed_lengthscale,
            "model.magnetometer.sigma_m": base.assumed_sigma_m,
            "model.odometry.sigma": base.assumed_sigma_odometry,
        }
    )
    PB = np.column_stack([np.linspace(-0.2, 0.2, 21), np.linspace(-0.08, 0.12, 21)])
    rng = np.random.default_rng(seed)
    X = np.vstack([PA, PB])
    C = field_covariance(get_kernel("se"), X, 0.1, 0.1)
    F = np.linalg.cholesky(C + 1e-8 * np.eye(C.shape[0])) @ rng.standard_normal(C.shape[0])
    Y = F.reshape(3, -1).T + 5e-4 * rng.standard_normal((X.shape[0], 3))

    def session(P, Yk, bias):
        U = np.diff(P, axis=0) + bias + 1e-4 * rng.standard_normal((P.shape[0] - 1, 2))
        return Dataset(U=U, Y=Yk, anchor=P[0].copy(), P_true=P, bias_true=np.array(bias))

    A = session(PA, Y[: PA.shape[0]], [1e-3, 1e-3])
    B = session(PB, Y[PA.shape[0] :], [-2e-3, 3e-3])
    return base, A, B


def test_stacked_dead_reckoning_restarts_at_every_anchor():
    _, A, B = _pair()
    d = stack([A, B])
    assert d.starts == (0, A.n_samples) and d.anchor.shape == (2, 2)
    np.testing.assert_allclose(
        d.dead_reckoning(), np.vstack([A.dead_reckoning(), B.dead_reckoning()])
    )
    parts = split(d, d.P_true)
    np.testing.assert_array_equal(parts[1], B.P_true)
    # A prefix reaches the sessions it cuts: the first whole, the second's first samples.
    cut = d.prefix(A.n_samples + 5)
    assert cut.starts == d.starts and cut.anchor.shape == (2, 2)
    np.testing.assert_array_equal(cut.dead_reckoning(), d.dead_reckoning()[: A.n_samples + 5])
    assert d.prefix(A.n_samples).starts == (0,)
    np.testing.assert_array_equal(d.prefix(A.n_samples).anchor, A.anchor.reshape(1, -1))
    # Each session's bias comes off its own steps only.
    b = np.array([[1e-3, 0.0], [0.0, -2e-3]])
    P = d.debiased(b).dead_reckoning()
    steps = np.arange(A.n_samples)[:, None]
    np.testing.assert_allclose(P[: A.n_samples], A.dead_reckoning() - steps * b[0])
    np.testing.assert_allclose(
        P[A.n_samples :], B.dead_reckoning() - np.arange(B.n_samples)[:, None] * b[1]
    )


def test_revisits_order_the_sessions():
    _, A, B = _pair()
    line = B.P_true
    assert revisit_fraction(line, 0.1, 8) == 0.0
    assert revisit_fraction(A.P_true, 0.1, 8) > 0.5
    assert session_order([B, A], 0.1) == [1, 0]


def test_a_line_is_localised_against_the_map_of_a_spiral():
    """Session B alone has no loop; with the spiral's session in the same problem its drift
    is removed, and the Laplace uncertainty is honest (NEES within 0.5-2 x its expected)."""
    base, A, B = _pair()
    result, data, order = solve_sessions(base, [B, A])
    assert order == [1, 0] and result.success
    # The spiral from its dead reckoning, then the line (too short for growing prefixes)
    # from its dead reckoning beside the spiral's estimate; the final solve starts there.
    starts = result.stages_named("start")
    assert [(st["session"], st["start"], st["kept"]) for st in starts] == [
        (0, "dead reckoning", True),
        (1, "dead reckoning", True),
    ]
    # The result's iterations and seconds count the starts' solves with the final one's.
    assert result.iterations > sum(st["iterations"] for st in starts)
    assert result.solve_seconds > sum(st["solve_seconds"] for st in starts)
    for P_odo, P_est, P_true in zip(
        split(data, result.arrays["P_odometry"]),
        split(data, result.arrays["P_estimate"]),
        split(data, data.P_true),
        strict=True,
    ):
        before, after = rmse_and_max(P_odo, P_true)[0], rmse_and_max(P_est, P_true)[0]
        assert after <= 0.1 * before, (before, after)
    bias = np.reshape(result.odometry_bias, (2, 2))
    np.testing.assert_allclose(bias, np.vstack([A.bias_true, B.bias_true]), atol=2e-4)
    u = result.uncertainty
    assert 0.5 * u["nees_expected"] <= u["nees_mean"] <= 2.0 * u["nees_expected"]


def test_cli_solves_several_recordings(tmp_path):
    _, A, B = _pair()
    recs = []
    for name, d in (("spiral", A), ("line", B)):
        path = tmp_path / f"{name}.csv"
        write_recording(path, 0.1 * np.arange(d.n_samples), d.Y, dxy=d.U, P_true=d.P_true)
        recs.append(str(path))
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["slam", *recs, "--out", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    saved = json.loads((out / "result.json").read_text())
    names = [s["name"] for s in saved["info"]["sessions"]]
    assert sorted(names) == ["line", "spiral"]
    assert (out / "sessions.png").is_file() and (out / "trajectory.png").is_file()
    for s in saved["info"]["sessions"]:
        assert s["rmse_after"] < s["rmse_before"]


def test_cli_refuses_a_planar_session(tmp_path):
    _, A, _ = _pair()
    a = tmp_path / "a.csv"
    write_recording(a, 0.1 * np.arange(A.n_samples), A.Y, dxy=A.U, P_true=A.P_true)
    p = tmp_path / "p.csv"
    n = A.n_samples
    write_recording(p, 0.1 * np.arange(n), A.Y, planar=np.zeros((n - 1, 3)))
    res = CliRunner().invoke(main, ["slam", str(a), str(p), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2
    assert "planar" in res.output and not (tmp_path / "o").exists()


def test_real_problem_takes_one_recording_or_sessions(tmp_path):
    from casmag.errors import CasmagError
    from casmag.experiments.realbench import load_real_problem

    rec = "{sequence: x/1, drift: 0.5}"
    both = tmp_path / "both.yaml"
    both.write_text(f"name: b\nrecording: {rec}\nsessions: [{rec}]\n")
    with pytest.raises(CasmagError, match="either recording or sessions"):
        load_real_problem(both)
    two = tmp_path / "two.yaml"
    two.write_text(f"name: t\nsessions: [{rec}, {rec}]\n")
    assert len(load_real_problem(two).recordings) == 2


def test_the_translational_staged_model_continues_each_session_from_its_own_start():
    """casmag.solver.translational.TranslationalStaged.extend: within the session it has
    reached, the bias-corrected dead reckoning joined to the last position; a session it
    has not reached, from that session's anchor, its bias still zero."""
    base, A, B = _pair()
    d = stack([A, B])
    model = TranslationalStaged(base, d)
    n1, n = A.n_samples, d.n_samples
    assert model.sessions(n1 - 10) == [(0, n1 - 10)]
    assert model.sessions(n) == [(0, n1), (n1, n)]
    P = A.P_true[: n1 - 10]
    bias = np.array([[1e-3, -1e-3]])
    out = model.extend({"P": P, "bias": bias}, n)
    assert out["P"].shape == (n, 2) and out["bias"].shape == (2, 2)
    np.testing.assert_array_equal(out["bias"], [[1e-3, -1e-3], [0.0, 0.0]])
    np.testing.assert_array_equal(out["P"][: n1 - 10], P)
    DR = A.debiased(bias).dead_reckoning()
    np.testing.assert_allclose(out["P"][n1 - 10 : n1], DR[n1 - 10 :] - DR[n1 - 11] + P[-1])
    np.testing.assert_allclose(out["P"][n1:], B.dead_reckoning())
    with pytest.raises(ValueError, match="no heading"):
        model.start(n, 0.01)
